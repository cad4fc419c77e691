"""The simulator's commands: ``simulate`` (sample files from the simulated arm) and
``calibrate`` (the simulator fitted to real samples).

Each checks its options and outputs before any work and raises
:class:`jaxinertia.errors.JaxinertiaError` subclasses for what the user can fix;
:func:`jaxinertia.app.cli.main` prints them. JAX is imported when a command's work starts.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from jaxinertia.app.arm_options import add_arm_option, lbipe_arm_only
from jaxinertia.app.commands import LBIPE_DIR_HELP, lbipe_dir_of
from jaxinertia.app.defaults import DEFAULT_ARM
from jaxinertia.app.options import (
    check_memory,
    check_outputs,
    distinct,
    enable_x64,
    positive_int,
    seed_int,
    unit_fraction,
)
from jaxinertia.errors import UsageError
from jaxinertia.fileio import check_output

__all__ = ["register"]

#: What one simulated sample takes while it is simulated and written (the stream's lanes,
#: the per-sample results and the file's arrays), with room to spare [bytes].
SIM_BYTES_PER_SAMPLE = 4096


def cmd_simulate(args) -> int:
    distinct(args.objects, "--objects")
    # The work's modules (JAX): imported when the command runs, not for --help.
    from jaxinertia import objects as objs

    _check_simulate(args, objs)  # the options first: a refused request leaves nothing
    if args.format == "lbipe":
        split = "test" if args.scenario == "test" else "train"
        names = (args.objects or list(objs.TEST_OBJECTS) if args.scenario == "test" else
                 [objs.load_name(m) for m in objs.TRAINING_LOADS_KG])
        for name in names:
            check_output(args.out / f"data_{split}_{name}.npz", overwrite=args.overwrite)
    else:
        check_outputs(args, "--out")
    if args.precision == "float32":
        import jax  # the work's module, not for --help

        jax.config.update("jax_enable_x64", False)
    else:
        enable_x64()
    # The work's modules (JAX): imported when the command runs, not for --help.
    import numpy as np

    from jaxinertia import __version__, design, samples  # (as above)
    from jaxinertia.app.programs import stream_programs  # (as above)
    from jaxinertia.arms import get_arm  # (as above)
    from jaxinertia.sim import continuous, run  # (as above)
    from jaxinertia.sim.params import arm_sim_params  # (as above)

    arm = get_arm(args.arm)
    params = arm_sim_params(arm, args.calibration)
    if args.scenario == "continuous":
        n = args.n or 2048
        fields, meta = continuous.simulate_continuous_run(
            params, n=n, objects=args.objects or ["empty", "cube", "white", "black"],
            switch_every=args.switch_every, seed=args.seed, arm=arm,
            lanes=continuous.walk_lanes(n))  # as reproduce walks it
        meta["version"] = __version__
        data = samples.Samples.from_fields(fields, meta["objects"], need_truth=True)
        path = samples.save_native(args.out, data, meta)
        print(f"wrote {path} ({data.n_samples} samples, object switching every "
              f"{args.switch_every})")
        return 0
    plan = None
    if args.plan is not None:
        plan = design.load_plan(args.plan, arm=arm.name)
        if plan[0].shape[1] != params.robot.n_joints:
            raise UsageError(f"--plan {args.plan}: {plan[0].shape[1]} joints per pose; the "
                             f"simulated arm has {params.robot.n_joints}")
    if args.sessions is not None:
        from jaxinertia.app.simdata import simulate_files  # (as above)
        from jaxinertia.sim.randomize import session_prior  # (as above)

        (f,) = simulate_files(params, [(args.out, "random", args.n, args.seed)],
                              spread=session_prior(params.robot.n_joints),
                              draws=args.sessions, arm=arm)
        print(f"wrote {f.path} ({f.samples.n_samples} samples, {args.sessions} recording "
              "sessions drawn)")
        return 0
    results = run.simulate_scenario(params, args.scenario, n=args.n, objects=args.objects,
                                    seed=args.seed, plan=plan, arm=arm,
                                    programs=stream_programs())
    for name, (_, r) in results.items():
        bad = int(np.sum(~np.asarray(r["at_rest"], bool)))
        if bad:
            print(f"{name}: {bad} of {len(r['q'])} samples timed out (flagged: at_rest = False)")
    fields, meta = run.native_fields(results, params, scenario=args.scenario,
                                     seed=args.seed, version=__version__)
    if args.plan is not None:
        meta["plan"] = str(args.plan.resolve())
    data = samples.Samples.from_fields(fields, meta["objects"], need_truth=True)
    if args.format == "lbipe":
        kept = data.at_rest_only()
        for path, part in zip(samples.save_lbipe(args.out, split, kept), kept.by_object()):
            print(f"wrote {path} ({part.n_samples} samples)")
        return 0
    path = samples.save_native(args.out, data, meta)
    print(f"wrote {path} ({data.n_samples} samples)")
    return 0


def _check_simulate(args, objs) -> None:
    """The request's memory and the options that go together, before any work."""
    if args.sessions is not None:
        if args.scenario != "random" or args.n is None:
            raise UsageError("--sessions draws recording sessions for the random scenario: "
                             "use --scenario random with --n")
        if args.plan is not None or args.objects or args.format != "native":
            raise UsageError("--sessions simulates the training loads' random goals into one "
                             "native file: no --plan, --objects or --format lbipe")
    if args.n is not None:
        per = 1 if args.scenario == "continuous" else len(
            args.objects or (objs.TEST_OBJECTS if args.scenario == "test"
                             else objs.TRAINING_LOADS_KG))
        check_memory(args.n * per * SIM_BYTES_PER_SAMPLE,
                     f"--n {args.n} ({args.n * per} simulated samples)")
    if args.scenario == "continuous":
        if args.arm not in (None, DEFAULT_ARM):
            raise UsageError(f"--arm {args.arm}: the continuous run simulates the "
                             f"{DEFAULT_ARM} only (so far); use --scenario random, "
                             "planning or test")
        if args.plan is not None:
            raise UsageError("--plan: the continuous run walks nearby random goals; use "
                             "--scenario test (or random, planning) with a plan")
        if args.format != "native":
            raise UsageError("the continuous run is one trajectory with switching objects: "
                             "use --format native")


