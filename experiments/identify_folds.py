"""Issue "Sim-to-real I", item 2, measured: per-sample identification against the fixed-point
calibration, judged on the held-out real object's replay.

Per fold (fit on one real object): the simulator from the datasheet, link gravity and the
fixed-point servo/friction/offset calibration on that object (as ``calibrate --real-objects``
and the held-out folds do), then :func:`jaxinertia.sim.identify.identify` on the same
object's samples. Both simulators replay the *other* object's real plan (its goals,
directions, the object with its fitted tag pose); printed per joint: the PE gain error [%]
and intercept error [N mm] against the real file, and the mismatch of the discrepancy
distribution per approach direction and load tercile (the identification's own score, here
on the held-out object: lower is better, 0 = the real groups' means, spreads and currents).

    python experiments/identify_folds.py [--lbipe-dir DIR] [--population 32] \\
        [--generations 15] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from jaxinertia.lbipe import default_lbipe_dir, find_layout, test_files  # noqa: E402
from jaxinertia.sim.calibration import (  # noqa: E402
    baseline_statistics,
    calibrate_servo_friction,
    fit_link_gravity,
    real_plan,
)
from jaxinertia.sim.identify import (  # noqa: E402
    ESConfig,
    group_index,
    group_stats,
    identify,
    score,
)
from jaxinertia.sim.params import datasheet_sim_params, params_to_dict  # noqa: E402
from jaxinertia.sim.sampling import simulate_samples  # noqa: E402


def _held_out_report(params, obj, d, key) -> dict:
    """The held-out file replayed in ``params``: PE law errors and the group score."""
    rec = simulate_samples(params, obj, jnp.asarray(d.q_d), jnp.asarray(d.direction), key)
    rec = jax.tree.map(np.asarray, rec)
    ok = rec.at_rest
    sim = baseline_statistics(rec.q_d[ok], rec.q[ok], rec.direction[ok], rec.tau[ok],
                              rec.current_tau[ok])
    real = baseline_statistics(d.q_d, d.q, d.direction, d.tau, d.current_tau)
    groups = jnp.asarray(group_index(d.tau, d.direction))
    ones = jnp.ones(d.n_samples)
    qe, cur = jnp.asarray(d.q_d - d.q), jnp.asarray(d.current_tau)
    m, s = group_stats(qe, groups, ones)
    c, sc = group_stats(cur, groups, ones)
    sc_ = score(jnp.asarray(rec.q_d - rec.q), jnp.asarray(rec.current_tau),
                jnp.asarray(rec.at_rest), groups, (m, s, c, jnp.maximum(sc, 1e-3)))
    return {"k_real": real["k"].tolist(), "k_sim": sim["k"].tolist(),
            "k_error_pct": (100 * (sim["k"] / real["k"] - 1)).tolist(),
            "c_error_Nmm": (1e3 * (sim["c"] - real["c"])).tolist(),
            "pe_mae_real_Nmm": (1e3 * real["pe_mae"]).tolist(),
            "pe_mae_sim_Nmm": (1e3 * sim["pe_mae"]).tolist(),
            "group_score": float(sc_), "at_rest": float(np.mean(ok))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lbipe-dir", default=None)
    ap.add_argument("--iterations", type=int, default=6)
    ap.add_argument("--population", type=int, default=32)
    ap.add_argument("--generations", type=int, default=15)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    lbipe = args.lbipe_dir or default_lbipe_dir()
    names = [d.name for d in test_files(find_layout(lbipe))]
    print(f"backend {jax.default_backend()}, real objects {names}")
    out = {"config": vars(args), "folds": {}}
    fmt = lambda v, f="{:+.1f}": " / ".join(f.format(x) for x in v)  # noqa: E731
    rows = []
    for fit_on in names:
        held = [n for n in names if n != fit_on][0]
        t0 = time.perf_counter()
        params = datasheet_sim_params()
        robot, _ = fit_link_gravity(params.robot, lbipe, [fit_on])
        params = params.replace(robot=robot)
        params, _ = calibrate_servo_friction(params, lbipe, iterations=args.iterations,
                                             seed=args.seed, fit_offset=True,
                                             objects=[fit_on], log=lambda m: None)
        t1 = time.perf_counter()
        _, obj_fit, d_fit = real_plan(params.robot, lbipe, [fit_on])[0]
        _, obj_held, d_held = real_plan(params.robot, lbipe, [held])[0]
        key = jax.random.key(args.seed + 7)
        before = _held_out_report(params, obj_held, d_held, key)
        ident, info = identify(params, obj_fit, d_fit, config=ESConfig(
            args.population, args.generations, args.seed))
        t2 = time.perf_counter()
        after = _held_out_report(ident, obj_held, d_held, key)
        out["folds"][fit_on] = {"held_out": held, "calibrated": before, "identified": after,
                                "identification": info, "params": params_to_dict(ident),
                                "wall_s": {"calibrate": t1 - t0, "identify": t2 - t1}}
        print(f"fold {fit_on} -> {held}: calibrate {t1 - t0:.1f} s, identify {t2 - t1:.1f} s "
              f"(fit score {info['history'][0]['best']:.3f} -> {info['history'][-1]['best']:.3f})")
        for label, r in (("fixed-point calibration", before), ("+ per-sample identification",
                                                               after)):
            rows.append(f"| {fit_on} | {held} | {label} | {fmt(r['k_error_pct'])} | "
                        f"{fmt(r['c_error_Nmm'])} | {fmt(r['pe_mae_sim_Nmm'], '{:.1f}')} "
                        f"(real {fmt(r['pe_mae_real_Nmm'], '{:.1f}')}) | "
                        f"{r['group_score']:.3f} |")
    print("\n| fit on | replayed | simulator | PE gain error [%] | PE intercept error [N mm] | "
          "PE MAE [N mm] | group mismatch |\n| --- | --- | --- | --- | --- | --- | --- |")
    print("\n".join(rows))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
