"""The paper's commands: ``lbipe-benchmark``, ``simulate``, ``calibrate``, ``train``,
``evaluate`` and ``reproduce`` (``estimate`` and ``plan-poses`` are in
:mod:`jaxinertia.app.estimate_commands`).

Each is a short function over :mod:`jaxinertia.app.pipeline` that checks its options and
outputs before any work and raises :class:`jaxinertia.errors.JaxinertiaError` subclasses
for what the user can fix; :func:`jaxinertia.app.cli.main` prints them.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import jax
import numpy as np

from jaxinertia import __version__
from jaxinertia.app.arm_options import add_arm_option, arm_name, arm_of, lbipe_arm_only
from jaxinertia.app.options import (
    check_outputs,
    distinct,
    enable_x64,
    fraction,
    nonnegative_float,
    positive_float,
    positive_int,
    unit_fraction,
    write_json_option,
)
from jaxinertia.app.pipeline import (
    evaluate_samples,
    released_benchmark,
    sim_to_real,
    train,
)
from jaxinertia.app.plots import plot_calibration, plot_lbipe_estimates
from jaxinertia.app.report import calibration_report, table1, table2, table3
from jaxinertia.app.reproduce import reproduce
from jaxinertia.arms import DEFAULT_ARM, get_arm
from jaxinertia.design import load_plan
from jaxinertia.errors import UsageError
from jaxinertia.fileio import check_output, write_json, write_text
from jaxinertia.lbipe import default_lbipe_dir
from jaxinertia.objects import TEST_OBJECTS, TRAINING_LOADS_KG, load_name
from jaxinertia.open_manipulator_x import CALIBRATION_FILE
from jaxinertia.robot import data_path
from jaxinertia.samples import Samples, save_lbipe, save_native
from jaxinertia.sim import params as sim_params
from jaxinertia.sim import run as sim_run
from jaxinertia.sim.calibration import calibrate_servo_friction, fit_link_gravity
from jaxinertia.sim.continuous import simulate_continuous_run
from jaxinertia.training import FINETUNE_DEFAULTS, TrainConfig

__all__ = ["register"]


def _parse_l_max(items: list[str]) -> dict[str, float]:
    out = {}
    for item in items or []:
        name, sep, value = item.partition("=")
        try:
            metres = float(value)
        except ValueError:
            metres = float("nan")
        if not sep or not name or not metres > 0:
            raise UsageError(f"--l-max expects NAME=METRES (positive), got {item!r}")
        out[name] = metres
    return out


def cmd_lbipe_benchmark(args) -> int:
    enable_x64()
    check_outputs(args, "--json", "--plot")
    res = released_benchmark(args.lbipe_dir, seed=args.seed, l_max=_parse_l_max(args.l_max))
    objects = res["objects"]
    print(table1(objects, "Table I: mass and COM error of the released models (10 pairs x "
                 "sets)", style="text", methods=("T", "T-A")))
    print()
    print(table3(objects, "Table III: mean attention weight per joint", style="text"))
    print()
    for name, src in res["set_source"].items():
        flags = ", ".join(
            f"{k}: {d['rank_deficient']} rank-deficient, {d['ill_conditioned']} ill-conditioned "
            f"of {d['n_solves']} (max cond {d['max_condition']:.1f})"
            for k, d in res["diagnostics"][name].items())
        print(f"{name}: sets from {src}; {flags}")
    t = res["timing_s"]
    print(f"load {t['load']:.2f} s, batched evaluation incl. compilation "
          f"{t['evaluate_incl_compile']:.2f} s")
    write_json_option(args, objects)
    if args.plot:
        plot_lbipe_estimates(res["real"].objects, res["estimates"], args.plot)
        print(f"wrote {args.plot}")
    return 0


def cmd_simulate(args) -> int:
    if args.precision == "float32":
        jax.config.update("jax_enable_x64", False)
    else:
        enable_x64()
    distinct(args.objects, "--objects")
    if args.format == "lbipe":
        split = "test" if args.scenario == "test" else "train"
        names = (args.objects or list(TEST_OBJECTS) if args.scenario == "test" else
                 [load_name(m) for m in TRAINING_LOADS_KG])
        for name in names:
            check_output(args.out / f"data_{split}_{name}.npz", overwrite=args.overwrite)
    else:
        check_outputs(args, "--out")
    arm = get_arm(args.arm)
    params = sim_params.arm_sim_params(arm, args.calibration)
    if args.scenario == "continuous":
        if arm.name != DEFAULT_ARM:
            raise UsageError(f"--arm {args.arm}: the continuous run simulates the "
                             f"{DEFAULT_ARM} only (so far); use --scenario random, "
                             "planning or test")
        if args.plan is not None:
            raise UsageError("--plan: the continuous run walks nearby random goals; use "
                             "--scenario test (or random, planning) with a plan")
        if args.format != "native":
            raise UsageError("the continuous run is one trajectory with switching objects: "
                             "use --format native")
        fields, meta = simulate_continuous_run(
            params, n=args.n or 2048, objects=args.objects or ["empty", "cube", "white",
                                                               "black"],
            switch_every=args.switch_every, seed=args.seed, arm=arm)
        meta["version"] = __version__
        samples = Samples.from_fields(fields, meta["objects"], need_truth=True)
        path = save_native(args.out, samples, meta)
        print(f"wrote {path} ({samples.n_samples} samples, object switching every "
              f"{args.switch_every})")
        return 0
    plan = None
    if args.plan is not None:
        plan = load_plan(args.plan, arm=arm.name)
        if plan[0].shape[1] != params.robot.n_joints:
            raise UsageError(f"--plan {args.plan}: {plan[0].shape[1]} joints per pose; the "
                             f"simulated arm has {params.robot.n_joints}")
    results = sim_run.simulate_scenario(params, args.scenario, n=args.n, objects=args.objects,
                                        seed=args.seed, plan=plan, arm=arm)
    for name, (_, r) in results.items():
        bad = int(np.sum(~r["at_rest"]))
        if bad:
            print(f"{name}: {bad} of {len(r['q'])} samples timed out (flagged: at_rest = False)")
    fields, meta = sim_run.native_fields(results, params, scenario=args.scenario,
                                         seed=args.seed, version=__version__)
    if args.plan is not None:
        meta["plan"] = str(args.plan.resolve())
    samples = Samples.from_fields(fields, meta["objects"], need_truth=True)
    if args.format == "lbipe":
        kept = samples.at_rest_only()
        for path, part in zip(save_lbipe(args.out, split, kept), kept.by_object()):
            print(f"wrote {path} ({part.n_samples} samples)")
        return 0
    path = save_native(args.out, samples, meta)
    print(f"wrote {path} ({samples.n_samples} samples)")
    return 0


def cmd_calibrate(args) -> int:
    enable_x64()
    lbipe_arm_only(args, "calibrate fits the simulator to")
    out = args.out or data_path(CALIBRATION_FILE)
    if args.out is not None:
        check_outputs(args, "--out")
    for name in ("report.md", "calibration.png"):
        check_output(args.report / name, overwrite=args.overwrite, option="--report")
    distinct(args.real_objects, "--real-objects")
    if args.real_objects and args.start is None:
        # Held out: start from the datasheet, not from the shipped fit (it saw every file).
        params = sim_params.datasheet_sim_params()
    else:
        params = sim_params.default_sim_params(args.start)
    robot, gravity_info = fit_link_gravity(params.robot, args.lbipe_dir, args.real_objects)
    params = params.replace(robot=robot)
    params, info = calibrate_servo_friction(params, args.lbipe_dir, iterations=args.iterations,
                                            seed=args.seed, kinetic_ratio=args.kinetic_ratio,
                                            fit_offset=args.fit_offset, progress=True,
                                            objects=args.real_objects)
    payload = {"robot": "open_manipulator_x", "link_gravity": gravity_info,
               "servo_friction": sim_params.params_to_dict(params),
               "fit": {"iterations": args.iterations, "seed": args.seed,
                       "fit_offset": args.fit_offset,
                       "real_objects": sorted(p[0] for p in info["plans"]),
                       "start": str(args.start) if args.start else (
                           "datasheet" if args.real_objects else "shipped"),
                       "real": info["real"],
                       "final_sim": info["history"][-1]["sim"]}}
    write_json(out, payload)
    print(f"wrote {out}")
    report = args.report
    real = {k: np.concatenate([getattr(d, k) for _, _, d in info["plans"]])
            for k in ("q_d", "q", "direction", "tau", "current_tau")}
    sim = {k: v[info["sim_samples"]["at_rest"]] for k, v in info["sim_samples"].items()}
    png = plot_calibration(real, sim, report / "calibration.png")
    text = calibration_report(real, sim, source=args.lbipe_dir, iterations=args.iterations,
                              parameters=out, figure=png.name)
    write_text(report / "report.md", text)
    print(f"wrote {report / 'report.md'} and {png}")
    return 0


def cmd_train(args) -> int:
    enable_x64()
    check_outputs(args, "--out")
    overrides = {k: v for k, v in vars(args).items()
                 if k in TrainConfig.__dataclass_fields__ and v is not None}
    if args.init is not None:
        overrides = {**FINETUNE_DEFAULTS, **overrides}
    cfg = TrainConfig(**overrides)
    info = train(args.data, args.out, cfg, overwrite=args.overwrite, init=args.init,
                 samples_per_object=args.samples_per_object, arm=arm_name(args))
    what = "fine-tuned" if args.init is not None else "trained"
    print(f"{what} {info['training']['n_models']} model pairs on {info['samples']['train']} "
          f"samples ({info['samples']['validation']} validation) in "
          f"{sum(info['wall_time_s'].values()):.1f} s; wrote {args.out}")
    return 0


def cmd_evaluate(args) -> int:
    enable_x64()
    check_outputs(args, "--json")
    released = None
    if args.samples:
        res = evaluate_samples(args.models, args.samples, n_sets=args.sets, seed=args.seed,
                               arm=arm_name(args))
        objects, torque = res["objects"], res["torque"]
    else:
        lbipe_arm_only(args, "without --samples, evaluate reads")
        real = sim_to_real(args.models, args.lbipe_dir, seed=args.seed, n_sets=args.sets)
        if real is None:
            raise UsageError(f"no real data at {args.lbipe_dir}: pass --lbipe-dir or --samples")
        objects, torque = real["ours"]["objects"], real["ours"]["torque"]
        released = real.get("released")
    print(table1(objects, f"Table I: models {args.models}"))
    if released:
        print()
        print(table1(released, "The authors' released models, same files and sets"))
    print()
    print(table2(torque, "Table II: joint torque"))
    print()
    print(table3(objects, "Table III: mean attention weights"))
    return write_json_option(args, objects)


def cmd_reproduce(args) -> int:
    enable_x64()
    reproduce(args.out, full=args.full, seed=args.seed, lbipe_dir=args.lbipe_dir,
              arm=arm_of(args))
    return 0


def register(sub) -> None:
    """Adds this module's subcommands to the ``jaxinertia`` argparse subparsers."""
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
    b.add_argument("--overwrite", action="store_true", help="replace an existing --json/--plot")
    b.set_defaults(func=cmd_lbipe_benchmark)

    s = sub.add_parser(
        "simulate",
        help="generate samples from a simulated arm (default: the OpenMANIPULATOR-X)",
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
    s.add_argument("--seed", type=int, default=0)
    add_arm_option(s)
    s.add_argument("--calibration", type=Path,
                   help="simulator parameter file (default: the arm's shipped calibration; "
                   "an arm without one is simulated from its datasheet values)")
    s.add_argument("--overwrite", action="store_true", help="replace an existing --out")
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
    c.add_argument("--lbipe-dir", type=Path, default=default_lbipe_dir())
    add_arm_option(c)
    c.add_argument("--iterations", type=positive_int, default=6)
    c.add_argument("--seed", type=int, default=0)
    c.add_argument("--out", type=Path,
                   help="parameter file (default: the package's data/open_manipulator_x_sim.json)")
    c.add_argument("--report", type=Path, default=Path("runs/calibration"))
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
    c.set_defaults(func=cmd_calibrate)

    t = sub.add_parser(
        "train", help="train torque and attention models (K seeds) and fit the baselines",
        description="Trains on native sample files of known objects (jaxinertia simulate or "
        "collect). Defaults are the paper's hyperparameters.")
    t.add_argument("--data", nargs="+", required=True, type=Path,
                   help="sample files of known objects (native or the authors' layout)")
    t.add_argument("--out", required=True, type=Path, help="model folder to write")
    add_arm_option(t, default=None, what="the arm the sample files record")
    t.add_argument("--overwrite", action="store_true", help="replace an existing model folder")
    t.add_argument("--init", type=Path, metavar="MODELS",
                   help="fine-tune this model folder (e.g. simulator-trained models on real "
                   "samples of known objects) instead of training from scratch; its feature "
                   "scaling and model count are kept, the defaults become "
                   + ", ".join(f"--{k.replace('_', '-')} {v}"
                               for k, v in FINETUNE_DEFAULTS.items()))
    t.add_argument("--samples-per-object", type=positive_int, metavar="N",
                   help="use at most N samples of each object (seeded random choice)")
    t.add_argument("--trainable", choices=["all", "head", "servo"], default=None,
                   help="what fine-tuning may change: all (default), head (the per-joint "
                   "encoders fixed) or servo (only the physical torque model's stiffness, "
                   "offset and friction; the attention model fixed)")
    t.add_argument("--torque-model", choices=["paper", "physical"], default=None,
                   help="the paper's network (default) or a physics-structured one: per "
                   "joint stiffness, offset, direction and load friction plus the paper's "
                   "network as a residual")
    for name, typ in (("n_models", positive_int), ("seed", int), ("torque_epochs", positive_int),
                      ("torque_batch", positive_int), ("torque_lr", positive_float),
                      ("attention_epochs", positive_int), ("attention_batch", positive_int),
                      ("attention_lr", positive_float), ("set_size", positive_int),
                      ("attention_sets", positive_int), ("attention_val_sets", positive_int),
                      ("w_mass", nonnegative_float), ("w_com", nonnegative_float),
                      ("val_fraction", fraction)):
        t.add_argument("--" + name.replace("_", "-"), dest=name, type=typ,
                       help=f"(default {getattr(TrainConfig(), name)})")
    t.set_defaults(func=cmd_train)

    e = sub.add_parser(
        "evaluate", help="Tables I-III of trained models on real (default) or simulated data",
        description="Evaluates a model folder on every data/data_test_<name>.npz in the lbipe "
        "folder (beside the released models on the same sets), or on a native sample file.")
    e.add_argument("--models", required=True, type=Path)
    add_arm_option(e, default=None, what="the samples' arm; another's models are refused")
    e.add_argument("--lbipe-dir", type=Path, default=default_lbipe_dir())
    e.add_argument("--samples", type=Path,
                   help="a sample file of known objects instead (native or the authors' layout)")
    e.add_argument("--json", type=Path, help="write Table I/III (lbipe-benchmark schema)")
    e.add_argument("--sets", type=positive_int, default=1000,
                   help="random sets per object (no golden)")
    e.add_argument("--overwrite", action="store_true", help="replace an existing --json")
    e.add_argument("--seed", type=int, default=0)
    e.set_defaults(func=cmd_evaluate)

    r = sub.add_parser(
        "reproduce", help="simulate, train, evaluate, switching loads, sim-to-real, report",
        description="The paper end to end into a run folder (report.md, tables.json, plots). "
        "Default: a quick run (minutes on a laptop CPU); --full: the paper's scale.")
    r.add_argument("--out", type=Path, default=Path("runs/reproduce"))
    r.add_argument("--full", action="store_true")
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--lbipe-dir", type=Path, default=default_lbipe_dir())
    add_arm_option(r)
    r.set_defaults(func=cmd_reproduce)
