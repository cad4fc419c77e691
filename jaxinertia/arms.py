"""The registry of arms: ``open_manipulator_x`` (the paper's), ``so101`` (LeRobot's SO-101,
Feetech STS3215), ``koch_v1_1`` (Koch v1.1, DYNAMIXEL XL430-W250 + XL330-M288), and a user's
own from a JSON or TOML file (:func:`get_arm` takes a name or a path).

The SO-101 and Koch descriptions are the published files, shipped unchanged under
``data/arms/`` with their licences (``data/arms/README.md``). What the files do not state is
estimated here and named in each record's ``estimates``: the workspace (around each arm's
zero pose, an L with the upper arm up and the forearm forward, +-40 deg on the pitch joints),
the planning grid's step (20 deg: five joints at 10 deg would give ~30x the
OpenMANIPULATOR-X's grid), the tag mount (the tag frame at the end-effector frame: measure
yours), the clearance (the OpenMANIPULATOR-X's 0.10 m: gripper and held object below the
end-effector point), and the motion timing (the OpenMANIPULATOR-X's).
"""

from __future__ import annotations

import os
from pathlib import Path

from jaxinertia.arm import Arm, arm_from_file
from jaxinertia.errors import ConfigError
from jaxinertia.open_manipulator_x import ARM as OPEN_MANIPULATOR_X

__all__ = ["ARMS", "DEFAULT_ARM", "KOCH_V1_1", "OPEN_MANIPULATOR_X", "SO101", "get_arm"]

_TABLE = (0.0, 0.0, -9.81)  # standing on a table, base z up (MuJoCo's default gravity)
_ESTIMATED = ("workspace_deg", "planning_step_deg", "tag_position", "mount_clearance_m",
              "timing", "armature")

SO101 = Arm(
    name="so101",
    description="arms/so101/so101_new_calib.xml",  # the URDF beside it describes the same arm
    ee_site="gripperframe",
    arm_joints=("shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll"),
    gripper_joint="gripper",
    # The standard follower kit's STS3215 (7.4 V, 1:345); a 12 V build names sts3215_12v.
    servos=("sts3215_7v4",) * 5,
    bus_ids=(1, 2, 3, 4, 5),  # LeRobot's SO-101 IDs; the gripper is 6
    gripper_servo="sts3215_7v4",
    gripper_id=6,
    baudrate=1_000_000,
    workspace_deg=((-30.0, 30.0), (-40.0, 40.0), (-40.0, 40.0), (-40.0, 40.0), (-40.0, 40.0)),
    tag_position=(0.0, 0.0, 0.0),
    mount_clearance_m=0.10,
    planning_step_deg=20.0,
    gravity=_TABLE,
    armature=0.028,  # the SO-101 MJCF's sts3215 joint class (armature="0.028")
    estimates=_ESTIMATED,
    notes="SO-101 follower, TheRobotStudio/SO-ARM100 so101_new_calib (zero = middle of each "
          "joint's range, LeRobot's calibration convention)",
)

KOCH_V1_1 = Arm(
    name="koch_v1_1",
    description="arms/koch_v1_1/follower.urdf",
    ee_body="link_5",  # the file has no end-effector frame: the static jaw's link
    arm_joints=("joint_1", "joint_2", "joint_3", "joint_4", "joint_5"),
    gripper_joint="joint_6",
    servos=("xl430_w250", "xl430_w250", "xl330_m288", "xl330_m288", "xl330_m288"),
    bus_ids=(1, 2, 3, 4, 5),  # LeRobot's Koch IDs; the gripper is 6
    gripper_servo="xl330_m288",
    gripper_id=6,
    baudrate=1_000_000,
    # LeRobot's Koch follower sets the elbow's position gains to P = 1500, I = 0, D = 600.
    gains=(None, None, (1500.0, 0.0, 600.0), None, None),
    workspace_deg=((-30.0, 30.0), (-40.0, 40.0), (-40.0, 40.0), (-40.0, 40.0), (-40.0, 40.0)),
    tag_position=(0.0, 0.0, 0.0),
    mount_clearance_m=0.10,
    planning_step_deg=20.0,
    gravity=_TABLE,
    armature=0.005,
    estimates=_ESTIMATED,
    notes="Koch v1.1 follower, s1lent4gnt/koch-v1-1 simulation/follower.urdf; joints 1-2 "
          "XL430-W250 (no current sensor), 3-6 XL330-M288",
)

#: Known arms by name.
ARMS: dict[str, Arm] = {a.name: a for a in (OPEN_MANIPULATOR_X, SO101, KOCH_V1_1)}

#: What every command uses without ``--arm``.
DEFAULT_ARM = OPEN_MANIPULATOR_X.name


def get_arm(name_or_path: str | os.PathLike | Arm | None = None) -> Arm:
    """A registered arm by name, a user's arm file (``.json`` / ``.toml``), or the default
    (None); an :class:`Arm` passes through."""
    if isinstance(name_or_path, Arm):
        return name_or_path
    if name_or_path is None:
        return ARMS[DEFAULT_ARM]
    key = str(name_or_path)
    if key in ARMS:
        return ARMS[key]
    path = Path(key)
    if path.suffix.lower() in (".json", ".toml"):
        return arm_from_file(path)
    raise ConfigError(key, None, f"not a known arm ({', '.join(sorted(ARMS))}) nor an arm "
                      "file (.json or .toml)")
