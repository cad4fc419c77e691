"""Subcommands ``virtual-robot`` and ``collect``: the virtual servo bus, and samples
collected on the arm (or a virtual robot) into a native sample file.

Errors are raised (:mod:`jaxinertia.errors`); ``main()`` prints them and picks the exit
code: 2 for a bad request (unknown object, a goal refused by the safety checks, a journal
that exists or belongs to another collection), 3 for a collection stopped by the bus or a
servo (the journal is kept; ``--resume`` continues). Ctrl-C during a collection is not an
error: the command says where the journal is and returns 130.
"""

from __future__ import annotations

import argparse
import signal
import sys
from pathlib import Path

import jax
import numpy as np

from jaxinertia import __version__, objects, plans
from jaxinertia.errors import HardwareError
from jaxinertia.hardware.collect import (
    DELTA,
    Journal,
    KinematicTagPose,
    collect,
    journal_path,
    plan_digest,
    samples_from_records,
)
from jaxinertia.hardware.driver import ArmConfig, DynamixelArm
from jaxinertia.hardware.safety import SafetyError, SafetyLimits
from jaxinertia.open_manipulator_x import GRIPPER_ID, JOINT_IDS, TAG_IN_EE, calibrated_robot
from jaxinertia.samples import save_native
from jaxinertia.sim.params import default_sim_params
from jaxinertia.virtual.bus import Faults
from jaxinertia.virtual.physics import VirtualServoBus

__all__ = ["register"]

#: Exit status of ``collect`` after Ctrl-C (journal kept, ``--resume`` continues).
EXIT_INTERRUPTED = 130

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


def _gripper(text: str) -> int | None:
    return None if text.lower() == "none" else int(text)


def cmd_virtual_robot(args) -> int:
    jax.config.update("jax_enable_x64", True)
    obj = objects.resolve(args.object)
    faults = Faults(drop_rate=args.drop_rate, corrupt_rate=args.corrupt_rate,
                    delay_rate=args.delay_rate, delay_s=args.delay_ms / 1000.0,
                    overload_id=args.overload_id, overload_after=args.overload_after,
                    seed=args.fault_seed)
    bus = VirtualServoBus(default_sim_params(args.calibration), obj, ids=args.ids,
                          extra_ids=() if args.gripper_id is None else (args.gripper_id,),
                          q0=np.radians(args.q0), speed=args.speed, faults=faults,
                          seed=args.seed)
    bus.compile()
    bus.start()
    # The device path is the first line of stdout: callers wait for it.
    print(bus.path, flush=True)
    print(f"virtual XM430-W350 servos {list(bus.servos)} on {bus.path}, object "
          f"{args.object}, {args.speed:g}x real time", file=sys.stderr, flush=True)

    def shutdown(signum, frame):  # noqa: ARG001
        bus.stop()

    signal.signal(signal.SIGTERM, shutdown)
    signal.signal(signal.SIGINT, shutdown)
    try:
        bus.wait()
    finally:
        bus.close()
    return 0


def cmd_collect(args) -> int:
    jax.config.update("jax_enable_x64", True)
    obj = None if args.object == UNKNOWN else objects.resolve(args.object)
    if args.plan == "planning":
        q_d, direction = plans.planning_plan()
        if args.n:
            q_d, direction = q_d[: args.n], direction[: args.n]
    else:
        q_d, direction = plans.random_plan(args.n or 1000, args.seed)
    # The calibrated bare arm: A and tau_g (as the simulator records them) and the FK of
    # the kinematic tag pose.
    robot = calibrated_robot(args.calibration)
    config = ArmConfig(
        port=args.port, baudrate=args.baudrate, joint_ids=args.ids, gripper_id=args.gripper_id,
        p_gain=args.p_gain, d_gain=args.d_gain, profile_velocity=args.profile_velocity,
        profile_acceleration=args.profile_acceleration, settle_time=args.settle_time,
        move_timeout=args.timeout, retries=args.retries, on_stop=args.on_stop,
        reboot_on_error=args.clear_errors)
    header = {"kind": "header", "plan": args.plan, "seed": args.seed, "n_samples": len(q_d),
              "object": args.object, "plan_digest": plan_digest(q_d, direction),
              "port": args.port, "servo_ids": list(args.ids), "delta": DELTA}
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    journal = Journal.open(journal_path(out), header, resume=args.resume)
    done = len(journal.records)
    if done:
        print(f"resuming: {done} of {len(q_d)} samples already in {journal.path}",
              file=sys.stderr)
    R_ee_tag, p_ee_tag = TAG_IN_EE
    tag_source = KinematicTagPose(robot, R_ee_tag, p_ee_tag)
    safety = SafetyLimits.around_workspace(robot)
    arm = DynamixelArm(config, robot=robot, safety=safety)

    def where() -> str:
        return (f"{len(journal.records)} of {len(q_d)} samples are in {journal.path}; "
                "continue with --resume")

    try:
        with arm:
            collect(arm, q_d, direction, journal, tag_pose=tag_source, delta=DELTA,
                    progress=not args.no_progress)
    except SafetyError as e:
        raise SafetyError(f"refused: {e}") from e
    except HardwareError as e:  # the bus or a servo (driver.CommError, driver.HardwareError)
        raise HardwareError(f"stopped ({config.on_stop}): {e}; {where()}") from e
    except KeyboardInterrupt:
        print(f"jaxinertia collect: interrupted ({config.on_stop}); {where()}",
              file=sys.stderr)
        return EXIT_INTERRUPTED
    finally:
        journal.close()
    print(f"bus: {arm.failed_transactions} failed transactions retried", file=sys.stderr)
    x = None if obj is None else np.asarray(obj.x)
    samples = samples_from_records(journal.records, robot, x, args.object)
    meta = {"version": __version__, "source": "dynamixel", "port": args.port,
            "plan": args.plan, "scenario": args.plan, "object": args.object,
            "objects": [args.object], "seed": args.seed, "servo_ids": list(args.ids),
            "gripper_id": args.gripper_id, "robot": robot.name, "delta": DELTA,
            "journal": str(journal.path), "plan_digest": header["plan_digest"],
            "tag_pose": "kinematic (open_manipulator_x.TAG_IN_EE)",
            "servo": {"p_gain": args.p_gain, "i_gain": 0, "d_gain": args.d_gain,
                      "profile_velocity": args.profile_velocity,
                      "profile_acceleration": args.profile_acceleration,
                      "settle_time": args.settle_time, "timeout": args.timeout}}
    path = save_native(out, samples, meta)
    bad = int(np.sum(~samples.at_rest))
    print(f"wrote {path} ({samples.n_samples} samples" + (
        f", {bad} timed out: at_rest = False)" if bad else ")"))
    return 0


