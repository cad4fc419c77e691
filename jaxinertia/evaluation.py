"""The paper's evaluation (Tables I-III) for trained models and the two baselines.

One jitted call per method family evaluates O objects x K model pairs x B sets of M samples:
the torque and attention models through :func:`jaxinertia.estimation.estimate_sets`, the
baselines (Sensor, PE: identity weights) through :func:`jaxinertia.identification.solve_sets`
vmapped over objects. The same code runs on simulated test objects and on the real lbipe
files (both are lists of :class:`jaxinertia.lbipe.LbipeDataset`).
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from jaxinertia.baselines import Baselines
from jaxinertia.estimation import Estimates, ModelPair, estimate_sets
from jaxinertia.features import FeatureConfig, featurize
from jaxinertia.identification import WLSResult, solve_sets
from jaxinertia.lbipe import LbipeDataset
from jaxinertia.metrics import inertial_metrics, torque_metrics

__all__ = ["METHODS", "ObjectBatch", "evaluate", "stack_objects"]

METHODS = ("Sensor", "PE", "T", "T-A")


@dataclass
class ObjectBatch:
    """Test objects padded to a common sample count, ready for one batched call."""

    datasets: list[LbipeDataset]
    l_max: list[float]
    sets: list[np.ndarray]  # per object (B, M) indices into its own samples
    features: jnp.ndarray  # (O, S, N, 4) float32
    A: jnp.ndarray  # (O, S, N, 4)
    tau_g: jnp.ndarray  # (O, S, N)
    sets_padded: jnp.ndarray  # (O, B, M)

    @property
    def names(self) -> list[str]:
        return [d.name for d in self.datasets]

    def padded(self, per_object: list[np.ndarray]) -> jnp.ndarray:
        return jnp.asarray(np.stack([_pad(a, self.features.shape[1]) for a in per_object]))


def _pad(a: np.ndarray, n: int) -> np.ndarray:
    return np.concatenate([a, np.repeat(a[-1:], n - a.shape[0], axis=0)], axis=0)


def stack_objects(datasets: list[LbipeDataset], l_max: list[float], sets: list[np.ndarray],
                  fc: FeatureConfig) -> ObjectBatch:
    """Pads every object's arrays to the largest sample count (sets index real samples)."""
    if len({np.shape(s) for s in sets}) != 1:
        raise ValueError(f"sample sets differ in shape across objects: "
                         f"{[np.shape(s) for s in sets]}")
    for d, s in zip(datasets, sets):
        if np.max(s) >= d.n_samples:
            raise ValueError(f"{d.name}: a set indexes sample {np.max(s)} of {d.n_samples}")
    n = max(d.n_samples for d in datasets)
    f64 = jnp.float64 if jax.config.jax_enable_x64 else jnp.float32
    # Features in float64 then float32, the precision the networks were trained with.
    feats = [np.asarray(featurize(fc, jnp.asarray(d.q, f64), d.q_d, d.direction), np.float32)
             for d in datasets]
    return ObjectBatch(
        datasets=list(datasets), l_max=list(l_max), sets=list(sets),
        features=jnp.asarray(np.stack([_pad(f, n) for f in feats])),
        A=jnp.asarray(np.stack([_pad(d.A, n) for d in datasets])),
        tau_g=jnp.asarray(np.stack([_pad(d.tau_g, n) for d in datasets])),
        sets_padded=jnp.asarray(np.stack(sets)),
    )


@jax.jit
def _solve_identity(A, y, tau_g, sets) -> WLSResult:
    """Identity-weight WLS for (O, S, N) torque estimates y."""
    return jax.vmap(lambda A_o, y_o, g_o, s_o: solve_sets(A_o, y_o - g_o, None, s_o))(
        A, y.astype(A.dtype), tau_g, sets)


def baseline_torques(baselines: Baselines, d: LbipeDataset) -> dict[str, np.ndarray]:
    s = jnp.asarray(d.direction)
    return {"Sensor": np.asarray(baselines.sensor(jnp.asarray(d.current_tau), s)),
            "PE": np.asarray(baselines.pe(jnp.asarray(d.q_d), jnp.asarray(d.q), s))}


