"""Several training draws averaged: the folds' recipe from one draw against the same recipe
with its members from every draw (issue 30; docs/results.md, "Other training draws").

Reads finished ``reproduce --full`` runs of the same tree with different ``--seed`` (their
``folds/fit_<object>/models*`` folders and ``tables.json``) and judges, on each fold's
held-out file over the same sets (the golden sets), the recipe that the folds chose in
sessions 24-41:

* the mass: every candidate of the fold averaged, T (no attention), session strength 0;
* the COM: the drawn-sessions current-input model from the simulator alone
  (``models_physical_current_sessions``), T-A (its attention), strength 1.

For each run alone, then with the members of every run averaged per model pair and set (the
way ``models_real`` averages its members), and (``--subsets``) of every subset of two or
more runs. Scores as the folds' recipe scores them: NMAE
over the released models' T-A on the same sets, the mean of both folds (mass and COM
apart). Nothing is chosen here: the recipe is fixed beforehand.

    python experiments/draws_averaged.py --runs DIR [DIR ...] --lbipe-dir DIR [--subsets]
"""

from __future__ import annotations

import argparse
import itertools
import json
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from candidate_ensemble import _metrics  # noqa: E402

from jaxinertia.app.pipeline import adapt_objects, load_real, session_reference  # noqa: E402
from jaxinertia.checkpoints import load_models  # noqa: E402
from jaxinertia.evaluation import evaluate  # noqa: E402

COM_FOLDER = "models_physical_current_sessions"


def _estimates(folder_dir: Path, real, o: int, strength: float, method: str) -> np.ndarray:
    """(K, B, 4) estimates of one folder on real object ``o`` at ``strength``."""
    folder = load_models(folder_dir)
    adapted, _ = adapt_objects([real.objects[o]], session_reference(folder.config, strength))
    res = evaluate(adapted, [real.sets[o]], pair=folder.pair, baselines=folder.baselines,
                   fc=folder.features, l_max=[real.l_max[o]])
    return np.asarray(res["estimates"][method])[0]


def _fold_parts(run: Path, fit: str, real, o: int) -> dict[str, np.ndarray]:
    """The mass part's and the COM part's (K, B, 4) estimates of one run's fold on the
    held-out object ``o``."""
    fold = run / "folds" / f"fit_{fit}"
    mass = [_estimates(f, real, o, 0.0, "T") for f in sorted(fold.glob("models*"))
            if (f / "config.json").is_file() and "randomized" not in f.name]
    return {"mass": np.mean(mass, axis=0),
            "com": _estimates(fold / COM_FOLDER, real, o, 1.0, "T-A")}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--runs", nargs="+", required=True, help="reproduce --full output folders")
    p.add_argument("--lbipe-dir", required=True)
    p.add_argument("--subsets", action="store_true",
                   help="also every subset of two or more runs, averaged")
    a = p.parse_args()
    real = load_real(a.lbipe_dir)
    names = [o.name for o in real.objects]
    runs = [Path(r) for r in a.runs]
    released = json.loads((runs[0] / "tables.json").read_text())["held_out"]["folds"]
    rows: dict[str, dict[str, list[float]]] = {}
    for fit in released:
        (held,) = [n for n in names if n != fit]
        o = names.index(held)
        ref = released[fit]["released"][held]["T-A"]
        parts = [_fold_parts(r, fit, real, o) for r in runs]
        groups = [(i,) for i in range(len(runs))] + (
            [c for n in range(2, len(runs) + 1) for c in itertools.combinations(
                range(len(runs)), n)] if a.subsets else [tuple(range(len(runs)))])
        for g in groups:
            label = " + ".join(runs[i].name for i in g)
            x = {k: np.mean([parts[i][k] for i in g], axis=0) for k in ("mass", "com")}
            mass, _, bias = _metrics(x["mass"], real.objects[o], real.l_max[o])
            _, com, _ = _metrics(x["com"], real.objects[o], real.l_max[o])
            r = rows.setdefault(label, {"mass": [], "com": []})
            r["mass"].append(mass / ref["mass_NMAE_pct"])
            r["com"].append(com / ref["com_NMAE_pct"])
            print(f"fit on {fit:5s} -> {held:5s} {label:22s} mass {mass:6.2f} % "
                  f"({bias:+6.2f}) COM {com:6.2f} %")
    print("\nscore over the released models' T-A (mean of both folds): mass / COM / recipe")
    for label, r in rows.items():
        m, c = float(np.mean(r["mass"])), float(np.mean(r["com"]))
        print(f"{label:22s} {m:.4f} / {c:.4f} / {0.5 * (m + c):.4f}")


if __name__ == "__main__":
    main()
