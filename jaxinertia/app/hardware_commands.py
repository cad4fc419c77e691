"""Subcommands ``virtual-robot`` and ``collect``: the virtual servo bus, and samples
collected on the arm (or a virtual robot) into a native sample file.

Errors are raised (:mod:`jaxinertia.errors`); ``main()`` prints them and picks the exit
code: 2 for a bad request (an option out of range, ``--ids`` of the wrong count, unknown
object, a goal refused by the safety checks, an existing output, a journal that exists,
is damaged or belongs to another collection), all before anything moves; 3 for the bus
or a servo (a port that cannot be opened, is in use by another ``collect`` or
disappears; a collection stopped by the bus or a servo: the journal is kept and
``--resume`` continues; with nothing collected no journal is left). Ctrl-C during a
collection is not an error: the command says where the journal is and returns 130.

One module for both: they share the bus options, the arm record's defaults for them
(``arm_options.bus_arm_options``) and the serving loop. Both serve whatever bus the arm
record names: ``virtual-robot`` answers as its servos (DYNAMIXEL Protocol 2.0,
:class:`jaxinertia.virtual.robot.VirtualServoBus`; Feetech STS for the SO-101,
:class:`jaxinertia.virtual.sts_robot.VirtualStsBus`), the simulated arm holding
``--object`` behind them; ``collect`` drives the arm's driver (``hardware.drivers``).
"""

from __future__ import annotations

import argparse
import gc
import signal
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from jaxinertia.app import defaults
from jaxinertia.app.arm_options import (
    add_arm_option,
    bus_arm_options,
)
from jaxinertia.app.options import (
    check_memory,
    finite_float,
    flag_wording,
    nonnegative_float,
    positive_float,
    positive_int,
    seed_int,
)
from jaxinertia.errors import HardwareError, UsageError
from jaxinertia.fileio import check_output

if TYPE_CHECKING:
    from jaxinertia.plans import Goals

__all__ = ["register"]

#: Exit status of ``collect`` after Ctrl-C (journal kept, ``--resume`` continues).
EXIT_INTERRUPTED = 130

#: What one goal of a plan takes while it is drawn and checked (its pre-position, forward
#: kinematics of both against the safety limits) [bytes], generous.
PLAN_BYTES_PER_POSE = 4096

#: A collected sample file's ``source``, by the arm's bus (``Arm.bus``).
SOURCE_OF_BUS = {"dynamixel2": "dynamixel", "feetech_sts": "feetech"}

#: ``collect --object unknown``: no ground truth (the file has no tau and no x).
UNKNOWN = "unknown"


