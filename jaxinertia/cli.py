"""Command line: ``jaxinertia <command> ...``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

__all__ = ["main"]


def _enable_x64():
    # Identification is float64 (see jaxinertia.identification); networks stay float32.
    import jax

    jax.config.update("jax_enable_x64", True)


def _parse_l_max(items: list[str]) -> dict[str, float]:
    out = {}
    for item in items or []:
        name, sep, value = item.partition("=")
        try:
            metres = float(value)
        except ValueError:
            metres = float("nan")
        if not sep or not name or not metres > 0:
            raise SystemExit(f"jaxinertia: --l-max expects NAME=METRES (positive), got {item!r}")
        out[name] = metres
    return out


def cmd_lbipe_benchmark(args) -> int:
    _enable_x64()
    from jaxinertia.lbipe import LbipeFormatError
    from jaxinertia.lbipe_benchmark import format_tables, run_lbipe_benchmark, write_json
    from jaxinertia.networks import WeightsError

    try:
        res = run_lbipe_benchmark(args.lbipe_dir, seed=args.seed, l_max=_parse_l_max(args.l_max))
    except (LbipeFormatError, WeightsError, ValueError) as e:
        print(f"jaxinertia lbipe-benchmark: error: {e}", file=sys.stderr)
        return 2
    print(format_tables(res["metrics"]))
    print()
    for name, src in res["set_source"].items():
        diag = res["diagnostics"][name]
        flags = ", ".join(
            f"{k}: {d['rank_deficient']} rank-deficient, {d['ill_conditioned']} ill-conditioned "
            f"of {d['n_solves']} (max cond {d['max_condition']:.1f})"
            for k, d in diag.items()
        )
        print(f"{name}: sets from {src}; {flags}")
    t = res["timing_s"]
    print(f"load {t['load']:.2f} s, batched evaluation incl. compilation "
          f"{t['evaluate_incl_compile']:.2f} s")
    if args.json:
        write_json(args.json, res["metrics"])
        print(f"wrote {args.json}")
    if args.plot:
        from jaxinertia.plots import plot_lbipe_estimates

        plot_lbipe_estimates(res, args.plot)
        print(f"wrote {args.plot}")
    return 0


def cmd_simulate(args) -> int:
    _enable_x64()
    import numpy as np

    from jaxinertia import __version__
    from jaxinertia.datasets import save_lbipe, save_native
    from jaxinertia.sim.run import default_sim_params, native_fields, simulate_scenario

    if args.scenario == "continuous":
        print("jaxinertia simulate: error: the continuous scenario is not implemented yet "
              "(issue 3)", file=sys.stderr)
        return 2
    params = default_sim_params(args.calibration)
    try:
        results = simulate_scenario(params, args.scenario, n=args.n, objects=args.objects,
                                    seed=args.seed)
    except ValueError as e:
        print(f"jaxinertia simulate: error: {e}", file=sys.stderr)
        return 2
    for name, (_, r) in results.items():
        bad = int(np.sum(~r["at_rest"]))
        if bad:
            print(f"{name}: {bad} of {len(r['q'])} samples timed out (flagged: at_rest = False)")
    out = args.out
    if args.format == "lbipe":
        split = "test" if args.scenario == "test" else "train"
        for name, (obj, r) in results.items():
            keep = r["at_rest"]
            path = save_lbipe(out, split, name, {k: v[keep] for k, v in r.items()},
                              np.asarray(obj.x))
            print(f"wrote {path} ({int(keep.sum())} samples)")
        return 0
    fields, meta = native_fields(results, params, scenario=args.scenario, seed=args.seed,
                                 version=__version__)
    path = save_native(out, fields, meta)
    print(f"wrote {path} ({len(fields['q'])} samples)")
    return 0


def cmd_calibrate(args) -> int:
    _enable_x64()
    import json

    import numpy as np

    from jaxinertia.lbipe import LbipeFormatError
    from jaxinertia.plots import plot_calibration
    from jaxinertia.robot import data_path
    from jaxinertia.sim.calibration import (
        SIM_CALIBRATION_FILE,
        baseline_statistics,
        calibrate_servo_friction,
        fit_link_gravity,
        params_to_dict,
    )
    from jaxinertia.sim.run import default_sim_params

    try:
        params = default_sim_params(args.start)
        robot, gravity_info = fit_link_gravity(params.robot, args.lbipe_dir)
        params = params.replace(robot=robot)
        params, info = calibrate_servo_friction(params, args.lbipe_dir,
                                                iterations=args.iterations, seed=args.seed,
                                                kinetic_ratio=args.kinetic_ratio,
                                                fit_offset=args.fit_offset, progress=True)
    except LbipeFormatError as e:
        print(f"jaxinertia calibrate: error: {e}", file=sys.stderr)
        return 2
    out = args.out or data_path(SIM_CALIBRATION_FILE)
    payload = {"robot": "open_manipulator_x", "link_gravity": gravity_info,
               "servo_friction": params_to_dict(params),
               "fit": {"iterations": args.iterations, "seed": args.seed, "real": info["real"],
                       "final_sim": info["history"][-1]["sim"]}}
    Path(out).write_text(json.dumps(payload, indent=2) + "\n")
    print(f"wrote {out}")
    report = args.report
    report.mkdir(parents=True, exist_ok=True)
    real = {k: np.concatenate([getattr(d, k) for _, _, d in info["plans"]])
            for k in ("q_d", "q", "direction", "tau", "current_tau")}
    sim = {k: v[info["sim_samples"]["at_rest"]] for k, v in info["sim_samples"].items()}
    png = plot_calibration(real, sim, report / "calibration.png")
    st_r = baseline_statistics(*(real[k] for k in ("q_d", "q", "direction", "tau",
                                                    "current_tau")))
    st_s = baseline_statistics(*(sim[k] for k in ("q_d", "q", "direction", "tau",
                                                   "current_tau")))
    rows = [("k [N m/rad]", "k", 1, 1), ("c [N mm]", "c", 1e3, 0), ("f0 [N mm]", "f0", 1e3, 0),
            ("mu", "mu", 1, 2),
            ("PE MAE [N mm]", "pe_mae", 1e3, 0), ("current gain", "gain", 1, 2),
            ("current MAE [N mm]", "current_mae", 1e3, 0), ("max abs tau [N m]", "tau_max", 1, 3)]
    lines = ["# Simulator calibration", "", f"Real data: {args.lbipe_dir}; "
             f"{args.iterations} iterations; parameters in `{out}`.", "",
             "| statistic | joint | real | simulated | ratio |", "| --- | --- | --- | --- | --- |"]
    for label, key, scale, nd in rows:
        for j in range(len(st_r[key])):
            r, s_ = st_r[key][j] * scale, st_s[key][j] * scale
            ratio = f"{s_ / r:.2f}" if abs(r) > 1e-12 else "-"
            lines.append(f"| {label} | {j + 1} | {r:.{nd}f} | {s_:.{nd}f} | {ratio} |")
    lines += ["", f"![calibration]({png.name})", ""]
    (report / "report.md").write_text("\n".join(lines))
    print(f"wrote {report / 'report.md'} and {png}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    from jaxinertia.lbipe import default_lbipe_dir

    p = argparse.ArgumentParser(
        prog="jaxinertia",
        description="Mass and centre of mass of a held object from servo encoder discrepancies.",
    )
    sub = p.add_subparsers(dest="command", required=True)

    b = sub.add_parser(
        "lbipe-benchmark",
        help="evaluate the authors' ten released model pairs on real data (Tables I and III)",
        description="Evaluates every data/data_test_<name>.npz in DIR with the ten released "
        "model pairs (weights/*.npz|.pt or dicts/*.pt) in one batched call.",
    )
    b.add_argument("--lbipe-dir", type=Path, default=default_lbipe_dir(),
                   help="shared/lbipe layout or a checkout of ChirikjianLab/lbipe "
                   "(default: %(default)s)")
    b.add_argument("--json", type=Path, help="write the metrics here (reference_metrics schema)")
    b.add_argument("--seed", type=int, default=0,
                   help="seed of the 1000 random 64-sample sets when no golden sets exist")
    b.add_argument("--l-max", action="append", metavar="NAME=METRES",
                   help="bounding-box diagonal of an object without a built-in one")
    b.add_argument("--plot", type=Path, help="write a PNG of the per-set estimates here")
    b.set_defaults(func=cmd_lbipe_benchmark)

    s = sub.add_parser(
        "simulate",
        help="generate samples from the simulated OpenMANIPULATOR-X",
        description="planning: the 10 deg grid x 16 direction patterns x training loads; "
        "random: N random goals per training load; test: N per test object.",
    )
    s.add_argument("--scenario", required=True,
                   choices=["planning", "random", "test", "continuous"])
    s.add_argument("--out", required=True, type=Path,
                   help="native: an .npz file; lbipe: a directory for data_<split>_<obj>.npz")
    s.add_argument("--format", choices=["native", "lbipe"], default="native")
    s.add_argument("--n", type=int, help="samples per object (random/test; caps planning)")
    s.add_argument("--objects", nargs="+", help="test objects (default: all four)")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--calibration", type=Path,
                   help="simulator parameter file (default: the shipped calibration)")
    s.set_defaults(func=cmd_simulate)

    c = sub.add_parser(
        "calibrate",
        help="fit the simulator's link gravity, servo and friction to real samples",
        description="Fits link gravity to the real tau_g, then servo gain, torque constant "
        "and friction so that the simulated real plan reproduces the real baseline fits.",
    )
    c.add_argument("--lbipe-dir", type=Path, default=default_lbipe_dir())
    c.add_argument("--iterations", type=int, default=6)
    c.add_argument("--seed", type=int, default=0)
    c.add_argument("--out", type=Path,
                   help="parameter file (default: the package's data/open_manipulator_x_sim.json)")
    c.add_argument("--report", type=Path, default=Path("runs/calibration"))
    c.add_argument("--start", type=Path, help="parameter file to start from (default: shipped)")
    c.add_argument("--kinetic-ratio", type=float, default=0.6,
                   help="Coulomb (sliding) friction as a fraction of breakaway (default 0.6)")
    c.add_argument("--fit-offset", action="store_true",
                   help="also fit a constant joint torque to the PE intercepts (experimental)")
    c.set_defaults(func=cmd_calibrate)

    # Hardware (DYNAMIXEL bus, virtual robot, collection) and camera commands live with
    # their packages; each module adds its own subcommands.
    from jaxinertia.hardware import commands as hardware_commands
    from jaxinertia.vision import commands as vision_commands

    hardware_commands.register(sub)
    vision_commands.register(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
