"""How long one servo period of the stream takes, and why (issue 30 item 4: a held-out
fold's calibration replays its real file's plan a dozen times, latency-bound).

Replays the cube's real plan (1,000 samples, one round of lanes on an accelerator) with the
datasheet simulator: the first call (compiling) and the median of the next ``--rounds``;
the number of servo periods stepped (the longest sample's two phases), the time per
period, and what the compiled stepping program holds (kernels of its loop body: fusions,
custom calls; loops). Run it under different ``XLA_FLAGS`` to compare.

    python experiments/step_latency.py --lbipe-dir DIR [--rounds 3] [--lanes L]
"""

from __future__ import annotations

import argparse
import os
import re
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from stream_lanes import cube_plan  # noqa: E402  (experiments/, this script's folder)

from jaxinertia.sim.run import run_plans  # noqa: E402
from jaxinertia.sim.stream import StreamPrograms  # noqa: E402


def _program_summary(programs: StreamPrograms, dump: str | None = None) -> str:
    """Counts in the compiled stepping programs' text (written to ``dump`` when given)."""
    out = []
    for key, fut in programs._programs.items():
        if key[0] != "steps" or not fut.done() or fut.exception() is not None:
            continue
        text = fut.result().as_text()
        if dump:
            with open(dump, "w") as f:
                f.write(text)
        fusions = len(re.findall(r"= [^\n]*\bfusion\(", text))
        calls = len(re.findall(r"custom-call\(", text))
        loops = len(re.findall(r"\bwhile\(", text))
        conds = len(re.findall(r"\bconditional\(", text))
        out.append(f"steps program: {fusions} fusion calls, {calls} custom calls, "
                   f"{loops} loops, {conds} conditionals, {len(text)} chars")
    return "; ".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--lbipe-dir", required=True)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--lanes", type=int, default=None)
    ap.add_argument("--dump", default=None, help="write the compiled stepping program here")
    args = ap.parse_args()
    params, name, d, request = cube_plan(args.lbipe_dir)
    print(f"device: {jax.devices()[0].device_kind}; XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r}")
    with StreamPrograms() as programs:
        times = []
        for _ in range(args.rounds + 1):
            t = time.perf_counter()
            out = run_plans(params, request, lanes=args.lanes, programs=programs,
                            progress=False)[0]
            times.append(time.perf_counter() - t)
        summary = _program_summary(programs, args.dump)
    med = float(np.median(times[1:]))
    settle = np.asarray(out["settle_time"])
    print(f"{name}'s plan, {d.n_samples} samples: first call {times[0]:.2f} s, then {med:.3f} s "
          f"(rounds {np.round(times[1:], 3)}); longest settle {settle.max():.3f} s, "
          f"median {np.median(settle):.3f} s")
    print(summary)
    print(f"digest of q: {float(np.sum(np.asarray(out['q']) * np.arange(1, 5))):.12e}")


if __name__ == "__main__":
    main()
