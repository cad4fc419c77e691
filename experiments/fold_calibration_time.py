"""Where a held-out fold's calibration spends its time on this machine (issue 30 item 4).

Runs :func:`jaxinertia.app.fold_calibration.fit_simulators` (link gravity, the servo/friction fixed
point with its offsets, the held-out replay) for one fold alone, then for every fold side
by side in threads (as ``reproduce`` ran them before session 26, and still does on a CPU),
then for every fold together (each replay one program for all folds, as ``reproduce``
runs them on an accelerator), timing each part: every replay of real plans
(:func:`jaxinertia.sim.real_fit.simulate_real_plan`, or ``simulate_real_plans`` for all
folds at once) and the link-gravity fit.

    python experiments/fold_calibration_time.py --lbipe-dir DIR [--scale quick|full]
"""

from __future__ import annotations

import argparse
import threading
import time
from pathlib import Path
from tempfile import TemporaryDirectory

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import jaxinertia.app.fold_calibration as fold_calibration  # noqa: E402
import jaxinertia.app.folds as folds  # noqa: E402
import jaxinertia.sim.real_fit as real_fit  # noqa: E402
from jaxinertia.app.pipeline import load_real  # noqa: E402
from jaxinertia.app.reproduce import FULL, QUICK  # noqa: E402

_local = threading.local()


def _timed(module, name: str) -> None:
    """Wraps ``module.name`` so that each call's wall time goes to this thread's log."""
    fn = getattr(module, name)

    def wrapper(*a, **k):
        t = time.perf_counter()
        try:
            return fn(*a, **k)
        finally:
            _local.log.append((name, time.perf_counter() - t))
    setattr(module, name, wrapper)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--lbipe-dir", required=True)
    ap.add_argument("--scale", choices=("quick", "full"), default="full")
    args = ap.parse_args()
    scale = FULL if args.scale == "full" else QUICK
    real = load_real(args.lbipe_dir)
    names = [o.name for o in real.objects]
    # real_fit's functions as the fold calibration calls them (imported names).
    for name in ("simulate_real_plan", "simulate_real_plans", "fit_link_gravity"):
        _timed(real_fit, name)
        setattr(fold_calibration, name, getattr(real_fit, name))
    fscale = folds.FoldScale(calibration_iterations=scale.fold_calibration_iterations,
                             random_per_load=scale.random_per_load, planning=scale.planning,
                             train=scale.train)
    print(f"device: {jax.devices()[0].device_kind}")
    with TemporaryDirectory() as tmp:
        def fold_of(fit_on: str, tag: str):
            fold = folds.Fold(Path(tmp) / tag / f"fit_{fit_on}", fit_on,
                               [n for n in names if n != fit_on], real, fscale, 0, False)
            fold.dir.mkdir(parents=True)
            return fold

        def one(fit_on: str | list, tag: str, together: bool = False) -> str:
            _local.log = []
            todo = [fold_of(n, tag) for n in (fit_on if together else [fit_on])]
            t = time.perf_counter()
            fold_calibration.fit_simulators(todo, together=together)
            total = time.perf_counter() - t
            sims = [s for n, s in _local.log if n.startswith("simulate_real_plan")]
            grav = sum(s for n, s in _local.log if n == "fit_link_gravity")
            return (f"{tag} fit on {fit_on}: {total:.1f} s; link gravity {grav:.2f} s; "
                    f"{len(sims)} replays {sum(sims):.1f} s: {np.round(sims, 2).tolist()}")

        print(one(names[0], "alone, first (compiling)"), flush=True)
        print(one(names[0], "alone, again"), flush=True)
        out = {}
        threads = [threading.Thread(target=lambda n=n: out.__setitem__(n, one(n, "side by side")))
                   for n in names]
        t = time.perf_counter()
        for th in threads:
            th.start()
        for th in threads:
            th.join()
        print(f"side by side: {time.perf_counter() - t:.1f} s")
        for n in names:
            print(out[n])
        print(one(names, "together, first (compiling)", together=True), flush=True)
        print(one(names, "together, again", together=True), flush=True)


if __name__ == "__main__":
    main()
