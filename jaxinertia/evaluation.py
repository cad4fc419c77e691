"""The one evaluator: the paper's Tables I-III for any models on any known objects.

``evaluate(objects, sets, pair=..., baselines=...)`` evaluates O objects x K model pairs x B
sets of M samples: per object, the torque and attention models of every pair on every set
in one jitted call (:func:`jaxinertia.estimation.estimate_sets`), the baselines (Sensor, PE:
identity weights) in one more (:func:`jaxinertia.identification.identity_solves`); one
program of each for any number of objects. The same
code serves the released models on the real files, trained models on simulated or real
objects, the estimate of an unknown object and the switching-load run; each object is a
:class:`jaxinertia.samples.Samples` of one object. Sets are chosen by :func:`choose_sets`.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Callable, Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxinertia.baselines import Baselines
from jaxinertia.errors import FileFormatError, UsageError
from jaxinertia.estimation import Estimates, ModelPair, estimate_sets
from jaxinertia.features import FeatureConfig, featurize
from jaxinertia.identification import WLSResult, identity_solves
from jaxinertia.metrics import inertial_metrics, torque_metrics
from jaxinertia.objects import bounding_box_diagonal
from jaxinertia.samples import Samples
from jaxinertia.sharding import shard

__all__ = [
    "METHODS",
    "Stacked",
    "average",
    "choose_sets",
    "continuous_force",
    "evaluate",
    "l_max_of",
    "mean_filter",
    "random_sets",
    "sliding_windows",
    "stack",
]

METHODS = ("Sensor", "PE", "T", "T-A")


# ---- sets -------------------------------------------------------------------------------


def random_sets(n_samples: int, *, n_sets: int = 1000, set_size: int = 64, seed: int = 0):
    """(n_sets, set_size) indices: each set drawn without replacement, sets independent."""
    if set_size > n_samples:
        raise UsageError(f"set size {set_size} exceeds the {n_samples} samples available")
    rng = np.random.default_rng(seed)
    return np.stack([rng.choice(n_samples, set_size, replace=False) for _ in range(n_sets)])


def choose_sets(objects: Sequence[Samples], *, n_sets: int = 1000, set_size: int = 64,
                seed: int = 0,
                golden: Callable[[Samples], np.ndarray | None] | None = None,
                ) -> tuple[list[np.ndarray], list[str]]:
    """The evaluation sets of each object and where they came from: ``golden(obj)`` when it
    gives sets (the authors' golden files), else ``n_sets`` random sets of ``set_size``
    drawn with seed ``seed + i`` for the i-th object."""
    sets, sources = [], []
    for i, obj in enumerate(objects):
        g = golden(obj) if golden is not None else None
        if g is not None:
            sets.append(np.asarray(g, np.int64))
            sources.append("golden")
        else:
            sets.append(random_sets(obj.n_samples, n_sets=n_sets, set_size=set_size,
                                    seed=seed + i))
            sources.append(f"random (seed {seed + i})")
    return sets, sources


def l_max_of(objects: Sequence[Samples], overrides: dict[str, float] | None = None,
             *, path: str | os.PathLike | None = None) -> list[float]:
    """Each known object's bounding-box diagonal (the COM error normaliser); an object
    without one is an error naming it (``overrides``, ``{name: metres}``, supplies it)."""
    out = []
    for obj in objects:
        d = bounding_box_diagonal(obj.name, overrides)
        if d is None and obj.known:
            msg = (f"no bounding-box diagonal for object {obj.name!r}: pass "
                   f"`l_max` {obj.name}=METRES")
            raise FileFormatError(path, None, msg) if path else UsageError(msg)
        out.append(np.nan if d is None else d)
    return out


# ---- stacking ---------------------------------------------------------------------------


class Stacked(NamedTuple):
    """Objects padded to a common sample count for one batched call (sets index the
    real samples; the padding repeats the last sample and is never selected)."""

    features: jnp.ndarray | None  # (O, S, N, 4) float32; None without a feature config
    A: jnp.ndarray  # (O, S, N, 4)
    tau_g: jnp.ndarray  # (O, S, N)
    sets: jnp.ndarray  # (O, B, M)


def _pad(a: np.ndarray, n: int) -> np.ndarray:
    a = np.asarray(a)
    return np.concatenate([a, np.repeat(a[-1:], n - a.shape[0], axis=0)], axis=0)


def _check_sets(objects: Sequence[Samples], sets: Sequence[np.ndarray]) -> None:
    """Every object's sets of one shape (B, M), each indexing only its object's samples."""
    if len({np.shape(s) for s in sets}) != 1:
        raise UsageError(f"sample sets differ in shape across objects: "
                         f"{[np.shape(s) for s in sets]}")
    for obj, s in zip(objects, sets):
        if np.max(s) >= obj.n_samples or np.min(s) < 0:
            raise UsageError(f"{obj.name}: a set indexes sample {np.max(s)} of "
                             f"{obj.n_samples}")


#: What a program of one's own is told when it evaluates without float64: the statics and the
#: weighted least squares then run in float32, and the attention's weights make the sets'
#: least squares ill-conditioned enough for that to show (the released models' T-A mass
#: NMAE on white over the same 1000 sets: 5.09 % in float32, 4.18 % in float64).
FLOAT32_WARNING = (
    "jax_enable_x64 is off: the statics and least squares run in float32, which moves the "
    "answers (the released models' T-A mass NMAE on the real white object 5.09 % against "
    "4.18 % in float64); call jax.config.update('jax_enable_x64', True) before any JAX "
    "computation, as the command line does")


def stack(objects: Sequence[Samples], sets: Sequence[np.ndarray],
          fc: FeatureConfig | None, n_samples: int | None = None) -> Stacked:
    """Pads every object's arrays to the largest sample count, or to ``n_samples`` (at
    least that; features only with ``fc``)."""
    _check_sets(objects, sets)
    n = max([obj.n_samples for obj in objects] + [n_samples or 0])
    if not jax.config.jax_enable_x64:
        warnings.warn(FLOAT32_WARNING, RuntimeWarning, stacklevel=3)
    f64 = jnp.float64 if jax.config.jax_enable_x64 else jnp.float32
    # Features in float64 then float32, the precision the networks were trained with.
    feats = None if fc is None else jnp.asarray(np.stack([
        _pad(np.asarray(featurize(fc, jnp.asarray(o.q, f64), o.q_d, o.direction,
                                  o.current_tau), np.float32), n)
        for o in objects]))
    return Stacked(features=feats,
                   A=jnp.asarray(np.stack([_pad(o.A, n) for o in objects])),
                   tau_g=jnp.asarray(np.stack([_pad(o.tau_g, n) for o in objects])),
                   sets=jnp.asarray(np.stack(sets)))


# ---- evaluation -------------------------------------------------------------------------


def baseline_methods(objects: Sequence[Samples]) -> tuple[tuple[str, ...], dict[str, str]]:
    """The baselines that ``objects`` allow, and why any other is unavailable: the Sensor
    baseline needs every joint's current-based torque, which a servo without a current
    sensor (XL430-W250: Present Load only) does not give."""
    missing = [o.name for o in objects if not o.has_current]
    if not missing:
        return ("Sensor", "PE"), {}
    joints = sorted({int(j) for o in objects
                     for j in np.flatnonzero(~np.all(np.isfinite(o.current_tau), axis=0))})
    return ("PE",), {"Sensor": f"unavailable: joints {joints} of {', '.join(missing)} have no "
                               "current sensor (Present Load only), so no current-based "
                               "torque"}


def baseline_torques(baselines: Baselines, obj: Samples) -> dict[str, np.ndarray]:
    """(S, N) torques [N m] of the Sensor and PE baselines (PE only where ``obj`` has no
    current-based torque: :func:`baseline_methods`)."""
    s = jnp.asarray(obj.direction)
    out = {"Sensor": lambda: baselines.sensor(jnp.asarray(obj.current_tau), s),
           "PE": lambda: baselines.pe(jnp.asarray(obj.q_d), jnp.asarray(obj.q), s)}
    return {m: np.asarray(out[m]()) for m in baseline_methods([obj])[0]}


def _finite(x: np.ndarray) -> np.ndarray:
    return x[np.all(np.isfinite(x), axis=-1)]


def _concat(parts: list):
    """Results of one object each (leading axis 1) as one of every object, on the host
    (a device concatenation would compile a program per shape)."""
    if len(parts) == 1:
        return parts[0]
    return jax.tree_util.tree_map(lambda *a: np.concatenate([np.asarray(x) for x in a]),
                                  *parts)


def _diagnostics(res: WLSResult, o: int) -> dict:
    # Indexed on the host: indexing the device arrays compiles a slice per shape.
    cond = np.asarray(res.condition)[o]
    return {"rank_deficient": int(np.sum(np.asarray(res.rank_deficient)[o])),
            "ill_conditioned": int(np.sum(np.asarray(res.ill_conditioned)[o])),
            "max_condition": float(np.nanmax(cond)), "n_solves": int(cond.size)}


def evaluate(objects: Sequence[Samples], sets: Sequence[np.ndarray], *,
             pair: ModelPair | None = None, baselines: Baselines | None = None,
             fc: FeatureConfig | None = None, l_max: Sequence[float] | None = None) -> dict:
    """Tables I-III and diagnostics of ``pair`` (features ``fc``) and ``baselines`` on
    ``objects`` (one object each), over each object's ``sets`` (B, M).

    Returns ``{"objects": {name: {method: Table I metrics, "mean_attention_weight": [...],
    "L_max_m": ...}}, "torque": {method: Table II metrics}, "diagnostics": {name: {method:
    flagged sets}}, "estimates": {method: (O, [K,] B, 4)}, "model_estimates": Estimates,
    "unavailable": {method: why}}`` (the Sensor baseline on an arm without current sensors).
    Metrics of the K model pairs are computed over all their sets together (as the paper's
    ten repeats); unknown objects get estimates but no metrics.
    """
    if pair is not None and fc is None:
        raise UsageError("evaluating models needs their feature configuration")
    names = [o.name for o in objects]
    if len(set(names)) != len(names):  # results are keyed by name: one would be lost
        raise UsageError(f"objects {names} repeat a name: each object needs its own")
    l_max = list(l_max) if l_max is not None else l_max_of(objects)
    _check_sets(objects, sets)  # the objects' results are stacked: one shape of sets
    n = max(obj.n_samples for obj in objects)
    # Object by object, each padded to the largest sample count: one program of each kind
    # (models, baselines) for any number of objects, so that the evaluations of one object
    # (a held-out fold's file) and of several (models_real on every real file, the
    # simulated test objects) share their compiled programs; each call still solves every
    # model pair and set of its object at once.
    batches = [stack([obj], [s], fc, n_samples=n) for obj, s in zip(objects, sets)]
    # The sets (1, B, M) split along B over every local device (jaxinertia.sharding).
    batches = [b._replace(sets=shard(b.sets, axis=1)) for b in batches]
    solves: dict[str, WLSResult] = {}
    tau_hat: dict[str, list[np.ndarray]] = {}
    usable, unavailable = baseline_methods(objects)
    if baselines is not None:
        per_obj = [baseline_torques(baselines, o) for o in objects]
        for m in usable:
            tau_hat[m] = [p[m] for p in per_obj]
            solves[m] = _concat([identity_solves(b.A, jnp.asarray(_pad(t, n)[None]), b.tau_g,
                                                 b.sets) for b, t in zip(batches, tau_hat[m])])
    est: Estimates | None = None
    if pair is not None:
        est = _concat([estimate_sets(pair, b.features, b.A, b.tau_g, b.sets) for b in batches])
        solves["T"], solves["T-A"] = est.T, est.TA
        tau_hat["T"] = [np.asarray(est.tau_hat[o, :, : obj.n_samples])
                        for o, obj in enumerate(objects)]
    estimates = {m: np.asarray(r.x) for m, r in solves.items()}
    results: dict[str, dict] = {}
    for o, obj in enumerate(objects):
        entry: dict = {}
        for m in METHODS:
            if m in estimates and obj.known:
                entry[m] = inertial_metrics(_finite(estimates[m][o].reshape(-1, 4)), obj.x[0],
                                            l_max[o])
        if est is not None:
            w = np.asarray(est.weights[o][:, : obj.n_samples], np.float64)
            entry["mean_attention_weight"] = w.reshape(-1, w.shape[-1]).mean(axis=0).tolist()
        entry["L_max_m"] = l_max[o]
        results[obj.name] = entry
    torque = {}
    if all(o.known for o in objects):
        tau = np.concatenate([o.tau for o in objects])
        for m, per in tau_hat.items():
            if m == "T":  # (K, S, N) per object: metrics per model, then the mean over models
                per_model = [torque_metrics(np.concatenate([p[k] for p in per]), tau)
                             for k in range(per[0].shape[0])]
                torque[m] = {key: np.mean([pm[key] for pm in per_model], axis=0).tolist()
                             for key in per_model[0]}
            else:
                torque[m] = torque_metrics(np.concatenate(per), tau)
    return {"objects": results, "torque": torque,
            "diagnostics": {n: {m: _diagnostics(r, o) for m, r in solves.items()}
                            for o, n in enumerate(names)},
            "estimates": estimates, "model_estimates": est,
            "unavailable": unavailable if baselines is not None else {}}


def average(objects: dict) -> dict[str, dict[str, float]]:
    """Table I's average row: the mean of every metric over the objects, per method."""
    out = {}
    for m in METHODS:
        rows = [e[m] for e in objects.values() if m in e]
        if rows:
            out[m] = {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}
    return out