def _finite(x: np.ndarray) -> np.ndarray:
    return x[np.all(np.isfinite(x), axis=-1)]


def evaluate(batch: ObjectBatch, pair: ModelPair | None, baselines: Baselines | None) -> dict:
    """Tables I-III and diagnostics.

    Returns ``{"objects": {name: {method: Table I metrics, "mean_attention_weight": [...],
    "L_max_m": ...}}, "torque": {method: Table II metrics}, "diagnostics": {...},
    "estimates": {method: (O, [K,] B, 4) arrays}}``. Metrics of the K model pairs are
    computed over all their sets together (as the paper's ten repeats).
    """
    results: dict[str, dict] = {}
    estimates: dict[str, np.ndarray] = {}
    flagged: dict[str, list[int]] = {}
    tau_hat: dict[str, list[np.ndarray]] = {}
    if baselines is not None:
        per_obj = [baseline_torques(baselines, d) for d in batch.datasets]
        for m in ("Sensor", "PE"):
            tau_hat[m] = [p[m] for p in per_obj]
            res = _solve_identity(batch.A, batch.padded(tau_hat[m]), batch.tau_g,
                                  batch.sets_padded)
            estimates[m] = np.asarray(res.x)
            flagged[m] = np.sum(~np.asarray(res.ok), axis=-1).tolist()
    est: Estimates | None = None
    if pair is not None:
        est = estimate_sets(pair, batch.features, batch.A, batch.tau_g, batch.sets_padded)
        estimates["T"], estimates["T-A"] = np.asarray(est.T.x), np.asarray(est.TA.x)
        for m, r in (("T", est.T), ("T-A", est.TA)):
            flagged[m] = np.sum(~np.asarray(r.ok), axis=(1, 2)).tolist()
        tau_hat["T"] = [np.asarray(est.tau_hat[o, :, : d.n_samples])
                        for o, d in enumerate(batch.datasets)]
    for o, d in enumerate(batch.datasets):
        entry: dict = {}
        for m in METHODS:
            if m in estimates and np.all(np.isfinite(d.x)):  # unknown objects: no metrics
                entry[m] = inertial_metrics(_finite(estimates[m][o].reshape(-1, 4)), d.x,
                                            batch.l_max[o])
        if est is not None:
            w = np.asarray(est.weights[o][:, : d.n_samples], np.float64)
            entry["mean_attention_weight"] = w.reshape(-1, w.shape[-1]).mean(axis=0).tolist()
        entry["L_max_m"] = batch.l_max[o]
        results[d.name] = entry
    tau = np.concatenate([d.tau for d in batch.datasets])
    torque = {}
    for m, per in tau_hat.items():
        if m == "T":  # (K, S, N) per object: metrics per model, then the mean over models
            per_model = [torque_metrics(np.concatenate([p[k] for p in per]), tau)
                         for k in range(per[0].shape[0])]
            torque[m] = {key: np.mean([pm[key] for pm in per_model], axis=0).tolist()
                         for key in per_model[0]}
        else:
            torque[m] = torque_metrics(np.concatenate(per), tau)
    return {"objects": results, "torque": torque,
            "diagnostics": {m: dict(zip(batch.names, v)) for m, v in flagged.items()},
            "estimates": estimates}


def average(objects: dict) -> dict[str, dict[str, float]]:
    """Table I's average row: the mean of every metric over the objects, per method."""
    out = {}
    for m in METHODS:
        rows = [e[m] for e in objects.values() if m in e]
        if rows:
            out[m] = {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}
    return out


def format_table1(objects: dict, title: str) -> str:
    """Table I (per object and average) as a markdown table."""
    cols = ["mass_MAE_g", "mass_NMAE_pct", "mass_NRMSE_pct", "com_MAE_mm", "com_NMAE_pct",
            "com_NRMSE_pct"]
    lines = [f"**{title}**", "", "| object | method | mass MAE [g] | mass NMAE [%] | "
             "mass NRMSE [%] | COM MAE [mm] | COM NMAE [%] | COM NRMSE [%] |",
             "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |"]
    rows = dict(objects)
    if len(objects) > 1:
        rows["average"] = average(objects)
    for name, e in rows.items():
        for m in METHODS:
            if m in e:
                lines.append(f"| {name} | {m} | " + " | ".join(f"{e[m][c]:.2f}" for c in cols)
                             + " |")
    return "\n".join(lines)


