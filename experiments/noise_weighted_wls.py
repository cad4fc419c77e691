"""Weights the WLS by each joint's torque error on the known object, not by attention.

The attention models were trained on the simulator and weight the joints by the
simulator's torque errors; on a held-out real file every candidate's T (all joints alike)
beats its T-A on the mass (docs/results.md, "Without the attention"). Between the two sits
classical weighted least squares: each joint's rows weighted by the inverse of that
joint's torque error variance, measured on the fold's *known* real object (the file the
fold calibrated and fine-tuned on; its true torques are known). Nothing is learned and
nothing is read from the held-out file.

Reads a finished ``reproduce`` run (its ``folds/fit_<object>/models*`` folders) and judges
every candidate folder on the held-out file over the same sets, at session strength 0 and
1: ``T`` (uniform), ``T-A`` (attention), ``T-W`` (inverse error variance per joint and
model pair), and the mean of every candidate (as ``ensemble.judge_mean``) for each.

    python experiments/noise_weighted_wls.py --run DIR --lbipe-dir DIR [--out results.json]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from candidate_ensemble import STRENGTHS, _metrics, folder_evaluations  # noqa: E402

from jaxinertia.app.pipeline import load_real  # noqa: E402
from jaxinertia.identification import solve_sets  # noqa: E402

#: WLS of every model pair's sets with per-joint weights w (K, N).
_solve = jax.jit(jax.vmap(lambda A, y, w, sets: solve_sets(
    A, y, jnp.broadcast_to(w, y.shape), sets).x, in_axes=(None, 0, 0, None)))


def judge_fold(fold_dir: Path, real, fit_on: str, held: str) -> dict:
    """Per (folder, strength): {method: estimates (K, B, 4)} on ``held``, and the weights."""
    names = [o.name for o in real.objects]
    i_fit, i_held = names.index(fit_on), names.index(held)
    objects = [real.objects[i_fit], real.objects[i_held]]
    sets = [real.sets[i_fit], real.sets[i_held]]
    l_max = [real.l_max[i_fit], real.l_max[i_held]]
    out, weights = {}, {}
    for name, s, res in folder_evaluations(fold_dir, objects, sets, l_max):
        tau_hat = np.asarray(res["model_estimates"].tau_hat)  # (O, K, S, N)
        known, unknown = objects
        err = tau_hat[0, :, : known.n_samples] - known.tau[None]  # (K, S, N)
        var = np.mean(err**2, axis=1)  # (K, N)
        w = (1.0 / var) / np.mean(1.0 / var, axis=-1, keepdims=True)
        y = tau_hat[1, :, : unknown.n_samples] - unknown.tau_g[None]
        x_w = _solve(jnp.asarray(unknown.A), jnp.asarray(y), jnp.asarray(w),
                     jnp.asarray(sets[1]))
        out[(name, s)] = {"T": np.asarray(res["estimates"]["T"][1]),
                          "T-A": np.asarray(res["estimates"]["T-A"][1]),
                          "T-W": np.asarray(x_w)}
        weights[(name, s)] = w.mean(axis=0)
    return {"estimates": out, "weights": weights, "object": objects[1], "l_max": l_max[1]}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run", required=True, help="a reproduce output folder (with folds/)")
    p.add_argument("--lbipe-dir", required=True)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None, help="write the numbers as JSON here")
    a = p.parse_args()

    real = load_real(a.lbipe_dir, seed=a.seed)
    names = [o.name for o in real.objects]
    rows = []
    for fit_on in names:
        for held in (n for n in names if n != fit_on):
            f = judge_fold(Path(a.run) / "folds" / f"fit_{fit_on}", real, fit_on, held)
            obj, l_max = f["object"], f["l_max"]
            for (folder, s), est in f["estimates"].items():
                w = f["weights"][(folder, s)]
                for m, x in est.items():
                    rows.append((fit_on, held, f"{folder} @{s:g}", m,
                                 *_metrics(x, obj, l_max),
                                 " ".join(f"{v:.2f}" for v in w) if m == "T-W" else ""))
            for s in STRENGTHS:
                for m in ("T", "T-A", "T-W"):
                    xs = np.stack([e[m] for (fo, st), e in f["estimates"].items() if st == s])
                    rows.append((fit_on, held, f"mean of every candidate @{s:g}", m,
                                 *_metrics(np.nanmean(xs, axis=0), obj, l_max), ""))
    for fit_on, held, label, m, mass, com, bias, w in rows:
        print(f"fit {fit_on:6s} judge {held:6s} {label:48s} {m:4s} mass {mass:6.2f} "
              f"(bias {bias:+7.2f})  COM {com:6.2f}  {w}")
    if a.out:
        Path(a.out).write_text(json.dumps(
            [dict(zip(("fit_on", "object", "estimator", "method", "mass_NMAE_pct",
                       "com_NMAE_pct", "mass_bias_pct", "mean_weights"), r)) for r in rows],
            indent=1))


if __name__ == "__main__":
    main()
