"""The released models on the real OpenMANIPULATOR-X data: Table I and Table III, batched.

Also holds a faithful per-set loop of the authors' test procedure (numpy, explicit
``(A^T W A)^-1 A^T W y`` per set as in the paper's eq. 15) as the speed and value reference
for ``experiments/bench_lbipe.py``.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxinertia.estimation import Estimates, ModelPair, estimate_sets
from jaxinertia.features import LBIPE_FEATURES, FeatureConfig, featurize
from jaxinertia.lbipe import (
    BOUNDING_BOX_DIAGONALS,
    LbipeDataset,
    LbipeFormatError,
    find_layout,
    load_golden,
    load_test_file,
)
from jaxinertia.metrics import inertial_metrics
from jaxinertia.networks import WeightsError, load_released_pair, stack_params

__all__ = [
    "BenchmarkInputs",
    "load_released_models",
    "prepare",
    "random_sets",
    "run_lbipe_benchmark",
    "tables",
    "reference_loop",
]

N_RELEASED = 10


def load_released_models(
    weights_dir: str | os.PathLike,
    *,
    prefer: str = "npz",
    n_models: int = N_RELEASED,
    features: FeatureConfig = LBIPE_FEATURES,
) -> ModelPair:
    """The authors' ten released model pairs, stacked for vmap."""
    pairs = [load_released_pair(weights_dir, k, prefer=prefer) for k in range(1, n_models + 1)]
    tm, am = pairs[0][0], pairs[0][2]
    for k, p in enumerate(pairs, start=1):
        if p[0] != tm or p[2] != am:
            raise WeightsError(f"{weights_dir}: model pair {k} has another architecture")
    return ModelPair(
        torque_vars=stack_params([p[1] for p in pairs]),
        attention_vars=stack_params([p[3] for p in pairs]),
        tau_scale=jnp.asarray(features.tau_scale, jnp.float32),
        torque_model=tm,
        attention_model=am,
    )


def random_sets(n_samples: int, *, n_sets: int = 1000, set_size: int = 64, seed: int = 0):
    """(n_sets, set_size) indices: each set drawn without replacement, sets independent."""
    if set_size > n_samples:
        raise ValueError(f"set size {set_size} exceeds the {n_samples} samples available")
    rng = np.random.default_rng(seed)
    return np.stack([rng.choice(n_samples, set_size, replace=False) for _ in range(n_sets)])


@dataclass
class BenchmarkInputs:
    names: list[str]
    datasets: list[LbipeDataset]
    l_max: list[float]
    sets: list[np.ndarray]
    set_source: list[str]
    features: jnp.ndarray  # (O, S, N, 4) float32, padded
    A: jnp.ndarray  # (O, S, N, 4)
    tau_g: jnp.ndarray  # (O, S, N)
    sets_padded: jnp.ndarray  # (O, B, M)
    golden: dict = field(default_factory=dict)


def prepare(
    lbipe_dir: str | os.PathLike,
    *,
    seed: int = 0,
    l_max: dict[str, float] | None = None,
    n_sets: int = 1000,
    set_size: int = 64,
    features: FeatureConfig = LBIPE_FEATURES,
) -> tuple[BenchmarkInputs, ModelPair]:
    """Loads every test object and the released models, and builds the batched inputs."""
    layout = find_layout(lbipe_dir)
    diag = {**BOUNDING_BOX_DIAGONALS, **(l_max or {})}
    names, datasets, sets, sources, goldens, lmax = [], [], [], [], {}, []
    for name, path in layout.test_files.items():
        if name not in diag:
            raise LbipeFormatError(
                path, None, f"no bounding-box diagonal for object {name!r}: pass "
                f"--l-max {name}=METRES"
            )
        ds = load_test_file(path, name)
        if ds.n_joints != features.n_joints:
            raise LbipeFormatError(path, "joint_data", f"{ds.n_joints} joints, the models "
                                   f"expect {features.n_joints}")
        gpath = layout.golden_dir / f"golden_{name}.npz" if layout.golden_dir else None
        if gpath is not None and gpath.exists():
            g = load_golden(gpath, ds.n_samples)
            goldens[name] = g
            s, src = g["sets"], f"{gpath}"
        else:
            s, src = random_sets(ds.n_samples, n_sets=n_sets, set_size=set_size,
                                 seed=seed), f"random (seed {seed})"
        names.append(name)
        datasets.append(ds)
        sets.append(s)
        sources.append(src)
        lmax.append(float(diag[name]))
    pair = load_released_models(layout.weights_dir, prefer=layout.prefer, features=features)

    s_max = max(d.n_samples for d in datasets)
    if len({s.shape for s in sets}) != 1:
        raise ValueError(f"sample sets differ in shape across objects: {[s.shape for s in sets]}")

    def pad(a):
        return np.concatenate([a, np.repeat(a[-1:], s_max - a.shape[0], axis=0)], axis=0)

    feats = [
        # Features in float64 then float32, the precision the networks were trained with.
        np.asarray(featurize(features, jnp.asarray(d.q, jnp.float64) if jax.config.jax_enable_x64
                             else d.q, d.q_d, d.direction), np.float32)
        for d in datasets
    ]
    inputs = BenchmarkInputs(
        names=names,
        datasets=datasets,
        l_max=lmax,
        sets=sets,
        set_source=sources,
        features=jnp.asarray(np.stack([pad(f) for f in feats])),
        A=jnp.asarray(np.stack([pad(d.A) for d in datasets])),
        tau_g=jnp.asarray(np.stack([pad(d.tau_g) for d in datasets])),
        sets_padded=jnp.asarray(np.stack(sets)),
        golden=goldens,
    )
    return inputs, pair