def cmd_calibrate(args) -> int:
    # Nothing shipped is written by a command: the fit goes where --out says (the shipped
    # data/open_manipulator_x_sim.json is replaced by hand, after review, if at all).
    distinct(args.real_objects, "--real-objects")
    lbipe_arm_only(args, "calibrate fits the simulator to")
    if args.out is None:
        raise UsageError("--out FILE.json is required: a fit is written where you say, never "
                         "over the shipped calibration (pass it to simulate --calibration)")
    check_outputs(args, "--out")
    for name in ("report.md", "calibration.png"):
        check_output(args.report / name, overwrite=args.overwrite, option="report")
    enable_x64()
    # The work's modules (JAX, matplotlib): imported when the command runs, not for --help.
    import numpy as np

    from jaxinertia.app.plots import plot_sim_fit  # (as above)
    from jaxinertia.app.programs import stream_programs  # (as above)
    from jaxinertia.app.report import sim_fit_report  # (as above)
    from jaxinertia.fileio import write_json, write_text  # (as above: light, used here only)
    from jaxinertia.sim.params import (  # (as above)
        datasheet_sim_params,
        default_sim_params,
        params_to_dict,
    )
    from jaxinertia.sim.real_fit import (  # (as above)
        fit_link_gravity,
        fit_servo_friction,
        real_files,
    )

    lbipe_dir = lbipe_dir_of(args)
    if args.real_objects and args.start is None:
        # Held out: start from the datasheet, not from the shipped fit (it saw every file).
        params = datasheet_sim_params()
    else:
        params = default_sim_params(args.start)
    data = real_files(lbipe_dir, args.real_objects)  # read once, handed to both fits
    robot, gravity_info = fit_link_gravity(params.robot, data)
    params = params.replace(robot=robot)
    params, info = fit_servo_friction(
        params, data, iterations=args.iterations, seed=args.seed,
        kinetic_ratio=args.kinetic_ratio, fit_offset=args.fit_offset, sessions=args.sessions,
        dead_band=args.dead_band, progress=True, programs=stream_programs())
    out = args.out
    payload = {"robot": "open_manipulator_x", "link_gravity": gravity_info,
               "servo_friction": params_to_dict(params),
               "fit": {"iterations": args.iterations, "seed": args.seed,
                       "fit_offset": args.fit_offset, "sessions": args.sessions,
                       "dead_band": args.dead_band,
                       "real_objects": sorted(p[0] for p in info["plans"]),
                       "start": str(args.start) if args.start else (
                           "datasheet" if args.real_objects else "shipped"),
                       "real": info["real"],
                       "final_sim": info["history"][-1]["sim"],
                       "real_sessions": info["real_sessions"]}}
    if info["sessions"] is not None:
        payload["sessions"] = {**info["sessions"],
                               "final_sim": info["history"][-1]["sessions"]}
    write_json(out, payload)
    print(f"wrote {out}")
    report = args.report
    real = {k: np.concatenate([getattr(d, k) for _, _, d in info["plans"]])
            for k in ("q_d", "q", "direction", "tau", "current_tau")}
    sim = {k: v[info["sim_samples"]["at_rest"]] for k, v in info["sim_samples"].items()}
    png = plot_sim_fit(real, sim, report / "calibration.png")
    text = sim_fit_report(real, sim, source=lbipe_dir, iterations=args.iterations,
                           parameters=out, figure=png.name)
    write_text(report / "report.md", text)
    print(f"wrote {report / 'report.md'} and {png}")
    return 0


