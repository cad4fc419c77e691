"""The simulated Present Current with and without the real files' dead band (session 39).

As a held-out fold fits its simulator (from the datasheet, on one real file alone: link
gravity, then servo, friction and the joint torques), once with a linear current reading
and once with the reading's dead band (``fit_servo_friction(dead_band=True)``); then both
real files' plans replayed in each. Per file: the share of samples whose current reads
exactly 0, the current gain of the baseline fit (``tau ~ a current - s f + c``) and the PE
gain ``k``, real against simulated, and the fitted torque constants.

    python experiments/dead_band_replay.py [--lbipe-dir DIR] [--fit-on cube]
"""

from __future__ import annotations

import argparse
import time

import jax
import numpy as np

from jaxinertia.app.options import enable_x64
from jaxinertia.lbipe import default_lbipe_dir
from jaxinertia.sim.params import datasheet_sim_params
from jaxinertia.sim.real_fit import (
    baseline_statistics,
    fit_link_gravity,
    fit_servo_friction,
    real_files,
    real_plan,
    simulate_real_plan,
)

FIELDS = ("q_d", "q", "direction", "tau", "current_tau")


def _row(label: str, values) -> str:
    return f"    {label:28s} " + " / ".join(f"{v:6.3f}" for v in np.asarray(values))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--lbipe-dir", default=None)
    ap.add_argument("--fit-on", default="cube", help="the real file the simulator is fitted on")
    args = ap.parse_args()
    enable_x64()
    data = real_files(args.lbipe_dir or default_lbipe_dir())
    fit = [d for d in data if d.name == args.fit_on]
    real = {d.name: baseline_statistics(*(getattr(d, k) for k in FIELDS)) for d in data}
    for band in (False, True):
        t = time.perf_counter()
        start = datasheet_sim_params()
        robot, _ = fit_link_gravity(start.robot, fit)
        params, _ = fit_servo_friction(start.replace(robot=robot), fit, fit_offset=True,
                                       dead_band=band, log=lambda m: None)
        sim = simulate_real_plan(params, real_plan(params.robot, data), jax.random.key(7))
        print(f"fit on {args.fit_on}, reading {'with the dead band' if band else 'linear'} "
              f"({time.perf_counter() - t:.0f} s): band "
              f"{np.round(np.asarray(params.servo.current_dead_band), 2)} ticks, torque "
              f"constant {np.round(np.asarray(params.servo.torque_constant), 2)} N m/A")
        start_row = 0
        for d in data:
            rows = slice(start_row, start_row + d.n_samples)
            start_row += d.n_samples
            st = baseline_statistics(*(sim[k][rows] for k in FIELDS))
            print(f"  {d.name}" + (" (the fit's)" if d.name == args.fit_on else ""))
            print(_row("current reads 0, real", np.mean(d.current_tau == 0, axis=0)))
            print(_row("current reads 0, simulated", np.mean(sim["current_tau"][rows] == 0,
                                                             axis=0)))
            print(_row("current gain, real", real[d.name]["gain"]))
            print(_row("current gain, simulated", st["gain"]))
            print(_row("PE gain k [N m/rad], real", real[d.name]["k"]))
            print(_row("PE gain k, simulated", st["k"]))


if __name__ == "__main__":
    main()