def tables(inputs: BenchmarkInputs, est: Estimates) -> dict:
    """Results in the schema of ``golden/reference_metrics.json`` (objects as keys)."""
    out = {}
    for o, (name, ds) in enumerate(zip(inputs.names, inputs.datasets)):
        entry = {}
        for key, res in (("T", est.T), ("T-A", est.TA)):
            x = np.asarray(res.x[o])
            good = np.all(np.isfinite(x), axis=-1)
            entry[key] = inertial_metrics(x[good], ds.x, inputs.l_max[o])
        w = np.asarray(est.weights[o][:, : ds.n_samples], np.float64)
        entry["mean_attention_weight"] = w.reshape(-1, w.shape[-1]).mean(axis=0).tolist()
        entry["L_max_m"] = inputs.l_max[o]
        out[name] = entry
    return out


def diagnostics(inputs: BenchmarkInputs, est: Estimates) -> dict:
    """Counts of flagged sets and condition numbers, per object and method."""
    out = {}
    for o, name in enumerate(inputs.names):
        out[name] = {
            key: {
                "rank_deficient": int(np.sum(np.asarray(r.rank_deficient[o]))),
                "ill_conditioned": int(np.sum(np.asarray(r.ill_conditioned[o]))),
                "max_condition": float(np.max(np.asarray(r.condition[o]))),
                "n_solves": int(np.asarray(r.condition[o]).size),
            }
            for key, r in (("T", est.T), ("T-A", est.TA))
        }
    return out


def run_lbipe_benchmark(lbipe_dir, *, seed: int = 0, l_max=None) -> dict:
    """Loads, evaluates in one batched call, and returns tables, diagnostics and timings."""
    t0 = time.perf_counter()
    inputs, pair = prepare(lbipe_dir, seed=seed, l_max=l_max)
    t1 = time.perf_counter()
    est = estimate_sets(pair, inputs.features, inputs.A, inputs.tau_g, inputs.sets_padded)
    jax.block_until_ready(est)
    t2 = time.perf_counter()
    return {
        "metrics": tables(inputs, est),
        "diagnostics": diagnostics(inputs, est),
        "set_source": dict(zip(inputs.names, inputs.set_source)),
        "timing_s": {"load": t1 - t0, "evaluate_incl_compile": t2 - t1},
        "inputs": inputs,
        "pair": pair,
        "estimates": est,
    }


# ----------------------------------------------------------------------------------------
# Reference: the authors' procedure, one set and one model at a time (numpy).


def _np_mlp(layers, x):
    for i, (w, b) in enumerate(layers):
        x = x @ w + b
        if i < len(layers) - 1:
            x = np.maximum(x, 0.0)
    return x