def register(sub) -> None:
    """Adds this module's subcommands to the ``jaxinertia`` argparse subparsers."""
    s = sub.add_parser(
        "simulate",
        help="generate samples from the simulated OpenMANIPULATOR-X",
        description="planning: the 10 deg grid x 16 direction patterns x training loads; "
        "random: N random goals per training load; test: N per test object; continuous: N "
        "consecutive nearby goals without stopping, the held object switching.",
    )
    s.add_argument("--scenario", required=True,
                   choices=["planning", "random", "test", "continuous"])
    s.add_argument("--out", required=True, type=Path,
                   help="native: an .npz file; lbipe: a directory for data_<split>_<obj>.npz")
    s.add_argument("--format", choices=["native", "lbipe"], default="native")
    s.add_argument("--n", type=positive_int,
                   help="samples per object (random/test; caps planning)")
    s.add_argument("--plan", type=Path, metavar="PLAN.json",
                   help="the goals and approach directions every object visits (from "
                   "`jaxinertia plan-poses`) instead of the scenario's own; --n repeats the "
                   "plan cyclically to N samples per object (default: once)")
    s.add_argument("--objects", nargs="+",
                   help="test objects (default: all four); continuous: the switching order, "
                   "'empty' or test objects or training loads like 100g")
    s.add_argument("--switch-every", type=positive_int, default=512,
                   help="continuous: samples between object switches (default 512)")
    s.add_argument("--seed", type=seed_int, default=0)
    add_arm_option(s)
    s.add_argument("--calibration", type=Path,
                   help="simulator parameter file (default: the arm's shipped calibration; "
                   "an arm without one is simulated from its datasheet values)")
    s.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    s.add_argument("--sessions", type=positive_int, metavar="N",
                   help="random scenario: the samples drawn over N recording sessions around "
                   "the calibration (each joint's supply log-normal, 5 %% spread: current and "
                   "torque per tick scaled alike), --n / N per load from each; the file "
                   "records the spread (default: the calibration's session only)")
    s.add_argument("--precision", choices=["float64", "float32"], default="float64",
                   help="arithmetic of the simulation (default: %(default)s). float32 runs "
                   "~1.8x faster on a CPU; its random friction jitter differs, so its samples "
                   "are another draw of the same distribution (docs/benchmarks.md); the file "
                   "stores float64 either way")
    s.set_defaults(func=cmd_simulate)

    c = sub.add_parser(
        "calibrate",
        help="fit the simulator's link gravity, servo and friction to real samples",
        description="Fits link gravity to the real tau_g, then servo gain, torque constant "
        "and friction so that the simulated real plan reproduces the real baseline fits.",
    )
    c.add_argument("--lbipe-dir", type=Path, help=LBIPE_DIR_HELP)
    c.add_argument("--iterations", type=positive_int, default=6,
                   help="fixed-point iterations of the servo and friction (default 6, about "
                   "where they converge on the real files; fewer leave the fit short of it); "
                   "with --fit-offset, the constant torques' steps and a last simulation are "
                   "logged as further iterations")
    c.add_argument("--seed", type=seed_int, default=0)
    c.add_argument("--out", type=Path,
                   help="parameter file to write (.json; required): the shipped "
                   "data/open_manipulator_x_sim.json is never written by a command")
    c.add_argument("--report", type=Path, default=Path("runs/calibration"),
                   help="folder of the fit's report and plots (default runs/calibration)")
    c.add_argument("--start", type=Path, help="parameter file to start from (default: shipped)")
    c.add_argument("--overwrite", action="store_true",
                   help="replace an existing --out parameter file or --report folder")
    c.add_argument("--real-objects", nargs="+", metavar="NAME",
                   help="fit on these real objects only (held-out protocol: judge on the "
                   "others); starts from the datasheet unless --start is given "
                   "(default: every real file, starting from the shipped calibration)")
    c.add_argument("--kinetic-ratio", type=unit_fraction, default=0.6,
                   help="Coulomb (sliding) friction as a fraction of breakaway (default 0.6)")
    c.add_argument("--fit-offset", action=argparse.BooleanOptionalAction, default=True,
                   help="after the servo and friction, fit a constant torque per joint "
                   "(unmodelled loads such as cables) to the real torque intercept at the "
                   "real PE gain (default: on)")
    c.add_argument("--sessions", action=argparse.BooleanOptionalAction, default=False,
                   help="each real file its own recording session: the servo's P gain and "
                   "torque constant fitted per file, the physics shared; the file records "
                   "each session's terms and their spread (default: off, one servo for the "
                   "pooled files, as shipped: models trained on a per-session fit estimate "
                   "mass worse on the real files, docs/results.md)")
    c.add_argument("--dead-band", action=argparse.BooleanOptionalAction, default=False,
                   help="the simulated Present Current reads nothing within the real files' "
                   "dead band (per joint, where the error takes both signs; the torque is "
                   "untouched) (default: off: in the held-out folds it made the mass "
                   "worse; docs/results.md, 'The current's dead band in the simulator')")
    add_arm_option(c)
    c.set_defaults(func=cmd_calibrate)
