"""LeRobot calibration files: a LeRobot-calibrated SO-101 or Koch read in the description's
joint angles without a second calibration.

LeRobot (0.2 and later) writes one JSON object per arm, keyed by motor name; each motor
has ``id`` (bus ID), ``drive_mode`` (0 or 1), ``homing_offset`` (signed ticks),
``range_min`` and ``range_max`` (ticks, the extremes recorded while the joint was moved
through its range by hand). LeRobot writes ``homing_offset`` into the servo's Homing
Offset register, so the Present Position a servo reports is already shifted by it:

* Feetech STS: Present = Actual - Homing_Offset (the register is sign-magnitude, bit 11);
* DYNAMIXEL X: Present = Actual + Homing_Offset (a 4-byte two's-complement register).

Both servo families count 4096 ticks per output turn (the STS3215's 12-bit encoder, the
X series' 4096). LeRobot's half-turn homing puts the pose the arm was in when calibrated
near tick 2047, and the middle of the recorded range is the joint's zero: the SO-101's
``so101_new_calib`` description is drawn with that zero. So, per joint,

    q = s * (Present - (range_min + range_max) / 2) * 2 pi / ticks_per_turn   [rad]

with ``s = -1`` where ``drive_mode`` is 1 and the reversal is not done by the servo
(Feetech: LeRobot flips the sign in software), else ``+1`` (DYNAMIXEL: the Drive Mode
register's reverse bit makes the servo report reversed positions itself). The inverse
rounds to the nearest tick. ``present=False`` takes raw encoder positions (Homing Offset
register 0) and applies the offset as the servo would. Details and the differences from
LeRobot's own degrees (it divides by 4095, not 4096, and ignores ``drive_mode`` there) are
in docs/hardware.md.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from jaxinertia.errors import ConfigError

__all__ = ["LEROBOT_ARM_MOTORS", "ArmCalibration", "MotorCalibration", "arm_calibration",
           "rad_to_ticks", "read_calibration", "ticks_to_rad"]

#: LeRobot's motor names of the SO-101's and the Koch's arm joints, base to tip (the
#: gripper is ``gripper``).
LEROBOT_ARM_MOTORS = ("shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll")

_FIELDS = ("id", "drive_mode", "homing_offset", "range_min", "range_max")


@dataclass(frozen=True)
class MotorCalibration:
    """One motor of a LeRobot calibration file (ticks)."""

    id: int
    drive_mode: int
    homing_offset: int
    range_min: int
    range_max: int

    @property
    def middle(self) -> float:
        """The joint's zero [ticks, Present Position]."""
        return 0.5 * (self.range_min + self.range_max)


def _sign(cal: MotorCalibration, protocol: str) -> float:
    return -1.0 if cal.drive_mode and protocol == "feetech_sts" else 1.0


def _homing(protocol: str) -> float:
    """Present = Actual + this * Homing_Offset."""
    return -1.0 if protocol == "feetech_sts" else 1.0


def ticks_to_rad(ticks, cal: MotorCalibration, *, protocol: str, ticks_per_rev: int = 4096,
                 present: bool = True) -> np.ndarray:
    """Joint angle [rad] of position ticks of one motor (``present``: Present Position as
    the servo reports it with the calibration's homing offset in its register; else raw
    encoder ticks). ``protocol``: ``"feetech_sts"`` or ``"dynamixel2"``."""
    p = np.asarray(ticks, np.float64)
    if not present:
        p = p + _homing(protocol) * cal.homing_offset
    return _sign(cal, protocol) * (p - cal.middle) * (2.0 * np.pi / ticks_per_rev)


def rad_to_ticks(q, cal: MotorCalibration, *, protocol: str, ticks_per_rev: int = 4096,
                 present: bool = True) -> np.ndarray:
    """The inverse of :func:`ticks_to_rad`, rounded to the nearest tick (int64)."""
    p = cal.middle + _sign(cal, protocol) * np.asarray(q, np.float64) * (
        ticks_per_rev / (2.0 * np.pi))
    if not present:
        p = p - _homing(protocol) * cal.homing_offset
    return np.rint(p).astype(np.int64)


