"""The servo's present current as a torque-model input, judged on the held-out folds
(issue 30, item 2: "also try the present current as an input of the torque model").

Runs the held-out folds of ``jaxinertia reproduce`` (calibrate on one real file, simulate,
train, fine-tune, judge on the other file) twice at the same scale and seed: the paper's
four inputs per joint, and with the current torque as a fifth (``train --current-input``).
Prints T and T-A mass / COM NMAE per candidate, fold and session strength, side by side.

    python experiments/current_input_folds.py --out runs/current [--scale full]
        [--compare RUN/tables.json]

``--compare``: run only the current-input folds and compare with the paper-input folds of
a ``reproduce`` run at the same scale and seed (its ``held_out``), saving one run of folds.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax

from jaxinertia import apply_xla_workarounds
from jaxinertia.app.folds import FoldScale, run_folds
from jaxinertia.app.pipeline import load_real
from jaxinertia.app.recipe import candidates
from jaxinertia.app.reproduce import FULL, QUICK
from jaxinertia.lbipe import default_lbipe_dir


def main():
    apply_xla_workarounds()  # XLA:CPU settings, before JAX starts its backend
    jax.config.update("jax_enable_x64", True)
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--scale", choices=["quick", "full"], default="quick")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--lbipe-dir", default=None)
    ap.add_argument("--compare", type=Path, default=None,
                    help="a reproduce run's tables.json: its folds are the paper-input ones")
    a = ap.parse_args()
    lbipe_dir = a.lbipe_dir or default_lbipe_dir()
    scale = FULL if a.scale == "full" else QUICK
    real = load_real(lbipe_dir, seed=a.seed, n_sets=scale.n_sets,
                     set_size=scale.train.set_size)
    results = {}
    if a.compare is not None:
        results["paper inputs"] = json.loads(a.compare.read_text())["held_out"]
    for current in (False, True):
        if not current and a.compare is not None:
            continue
        fs = FoldScale(calibration_iterations=scale.fold_calibration_iterations,
                       random_per_load=scale.random_per_load, planning=scale.planning,
                       train=scale.train.replace(current_input=current),
                       finetune_samples=scale.fold_finetune_samples)
        name = "current" if current else "paper inputs"
        results[name] = run_folds(a.out / name.replace(" ", "_"), lbipe_dir, fs, seed=a.seed,
                                  progress=False, real=real)
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "current_input_folds.json").write_text(json.dumps(results, indent=1))
    print("| fold | candidate | strength | inputs | T mass | T COM | T-A mass | T-A COM |")
    print("| --- | --- | ---: | --- | ---: | ---: | ---: | ---: |")
    base = results["paper inputs"]["folds"]
    for fit, fold in base.items():
        held = fold["held_out"][0]
        for cand, by_s in candidates(fold).items():
            for s in by_s:
                for name, res in results.items():
                    o = candidates(res["folds"][fit])[cand][s][held]
                    print(f"| {fit} -> {held} | {cand} | {s} | {name} | "
                          f"{o['T']['mass_NMAE_pct']:.2f} | {o['T']['com_NMAE_pct']:.2f} | "
                          f"{o['T-A']['mass_NMAE_pct']:.2f} | {o['T-A']['com_NMAE_pct']:.2f} |")
    for name, res in results.items():
        r = res["recipe"]
        print(f"recipe with {name}: {r['candidate']}, strength {r['session_strength']}, "
              f"score {r['score']:.3f}")


if __name__ == "__main__":
    main()