def format_table2(torque: dict, title: str) -> str:
    n = len(next(iter(torque.values()))["MAE_Nmm"])
    lines = [f"**{title}**", "", "| method | metric | " +
             " | ".join(f"joint {j + 1}" for j in range(n)) + " |",
             "| --- | --- |" + " ---: |" * n]
    for m in METHODS:
        if m in torque:
            for key, label in (("MAE_Nmm", "MAE [N mm]"), ("NMAE_pct", "NMAE [%]"),
                               ("NRMSE_pct", "NRMSE [%]")):
                lines.append(f"| {m} | {label} | " +
                             " | ".join(f"{v:.2f}" for v in torque[m][key]) + " |")
    return "\n".join(lines)


def format_table3(objects: dict, title: str) -> str:
    have = {k: e for k, e in objects.items() if "mean_attention_weight" in e}
    if not have:
        return ""
    n = len(next(iter(have.values()))["mean_attention_weight"])
    lines = [f"**{title}**", "", "| object | " +
             " | ".join(f"joint {j + 1}" for j in range(n)) + " |", "| --- |" + " ---: |" * n]
    for name, e in have.items():
        lines.append(f"| {name} | " + " | ".join(f"{w:.4f}" for w in e["mean_attention_weight"])
                     + " |")
    return "\n".join(lines)


def sliding_windows(n_samples: int, width: int) -> np.ndarray:
    """(n - width + 1, width) indices of consecutive samples."""
    if n_samples < width:
        raise ValueError(f"{n_samples} samples are fewer than one window of {width}")
    return np.arange(n_samples - width + 1)[:, None] + np.arange(width)[None]


def mean_filter(x: np.ndarray, width: int) -> np.ndarray:
    """Centred moving average along axis 0 (shrinking at the ends)."""
    x = np.asarray(x, np.float64)
    c = np.cumsum(np.concatenate([np.zeros((1,) + x.shape[1:]), x]), axis=0)
    n = len(x)
    lo = np.clip(np.arange(n) - width // 2, 0, n)
    hi = np.clip(np.arange(n) + (width - width // 2), 0, n)
    return (c[hi] - c[lo]) / (hi - lo).reshape((-1,) + (1,) * (x.ndim - 1))


def continuous_force(batch: ObjectBatch, pair: ModelPair, baselines: Baselines,
                     true_mass: np.ndarray, *, width: int = 128, g: float = 9.81) -> dict:
    """The switching-load experiment: vertical force ``m_hat g`` from windows of ``width``
    consecutive samples (``batch`` holds one object: the trajectory, with sliding windows as
    its sets), averaged over the K model pairs, then a ``width``-wide mean filter.

    Each window's estimate is placed at its centre sample; the truth there is
    ``true_mass * g``. Returns per method the raw and filtered force, the MAE of the
    filtered force [N], and the per-sample torque estimates.
    """
    res = evaluate(batch, pair, baselines)
    n = batch.datasets[0].n_samples
    centre = np.arange(batch.sets[0].shape[0]) + width // 2
    truth = np.asarray(true_mass, np.float64)[centre] * g
    out = {"sample": centre, "truth_N": truth, "methods": {}}
    for m, x in res["estimates"].items():
        mass = np.asarray(x)[0, ..., 0]  # (B,) or (K, B)
        mass = np.nanmean(mass.reshape(-1, mass.shape[-1]), axis=0)
        force = mean_filter(mass * g, width)
        out["methods"][m] = {"force_N": force, "raw_N": mass * g,
                             "MAE_N": float(np.nanmean(np.abs(force - truth)))}
    d = batch.datasets[0]
    torques = {"truth": d.tau}
    torques.update({m: v for m, v in baseline_torques(baselines, d).items()})
    if pair is not None:
        tau_hat = estimate_sets(pair, batch.features, batch.A, batch.tau_g,
                                batch.sets_padded[:, :1]).tau_hat
        torques["T"] = np.asarray(tau_hat[0, :, :n]).mean(axis=0)
    out["torques"] = torques
    return out