def _ids(text: str) -> tuple[int, ...]:
    try:
        ids = tuple(int(t) for t in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated IDs, got {text!r}") from None
    if not ids or any(not 0 <= i <= 252 for i in ids):
        raise argparse.ArgumentTypeError(f"IDs must be in 0..252, got {text!r}")
    return ids


def _gripper(text: str) -> int | str:
    if text.lower() == "none":
        return "none"  # no gripper (None: the option left out, the arm's)
    (dxl_id,) = _ids(text)
    return dxl_id


def _count(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be an integer >= 0, got {text!r}")
    return value


def _probability(text: str) -> float:
    value = nonnegative_float(text)
    if value > 1:
        raise argparse.ArgumentTypeError(f"must be a probability in [0, 1], got {text!r}")
    return value


def _register(limit: int):
    """A register value in 0..limit."""
    def parse(text: str) -> int:
        value = _count(text)
        if value > limit:
            raise argparse.ArgumentTypeError(f"must be in 0..{limit}, got {text!r}")
        return value
    parse.__name__ = f"an integer in 0..{limit}"
    return parse


def _check_ids(args, n_joints: int) -> None:
    """One servo ID per joint, all distinct, the gripper's apart (before anything moves)."""
    ids = tuple(args.ids)
    if len(ids) != n_joints:
        raise UsageError(f"--ids needs {n_joints} joint servo IDs (one per joint), got "
                         f"{len(ids)}: {','.join(map(str, ids))}")
    if len(set(ids)) != len(ids):
        raise UsageError(f"--ids must be distinct, got {','.join(map(str, ids))}")
    if args.gripper_id is not None and args.gripper_id in ids:
        raise UsageError(f"--gripper-id {args.gripper_id} is also a joint in --ids")


def cmd_virtual_robot(args) -> int:
    # The work's modules (JAX, the simulator): imported when the command runs, not for --help.

    import jax  # (as above)
    import numpy as np  # (as above)

    from jaxinertia import objects  # (as above)
    from jaxinertia.servos import servo_model  # (as above)
    from jaxinertia.sim.params import arm_sim_params  # (as above)
    from jaxinertia.virtual.bus import Faults  # (as above)
    from jaxinertia.virtual.robot import VirtualServoBus  # (as above)
    from jaxinertia.virtual.sts_robot import VirtualStsBus  # (as above)

    jax.config.update("jax_enable_x64", True)
    faults = Faults(drop_rate=args.drop_rate, corrupt_rate=args.corrupt_rate,
                    delay_rate=args.delay_rate, delay_s=args.delay_ms / 1000.0,
                    overload_id=args.overload_id, overload_after=args.overload_after,
                    seed=args.fault_seed)
    arm = bus_arm_options(args)
    obj = objects.resolve(args.object, tag_in_ee=arm.tag_in_ee)
    params = arm_sim_params(arm, args.calibration)
    _check_ids(args, params.robot.n_joints)
    gripper = () if args.gripper_id is None else (arm.gripper_servo or arm.servos[0],)
    # The arm record names its servos' protocol: DYNAMIXEL Protocol 2.0 or Feetech STS.
    bus_class = {"dynamixel2": VirtualServoBus, "feetech_sts": VirtualStsBus}[arm.bus]
    # Each servo answers as its model (the Koch's XL430s with Present Load); each joint's
    # simulated gain belongs to its P register (the arm's, or the servo model's).
    bus = bus_class(params, obj, ids=args.ids,
                    extra_ids=() if args.gripper_id is None else (args.gripper_id,),
                    q0=np.radians(args.q0), speed=args.speed, faults=faults, seed=args.seed,
                    servo_models=[servo_model(m) for m in (*arm.servos, *gripper)],
                    gain_registers=[g[0] for g in arm.joint_gains])
    bus.compile()  # every physics path, so that no reply waits on a compilation
    return _serve(bus, f"virtual {arm.name} servos {list(bus.servos)} on {bus.path}, object "
                       f"{args.object}, {args.speed:g}x real time")


def _serve(bus, what: str) -> int:
    """Starts ``bus``, prints its device path as the first line of stdout and ``what`` on
    stderr, and serves until SIGTERM or Ctrl-C."""
    # What is alive now lives as long as the process: out of the garbage collector's way,
    # so that a full collection (100-200 ms over all the imported modules) never stalls a
    # reply past the master's ~35 ms timeout.
    gc.freeze()
    bus.start()
    # The device path is the first line of stdout: callers wait for it.
    print(bus.path, flush=True)
    print(what, file=sys.stderr, flush=True)

    def shutdown(signum, frame):  # noqa: ARG001
        bus.stop()

    signal.signal(signal.SIGTERM, shutdown)
    signal.signal(signal.SIGINT, shutdown)
    try:
        bus.wait()
    finally:
        bus.close()
    return 0


def _check_collect_options(args) -> None:
    from jaxinertia.hardware.transport import LockedPortHandler  # dynamixel-sdk: at run time

    if LockedPortHandler(args.port).getCFlagBaud(args.baudrate) <= 0:
        raise UsageError(f"--baudrate {args.baudrate} is not a rate dynamixel-sdk supports")
    if args.timeout <= args.settle_time:
        raise UsageError(f"--timeout {args.timeout:g} s must exceed --settle-time "
                         f"{args.settle_time:g} s")


def _collect_plan(args, arm, robot) -> Goals:
    """The goals and approach directions of ``--plan`` (the arm's planning grid, random
    goals in its workspace, or a plan file of ``jaxinertia plan-poses`` for that arm;
    ``--n`` cuts the planning grid or a file's plan)."""
    # The work's modules (JAX): imported when the command runs, not for --help.
    from jaxinertia import plans
    from jaxinertia.design import load_plan  # (as above)

    if args.plan == "planning":
        q_d, direction = plans.planning_plan(arm.planning_step_deg, robot=robot,
                                             clearance=arm.mount_clearance_m,
                                             workspace=arm.workspace_deg)
    elif args.plan == "random":
        n = 1000 if args.n is None else args.n
        check_memory(n * PLAN_BYTES_PER_POSE, f"--n {n} (random goals, each checked)")
        return plans.random_plan(n, args.seed, workspace=arm.workspace_deg)
    else:
        q_d, direction = load_plan(args.plan, arm=arm.name)
    if args.n is not None:
        q_d, direction = q_d[: args.n], direction[: args.n]
    return plans.Goals(q_d, direction)


def _collect_request(args):
    """The arm, object, robot, safety limits and plan of a collection, every goal checked
    against the limits: all that can be refused, before the port is opened."""
    from jaxinertia import objects  # the work's modules: imported when the command runs
    from jaxinertia.hardware.arm_config import safety_limits  # (as above)
    from jaxinertia.open_manipulator_x import sim_fit_robot  # (as above)
    from jaxinertia.sim.params import arm_sim_params  # (as above)

    arm = bus_arm_options(args)  # any bus: the record names its driver
    _check_collect_options(args)
    obj = None if args.object == UNKNOWN else objects.resolve(args.object,
                                                            tag_in_ee=arm.tag_in_ee)
    # The calibrated bare arm: A and tau_g (as the simulator records them) and the FK of
    # the kinematic tag pose (an arm without a calibration: its description's links).
    robot = (sim_fit_robot(args.calibration) if arm.sim_fit_file is not None
             else arm_sim_params(arm, args.calibration).robot)
    q_d, direction = _collect_plan(args, arm, robot)
    _check_ids(args, robot.n_joints)
    if q_d.shape[1] != robot.n_joints:
        raise UsageError(f"--plan {args.plan}: {q_d.shape[1]} joints per pose; the arm has "
                         f"{robot.n_joints}")
    safety = safety_limits(arm, robot)
    for i, (goal, d) in enumerate(zip(q_d, direction)):  # every goal before the port opens
        try:
            for q in (goal, goal - d * arm.pre_position):
                safety.check(q, robot)
        except UsageError as e:
            raise UsageError(f"--plan {args.plan}: pose {i}: {e}") from None
    return arm, obj, robot, safety, (q_d, direction)


def cmd_collect(args) -> int:
    # The work's modules (JAX, dynamixel-sdk): imported when the command runs, not for --help.
    import jax
    import numpy as np  # (as above)

    from jaxinertia.hardware.arm_config import arm_config  # (as above)
    from jaxinertia.hardware.collect import (  # (as above)
        Journal,
        KinematicTagPose,
        collect,
        journal_path,
        plan_digest,
        samples_from_records,
    )
    from jaxinertia.hardware.driver import PortError  # (as above)
    from jaxinertia.hardware.drivers import driver_class  # (as above)
    from jaxinertia.hardware.safety import SafetyError  # (as above)
    from jaxinertia.samples import save_native  # (as above)

    jax.config.update("jax_enable_x64", True)
    # Everything that can be refused is refused before the port is opened (exit code 2).
    arm, obj, robot, safety, (q_d, direction) = _collect_request(args)
    delta = arm.pre_position
    out = check_output(args.out, overwrite=args.overwrite)
    config = arm_config(
        arm, args.port, baudrate=args.baudrate, joint_ids=args.ids, gripper_id=args.gripper_id,
        p_gain=args.p_gain, d_gain=args.d_gain, profile_velocity=args.profile_velocity,
        profile_acceleration=args.profile_acceleration, settle_time=args.settle_time,
        move_timeout=args.timeout, retries=args.retries, on_stop=args.on_stop,
        reboot_on_error=args.clear_errors)
    header = {"kind": "header", "plan": args.plan, "seed": args.seed, "n_samples": len(q_d),
              "object": args.object, "plan_digest": plan_digest(q_d, direction),
              "port": args.port, "servo_ids": list(args.ids), "delta": delta}
    journal = Journal.open(journal_path(out), header, resume=args.resume,
                           plan=(q_d, direction))
    done = len(journal.records)
    if done:
        print(f"resuming: {done} of {len(q_d)} samples already in {journal.path}",
              file=sys.stderr)
    R_ee_tag, p_ee_tag = arm.tag_in_ee
    tag_source = KinematicTagPose(robot, R_ee_tag, p_ee_tag)
    dxl = driver_class(arm)(config, robot=robot, safety=safety)  # the arm's bus

    def where() -> str:
        if not journal.path.exists():
            return "nothing was collected (no journal written); run the command again"
        return (f"{len(journal.records)} of {len(q_d)} samples are in {journal.path}; "
                "continue with --resume")

    try:
        dxl.open()  # locked for this collection: a second collect on the port is refused
        with dxl:
            collect(dxl, q_d, direction, journal, tag_pose=tag_source, delta=delta,
                    progress=not args.no_progress)
    except SafetyError as e:
        raise SafetyError(f"refused: {e}") from e
    except PortError:  # nothing has moved; the journal is as it was
        raise
    except HardwareError as e:  # the bus or a servo (CommError, ServoHardwareError)
        raise HardwareError(f"stopped ({config.on_stop}): {e}; {where()}") from e
    except KeyboardInterrupt:
        print(f"jaxinertia collect: interrupted ({config.on_stop}); {where()}",
              file=sys.stderr)
        return EXIT_INTERRUPTED
    finally:
        journal.close()
        dxl.close()
    print(f"bus: {flag_wording(dxl.bus_report())}", file=sys.stderr)
    x = None if obj is None else np.asarray(obj.x)
    samples = samples_from_records(journal.records, robot, x, args.object)
    path = save_native(out, samples, _collected_meta(args, arm, robot, journal, header))
    bad = int(np.sum(~samples.at_rest))
    print(f"wrote {path} ({samples.n_samples} samples" + (
        f", {bad} timed out: at_rest = False)" if bad else ")"))
    return 0


def _collected_meta(args, arm, robot, journal, header) -> dict:
    """What a collected sample file records of its collection."""
    from jaxinertia import __version__  # (light; the package's own version)

    return {"version": __version__, "source": SOURCE_OF_BUS[arm.bus], "port": args.port,
            "plan": args.plan, "object": args.object,
            "scenario": args.plan if args.plan in ("planning", "random") else "plan",
            "objects": [args.object], "seed": args.seed, "servo_ids": list(args.ids),
            "gripper_id": args.gripper_id, "robot": robot.name, "arm": arm.name,
            "delta": arm.pre_position,
            "journal": str(journal.path), "plan_digest": header["plan_digest"],
            "tag_pose": f"kinematic (the {arm.name} record's tag_in_ee)",
            "servo": {"p_gain": args.p_gain, "i_gain": 0, "d_gain": args.d_gain,
                      "profile_velocity": args.profile_velocity,
                      "profile_acceleration": args.profile_acceleration,
                      "settle_time": args.settle_time, "timeout": args.timeout}}


def register(sub) -> None:
    """Adds this module's subcommands to the ``jaxinertia`` argparse subparsers."""
    names = ", ".join(defaults.OBJECT_NAMES)
    _register_virtual_robot(sub, names)
    _register_collect(sub, names)


def _register_virtual_robot(sub, names: str) -> None:
    v = sub.add_parser(
        "virtual-robot",
        help="the simulated arm's servos (DYNAMIXEL, or Feetech STS) on a pseudo-terminal",
        description="Opens a pseudo-terminal, prints its path as the first line of stdout "
        "and answers there as the arm's servos (DYNAMIXEL Protocol 2.0, each servo its "
        "model's control table; Feetech STS for the SO-101) whose joints are the simulated "
        "arm (default: the OpenMANIPULATOR-X). Runs until SIGTERM or Ctrl-C.",
    )
    add_arm_option(v)  # Feetech STS servos for the so101, DYNAMIXEL for the others
    v.add_argument("--object", default="none",
                   help=f"held object: {names} (none: the empty gripper)")
    v.add_argument("--speed", type=positive_float, default=1.0,
                   help="simulated seconds per second")
    v.add_argument("--ids", type=_ids, help="joint servo IDs (default: the arm's)")
    v.add_argument("--gripper-id", type=_gripper,
                   help="gripper ID or none (default: the arm's)")
    v.add_argument("--q0", type=finite_float, nargs="+", metavar="DEG",
                   help="initial joint angles [deg], one per joint (default: the middle of "
                   "the arm's workspace, 0 -30 30 0 for the OpenMANIPULATOR-X)")
    v.add_argument("--seed", type=seed_int, default=0, help="friction draws and current noise")
    v.add_argument("--calibration", type=Path, help="simulator parameter file")
    g = v.add_argument_group("fault injection")
    g.add_argument("--drop-rate", type=_probability, default=0.0,
                   help="status packets not sent")
    g.add_argument("--corrupt-rate", type=_probability, default=0.0,
                   help="status packets with bad CRC")
    g.add_argument("--delay-rate", type=_probability, default=0.0,
                   help="status packets delayed")
    g.add_argument("--delay-ms", type=nonnegative_float, default=10.0)
    g.add_argument("--overload-id", type=int, help="servo that raises an overload error")
    g.add_argument("--overload-after", type=_count, default=0,
                   help="... after this many Goal Position writes to it")
    g.add_argument("--fault-seed", type=seed_int, default=0)
    v.set_defaults(func=cmd_virtual_robot)


def _register_collect(sub, names: str) -> None:
    c = sub.add_parser(
        "collect",
        help="collect samples on the arm (or a virtual robot) into a native sample file",
        description="Runs a plan with the paper's protocol (pre-position q_d - s*3 deg (the "
        "arm's pre-position), then "
        "q_d, record at rest). Every sample is appended to OUT.journal.jsonl and flushed; "
        "an interrupted collection continues with --resume.",
    )
    c.add_argument("--port", required=True, help="serial device (e.g. /dev/ttyUSB0)")
    c.add_argument("--plan", required=True, metavar="{planning,random,PLAN.json}",
                   help="the paper's planning grid, random goals, or a plan file of "
                   "`jaxinertia plan-poses` (every goal is checked against the safety limits "
                   "before the port opens)")
    c.add_argument("--object", required=True,
                   help=f"held object ({names}) or {UNKNOWN} (no ground truth: the file has "
                   "no tau and no x)")
    c.add_argument("--out", required=True, type=Path, help="native sample file (.npz)")
    c.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    c.add_argument("--resume", action="store_true", help="continue OUT.journal.jsonl")
    c.add_argument("--n", type=positive_int,
                   help="samples (random: default 1000; planning: the first N)")
    c.add_argument("--seed", type=seed_int, default=0, help="seed of the random plan")
    add_arm_option(c)
    c.add_argument("--baudrate", type=int, help="(default: the arm's, 1000000)")
    c.add_argument("--ids", type=_ids, help="joint servo IDs (default: the arm's)")
    c.add_argument("--gripper-id", type=_gripper,
                   help="gripper ID (pinged) or none (default: the arm's)")
    c.add_argument("--p-gain", type=_register(16383),
                   help="Position P Gain register (default: the arm's servo's, 800 on the "
                   "OpenMANIPULATOR-X)")
    c.add_argument("--d-gain", type=_register(16383),
                   help="Position D Gain register (I is 0; default: the arm's servo's)")
    c.add_argument("--profile-velocity", type=positive_float,
                   help="[rad/s] (default: the arm's, 0.5)")
    c.add_argument("--profile-acceleration", type=positive_float,
                   help="[rad/s^2] (default: the arm's, 2.0)")
    c.add_argument("--settle-time", type=positive_float,
                   help="no tick may change for this long to count as at rest [s, servo "
                   "clock] (default: the arm's, 0.2)")
    c.add_argument("--timeout", type=positive_float,
                   help="per move [s, servo clock] (default: the arm's, 6.0)")
    c.add_argument("--retries", type=_count, default=defaults.BUS_RETRIES,
                   help="per bus transaction (each after the bus has gone quiet, about 70 ms "
                   "a try: a dead bus is reported within a second)")
    c.add_argument("--on-stop", choices=["hold", "torque_off"], default="hold",
                   help="state to leave the arm in after an error or Ctrl-C")
    c.add_argument("--clear-errors", action="store_true",
                   help="reboot servos that report a hardware error on connect (after the "
                   "cause is fixed)")
    c.add_argument("--calibration", type=Path, help="simulator parameter file (the bare arm)")
    c.add_argument("--no-progress", action="store_true", help="no progress bar")
    c.set_defaults(func=cmd_collect)
