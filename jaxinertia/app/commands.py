"""The paper's commands: ``lbipe-benchmark``, ``train``, ``evaluate`` and ``reproduce``
(``simulate`` and ``calibrate`` are in :mod:`jaxinertia.app.sim_commands`, ``estimate``
and ``plan-poses`` in :mod:`jaxinertia.app.estimate_commands`).

Each is a short function over :mod:`jaxinertia.app.pipeline` that checks its options and
outputs before any work and raises :class:`jaxinertia.errors.JaxinertiaError` subclasses
for what the user can fix; :func:`jaxinertia.app.cli.main` prints them.
"""

from __future__ import annotations

from pathlib import Path

from jaxinertia.app import defaults
from jaxinertia.app.arm_options import add_arm_option, arm_name, arm_of, lbipe_arm_only
from jaxinertia.app.options import (
    add_session_strength,
    check_outputs,
    enable_x64,
    fraction,
    nonnegative_float,
    positive_float,
    positive_int,
    seed_int,
    session_line,
    write_json_option,
    zero_to_one,
)
from jaxinertia.errors import UsageError
from jaxinertia.fileio import check_output

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


LBIPE_DIR_HELP = ("shared/lbipe layout or a checkout of ChirikjianLab/lbipe (default: "
                  "$JAXINERTIA_LBIPE_DIR, else ../shared/lbipe beside the repository)")

#: What ``--plot`` can write (matplotlib's formats), checked before the work.
PLOT_SUFFIXES = (".png", ".pdf", ".svg", ".svgz", ".jpg", ".jpeg", ".eps", ".ps", ".tif",
                 ".tiff", ".webp", ".pgf")


def lbipe_dir_of(args) -> Path:
    """``--lbipe-dir``, else the library's default (``lbipe.default_lbipe_dir``)."""
    if args.lbipe_dir is not None:
        return args.lbipe_dir
    from jaxinertia.lbipe import default_lbipe_dir  # the work's modules (JAX), not for --help

    return default_lbipe_dir()


def _check_plot(args) -> None:
    if args.plot is not None and args.plot.suffix.lower() not in PLOT_SUFFIXES:
        raise UsageError(f"--plot {args.plot}: unknown figure format "
                         f"{args.plot.suffix or '(no extension)'}; use one of "
                         + ", ".join(PLOT_SUFFIXES))


def cmd_lbipe_benchmark(args) -> int:
    _check_plot(args)
    check_outputs(args, "--json", "--plot")
    l_max = _parse_l_max(args.l_max)
    enable_x64()
    # The work's modules (JAX, matplotlib): imported when the command runs, not for --help.
    from jaxinertia.app import pipeline, plots, report

    res = pipeline.released_benchmark(lbipe_dir_of(args), seed=args.seed, l_max=l_max)
    objects = res["objects"]
    print(report.table1(objects, "Table I: mass and COM error of the released models (10 "
                        "pairs x sets)", style="text", methods=("T", "T-A")))
    print()
    print(report.table3(objects, "Table III: mean attention weight per joint", style="text"))
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
        plots.plot_lbipe_estimates(res["real"].objects, res["estimates"], args.plot)
        print(f"wrote {args.plot}")
    return 0


def _check_train_data(args) -> None:
    """``--data`` names each file once (by path or by content: a copy of a training file
    would land in the validation split), ``--torque-model`` agrees with ``--init`` and
    ``--trainable attention`` has torque models to keep."""
    if args.trainable == "attention" and args.init is None:
        raise UsageError("--trainable attention keeps the torque models of --init: give the "
                         "model folder to start from")
    seen: dict[tuple, Path] = {}
    for f in args.data:
        try:
            st = f.stat()
        except OSError:
            continue  # the loader names a missing file
        for key in ((st.st_dev, st.st_ino), ("size", st.st_size, _digest(f))):
            if key in seen:
                raise UsageError(f"--data: {f} is the same file as {seen[key]}; give each "
                                 "file once (a repeated file would put copies of training "
                                 "samples into the validation split)")
            seen[key] = f
    if args.init is not None and args.torque_model is not None:
        import json  # (light) the folder's config only, before any loading

        try:
            config = json.loads((args.init / "config.json").read_text())
            kind = config["torque_model"].get("kind", "paper")
        except (OSError, ValueError, KeyError, TypeError, AttributeError):
            return  # loading the folder names what is wrong with it
        if kind != args.torque_model:
            raise UsageError(f"--torque-model {args.torque_model}: --init {args.init} holds "
                             f"{kind!r} torque models; fine-tuning keeps the models' kind "
                             f"(leave out --torque-model, or train from scratch)")


