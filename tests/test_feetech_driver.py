"""The Feetech driver (:class:`jaxinertia.hardware.feetech.FeetechArm`, scservo_sdk)
against the virtual SO-101 bus in this process (no simulator): connect (model 777),
configure (EEPROM behind the lock, read back), moves that settle at rest, safety refusals
before anything is written, an overload stop and its clearing, and a faulty bus crossed
without a false alarm. Limits are generous (a busy host); no wall-clock assertions."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from jaxinertia.arms import SO101
from jaxinertia.hardware import feetech_table as ft
from jaxinertia.hardware.driver import CommError, PortError
from jaxinertia.hardware.feetech import FeetechArm, StsHardwareError, feetech_config
from jaxinertia.hardware.feetech_transport import LockedScsPortHandler
from jaxinertia.hardware.safety import SafetyError
from jaxinertia.virtual.bus import Faults
from jaxinertia.virtual.sts_bus import StsServoBus

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"),
                                reason="the virtual servo bus needs a Linux pseudo-terminal")

LOADS = (0.0, 0.12, -0.08, 0.03, 0.0)
RETRIES = 400  # as the DYNAMIXEL hardware tests (support.hardware.RETRIES)
GOALS = np.radians([[10.0, -15.0, 20.0, 5.0, -10.0], [-5.0, 10.0, -10.0, 0.0, 8.0]])


class PatientPort(LockedScsPortHandler):
    """The driver's port, waiting up to 2 s for a status packet (tests/test_feetech_bus.py
    says why): a clean bus must then show no failed transaction."""

    def setPacketTimeout(self, packet_length):  # noqa: N802 (the SDK's name)
        super().setPacketTimeout(packet_length)
        self.packet_timeout = max(self.packet_timeout, 2000.0)


def patient(arm: FeetechArm) -> FeetechArm:
    arm.port = PatientPort(arm.config.port)
    return arm


def config(path: str, **kw):
    kw = {"retries": RETRIES, "move_timeout": 120.0, "profile_velocity": 2.0, **kw}
    return feetech_config(path, SO101, **kw)


def check_at_rest(bus, arm, goal, state, at_rest):
    assert at_rest, state
    # Short of the goal by the joint's load / P (16 on the SO-101), to the tick.
    rest = ft.rad_to_ticks(goal) - np.asarray(LOADS) * 1000 / arm.config.p_gain
    assert np.all(np.abs(state.ticks - rest) <= 1), (state.ticks, rest)
    assert not state.moving.any()
    np.testing.assert_allclose(state.voltage, 7.4)
    assert np.all(np.sign(state.load) == np.sign(np.round(LOADS, 2)))


def test_connect_configure_and_move():
    with StsServoBus(loads=LOADS) as bus, patient(FeetechArm(config(bus.path))) as arm:
        for i in SO101.bus_ids:
            mem = bus.servos[i]
            assert (mem.get("p_coefficient"), mem.get("i_coefficient"),
                    mem.get("d_coefficient")) == (16, 0, 0)
            assert mem.get("lock") == 1 and mem.get("torque_enable") == 1
            lo, hi = mem.get("min_position_limit"), mem.get("max_position_limit")
            assert 0 < lo < ft.ZERO_TICKS < hi < 4095
        assert bus.servos[6].get("p_coefficient") == 32  # the gripper is left alone
        for goal in GOALS:
            state, at_rest, _ = arm.move_and_settle(goal)
            check_at_rest(bus, arm, goal, state, at_rest)
        writes = bus.goal_position_writes
        with pytest.raises(SafetyError):
            arm.move_and_settle(np.radians([60.0, 0, 0, 0, 0]))  # beyond the workspace
        assert bus.goal_position_writes == writes, "nothing written for a refused goal"
        # A locked EEPROM is noticed on read-back, not taken for written.
        with pytest.raises(CommError, match="EEPROM locked"):
            arm._write_eeprom("p_coefficient", 20)
    assert arm.failed_transactions == 0 and arm.unconfirmed_alarms == 0
    assert arm.bus_report().startswith("0 failed transactions")
    for i in SO101.bus_ids:  # on_stop="hold": torque on, goal = where it stopped
        assert bus.servos[i].get("torque_enable") == 1


def test_wrong_model_port_errors_and_the_lock():
    with StsServoBus(loads=LOADS) as bus:
        bus.servos[3].set("model_number", 2825)  # an STS3250
        with pytest.raises(CommError, match="ID 3 is model 2825"), \
                FeetechArm(config(bus.path)):
            pass
        bus.servos[3].set("model_number", ft.STS3215_MODEL)
        first = FeetechArm(config(bus.path))
        first.open()
        with pytest.raises(PortError, match="in use"):
            FeetechArm(config(bus.path)).open()
        first.close()
    with pytest.raises(PortError, match="cannot open"):
        FeetechArm(config("/dev/nonexistent-sts")).open()


def test_an_overload_stops_and_clear_errors_resumes():
    faults = Faults(overload_id=2, overload_after=2)  # the 3rd goal write to servo 2
    with StsServoBus(loads=LOADS, faults=faults) as bus:
        with pytest.raises(StsHardwareError, match="ID 2: overload"), \
                FeetechArm(config(bus.path)) as arm:  # configure writes goal 1
            for goal in GOALS:
                arm.move_and_settle(goal)
        with pytest.raises(StsHardwareError, match="overload"), FeetechArm(config(bus.path)):
            pass  # refused until cleared
        with FeetechArm(config(bus.path, reboot_on_error=True)) as arm:
            state, at_rest, _ = arm.move_and_settle(GOALS[1])
            check_at_rest(bus, arm, GOALS[1], state, at_rest)


def test_a_faulty_bus_without_a_false_alarm():
    faults = Faults(drop_rate=0.02, corrupt_rate=0.02, delay_rate=0.02, delay_s=0.05, seed=3)
    with StsServoBus(loads=LOADS, faults=faults) as bus, FeetechArm(config(bus.path)) as arm:
        for goal in GOALS:
            state, at_rest, _ = arm.move_and_settle(goal)
            check_at_rest(bus, arm, goal, state, at_rest)
    print(f"faulty bus: {arm.bus_report()}")
    assert arm.failed_transactions > 0, "the injected faults must have been met"
    assert arm.unconfirmed_alarms == 0
