"""``--arm NAME|FILE`` on every command that touches an arm, and the checks that files of
one arm (sample files, model folders, plans) are not used with another's.

Sample files record ``meta["arm"]`` (and ``meta["robot"]``, the same name: an arm's robot
is named after it); files in the authors' layout record neither and are taken to be of the
arm given with ``--arm`` (else any).
"""

from __future__ import annotations

import os
from typing import TYPE_CHECKING

from jaxinertia.app.defaults import ARM_NAMES, DEFAULT_ARM
from jaxinertia.errors import RobotMismatchError, UsageError

if TYPE_CHECKING:
    from jaxinertia.arm import Arm

__all__ = ["LBIPE_ARM", "add_arm_option", "arm_name", "arm_of", "bus_arm_options",
           "lbipe_arm_only", "samples_arm"]

#: The arm of the authors' real files (the lbipe folder).
LBIPE_ARM = DEFAULT_ARM


def add_arm_option(parser, *, default: str | None = DEFAULT_ARM, what: str = "") -> None:
    """Adds ``--arm NAME|FILE`` to ``parser`` (``default`` None: ``what`` says what the
    command takes instead)."""
    said = "%(default)s" if default is not None else what
    parser.add_argument("--arm", default=default, metavar="NAME|FILE",
                        help=f"the arm: {', '.join(ARM_NAMES)}, or an arm file (.json/.toml) "
                        f"(default: {said})")


def arm_of(args, fallback: str | None = None) -> Arm:
    """The :class:`Arm` of ``--arm`` (``fallback`` when not given, else the default arm)."""
    from jaxinertia.arms import get_arm  # the registry loads descriptions: when a command runs

    return get_arm(args.arm or fallback or DEFAULT_ARM)


def arm_name(args) -> str | None:
    """The name of the ``--arm`` record, None when the option was left out."""
    return None if args.arm is None else arm_of(args).name


def samples_arm(path: str | os.PathLike, meta: dict, arm: str | None = None) -> str | None:
    """The arm a sample file's samples come from: what the file records, checked against
    ``arm`` (the command's ``--arm``) when both say; ``arm`` when the file records none."""
    recorded = meta.get("arm") or meta.get("robot")
    if arm is not None and recorded is not None and recorded != arm:
        raise RobotMismatchError(f"{path}: samples of the arm {recorded!r}, not of --arm "
                                 f"{arm!r}")
    return recorded or arm


def lbipe_arm_only(args, what: str) -> None:
    """Refuses ``--arm`` of another arm than the real lbipe files' for a stage on them."""
    if args.arm is not None and arm_of(args).name != LBIPE_ARM:
        raise UsageError(f"--arm {args.arm}: {what} the real lbipe files, which are the "
                         f"{LBIPE_ARM}'s")


def bus_arm_options(args):
    """The ``--arm`` record, its values filling the options left out (IDs, gripper ID,
    baud rate, position gains (per joint where they differ), motion timing, initial
    pose), whatever its bus."""
    import numpy as np  # (light; with the arm's records, which load JAX: at run time)

    from jaxinertia.hardware.arm_config import arm_config  # (as above)

    arm = arm_of(args)
    cfg = arm_config(arm, "")
    given = {"ids": cfg.joint_ids, "gripper_id": cfg.gripper_id, "baudrate": cfg.baudrate,
                "p_gain": cfg.p_gain, "d_gain": cfg.d_gain,
                "profile_velocity": cfg.profile_velocity,
                "profile_acceleration": cfg.profile_acceleration,
                "settle_time": cfg.settle_time, "timeout": cfg.move_timeout,
                "q0": [float(np.mean(w)) for w in arm.workspace_deg]}
    for k, v in given.items():
        if getattr(args, k, v) is None:
            setattr(args, k, v)
    if args.gripper_id == "none":
        args.gripper_id = None
    if hasattr(args, "q0") and len(args.q0) != arm.n_joints:
        raise UsageError(f"--q0 needs {arm.n_joints} angles (one per joint of {arm.name}), "
                         f"got {len(args.q0)}")
    return arm