def _digest(path: Path) -> str:
    import hashlib  # (light) only for --data files of equal size

    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def cmd_train(args) -> int:
    check_output(args.out, overwrite=args.overwrite, folder=True)
    _check_train_data(args)
    enable_x64()
    # The work's modules (JAX, flax, optax): imported when the command runs, not for --help.
    from jaxinertia.app import pipeline
    from jaxinertia.training import FINETUNE_DEFAULTS, TrainConfig  # (as above)

    overrides = {k: v for k, v in vars(args).items()
                 if k in TrainConfig.__dataclass_fields__ and v is not None}
    if args.init is not None:
        overrides = {**FINETUNE_DEFAULTS, **overrides}
    cfg = TrainConfig(**overrides)
    session = None
    if args.session_of is not None:  # the real files whose servo state the models take
        from jaxinertia.samples import load_samples  # (as above)
        from jaxinertia.session import servo_session  # (as above)

        session = servo_session([load_samples(f, need_truth=False)[0] for f in args.session_of])
    info = pipeline.train(args.data, args.out, cfg, overwrite=args.overwrite, init=args.init,
                          samples_per_object=args.samples_per_object, session=session,
                          arm=arm_name(args))
    what = "fine-tuned" if args.init is not None else "trained"
    print(f"{what} {info['training']['n_models']} model pairs on {info['samples']['train']} "
          f"samples ({info['samples']['validation']} validation) in "
          f"{sum(info['wall_time_s'].values()):.1f} s; wrote {args.out}")
    return 0


def _floats(values) -> list[float] | None:
    return None if values is None else [float(v) for v in values]


def cmd_evaluate(args) -> int:
    check_outputs(args, "--json")
    l_max = _parse_l_max(args.l_max)
    enable_x64()
    # The work's modules (JAX): imported when the command runs, not for --help.
    from jaxinertia.app import pipeline, report

    released = None
    if args.samples:
        from jaxinertia.app.with_reference import read_reference  # (as above)

        ref = (None if args.reference is None else
               read_reference(args.reference, arm_name(args)))
        res = pipeline.evaluate_samples(args.models, args.samples, n_sets=args.sets,
                                        seed=args.seed, l_max=l_max, arm=arm_name(args),
                                        session_strength=args.session_strength,
                                        known=None if ref is None else ref.objects)
        if ref is not None:
            res["reference"] = ref.record()
    else:
        if args.reference is not None:
            raise UsageError("--reference needs --samples: a reference is recorded in the "
                             "session of the file it corrects (the real lbipe files are two "
                             "sessions; docs/results.md, 'A reference in the same session')")
        lbipe_arm_only(args, "without --samples, evaluate reads")
        lbipe_dir = lbipe_dir_of(args)
        real = pipeline.sim_to_real(args.models, lbipe_dir, seed=args.seed, n_sets=args.sets,
                                    l_max=l_max, session_strength=args.session_strength)
        if real is None:
            raise UsageError(f"no real data at {lbipe_dir}: pass --lbipe-dir or --samples")
        res, released = real["ours"], real.get("released")
    objects, torque = res["objects"], res["torque"]
    from jaxinertia.app.provenance import not_held_out_line, seen_by  # (as above)

    about = {}  # per object, beside its tables in --json: its file, session, provenance
    if ref := res.get("reference"):
        c = res["reference_correction"]
        print(f"reference {ref['file']} ({', '.join(ref['objects'])}, {ref['n_samples']} "
              "samples of known torque): the networks' torques read x "
              + " / ".join(f"{g:.3f}" for g in c["gain"]) + ", "
              + " / ".join(f"{b * 1e3:+.1f}" for b in c["offset_Nm"])
              + " N mm per joint (each folder fits its own; the baselines as recorded)")
    for name, ratio in res["session_ratio"].items():
        print(session_line(name, res["session_strength"], ratio))
        about[name] = {"sha256": res["sha256"][name], "session": {
            "strength": res["session_strength"], "ratio": _floats(ratio)}}
        if com := res.get("com_session"):  # the COM's models, in their own session
            print(session_line(name, com["strength"], com["ratio"][name]).replace(
                f"{name}: ", f"{name}: the COM's models ({res['com_models']}): ", 1))
            about[name]["com_session"] = {"models": str(res["com_models"]),
                                          "strength": com["strength"],
                                          "ratio": _floats(com["ratio"][name])}
        seen = seen_by(args.models, res["sha256"][name])
        about[name]["fitted_on_this_file"] = {p: {"folders": k, "of": n}
                                              for p, (k, n) in seen.items()}
        if ref:  # the known loads that corrected the networks, and the folder's correction
            about[name]["reference"] = {**ref, "correction": res["reference_correction"]}
        if line := not_held_out_line(name, seen):
            print(line)
    print()
    print(report.table1(objects, f"Table I: models {args.models}"))
    if released:
        print()
        print(report.table1(released, "The authors' released models, same files and sets"))
    print()
    print(report.table2(torque, "Table II: joint torque"))
    print()
    print(report.table3(objects, "Table III: mean attention weights"))
    return write_json_option(args, {name: {**tables, **about.get(name, {})}
                                    for name, tables in objects.items()})


