"""LeRobot calibration files (jaxinertia.lerobot_calibration): ticks <-> the description's
joint angles as docs/hardware.md describes, on the written examples in
tests/assets/lerobot (no JAX; milliseconds)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from jaxinertia.arms import KOCH_V1_1, SO101
from jaxinertia.errors import ConfigError
from jaxinertia.lerobot_calibration import (
    MotorCalibration,
    arm_calibration,
    rad_to_ticks,
    read_calibration,
    ticks_to_rad,
)

ASSETS = Path(__file__).parent / "assets" / "lerobot"
QUARTER = 1024  # ticks per quarter turn on both families (4096 a turn)


def test_the_example_files_read_as_written():
    so101 = read_calibration(ASSETS / "so101_follower.json")
    assert list(so101) == ["shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex",
                           "wrist_roll", "gripper"]
    assert so101["shoulder_pan"] == MotorCalibration(1, 0, -1470, 758, 3292)
    cal = arm_calibration(ASSETS / "so101_follower.json", SO101)
    assert cal.protocols == ("feetech_sts",) * 5 and cal.ticks_per_rev == (4096,) * 5
    koch = arm_calibration(ASSETS / "koch_follower.json", KOCH_V1_1)
    assert koch.protocols == ("dynamixel2",) * 5 and koch.ticks_per_rev == (4096,) * 5


def test_known_values():
    pan = MotorCalibration(id=1, drive_mode=0, homing_offset=-1470, range_min=758,
                           range_max=3292)  # middle 2025
    for protocol in ("feetech_sts", "dynamixel2"):
        assert ticks_to_rad(2025, pan, protocol=protocol) == 0.0
        np.testing.assert_allclose(ticks_to_rad(2025 + QUARTER, pan, protocol=protocol),
                                   np.pi / 2, rtol=0, atol=1e-15)
        np.testing.assert_allclose(ticks_to_rad(2025 - 2 * QUARTER, pan, protocol=protocol),
                                   -np.pi, rtol=0, atol=1e-15)
    # Raw encoder ticks (Homing Offset register 0): Feetech Present = Actual - offset,
    # DYNAMIXEL Present = Actual + offset.
    assert ticks_to_rad(2025 - 1470, pan, protocol="feetech_sts", present=False) == 0.0
    assert ticks_to_rad(2025 + 1470, pan, protocol="dynamixel2", present=False) == 0.0
    # drive_mode 1: Feetech reverses in software (LeRobot), DYNAMIXEL in the servo.
    rev = MotorCalibration(id=1, drive_mode=1, homing_offset=0, range_min=758, range_max=3292)
    np.testing.assert_allclose(ticks_to_rad(2025 + QUARTER, rev, protocol="feetech_sts"),
                               -np.pi / 2, rtol=0, atol=1e-15)
    np.testing.assert_allclose(ticks_to_rad(2025 + QUARTER, rev, protocol="dynamixel2"),
                               np.pi / 2, rtol=0, atol=1e-15)
    assert rad_to_ticks(-np.pi / 2, rev, protocol="feetech_sts") == 2025 + QUARTER
    # An odd range: the middle is half a tick.
    odd = MotorCalibration(id=2, drive_mode=0, homing_offset=0, range_min=612, range_max=3401)
    np.testing.assert_allclose(ticks_to_rad(2006.5, odd, protocol="feetech_sts"), 0.0, atol=0)


@pytest.mark.parametrize("name, arm", [("so101_follower.json", SO101),
                                       ("koch_follower.json", KOCH_V1_1)])
@pytest.mark.parametrize("present", [True, False])
def test_round_trip(name, arm, present):
    cal = arm_calibration(ASSETS / name, arm)
    ticks = np.stack([np.arange(c.range_min, c.range_max + 1)[:1000] for c in cal.calibrations],
                     axis=-1)
    if not present:  # raw encoder ticks of the same positions
        h = np.array([c.homing_offset for c in cal.calibrations])
        ticks = ticks + np.where(np.array(cal.protocols) == "feetech_sts", h, -h)
    q = cal.ticks_to_rad(ticks, present=present)
    assert q.shape == ticks.shape
    np.testing.assert_array_equal(cal.rad_to_ticks(q, present=present), ticks)
    # Every recorded range maps symmetrically about the description's zero.
    lo = cal.ticks_to_rad(np.array([c.range_min for c in cal.calibrations]))
    hi = cal.ticks_to_rad(np.array([c.range_max for c in cal.calibrations]))
    np.testing.assert_allclose(np.abs(lo), np.abs(hi), rtol=0, atol=1e-15)


def test_bad_files_say_what_is_wrong(tmp_path):
    doc = json.loads((ASSETS / "so101_follower.json").read_text())
    path = tmp_path / "cal.json"
    del doc["elbow_flex"]
    path.write_text(json.dumps(doc))
    with pytest.raises(ConfigError, match="elbow_flex.*no such motor \\(joint 3 of so101") as e:
        arm_calibration(path, SO101)
    assert "\n" not in str(e.value)
    doc = json.loads((ASSETS / "so101_follower.json").read_text())
    for change, match in [({"id": 7}, "7, but so101's joint 1 is bus ID 1"),
                          ({"range_max": 700}, "is empty"),
                          ({"drive_mode": 2}, "must be 0 or 1"),
                          ({"homing_offset": 1.5}, "must be an integer")]:
        path.write_text(json.dumps({**doc, "shoulder_pan": {**doc["shoulder_pan"], **change}}))
        with pytest.raises(ConfigError, match=match):
            arm_calibration(path, SO101)
    path.write_text("{")
    with pytest.raises(ConfigError, match="not a readable LeRobot calibration file"):
        read_calibration(path)
