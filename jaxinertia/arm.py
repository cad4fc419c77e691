"""The arm as data: one frozen record holds every constant of an arm (as MuJoCo Playground
keeps ``<robot>_constants.py``), handed to the layers that need it.

An :class:`Arm` names its robot description (a file shipped under ``data/`` or a path), which
joints are the arm's and which is the gripper's jaw, the servo model and bus ID of every
joint, the workspace and safety limits, the tag mount, the clearance to the mounting
surface, the motion timing of the collection protocol, the pre-position offset, the planning
grid and the mounting (gravity in the base frame). :mod:`jaxinertia.arms` registers the
known arms and reads a user's own from a JSON or TOML file (:func:`arm_from_file`).
"""

from __future__ import annotations

import dataclasses
import json
import os
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from jaxinertia.errors import ConfigError
from jaxinertia.robot import Robot, data_path, load_robot
from jaxinertia.servos import ServoModel, servo_model

__all__ = ["Arm", "MotionTiming", "arm_from_dict", "arm_from_file", "arm_to_dict"]

_DEG = np.pi / 180.0


@dataclass(frozen=True)
class MotionTiming:
    """The collection protocol's motion, the same for the simulated and the real arm."""

    profile_velocity: float = 0.5  # trapezoidal profile's top speed [rad/s]
    profile_acceleration: float = 2.0  # [rad/s^2]
    settle_time: float = 0.2  # at rest when no tick changed for this long [s]
    move_timeout: float = 6.0  # per move; a sample not at rest by then is flagged [s]


@dataclass(frozen=True)
class Arm:
    """Every constant of one arm. Angles in degrees where a person writes them (workspace,
    offsets), SI otherwise; per-joint tuples are in ``arm_joints`` order.

    Attributes:
      name: registry name, and ``Robot.name`` of its robot (sample files and model folders
        record it).
      description: the robot description (URDF or MJCF): a path under the package's
        ``data/`` folder, or an absolute path (a relative one in a user's file is relative
        to that file).
      ee_site / ee_body: the end-effector frame the held object hangs from.
      arm_joints: the arm's joints, base to tip; gripper_joint: the jaw's (welded at zero
        in statics, its link lumped into the arm link carrying it), or None.
      servos: servo model name per arm joint (:data:`jaxinertia.servos.SERVO_MODELS`);
      bus_ids: bus ID per arm joint; gripper_servo, gripper_id: the jaw's; baudrate [bit/s].
      gains: per arm joint (P, I, D) registers overriding the servo model's, or None.
      workspace_deg: (lo, hi) per arm joint: planning grid and random goals.
      safety_margin_deg: joint limits = workspace widened by this much; safety_box_margin_m:
        the end-effector box around the workspace grows by this much [m].
      tag_rotation, tag_position: the tag frame in the end-effector frame.
      mount_clearance_m: end-effector clearance to the mounting surface (z = 0 of the base)
        below which a planning configuration counts as colliding [m].
      timing: :class:`MotionTiming`; pre_position_deg: the protocol's pre-position offset.
      planning_step_deg: the planning grid's step.
      gravity: gravitational acceleration in the base frame [m/s^2] (the mounting).
      armature: reflected rotor inertia per joint until a simulator fit sets it [kg m^2].
      sim_fit_file: the shipped simulator fit (under ``data/``), or None (an arm file's
        older key ``calibration_file`` is read as this).
      estimates: names of the fields that are estimates; notes: sources.
    """

    name: str
    description: str
    arm_joints: tuple[str, ...]
    servos: tuple[str, ...]
    bus_ids: tuple[int, ...]
    workspace_deg: tuple[tuple[float, float], ...]
    tag_position: tuple[float, float, float]
    mount_clearance_m: float
    gravity: tuple[float, float, float]
    ee_site: str | None = None
    ee_body: str | None = None
    gripper_joint: str | None = None
    gripper_servo: str | None = None
    gripper_id: int | None = None
    baudrate: int = 1_000_000
    gains: tuple[tuple[float, float, float] | None, ...] | None = None
    safety_margin_deg: float = 8.0
    safety_box_margin_m: float = 0.03
    tag_rotation: tuple[tuple[float, float, float], ...] = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0),
                                                            (0.0, 0.0, 1.0))
    timing: MotionTiming = field(default_factory=MotionTiming)
    pre_position_deg: float = 3.0
    planning_step_deg: float = 10.0
    armature: float = 0.01
    sim_fit_file: str | None = None
    estimates: tuple[str, ...] = ()
    notes: str = ""

    def __post_init__(self):
        n = len(self.arm_joints)
        for what in ("servos", "bus_ids", "workspace_deg"):
            if len(getattr(self, what)) != n:
                raise ConfigError(self.name, what, f"needs {n} entries (one per arm joint), "
                                  f"got {len(getattr(self, what))}")
        if self.gains is not None and len(self.gains) != n:
            raise ConfigError(self.name, "gains", f"needs {n} entries or none")
        for lo, hi in self.workspace_deg:
            if not lo < hi:
                raise ConfigError(self.name, "workspace_deg", f"({lo}, {hi}) is empty")
        ids = list(self.bus_ids) + ([self.gripper_id] if self.gripper_id is not None else [])
        if len(set(ids)) != len(ids):
            raise ConfigError(self.name, "bus_ids", f"IDs repeat: {ids}")
        for s in self.servos + ((self.gripper_servo,) if self.gripper_servo else ()):
            try:
                servo_model(s)
            except KeyError as e:
                raise ConfigError(self.name, "servos", str(e.args[0])) from None
        if (self.ee_site is None) == (self.ee_body is None):
            raise ConfigError(self.name, "ee_site", "give exactly one of ee_site, ee_body")
        if not all(t >= 0 for t in (self.pre_position_deg, self.mount_clearance_m)):
            raise ConfigError(self.name, None, "offsets and clearances must be >= 0")

    # ---- derived -----------------------------------------------------------------------
    @property
    def n_joints(self) -> int:
        return len(self.arm_joints)

    @property
    def servo_models(self) -> tuple[ServoModel, ...]:
        return tuple(servo_model(s) for s in self.servos)

    @property
    def joint_gains(self) -> tuple[tuple[float, float, float], ...]:
        """(P, I, D) registers per arm joint: the record's override, else the servo model's."""
        overrides = self.gains or (None,) * self.n_joints
        return tuple(tuple(g) if g else m.gains for g, m in zip(overrides, self.servo_models))

    @property
    def bus(self) -> str:
        """The protocol every servo of the arm speaks (``ServoModel.protocol``); one bus
        cannot mix protocols (:class:`ConfigError`)."""
        models = self.servo_models + ((servo_model(self.gripper_servo),)
                                      if self.gripper_servo else ())
        protocols = sorted({m.protocol for m in models})
        if len(protocols) != 1:
            raise ConfigError(self.name, "servos", f"one bus cannot mix {protocols} servos")
        return protocols[0]

    @property
    def has_current_sensors(self) -> bool:
        """Whether every arm joint's servo reads its motor current (the Sensor baseline)."""
        return all(m.has_current_sensor for m in self.servo_models)

    @property
    def pre_position(self) -> float:
        """The pre-position offset [rad]."""
        return self.pre_position_deg * np.pi / 180.0

    @property
    def tag_in_ee(self) -> tuple[np.ndarray, np.ndarray]:
        """(R, p) of the tag frame in the end-effector frame."""
        return np.array(self.tag_rotation, np.float64), np.array(self.tag_position, np.float64)

    def description_path(self) -> Path:
        p = Path(self.description)
        return p if p.is_absolute() else data_path(self.description)

    def robot(self, *, dtype=None) -> Robot:
        """The bare arm from its description (arm joints only, the jaw welded), mounted as
        the record says, named after the arm."""
        robot = load_robot(self.description_path(), ee_site=self.ee_site, ee_body=self.ee_body,
                           arm_joints=self.arm_joints, gravity=self.gravity, dtype=dtype)
        if robot.joint_names != self.arm_joints:
            raise ConfigError(self.name, "arm_joints", f"the description's chain is "
                              f"{robot.joint_names}, not {self.arm_joints}")
        return robot.replace(name=self.name)