def cmd_reproduce(args) -> int:
    enable_x64()
    # The work's modules (JAX, flax, optax): imported when the command runs, not for --help.
    from jaxinertia.app.reproduce import reproduce

    reproduce(args.out, full=args.full, seed=args.seed, lbipe_dir=lbipe_dir_of(args),
              arm=arm_of(args), draws=args.draws)
    return 0


def register(sub) -> None:
    """Adds this module's subcommands to the ``jaxinertia`` argparse subparsers."""
    b = sub.add_parser(
        "lbipe-benchmark",
        help="evaluate the authors' ten released model pairs on real data (Tables I and III)",
        description="Evaluates every data/data_test_<name>.npz in DIR with the ten released "
        "model pairs (weights/*.npz|.pt or dicts/*.pt) in one batched call.",
    )
    b.add_argument("--lbipe-dir", type=Path, help=LBIPE_DIR_HELP)
    b.add_argument("--json", type=Path, help="write the metrics here (reference_metrics schema)")
    b.add_argument("--seed", type=seed_int, default=0,
                   help="seed of the 1000 random 64-sample sets when no golden sets exist")
    b.add_argument("--l-max", action="append", metavar="NAME=METRES",
                   help="bounding-box diagonal of an object without a built-in one")
    b.add_argument("--plot", type=Path, help="write a figure of the per-set estimates here "
                   "(.png, .pdf, .svg, ...)")
    b.add_argument("--overwrite", action="store_true", help="replace an existing --json/--plot")
    b.set_defaults(func=cmd_lbipe_benchmark)
    _register_train(sub)

    e = sub.add_parser(
        "evaluate", help="Tables I-III of trained models on real (default) or simulated data",
        description="Evaluates a model folder on every data/data_test_<name>.npz in the lbipe "
        "folder (beside the released models on the same sets), or on a native sample file.")
    e.add_argument("--models", required=True, type=Path)
    add_arm_option(e, default=None, what="the samples' arm; another's models are refused")
    e.add_argument("--lbipe-dir", type=Path, help=LBIPE_DIR_HELP)
    e.add_argument("--samples", type=Path,
                   help="a sample file of known objects instead (native or the authors' layout)")
    e.add_argument("--json", type=Path, help="write Table I/III (lbipe-benchmark schema) and "
                   "per object its file's SHA-256, the session ratios it was read with and how "
                   "many of the folders answering were fitted on it (fitted_on_this_file)")
    e.add_argument("--reference", type=Path, default=None, metavar="FILE",
                   help="with --samples: known loads recorded in the same session; each "
                   "folder's networks read the objects through the torque gain and offset "
                   "per joint fitted on it (as estimate --reference)")
    e.add_argument("--sets", type=positive_int, default=1000,
                   help="random sets per object (no golden)")
    e.add_argument("--overwrite", action="store_true", help="replace an existing --json")
    e.add_argument("--seed", type=seed_int, default=0)
    e.add_argument("--l-max", action="append", metavar="NAME=METRES",
                   help="bounding-box diagonal of an object without a built-in one")
    add_session_strength(e)
    e.set_defaults(func=cmd_evaluate)

    r = sub.add_parser(
        "reproduce", help="simulate, train, evaluate, switching loads, sim-to-real, report",
        description="The paper end to end into a run folder (report.md, tables.json, plots). "
        "Default: a quick run (minutes on a laptop CPU); --full: the paper's scale.")
    r.add_argument("--out", type=Path, default=Path("runs/reproduce"))
    r.add_argument("--full", action="store_true")
    r.add_argument("--seed", type=seed_int, default=0)
    r.add_argument("--draws", type=positive_int, metavar="N",
                   help="the held-out folds of N training draws (seeds SEED, SEED+1, ...), "
                   "models_real the mean of every draw's; default: the scale's (quick 1, "
                   "full 3)")
    r.add_argument("--lbipe-dir", type=Path, help=LBIPE_DIR_HELP)
    add_arm_option(r)
    r.set_defaults(func=cmd_reproduce)


