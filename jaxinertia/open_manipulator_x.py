"""The OpenMANIPULATOR-X as the paper mounts and uses it: every constant of the arm in one
place (as MuJoCo Playground keeps ``<robot>_constants.py``).

The constants below are the data of :data:`ARM`, the arm's :class:`jaxinertia.arm.Arm`
record (registered in :mod:`jaxinertia.arms` as ``open_manipulator_x``); other arms are
records there. Nothing else in the library assumes four joints.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from jaxinertia.arm import Arm, MotionTiming
from jaxinertia.errors import ConfigError
from jaxinertia.robot import OPEN_MANIPULATOR_X_XML, Robot, data_path, open_manipulator_x

__all__ = [
    "ARM",
    "SIM_FIT_FILE",
    "DEFAULT_ARMATURE",
    "JOINT_IDS",
    "MOUNT_CLEARANCE_M",
    "NAME",
    "TAG_IN_EE",
    "WORKSPACE_DEG",
    "sim_fit_robot",
    "load_sim_fit",
]

#: ``Robot.name`` of the embedded description (sample files and model folders record it).
NAME = "open_manipulator_x"

#: DYNAMIXEL IDs of joints 1-4 (the ROBOTIS default) and of the gripper servo.
JOINT_IDS = (11, 12, 13, 14)
GRIPPER_ID = 15

#: The authors' workspace per joint [deg] (planning grid and random goals).
WORKSPACE_DEG = ((-30.0, 30.0), (-50.0, -10.0), (10.0, 50.0), (-20.0, 20.0))

#: Tag frame in the end-effector frame: the offset fitted on the real cube data
#: (lbipe README: about [9.3, -0.4, 23.2] mm), orientation identity.
TAG_IN_EE = (np.eye(3), np.array([0.00925, -0.00043, 0.0232]))

#: Clearance of the end-effector point from the mounting surface (the plane z = 0 of the
#: base frame, vertical on the paper's wall-mounted arm) below which a planning
#: configuration counts as colliding: gripper and held object (up to ~70 mm) need it.
#: Any value between 97.8 and 102.5 mm removes the same 22 of the 125 (q2, q3, q4) grid
#: points and leaves 721 configurations, i.e. the paper's 46,144 planning samples.
MOUNT_CLEARANCE_M = 0.10

#: Reflected rotor inertia of the XM430 gear train [kg m^2] (until a simulator fit sets it).
DEFAULT_ARMATURE = 0.01

#: The shipped simulator fit: link gravity fitted to the real ``tau_g``, servo and friction
#: parameters of the simulated arm (``jaxinertia calibrate`` writes it).
SIM_FIT_FILE = "open_manipulator_x_sim.json"


#: The arm as one record (the constants above, the collection protocol's motion timing and
#: pre-position, the planning grid, the paper's wall mounting).
ARM = Arm(
    name=NAME,
    description=OPEN_MANIPULATOR_X_XML,
    ee_site="end_effector",
    arm_joints=("joint1", "joint2", "joint3", "joint4"),
    gripper_joint=None,  # the embedded description has no jaw (shared/robots/README.md)
    servos=("xm430_w350",) * 4,
    bus_ids=JOINT_IDS,
    gripper_servo="xm430_w350",
    gripper_id=GRIPPER_ID,
    baudrate=1_000_000,
    workspace_deg=WORKSPACE_DEG,
    safety_margin_deg=8.0,
    safety_box_margin_m=0.03,
    tag_position=tuple(float(x) for x in TAG_IN_EE[1]),
    mount_clearance_m=MOUNT_CLEARANCE_M,
    timing=MotionTiming(profile_velocity=0.5, profile_acceleration=2.0, settle_time=0.2,
                        move_timeout=6.0),
    pre_position_deg=3.0,
    planning_step_deg=10.0,
    gravity=(-9.81, 0.0, 0.0),  # joint 1's axis horizontal (Lao et al.)
    armature=DEFAULT_ARMATURE,
    sim_fit_file=SIM_FIT_FILE,
    notes="ROBOTIS OpenMANIPULATOR-X (RM-X52-TNM) as the paper mounts and uses it",
)


def load_sim_fit(path: str | os.PathLike | None = None) -> dict:
    """The simulator-fit file at ``path`` (default: the shipped one) as a dict (the
    command line's ``--calibration FILE``)."""
    path = Path(path) if path else data_path(SIM_FIT_FILE)
    try:
        cal = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise ConfigError(path, None, f"not a readable calibration file ({e})") from e
    if not isinstance(cal, dict):
        raise ConfigError(path, None, "not a calibration file (a JSON object expected, got "
                          f"{type(cal).__name__})")
    g = cal.get("link_gravity")
    if g is None:
        raise ConfigError(path, "link_gravity", "missing")
    if not isinstance(g, dict) or not {"link_mass", "link_com"} <= set(g):
        raise ConfigError(path, "link_gravity", "must hold link_mass and link_com")
    return cal


def sim_fit_robot(fit: dict | str | os.PathLike | None = None) -> Robot:
    """The bare arm with the link masses and first moments fitted to the real ``tau_g``
    (the robot that ``A`` and ``tau_g`` of samples are computed with) and the default
    armature; ``fit`` is a loaded dict, a path, or None for the shipped file."""
    if not isinstance(fit, dict):
        fit = load_sim_fit(fit)
    robot = open_manipulator_x()
    g = fit["link_gravity"]
    return robot.replace(mass=jnp.asarray(g["link_mass"], robot.mass.dtype),
                         com=jnp.asarray(g["link_com"], robot.com.dtype),
                         armature=jnp.full(robot.n_joints, DEFAULT_ARMATURE))
