"""Issue "Sim-to-real I", item 2, measured: per-sample identification against the fixed-point
calibration, judged on the held-out real object's replay.

Per fold (fit on one real object): the simulator from the datasheet, link gravity and the
fixed-point servo/friction/offset calibration on that object (as ``calibrate --real-objects``
and the held-out folds do), then :func:`jaxinertia.sim.identify.identify` on the same
object's samples. Both simulators replay the *other* object's real plan (its goals,
directions, the object with its fitted tag pose); printed per joint: the PE gain error [%]
and intercept error [N mm] against the real file, and the mismatch of the discrepancy
distribution per approach direction and load tercile (the identification's own score, here
on the held-out object: lower is better, 0 = the real groups' discrepancy lines, scatter
and currents).

    python experiments/identify_folds.py [--lbipe-dir DIR] [--population 32] \\
        [--generations 15] [--json OUT]

With ``--train quick|full DIR``: instead, the held-out folds (``reproduce``'s settings at that
scale, no fine-tuning) end to end with the identified simulator and without it, both into
DIR, and their held-out Table I (NMAE) beside the released models.
"""

from __future__ import annotations

import argparse
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from jaxinertia import apply_xla_workarounds  # noqa: E402
from jaxinertia.fileio import write_json  # noqa: E402
from jaxinertia.lbipe import default_lbipe_dir, find_layout, load_test_files  # noqa: E402
from jaxinertia.sim.identify import (  # noqa: E402
    ESConfig,
    group_index,
    identify,
    score,
    target_of,
)
from jaxinertia.sim.params import datasheet_sim_params, params_to_dict  # noqa: E402
from jaxinertia.sim.real_fit import (  # noqa: E402
    baseline_statistics,
    fit_link_gravity,
    fit_servo_friction,
    real_files,
    real_plan,
)
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
    target = target_of(jnp.asarray(d.q_d - d.q), jnp.asarray(d.current_tau),
                       jnp.asarray(d.tau), groups)
    sc_ = score(jnp.asarray(rec.q_d - rec.q), jnp.asarray(rec.current_tau),
                jnp.asarray(rec.tau), jnp.asarray(rec.at_rest), groups, target)
    return {"k_real": real["k"].tolist(), "k_sim": sim["k"].tolist(),
            "k_error_pct": (100 * (sim["k"] / real["k"] - 1)).tolist(),
            "c_error_Nmm": (1e3 * (sim["c"] - real["c"])).tolist(),
            "pe_mae_real_Nmm": (1e3 * real["pe_mae"]).tolist(),
            "pe_mae_sim_Nmm": (1e3 * sim["pe_mae"]).tolist(),
            "group_score": float(sc_), "at_rest": float(np.mean(ok))}


def train_folds(args) -> None:
    """The held-out folds trained on the identified simulator and on the calibrated one."""
    from pathlib import Path  # noqa: PLC0415

    from jaxinertia.app.folds import FoldScale, run_folds  # noqa: PLC0415
    from jaxinertia.app.reproduce import FULL, QUICK  # noqa: PLC0415

    scale = {"quick": QUICK, "full": FULL}[args.train[0]]
    root = Path(args.train[1])
    lbipe = args.lbipe_dir or default_lbipe_dir()
    rows = []
    runs = [("identified", args.generations), ("calibrated only", 0)]
    for label, gens in runs[:1] if args.skip_calibrated_only else runs:
        t0 = time.perf_counter()
        res = run_folds(root / label.replace(" ", "_"), lbipe, FoldScale(
            calibration_iterations=scale.fold_calibration_iterations,
            random_per_load=scale.random_per_load, planning=scale.planning, train=scale.train,
            finetune_samples=(), identify_generations=gens,
            identify_population=args.population), seed=args.seed, progress=False)
        write_json(root / f"{label.replace(' ', '_')}.json", res)
        print(f"{label}: {time.perf_counter() - t0:.0f} s "
              f"{ {k: v['wall_time_s'] for k, v in res['folds'].items()} }", flush=True)
        for fit_on, f in res["folds"].items():
            for held, per in f["ours"].items():
                for m in ("PE", "T", "T-A"):
                    e = per[m]
                    rows.append(f"| {fit_on} | {held} | {label} | {m} | "
                                f"{e['mass_NMAE_pct']:.2f} | {e['com_NMAE_pct']:.2f} |")
                for m in ("T", "T-A"):
                    e = f["released"][held][m]
                    rows.append(f"| {fit_on} | {held} | released | {m} | "
                                f"{e['mass_NMAE_pct']:.2f} | {e['com_NMAE_pct']:.2f} |")
    print("| fit on | judged on | simulator | method | mass NMAE [%] | COM NMAE [%] |\n"
          "| --- | --- | --- | --- | ---: | ---: |")
    print("\n".join(rows))


def main() -> None:
    apply_xla_workarounds()  # XLA:CPU settings, before JAX starts its backend
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lbipe-dir", default=None)
    ap.add_argument("--iterations", type=int, default=6)
    ap.add_argument("--population", type=int, default=32)
    ap.add_argument("--generations", type=int, default=15)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", default=None)
    ap.add_argument("--train", nargs=2, metavar=("SCALE", "DIR"), default=None)
    ap.add_argument("--skip-calibrated-only", action="store_true",
                    help="with --train: only the folds on the identified simulator")
    args = ap.parse_args()
    if args.train:
        return train_folds(args)
    lbipe = args.lbipe_dir or default_lbipe_dir()
    names = [d.name for d in load_test_files(find_layout(lbipe))]
    print(f"backend {jax.default_backend()}, real objects {names}")
    out = {"config": vars(args), "folds": {}}
    fmt = lambda v, f="{:+.1f}": " / ".join(f.format(x) for x in v)  # noqa: E731
    rows = []
    for fit_on in names:
        held = [n for n in names if n != fit_on][0]
        t0 = time.perf_counter()
        params = datasheet_sim_params()
        fit, other = real_files(lbipe, [fit_on]), real_files(lbipe, [held])
        robot, _ = fit_link_gravity(params.robot, fit)
        params = params.replace(robot=robot)
        params, _ = fit_servo_friction(params, fit, iterations=args.iterations,
                                             seed=args.seed, fit_offset=True,
                                             log=lambda m: None)
        t1 = time.perf_counter()
        _, obj_fit, d_fit = real_plan(params.robot, fit)[0]
        _, obj_held, d_held = real_plan(params.robot, other)[0]
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
        write_json(args.json, out)


if __name__ == "__main__":
    main()