def _register_train(sub) -> None:
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
                               for k, v in defaults.FINETUNE.items()))
    t.add_argument("--samples-per-object", type=positive_int, metavar="N",
                   help="use at most N samples of each object (seeded random choice)")
    t.add_argument("--trainable", choices=list(defaults.TRAINABLE),
                   default=None,
                   help="what fine-tuning may change: all (default), head (the per-joint "
                   "encoders fixed), servo (only the physical torque model's stiffness, "
                   "offset and friction; the attention model fixed), servo+input (those "
                   "and the first layer of the residual's per-joint encoders, how it reads "
                   "its inputs, the current among them), servo+attention "
                   "(those and the attention model) or attention (the attention model "
                   "alone; the torque models fixed)")
    t.add_argument("--attention-torque-spread", type=nonnegative_float, default=None,
                   metavar="S",
                   help="train the attention on sets whose predicted torques carry a "
                   "recording session the torque models do not know: each set's torque of "
                   "each joint scaled by 1 + S z, z standard normal (e.g. 0.02; default "
                   f"{defaults.TRAIN['attention_torque_spread']:g}: the paper's training)")
    t.add_argument("--session-strength", type=zero_to_one, default=None, metavar="S",
                   help="each real file's discrepancy read in the models' recording session "
                   "from its own current gain, this strongly (0: off; default "
                   f"{defaults.TRAIN['session_strength']:g}); the folder keeps it for "
                   "evaluate and estimate")
    t.add_argument("--session-of", type=Path, nargs="+", metavar="REAL.npz",
                   help="real sample files whose recording session is the models' (e.g. the "
                   "files the simulator was calibrated on; default: --init's, else the "
                   "training data's own)")
    t.add_argument("--session-terms", action="store_true", default=None,
                   help="with --init and several files: each file its own servo term (a "
                   "factor per joint on its discrepancy, fitted from its known torques, "
                   "centred over the files), so that the fine-tuning's shared servo learns "
                   "what the files' sessions share, not their difference")
    t.add_argument("--torque-model", choices=["paper", "physical"], default=None,
                   help="the paper's network (default) or a physics-structured one: per "
                   "joint stiffness, offset, direction and load friction plus the paper's "
                   "network as a residual")
    t.add_argument("--current-input", action="store_true", default=None,
                   help="give the torque model the servo's current torque as a fifth input "
                   "per joint (the samples then need their current; --init: the folder's "
                   "inputs are kept)")
    for name, typ in (("n_models", positive_int), ("seed", seed_int),
                      ("torque_epochs", positive_int),
                      ("torque_batch", positive_int), ("torque_lr", positive_float),
                      ("attention_epochs", positive_int), ("attention_batch", positive_int),
                      ("attention_lr", positive_float), ("set_size", positive_int),
                      ("attention_sets", positive_int), ("attention_val_sets", positive_int),
                      ("w_mass", nonnegative_float), ("w_com", nonnegative_float),
                      ("val_fraction", fraction)):
        t.add_argument("--" + name.replace("_", "-"), dest=name, type=typ,
                       help=f"(default {defaults.TRAIN[name]})")
    t.set_defaults(func=cmd_train)