def register(sub) -> None:
    """Adds this module's subcommands to the ``jaxinertia`` argparse subparsers."""
    names = ", ".join(objects.known_names())
    v = sub.add_parser(
        "virtual-robot",
        help="a simulated chain of XM430-W350-T servos on a pseudo-terminal",
        description="Opens a pseudo-terminal, prints its path as the first line of stdout "
        "and answers there as DYNAMIXEL servos (Protocol 2.0) whose joints are the "
        "simulated OpenMANIPULATOR-X. Runs until SIGTERM or Ctrl-C.",
    )
    v.add_argument("--object", default="none",
                   help=f"held object: {names} (none: the empty gripper)")
    v.add_argument("--speed", type=float, default=1.0, help="simulated seconds per second")
    v.add_argument("--ids", type=_ids, default=JOINT_IDS, help="joint servo IDs")
    v.add_argument("--gripper-id", type=_gripper, default=GRIPPER_ID, help="gripper ID or none")
    v.add_argument("--q0", type=float, nargs=4, default=(0.0, -30.0, 30.0, 0.0),
                   metavar="DEG", help="initial joint angles [deg]")
    v.add_argument("--seed", type=int, default=0, help="friction draws and current noise")
    v.add_argument("--calibration", type=Path, help="simulator parameter file")
    g = v.add_argument_group("fault injection")
    g.add_argument("--drop-rate", type=float, default=0.0, help="status packets not sent")
    g.add_argument("--corrupt-rate", type=float, default=0.0, help="status packets with bad CRC")
    g.add_argument("--delay-rate", type=float, default=0.0, help="status packets delayed")
    g.add_argument("--delay-ms", type=float, default=10.0)
    g.add_argument("--overload-id", type=int, help="servo that raises an overload error")
    g.add_argument("--overload-after", type=int, default=0,
                   help="... after this many Goal Position writes to it")
    g.add_argument("--fault-seed", type=int, default=0)
    v.set_defaults(func=cmd_virtual_robot)

    c = sub.add_parser(
        "collect",
        help="collect samples on the arm (or a virtual robot) into a native sample file",
        description="Runs a plan with the paper's protocol (pre-position q_d - s*3 deg, then "
        "q_d, record at rest). Every sample is appended to OUT.journal.jsonl and flushed; "
        "an interrupted collection continues with --resume.",
    )
    c.add_argument("--port", required=True, help="serial device (e.g. /dev/ttyUSB0)")
    c.add_argument("--plan", required=True, choices=["planning", "random"])
    c.add_argument("--object", required=True,
                   help=f"held object ({names}) or {UNKNOWN} (no ground truth: the file has "
                   "no tau and no x)")
    c.add_argument("--out", required=True, type=Path, help="native sample file (.npz)")
    c.add_argument("--resume", action="store_true", help="continue OUT.journal.jsonl")
    c.add_argument("--n", type=int, help="samples (random; caps planning)")
    c.add_argument("--seed", type=int, default=0, help="seed of the random plan")
    c.add_argument("--baudrate", type=int, default=1_000_000)
    c.add_argument("--ids", type=_ids, default=JOINT_IDS, help="joint servo IDs")
    c.add_argument("--gripper-id", type=_gripper, default=GRIPPER_ID,
                   help="gripper ID (pinged) or none")
    c.add_argument("--p-gain", type=int, default=800, help="Position P Gain register")
    c.add_argument("--d-gain", type=int, default=0, help="Position D Gain register (I is 0)")
    c.add_argument("--profile-velocity", type=float, default=0.5, help="[rad/s]")
    c.add_argument("--profile-acceleration", type=float, default=2.0, help="[rad/s^2]")
    c.add_argument("--settle-time", type=float, default=0.2,
                   help="no tick may change for this long to count as at rest [s, servo clock]")
    c.add_argument("--timeout", type=float, default=6.0, help="per move [s, servo clock]")
    c.add_argument("--retries", type=int, default=3, help="per bus transaction")
    c.add_argument("--on-stop", choices=["hold", "torque_off"], default="hold",
                   help="state to leave the arm in after an error or Ctrl-C")
    c.add_argument("--clear-errors", action="store_true",
                   help="reboot servos that report a hardware error on connect (after the "
                   "cause is fixed)")
    c.add_argument("--calibration", type=Path, help="simulator parameter file (the bare arm)")
    c.add_argument("--no-progress", action="store_true", help="no progress bar")
    c.set_defaults(func=cmd_collect)
