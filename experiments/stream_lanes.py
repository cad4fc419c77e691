"""A real file's plan (1,000 samples, what a held-out fold's calibration simulates a dozen
times) streamed on as many lanes as it has samples against the accelerator's default
16,384: the first call (compiling) and the median of the next ``--rounds``, in the same
run; the recorded ticks compared. (On a CPU both are its default 256 lanes.)

    python experiments/stream_lanes.py --lbipe-dir DIR [--rounds 5]
"""

from __future__ import annotations

import argparse
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from jaxinertia.app.pipeline import load_real  # noqa: E402
from jaxinertia.sim.params import arm_sim_params  # noqa: E402
from jaxinertia.sim.real_fit import real_plan  # noqa: E402
from jaxinertia.sim.run import run_plans  # noqa: E402
from jaxinertia.sim.stream import StreamPrograms, default_lanes, stream_lanes  # noqa: E402


def cube_plan(lbipe_dir: str):
    """The shipped simulator and the first real file's plan as one ``run_plans`` request:
    ``(params, name, samples, request)``."""
    params = arm_sim_params()
    obj = load_real(lbipe_dir).objects[0]
    (name, held, d), = real_plan(params.robot, [obj])
    return params, name, d, [(held, d.q_d, d.direction, jax.random.key(0))]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--lbipe-dir", required=True)
    ap.add_argument("--rounds", type=int, default=5)
    args = ap.parse_args()
    params, name, d, request = cube_plan(args.lbipe_dir)
    print(f"device: {jax.devices()[0].device_kind}; {name}'s plan, {d.n_samples} samples")
    out, base = {}, None
    with StreamPrograms() as programs:
        for lanes in (default_lanes(), stream_lanes(d.n_samples)):
            times = []
            for _ in range(args.rounds + 1):
                t = time.perf_counter()
                out[lanes] = run_plans(params, request, lanes=lanes, programs=programs,
                                       progress=False)[0]
                times.append(time.perf_counter() - t)
            med = float(np.median(times[1:]))
            base = base or med
            print(f"{lanes} lanes: first call {times[0]:.2f} s, then {med:.3f} s "
                  f"({med / base:.2f} x)", flush=True)
    if len(out) < 2:
        return  # a CPU: both are the default
    a, b = out.values()
    same = all(np.array_equal(a[k], b[k]) for k in ("q", "at_rest", "settle_time"))
    print(f"ticks, rest flags and settle times the same: {same}")


if __name__ == "__main__":
    main()
