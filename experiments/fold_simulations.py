"""The held-out folds' training files on this machine: one stream per fold in threads
against every fold's streams together (issue 30 item 4).

Each fold of ``reproduce`` simulates its own training files in its calibrated simulator:
the random scenario and the planning grid (one stream), and the random scenario over the
drawn recording sessions (one stream per session). With three training draws that is six
folds, thirty streams. Until session 43 each fold simulated them in its own thread, its
two files side by side (``threads``); now the folds' streams of like shapes run as one
program each (``together``: :func:`jaxinertia.app.simdata.simulate_many`). Each mode runs
cold in its own process (no persistent compilation cache), the same simulators (the
datasheet's, each fold's a recording session drawn around it, standing in for its
calibration) and the same files; the ratio is printed against ``threads`` of the same run.

    python experiments/fold_simulations.py [--scale full|quick] [--folds 6] [--repeat 1]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from functools import partial
from pathlib import Path
from tempfile import TemporaryDirectory


def _simulate(mode: str, scale_name: str, n_folds: int) -> dict:
    import jax

    jax.config.update("jax_enable_x64", True)
    from jaxinertia.app.programs import side_by_side
    from jaxinertia.app.reproduce import FULL, QUICK
    from jaxinertia.app.simdata import FilesRequest, simulate_many
    from jaxinertia.sim.params import datasheet_sim_params
    from jaxinertia.sim.randomize import session_drawn, session_prior

    scale = FULL if scale_name == "full" else QUICK
    base = datasheet_sim_params()
    prior = session_prior(base.robot.n_joints)
    with TemporaryDirectory() as tmp:
        def requests(k: int) -> list[FilesRequest]:  # as app.folds._simulations makes them
            params = session_drawn(base, jax.random.key(100 + k), prior)
            data = Path(tmp) / f"fold{k}"
            wanted = [(data / "train_random.npz", "random", scale.random_per_load, k)]
            if scale.planning:
                wanted.append((data / "train_planning.npz", "planning", None, k))
            out = [FilesRequest(params, wanted)]
            if scale.fold_session_draws:
                out.append(FilesRequest(params, [(data / "train_random_sessions.npz",
                                                  "random", scale.random_per_load, k)],
                                        spread=prior, draws=scale.fold_session_draws))
            return out

        todo = [requests(k) for k in range(n_folds)]
        t = time.perf_counter()
        if mode == "together":
            made = simulate_many([r for rs in todo for r in rs], progress=False)
        else:  # each fold in its thread, its files side by side (reproduce before session 43)
            def alone(r):
                return simulate_many([r], progress=False, together=False)[0]

            def fold(rs):
                return side_by_side([partial(alone, r) for r in rs], len(rs))
            made = [f for one in side_by_side([partial(fold, rs) for rs in todo], len(todo))
                    for f in one]
        wall = time.perf_counter() - t
        samples = sum(len(f.samples.q) for files in made for f in files)
    return {"mode": mode, "wall_s": wall, "samples": samples,
            "device": str(jax.devices()[0].device_kind)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scale", choices=("quick", "full"), default="full")
    ap.add_argument("--folds", type=int, default=6, help="folds (default 6: three draws)")
    ap.add_argument("--repeat", type=int, default=1, help="cold runs of each mode")
    ap.add_argument("--mode", choices=("threads", "together"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.mode:  # one cold run, in this process
        print(json.dumps(_simulate(args.mode, args.scale, args.folds)))
        return
    env = {**os.environ, "JAXINERTIA_CACHE_DIR": "off"}
    runs: dict[str, list[float]] = {"threads": [], "together": []}
    for _ in range(args.repeat):
        for mode in runs:
            out = subprocess.run([sys.executable, __file__, "--mode", mode, "--scale",
                                  args.scale, "--folds", str(args.folds)], env=env,
                                 check=True, capture_output=True, text=True).stdout
            res = json.loads(out.strip().splitlines()[-1])
            runs[mode].append(res["wall_s"])
            print(f"{mode:9s} {res['wall_s']:7.1f} s  ({res['samples']} samples, "
                  f"{args.folds} folds, {res['device']})", flush=True)
    best = {m: min(v) for m, v in runs.items()}
    print(f"together / threads: {best['together'] / best['threads']:.2f} "
          f"(best of {args.repeat}: {best['together']:.1f} s against {best['threads']:.1f} s)")


if __name__ == "__main__":
    main()
