"""The held-out folds alone, at a run's scale, without the simulated stages beside them
(issue 30, item 4): how long the folds take when they have the device to themselves.

In ``reproduce`` the folds share the device with the simulated stages (their data, the ten
paper pairs' training, the uncertainty's trainings, the switching-load run). This runs
``run_folds`` exactly as ``reproduce`` calls it (the same ``FoldScale``, seed and real
sets), nothing beside it, and prints each fold's stage times and the total: the floor that
overlap alone cannot go below.

    python experiments/folds_alone.py --lbipe-dir DIR --out DIR [--full]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax

from jaxinertia.app.folds import FoldScale, run_folds
from jaxinertia.app.options import enable_x64
from jaxinertia.app.pipeline import load_real
from jaxinertia.app.reproduce import FULL, QUICK

#: XLA's compile time in this process (every thread), and the number of programs compiled.
_compiled = [0.0, 0]


def _on_duration(name, secs, **kwargs):  # noqa: ARG001
    if name == "/jax/core/compile/backend_compile_duration":
        _compiled[0] += secs
        _compiled[1] += 1


def fold_scale(scale) -> FoldScale:
    """The ``FoldScale`` that ``reproduce`` gives ``run_folds`` at ``scale``."""
    return FoldScale(calibration_iterations=scale.fold_calibration_iterations,
                     random_per_load=scale.random_per_load, planning=scale.planning,
                     train=scale.train, finetune_samples=scale.fold_finetune_samples,
                     current_input=scale.fold_current_input,
                     session_draws=scale.fold_session_draws)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--lbipe-dir", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--full", action="store_true", help="the paper's scale (default: quick)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    enable_x64()  # as the command line: float64 statics and least squares (before session 39
    #               this script ran them in float32, unlike `reproduce`)
    jax.monitoring.register_event_duration_secs_listener(_on_duration)
    scale = FULL if args.full else QUICK
    real = load_real(args.lbipe_dir, seed=args.seed, n_sets=scale.n_sets)
    t = time.perf_counter()
    res = run_folds(Path(args.out), args.lbipe_dir, fold_scale(scale), seed=args.seed,
                    progress=False, real=real)
    wall = time.perf_counter() - t
    print(f"held-out folds alone: {wall:.1f} s, of it XLA compiling {_compiled[0]:.1f} s "
          f"({_compiled[1]} programs, summed over threads)")
    for name, fold in res["folds"].items():
        print(f"  fit on {name}: " + ", ".join(f"{k} {v:.1f} s"
                                               for k, v in fold["wall_time_s"].items()))
    parts = res["recipe"].get("by_part") or {}
    print("recipe:", json.dumps({k: v if not isinstance(v, dict) else
                                 {"candidate": v.get("candidate"), "score": v.get("score")}
                                 for k, v in parts.items()}))


if __name__ == "__main__":
    main()
