"""Do the folds' candidates, averaged, beat the best one? (issue 30, the mass part's near tie)

Reads a finished ``reproduce`` run (its ``folds/fit_<object>/models*`` folders) and judges,
on each fold's held-out file over the same 1000 sets, every candidate folder at each
session strength, then estimators made of several of them, per set:

* ``pairs averaged``: one candidate, its K model pairs' estimates averaged per set (what
  ``estimate`` answers) instead of pooled (the paper's protocol, the tables' numbers);
* ``mean`` / ``median`` of all candidates (and strengths): per model pair k and set, of the
  candidates' ``x`` (pooled over the K pairs like a single candidate, so the pairs' own
  averaging is not counted as the ensemble's gain): no choice at all, so nothing is tuned
  on the file it is judged on;
* ``top k by the other fold``: the k candidates that scored best on the *other* fold's
  held-out file, averaged: a choice judged on a file it did not see;
* (session 39) ``trimmed mean`` (the two lowest and highest masses per pair and set left
  out), ``inverse-variance weights`` (each candidate weighted by the inverse of its mass's
  variance over the sets of the file itself: no truth needed) and ``mean of the starts``
  (each from-scratch start with its fine-tunings averaged first, then the starts).

    python experiments/candidate_ensemble.py --run DIR --lbipe-dir DIR [--out results.json]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from jaxinertia.app.pipeline import adapt_objects, load_real, session_reference  # noqa: E402
from jaxinertia.checkpoints import load_models  # noqa: E402
from jaxinertia.evaluation import evaluate  # noqa: E402
from jaxinertia.metrics import inertial_metrics  # noqa: E402

STRENGTHS = (0.0, 1.0)
METHODS = ("T", "T-A")


def _metrics(x: np.ndarray, obj, l_max: float) -> tuple[float, float, float]:
    """T-A style mass and COM NMAE [%] of estimates ``x`` (..., 4), and the mass's bias [%]
    (mean signed error over the true mass)."""
    x = x.reshape(-1, 4)
    x = x[np.all(np.isfinite(x), axis=-1)]
    m = inertial_metrics(x, obj.x[0], l_max)
    bias = 100 * float(np.mean(x[:, 0] - obj.x[0, 0]) / obj.x[0, 0])
    return m["mass_NMAE_pct"], m["com_NMAE_pct"], bias


def _trimmed_mean(xs: np.ndarray, axis: int = 0, cut: int = 2) -> np.ndarray:
    """The mean over ``axis`` (the candidates) with ``cut`` candidates of the lowest and of
    the highest mass left out per pair and set (all four components of the same ones)."""
    order = np.argsort(xs[..., 0], axis=axis)[cut:-cut]
    return np.nanmean(np.take_along_axis(xs, order[..., None], axis=axis), axis=axis)


def _inverse_variance_mean(xs: np.ndarray, axis: int = 0) -> np.ndarray:
    """The candidates' weighted mean, each weighted by the inverse of its mass's variance
    over every pair and set of the file (what the file alone tells, no truth)."""
    var = np.nanvar(xs[..., 0].reshape(xs.shape[0], -1), axis=1)
    w = (1.0 / var) / np.sum(1.0 / var)
    return np.tensordot(w, xs, axes=(0, axis))


def _starts(names: list[str]) -> dict[str, list[str]]:
    """The candidate folders grouped by the start they were trained or fine-tuned from
    (``models``: the paper network; ``models_physical[_current[_sessions]]`` and their
    ``models_finetuned[_current[_sessions]]_N``); empty when a folder fits no group."""
    groups: dict[str, list[str]] = {}
    for n in names:
        rest = n.removeprefix("models_physical").removeprefix("models_finetuned")
        key = "paper" if n == "models" else (
            "physical" + rest.rstrip("0123456789").rstrip("_") if rest != n else n)
        groups.setdefault(key, []).append(n)
    return groups if len(groups) > 1 else {}


def folder_evaluations(fold_dir: Path, objects, sets, l_max, strengths=STRENGTHS):
    """Every model folder of a fold on ``objects`` at each session strength: yields
    ``(folder name, strength, evaluate's result)``."""
    for models in sorted(fold_dir.glob("models*")):
        if not (models / "config.json").is_file():
            continue
        folder = load_models(models)
        for s in strengths:
            adapted, _ = adapt_objects(objects, session_reference(folder.config, s))
            yield models.name, s, evaluate(adapted, sets, pair=folder.pair, baselines=None,
                                           fc=folder.features, l_max=l_max)


def judge_fold(fold_dir: Path, real, held: list[str]) -> dict:
    """Per (folder, strength, method, held object): the estimates (K, B, 4)."""
    idx = [[o.name for o in real.objects].index(n) for n in held]
    objects = [real.objects[i] for i in idx]
    sets = [real.sets[i] for i in idx]
    l_max = [real.l_max[i] for i in idx]
    out = {}
    for name, s, res in folder_evaluations(fold_dir, objects, sets, l_max):
        for m in METHODS:
            for o, obj in enumerate(objects):
                out[(name, s, m, obj.name)] = np.asarray(res["estimates"][m][o])
    return {"estimates": out, "objects": objects, "l_max": l_max}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run", required=True, help="a reproduce output folder (with folds/)")
    p.add_argument("--lbipe-dir", required=True)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--top", type=int, nargs="+", default=[2, 3, 5])
    p.add_argument("--out", default=None, help="write the numbers as JSON here")
    a = p.parse_args()

    real = load_real(a.lbipe_dir, seed=a.seed)
    names = [o.name for o in real.objects]
    folds = {}
    for fit_on in names:
        held = [n for n in names if n != fit_on]
        folds[fit_on] = judge_fold(Path(a.run) / "folds" / f"fit_{fit_on}", real, held)

    rows = []  # (fold, estimator, method, object, mass, com, mass bias)
    singles = {}  # (fold, folder, s, method) -> (mass, com) mean over held objects
    for fit_on, f in folds.items():
        est = f["estimates"]
        for o, obj in enumerate(f["objects"]):
            for m in METHODS:
                keys = [k for k in est if k[2] == m and k[3] == obj.name]
                avg = {}
                for k in keys:
                    pooled = _metrics(est[k], obj, f["l_max"][o])
                    avg[k] = est[k]  # (K, B, 4)
                    pa = _metrics(np.nanmean(est[k], axis=0), obj, f["l_max"][o])
                    rows.append((fit_on, f"{k[0]} @{k[1]:g}", m, obj.name, *pooled))
                    rows.append((fit_on, f"{k[0]} @{k[1]:g} pairs averaged", m, obj.name, *pa))
                    singles[(fit_on, k[0], k[1], m)] = pooled
                for s_sel, label in ((None, "all strengths"), (0.0, "@0"), (1.0, "@1")):
                    xs = np.stack([v for k, v in avg.items() if s_sel is None or k[1] == s_sel])
                    for how, fn in (("mean", np.nanmean), ("median", np.nanmedian),
                                    ("trimmed mean", _trimmed_mean),
                                    ("inverse-variance weights", _inverse_variance_mean)):
                        if how == "trimmed mean" and len(xs) < 5:  # (2 + 2 left out)
                            continue
                        rows.append((fit_on, f"{how} of all candidates, {label}", m, obj.name,
                                     *_metrics(fn(xs, axis=0), obj, f["l_max"][o])))
                    # (per strength: a start's folders at one strength each)
                    starts = {} if s_sel is None else _starts(
                        [k[0] for k in avg if k[1] == s_sel])
                    if starts:
                        by = {k[0]: v for k, v in avg.items() if k[1] == s_sel}
                        x = np.nanmean([np.nanmean([by[n] for n in ns], axis=0)
                                        for ns in starts.values()], axis=0)
                        rows.append((fit_on, f"mean of the starts, {label}", m, obj.name,
                                     *_metrics(x, obj, f["l_max"][o])))
    # top k chosen on the other fold (two folds: each judges the other's choice)
    for fit_on, f in folds.items():
        other = [n for n in folds if n != fit_on]
        for m in METHODS:
            ranked = sorted(((k[1], k[2]) for k in singles if k[0] in other and k[3] == m),
                            key=lambda c: np.mean([singles[(o, c[0], c[1], m)]
                                                   for o in other], axis=0)[0])
            ranked = list(dict.fromkeys(ranked))
            for o, obj in enumerate(f["objects"]):
                for k_top in a.top:
                    chosen = ranked[:k_top]
                    xs = np.stack([f["estimates"][(c[0], c[1], m, obj.name)] for c in chosen])
                    rows.append((fit_on, f"mean of top {k_top} by the other fold's mass", m,
                                 obj.name, *_metrics(np.nanmean(xs, axis=0), obj,
                                                     f["l_max"][o])))
    for fit_on, label, m, obj, mass, com, bias in rows:
        print(f"fit {fit_on:6s} judge {obj:6s} {m:4s} {label:62s} mass {mass:6.2f} "
              f"(bias {bias:+7.2f})  COM {com:6.2f}")
    if a.out:
        Path(a.out).write_text(json.dumps(
            [dict(zip(("fit_on", "estimator", "method", "object", "mass_NMAE_pct",
                       "com_NMAE_pct", "mass_bias_pct"), r)) for r in rows], indent=1))


if __name__ == "__main__":
    main()