def arm_to_dict(arm: Arm) -> dict:
    """The record as plain data (what :func:`arm_from_dict` reads back)."""
    return json.loads(json.dumps(dataclasses.asdict(arm)))


def arm_from_dict(data: dict, *, where: str | os.PathLike = "arm", base: Path | None = None
                  ) -> Arm:
    """An :class:`Arm` from plain data; a relative ``description`` is taken relative to
    ``base`` (the file's folder) when that file exists there, else under ``data/``."""
    fields = {f.name for f in dataclasses.fields(Arm)}
    if "calibration_file" in data and "sim_fit_file" not in data:  # arm files written before
        data = {("sim_fit_file" if k == "calibration_file" else k): v for k, v in data.items()}
    unknown = sorted(set(data) - fields)
    if unknown:
        raise ConfigError(where, unknown[0], f"unknown field (known: {sorted(fields)})")
    d = dict(data)
    try:
        if "timing" in d:
            d["timing"] = MotionTiming(**d["timing"])
        for k in ("arm_joints", "servos", "bus_ids", "tag_position", "gravity", "estimates"):
            if k in d:
                d[k] = tuple(d[k])
        for k in ("workspace_deg", "tag_rotation"):
            if k in d:
                d[k] = tuple(tuple(float(x) for x in row) for row in d[k])
        if d.get("gains") is not None:
            d["gains"] = tuple(None if g is None else tuple(float(x) for x in g)
                               for g in d["gains"])
        if base is not None and "description" in d and not Path(d["description"]).is_absolute():
            local = (base / d["description"]).resolve()
            if local.exists():
                d["description"] = str(local)
        return Arm(**d)
    except ConfigError:
        raise
    except (TypeError, ValueError) as e:
        raise ConfigError(where, None, f"not a usable arm ({type(e).__name__}: {e})") from None


def arm_from_file(path: str | os.PathLike) -> Arm:
    """A user's arm from a JSON (``.json``) or TOML (``.toml``) file with :class:`Arm`'s
    fields (``timing`` a table/object of :class:`MotionTiming`'s)."""
    path = Path(path)
    try:
        text = path.read_text()
        data = tomllib.loads(text) if path.suffix.lower() == ".toml" else json.loads(text)
    except (OSError, ValueError) as e:
        raise ConfigError(path, None, f"not a readable arm file ({e})") from e
    if not isinstance(data, dict):
        raise ConfigError(path, None, "an arm file holds one object/table of fields")
    return arm_from_dict(data, where=path, base=path.parent)
