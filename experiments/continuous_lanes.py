"""The continuous switching-load walk stepped as one sequence against the same walk cut
into lanes (issue 19 item 1): the statistics the paper reports (vertical-force MAE per
method, from the same trained models) and the settle behaviour must agree; prints the
wall time of each.

    python experiments/continuous_lanes.py MODELS_DIR [--n 4096] [--lanes 128]
        [--json OUT.json]

MODELS_DIR: a trained model folder (``reproduce``'s ``models``). The single sequence runs
on the host CPU (where it is fastest), the lanes on the default device.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax
import numpy as np

from jaxinertia import apply_xla_workarounds
from jaxinertia.app.reproduce import CONTINUOUS_OBJECTS
from jaxinertia.checkpoints import load_models
from jaxinertia.evaluation import continuous_force
from jaxinertia.fileio import write_json
from jaxinertia.samples import Samples
from jaxinertia.sim.continuous import simulate_continuous_run
from jaxinertia.sim.params import default_sim_params

TICK = 2 * np.pi / 4096


def main() -> None:
    apply_xla_workarounds()  # XLA:CPU settings, before JAX starts its backend
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("models", type=Path)
    ap.add_argument("--n", type=int, default=4096)
    ap.add_argument("--switch-every", type=int, default=1024)
    ap.add_argument("--lanes", type=int, default=128)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    jax.config.update("jax_enable_x64", True)
    params = default_sim_params()
    folder = load_models(args.models)
    pair, baselines, fc = folder.pair, folder.baselines, folder.features
    kw = dict(n=args.n, objects=CONTINUOUS_OBJECTS, switch_every=args.switch_every, seed=0,
              progress=False)
    runs = {}
    for name, lanes, device in (("single", 1, jax.devices("cpu")[0]),
                                ("lanes", args.lanes, jax.devices()[0])):
        with jax.default_device(device):
            t = time.perf_counter()
            fields, meta = simulate_continuous_run(params, lanes=lanes, **kw)
            wall = time.perf_counter() - t
        run = Samples.from_fields(fields, meta["objects"], need_truth=True)
        res = continuous_force(run, pair, baselines, fc)
        runs[name] = {"lanes": lanes, "device": str(device), "wall_s": wall,
                      "at_rest_fraction": float(np.mean(fields["at_rest"])),
                      "MAE_N": {m: v["MAE_N"] for m, v in res["methods"].items()},
                      "fields": fields}
        print(f"{name:6s} ({lanes} lanes, {device}): {wall:6.1f} s; at rest after the dwell "
              f"{runs[name]['at_rest_fraction']:.3f}; force MAE "
              + ", ".join(f"{m} {v:.3f} N" for m, v in runs[name]["MAE_N"].items()),
              flush=True)
    a, b = runs["single"]["fields"], runs["lanes"]["fields"]
    dq = np.abs(a["q_true"] - b["q_true"]).max(axis=1) / TICK
    flips = np.mean(np.any(a["q"] != b["q"], axis=1))
    dc = np.abs(a["current_tau"] - b["current_tau"]).max(axis=1)
    diff = {"q_true_max_ticks": float(dq.max()), "q_true_median_ticks": float(np.median(dq)),
            "samples_with_a_tick_flip": float(flips),
            "current_tau_max_Nm": float(dc.max()),
            "ratio_single_over_lanes_wall": runs["single"]["wall_s"] / runs["lanes"]["wall_s"]}
    print(f"per sample, lanes - single: true position max {dq.max():.3f} ticks (median "
          f"{np.median(dq):.4f}); a reading differs in {100 * flips:.1f} % of samples; "
          f"wall single / lanes = {diff['ratio_single_over_lanes_wall']:.1f}x")
    if args.json:
        write_json(args.json, {"machine": str(jax.devices()[0]), "n": args.n, "difference": diff,
                               **{k: {kk: vv for kk, vv in v.items() if kk != "fields"}
                                  for k, v in runs.items()}})


if __name__ == "__main__":
    main()
