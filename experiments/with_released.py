"""``models_real`` averaged with the authors' released models, from a finished run.

Reads a ``reproduce`` output folder (``tables.json``, ``folds/fit_<object>/models*``,
``models_real``), judges each fold's own models of ``models_real``'s parts on the fold's
held-out file again (as the fold did), and averages them with the released models'
estimates on the same sets at several shares of the released models: 0 is
``models_real``'s parts as the folds judged them, 1 the released models (T-A), 0.5 what
``reproduce`` writes to ``models_real_with_released`` (the share was fixed before any of
these numbers; the others are printed to show how the mean moves, not to choose one).
``--make`` also writes ``DIR/models_real_with_released`` and evaluates it on the real files
(not held out).

    python experiments/with_released.py --run DIR --lbipe-dir DIR [--make]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax

# The least squares in float64, as the command line solves them (jaxinertia.app.options):
# in float32 a GPU's TF32 products move the weighted solves by percents.
jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from jaxinertia.app.pipeline import (  # noqa: E402
    adapt_objects,
    load_real,
    released_benchmark,
    session_reference,
)
from jaxinertia.app.with_released import judge_with_released, models_with_released  # noqa: E402
from jaxinertia.checkpoints import load_models  # noqa: E402
from jaxinertia.evaluation import evaluate  # noqa: E402

SHARES = (0.0, 0.25, 0.5, 0.75, 1.0)


def fold_estimates(run: Path, folds: dict, real, strengths) -> dict:
    """fold -> (folder, strength) -> {method: (held objects, K, B, 4)}, as the folds
    judged them."""
    names = [o.name for o in real.objects]
    out = {}
    for fit_on, fold in folds["folds"].items():
        idx = [names.index(n) for n in fold["held_out"]]
        objects = [real.objects[i] for i in idx]
        sets, l_max = [real.sets[i] for i in idx], [real.l_max[i] for i in idx]
        est = {}
        for models in sorted((run / "folds" / f"fit_{fit_on}").glob("models*")):
            if not (models / "config.json").is_file():
                continue
            folder = load_models(models)
            for s in strengths:
                adapted, _ = adapt_objects(objects, session_reference(folder.config, s))
                res = evaluate(adapted, sets, pair=folder.pair, fc=folder.features,
                               l_max=l_max)
                est[(models.name, s)] = {m: np.asarray(res["estimates"][m])
                                         for m in ("T", "T-A")}
        out[fit_on] = est
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run", required=True, type=Path, help="a reproduce output folder")
    p.add_argument("--lbipe-dir", required=True)
    p.add_argument("--make", action="store_true",
                   help="also write and evaluate DIR/models_real_with_released")
    args = p.parse_args()
    tables = json.loads((args.run / "tables.json").read_text())
    folds, recipe = tables["held_out"], tables["real_finetuned"]["recipe"]
    real = load_real(args.lbipe_dir)
    strengths = sorted({float(recipe["session_strength"]),
                        float((recipe.get("com") or recipe)["session_strength"])})
    estimates = fold_estimates(args.run, folds, real, strengths)
    released = {m: np.asarray(x) for m, x in
                released_benchmark(args.lbipe_dir, real=real)["estimates"].items()}
    print("held out: T-A mass / COM NMAE [%] per fold, and the scores over the released "
          "models' (mass, COM, mean)")
    for share in SHARES:
        j = judge_with_released(folds, estimates, released, real, recipe, share)
        cells = [f"{fit} -> {held}: {r['mass_NMAE_pct']:5.2f} / {r['com_NMAE_pct']:5.2f}"
                 for fit, f in j["folds"].items() for held, r in f.items()]
        print(f"share of the released models {share:4.2f}: " + "; ".join(cells)
              + f" | {j['mass_score']:.3f} {j['com_score']:.3f} {j['score']:.3f}")
    if args.make:
        made = models_with_released(args.run, real)
        for name, o in made["objects"].items():
            print(f"{made['models']} on {name} (not held out): T-A mass "
                  f"{o['T-A']['mass_NMAE_pct']:.2f} %, COM {o['T-A']['com_NMAE_pct']:.2f} %")


if __name__ == "__main__":
    main()