def read_calibration(source: str | os.PathLike | dict) -> dict[str, MotorCalibration]:
    """A LeRobot calibration file (or its loaded JSON) -> ``{motor name: calibration}``,
    every field checked (one error naming the file, the motor and the field)."""
    where = "calibration" if isinstance(source, dict) else Path(source)
    if isinstance(source, dict):
        doc = source
    else:
        try:
            doc = json.loads(Path(source).read_text())
        except (OSError, ValueError) as e:
            raise ConfigError(where, None, f"not a readable LeRobot calibration file ({e})"
                              ) from None
    if not isinstance(doc, dict) or not doc:
        raise ConfigError(where, None, "a LeRobot calibration file is one object keyed by "
                          "motor name")
    out = {}
    for name, m in doc.items():
        if not isinstance(m, dict):
            raise ConfigError(where, name, "not an object of id, drive_mode, homing_offset, "
                              "range_min, range_max")
        missing = [f for f in _FIELDS if f not in m]
        if missing:
            raise ConfigError(where, f"{name}.{missing[0]}", "missing")
        bad = [f for f in _FIELDS if isinstance(m[f], bool) or not isinstance(m[f], int)]
        if bad:
            raise ConfigError(where, f"{name}.{bad[0]}", f"must be an integer, got {m[bad[0]]!r}")
        cal = MotorCalibration(**{f: int(m[f]) for f in _FIELDS})
        if cal.drive_mode not in (0, 1):
            raise ConfigError(where, f"{name}.drive_mode", f"must be 0 or 1, got {cal.drive_mode}")
        if not cal.range_min < cal.range_max:
            raise ConfigError(where, f"{name}.range_max", f"range [{cal.range_min}, "
                              f"{cal.range_max}] is empty")
        out[name] = cal
    return out


@dataclass(frozen=True)
class ArmCalibration:
    """An arm's joints in LeRobot's calibration: per arm joint (base to tip) its motor's
    calibration, servo protocol and ticks per turn."""

    motors: tuple[str, ...]
    calibrations: tuple[MotorCalibration, ...]
    protocols: tuple[str, ...]
    ticks_per_rev: tuple[int, ...]

    def ticks_to_rad(self, ticks, *, present: bool = True) -> np.ndarray:
        """(..., N) ticks -> (..., N) joint angles [rad] of the description."""
        t = np.asarray(ticks)
        return np.stack([ticks_to_rad(t[..., j], c, protocol=p, ticks_per_rev=r,
                                      present=present)
                         for j, (c, p, r) in enumerate(self._joints())], axis=-1)

    def rad_to_ticks(self, q, *, present: bool = True) -> np.ndarray:
        """(..., N) joint angles [rad] -> (..., N) ticks (int64)."""
        q = np.asarray(q)
        return np.stack([rad_to_ticks(q[..., j], c, protocol=p, ticks_per_rev=r,
                                      present=present)
                         for j, (c, p, r) in enumerate(self._joints())], axis=-1)

    def _joints(self):
        return zip(self.calibrations, self.protocols, self.ticks_per_rev)


def arm_calibration(source: str | os.PathLike | dict, arm, *,
                    motors: tuple[str, ...] = LEROBOT_ARM_MOTORS) -> ArmCalibration:
    """The calibration of ``arm`` (an :class:`jaxinertia.arm.Arm`) from a LeRobot file:
    ``motors`` names its arm joints' motors in the file (LeRobot's names by default). A
    motor the file lacks, or whose ID is not the record's bus ID, is an error."""
    where = "calibration" if isinstance(source, dict) else source
    file = read_calibration(source)
    if len(motors) != arm.n_joints:
        raise ConfigError(where, None, f"{len(motors)} motor names for the {arm.n_joints} "
                          f"joints of {arm.name}")
    cals = []
    for j, (name, bus_id) in enumerate(zip(motors, arm.bus_ids)):
        if name not in file:
            raise ConfigError(where, name, f"no such motor (joint {j + 1} of {arm.name}, "
                              f"{arm.arm_joints[j]}); the file has {sorted(file)}")
        if file[name].id != bus_id:
            raise ConfigError(where, f"{name}.id", f"{file[name].id}, but {arm.name}'s "
                              f"joint {j + 1} is bus ID {bus_id}")
        cals.append(file[name])
    models = arm.servo_models
    return ArmCalibration(tuple(motors), tuple(cals), tuple(m.protocol for m in models),
                          tuple(m.ticks_per_rev for m in models))