# ---- the switching-load run -------------------------------------------------------------


def sliding_windows(n_samples: int, width: int) -> np.ndarray:
    """(n - width + 1, width) indices of consecutive samples."""
    if n_samples < width:
        raise UsageError(f"{n_samples} samples are fewer than one window of {width}")
    return np.arange(n_samples - width + 1)[:, None] + np.arange(width)[None]


def mean_filter(x: np.ndarray, width: int) -> np.ndarray:
    """Centred moving average along axis 0 (shrinking at the ends)."""
    x = np.asarray(x, np.float64)
    c = np.cumsum(np.concatenate([np.zeros((1,) + x.shape[1:]), x]), axis=0)
    n = len(x)
    lo = np.clip(np.arange(n) - width // 2, 0, n)
    hi = np.clip(np.arange(n) + (width - width // 2), 0, n)
    return (c[hi] - c[lo]) / (hi - lo).reshape((-1,) + (1,) * (x.ndim - 1))


def continuous_force(run: Samples, pair: ModelPair, baselines: Baselines, fc: FeatureConfig,
                     *, width: int = 128, g: float = 9.81) -> dict:
    """The switching-load experiment: vertical force ``m_hat g`` from windows of ``width``
    consecutive samples of the trajectory ``run`` (several objects, switching), averaged
    over the K model pairs, then a ``width``-wide mean filter.

    Each window's estimate is placed at its centre sample; the truth there is the mass of
    the object held at that sample times ``g``. Returns per method the raw and filtered
    force, the MAE of the filtered force [N], and the per-sample torque estimates.
    """
    if not run.known:
        raise UsageError("the switching-load run needs the held objects' masses")
    true_mass = np.asarray(run.x)[np.asarray(run.object_id), 0]
    traj = run.without_truth().replace(object_id=np.zeros(run.n_samples, np.int64),
                                       names=("continuous",))
    windows = sliding_windows(run.n_samples, width)
    res = evaluate([traj], [windows], pair=pair, baselines=baselines, fc=fc, l_max=[np.nan])
    centre = np.arange(windows.shape[0]) + width // 2
    truth = true_mass[centre] * g
    out = {"sample": centre, "truth_N": truth, "methods": {}}
    for m, x in res["estimates"].items():
        mass = np.asarray(x)[0, ..., 0]  # (B,) or (K, B)
        mass = np.nanmean(mass.reshape(-1, mass.shape[-1]), axis=0)
        force = mean_filter(mass * g, width)
        out["methods"][m] = {"force_N": force, "raw_N": mass * g,
                             "MAE_N": float(np.nanmean(np.abs(force - truth)))}
    torques = {"truth": run.tau}
    torques.update(baseline_torques(baselines, traj))
    if pair is not None:
        batch = stack([traj], [windows[:1]], fc)
        tau_hat = estimate_sets(pair, batch.features, batch.A, batch.tau_g, batch.sets).tau_hat
        torques["T"] = np.asarray(tau_hat[0, :, : run.n_samples]).mean(axis=0)
    out["torques"] = torques
    return out