def _np_params(pair: ModelPair, k: int):
    tv = jax.tree_util.tree_map(lambda a: np.asarray(a[k]), pair.torque_vars)["params"]
    av = jax.tree_util.tree_map(lambda a: np.asarray(a[k]), pair.attention_vars)["params"]

    def lyr(d):
        return (d["kernel"], d["bias"])

    n = pair.torque_model.n_joints
    t_joint = [[lyr(tv[f"joint{j}"]["hidden"]), lyr(tv[f"joint{j}"]["embed"])] for j in range(n)]
    t_head = [lyr(tv[f"head{i}"]) for i in range(len(pair.torque_model.head))] + [lyr(tv["out"])]
    a_joint = [[lyr(av[f"joint{j}"]["hidden"]), lyr(av[f"joint{j}"]["embed"])] for j in range(n)]
    a_score = [lyr(av[f"scorer{i}"]) for i in range(len(pair.attention_model.scorer))]
    a_score.append(lyr(av["score"]))
    return t_joint, t_head, a_joint, a_score


def reference_loop(pair: ModelPair, inputs: BenchmarkInputs, o: int) -> tuple[np.ndarray, ...]:
    """x for T and T-A, (K, B, 4) each, computed set by set as the authors' test loop does."""
    ds = inputs.datasets[o]
    feats = np.asarray(inputs.features[o][: ds.n_samples])
    A = np.asarray(inputs.A[o][: ds.n_samples])
    tau_g = np.asarray(inputs.tau_g[o][: ds.n_samples])
    scale = np.asarray(pair.tau_scale)
    n = ds.n_joints
    xs_t, xs_ta = [], []
    for k in range(pair.n_models):
        t_joint, t_head, a_joint, a_score = _np_params(pair, k)
        xt, xta = [], []
        for idx in inputs.sets[o]:
            f = feats[idx]
            h = np.concatenate([_np_mlp(t_joint[j], f[:, j]) for j in range(n)], axis=-1)
            tau_hat = _np_mlp(t_head, h) * scale
            e = np.stack([_np_mlp(a_joint[j], f[:, j]) for j in range(n)], axis=1)
            z = np.broadcast_to(np.eye(n, dtype=e.dtype), e.shape[:2] + (n,))
            s = _np_mlp(a_score, np.concatenate([e, z], axis=-1))[..., 0]
            w = np.exp(s - s.max(axis=1, keepdims=True))
            w = w / w.sum(axis=1, keepdims=True)
            A_s = A[idx].reshape(-1, 4)
            y = (tau_hat.astype(np.float64) - tau_g[idx]).reshape(-1)
            for W, out in ((np.eye(A_s.shape[0]), xt), (np.diag(w.reshape(-1)), xta)):
                out.append(np.linalg.inv(A_s.T @ W @ A_s) @ A_s.T @ W @ y)
        xs_t.append(xt)
        xs_ta.append(xta)
    return np.asarray(xs_t), np.asarray(xs_ta)


def format_tables(metrics: dict) -> str:
    """Table I and Table III as plain text."""
    lines = ["Table I: mass and COM error of the released models (10 pairs x sets)", ""]
    hdr = (f"{'object':<8} {'method':<5} {'mass MAE g':>11} {'NMAE %':>8} {'NRMSE %':>8}"
           f" {'COM MAE mm':>11} {'NMAE %':>8} {'NRMSE %':>8}")
    lines += [hdr, "-" * len(hdr)]
    avg: dict[str, list] = {"T": [], "T-A": []}
    for name, e in metrics.items():
        for key in ("T", "T-A"):
            r = e[key]
            vals = [r["mass_MAE_g"], r["mass_NMAE_pct"], r["mass_NRMSE_pct"], r["com_MAE_mm"],
                    r["com_NMAE_pct"], r["com_NRMSE_pct"]]
            avg[key].append(vals)
            lines.append(f"{name:<8} {key:<5} " + " ".join(
                f"{v:>{w}.2f}" for v, w in zip(vals, (11, 8, 8, 11, 8, 8))))
    if len(metrics) > 1:
        for key in ("T", "T-A"):
            vals = np.mean(avg[key], axis=0)
            lines.append(f"{'average':<8} {key:<5} " + " ".join(
                f"{v:>{w}.2f}" for v, w in zip(vals, (11, 8, 8, 11, 8, 8))))
    lines += ["", "Table III: mean attention weight per joint", ""]
    n = len(next(iter(metrics.values()))["mean_attention_weight"])
    lines.append(f"{'object':<8} " + " ".join(f"{'joint ' + str(j + 1):>9}" for j in range(n)))
    for name, e in metrics.items():
        lines.append(f"{name:<8} " + " ".join(f"{w:>9.4f}" for w in e["mean_attention_weight"]))
    return "\n".join(lines)


def write_json(path: str | os.PathLike, metrics: dict) -> None:
    import json

    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json.dumps(metrics, indent=2) + "\n")
