"""Protocol 2.0 conformance of the virtual servo bus, checked with dynamixel-sdk's own
packet handler through the pseudo-terminal; plus the driver's safety checks.

Registers are integers and compared exactly; failures name the register and the servo.
"""

from __future__ import annotations

import os
import sys
import time

import numpy as np
import pytest
from dynamixel_sdk import (
    COMM_RX_TIMEOUT,
    COMM_SUCCESS,
    GroupBulkRead,
    GroupSyncRead,
    GroupSyncWrite,
    PacketHandler,
    PortHandler,
)

from jaxinertia.hardware import control_table as ct
from jaxinertia.hardware.driver import ArmConfig, DynamixelArm
from jaxinertia.hardware.protocol import (
    Instruction,
    add_stuffing,
    crc16,
    encode_packet,
    remove_stuffing,
)
from jaxinertia.hardware.safety import SafetyError, SafetyLimits
from jaxinertia.objects import resolve
from jaxinertia.open_manipulator_x import calibrated_robot
from jaxinertia.sim.params import default_sim_params
from jaxinertia.virtual.physics import VirtualServoBus
from jaxinertia.virtual.testing import VirtualRobotProcess

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"),
                                reason="the virtual servo bus needs a Linux pseudo-terminal")

IDS = (11, 12, 13, 14)
#: The one tolerance of this module: register gains mapped onto the simulator's (float64
#: arithmetic on the same numbers).
RTOL = 1e-7


@pytest.fixture(scope="module")
def bus():
    b = VirtualServoBus(default_sim_params(), resolve("cube"),
                        q0=np.radians([0.0, -30.0, 30.0, 0.0]), speed=5.0)
    with b:
        yield b


@pytest.fixture()
def sdk(bus):
    port = PortHandler(bus.path)
    assert port.openPort()
    yield port, PacketHandler(2.0)
    port.closePort()


def test_crc_and_stuffing_agree_with_the_sdk():
    ph = PacketHandler(2.0)
    rng = np.random.default_rng(0)
    for n in (1, 7, 64, 300):
        data = rng.integers(0, 256, n).tolist()
        assert crc16(bytes(data)) == ph.updateCRC(0, data, n), f"CRC of {n} bytes"
    body = bytes([0x03, 0x70, 0x00, 0xFF, 0xFF, 0xFD, 0x00, 0xFF, 0xFF, 0xFD])
    stuffed = add_stuffing(body)
    assert stuffed == body[:6] + b"\xfd" + body[6:] + b"\xfd", "stuffed packet body"
    assert remove_stuffing(stuffed) == body, "unstuffed packet body"


def test_ping_read_write_with_the_sdk(sdk):
    port, ph = sdk
    for dxl_id in (*IDS, 15):
        assert ph.ping(port, dxl_id) == (1020, COMM_SUCCESS, 0), f"ping ID {dxl_id}"
    assert ph.ping(port, 99)[1] == COMM_RX_TIMEOUT, "ping ID 99"  # no such servo: silence
    found, result = ph.broadcastPing(port)
    assert result == COMM_SUCCESS and sorted(found) == [*IDS, 15], f"broadcast ping: {found}"
    assert ph.read1ByteTxRx(port, 11, 11) == (3, COMM_SUCCESS, 0), "operating_mode of ID 11"
    assert ph.read2ByteTxRx(port, 12, 84) == (800, COMM_SUCCESS, 0), "position_p_gain of ID 12"
    assert ph.read4ByteTxRx(port, 12, 132)[0] == 2048 - 341, "present_position of ID 12"
    # A WRITE whose data contain FF FF FD (byte stuffing both ways).
    value = int.from_bytes(b"\xff\xff\xfd\x00", "little")
    assert ph.write4ByteTxRx(port, 13, 112, value) == (COMM_SUCCESS, 0), "write profile_velocity"
    assert ph.read4ByteTxRx(port, 13, 112) == (value, COMM_SUCCESS, 0), "profile_velocity of ID 13"
    assert ph.write4ByteTxRx(port, 13, 112, 0) == (COMM_SUCCESS, 0), "write profile_velocity"
    # Read-only item and unknown instruction: status packets with the error number.
    assert ph.write2ByteTxRx(port, 11, 126, 5) == (COMM_SUCCESS, 7), "write present_current"
    rx, result, error = ph.txRxPacket(port, [0, 0, 0, 0, 11, 3, 0, 0x7E, 0, 0])
    assert result == COMM_SUCCESS and error == 2, "unknown instruction: instruction error"


def test_sync_and_bulk_instructions(sdk):
    port, ph = sdk
    w = GroupSyncWrite(port, ph, 108, 4)
    for k, dxl_id in enumerate(IDS):
        assert w.addParam(dxl_id, (100 + k).to_bytes(4, "little"))
    assert w.txPacket() == COMM_SUCCESS, "sync write profile_acceleration"
    r = GroupSyncRead(port, ph, 108, 8)  # profile acceleration + velocity
    for dxl_id in IDS:
        r.addParam(dxl_id)
    assert r.txRxPacket() == COMM_SUCCESS, "sync read profile_acceleration + velocity"
    got = [r.getData(i, 108, 4) for i in IDS]
    assert got == [100, 101, 102, 103], f"profile_acceleration of IDs {IDS}: {got}"
    b = GroupBulkRead(port, ph)
    assert b.addParam(11, 84, 2) and b.addParam(14, 0, 2) and b.addParam(15, 7, 1)
    assert b.txRxPacket() == COMM_SUCCESS, "bulk read"
    got = (b.getData(11, 84, 2), b.getData(14, 0, 2), b.getData(15, 7, 1))
    assert got == (800, 1020, 15), f"position_p_gain of 11, model_number of 14, id of 15: {got}"
    for dxl_id in IDS:
        assert ph.write4ByteTxRx(port, dxl_id, 108, 0) == (COMM_SUCCESS, 0), (
            f"write profile_acceleration of ID {dxl_id}")


def test_a_corrupted_packet_gets_no_reply_and_changes_nothing(bus, sdk):
    port, ph = sdk
    good = encode_packet(12, Instruction.WRITE, bytes([112, 0, 9, 0, 0, 0]))
    bad = good[:-1] + bytes([good[-1] ^ 0xFF])
    port.clearPort()
    port.writePort(bad)
    time.sleep(0.1)
    assert port.getBytesAvailable() == 0, "reply bytes to a corrupted packet"
    assert ph.read4ByteTxRx(port, 12, 112)[0] == 0, "profile_velocity of ID 12"
    port.writePort(good)  # the same packet with its CRC intact is executed and answered
    time.sleep(0.1)
    assert port.getBytesAvailable() == 11, "reply bytes to the intact packet"
    assert ph.read4ByteTxRx(port, 12, 112)[0] == 9, "profile_velocity of ID 12"
    ph.write4ByteTxRx(port, 12, 112, 0)


def test_overload_sets_the_alert_bit_and_reboot_clears_it(bus, sdk):
    port, ph = sdk
    mem = bus.servos[14]
    with bus._lock:  # inject: as a servo that detected an overload
        mem.set("hardware_error_status", ct.HW_ERROR_OVERLOAD)
    model, result, error = ph.ping(port, 14)
    assert result == COMM_SUCCESS and error == 0x80, "alert bit in the ping status of ID 14"
    assert ph.read1ByteTxRx(port, 14, 70) == (ct.HW_ERROR_OVERLOAD, COMM_SUCCESS, 0x80), (
        "hardware_error_status of ID 14")
    assert ph.reboot(port, 14) == (COMM_SUCCESS, 0), "reboot ID 14"
    assert ph.read1ByteTxRx(port, 14, 70) == (0, COMM_SUCCESS, 0), (
        "hardware_error_status of ID 14 after reboot")


def test_a_goal_outside_the_limits_is_refused_before_anything_moves(bus):
    robot = calibrated_robot()
    arm = DynamixelArm(ArmConfig(port=bus.path), robot=robot,
                       safety=SafetyLimits.around_workspace(robot))
    with arm:
        before = bus.goal_position_writes
        goals = {i: bus.servos[i].get("goal_position") for i in IDS}
        with pytest.raises(SafetyError, match="joint 2"):
            arm.command(np.radians([0.0, -80.0, 30.0, 0.0]))  # joint 2 limit: -58 deg
        with pytest.raises(SafetyError, match="not finite"):
            arm.command(np.array([0.0, np.nan, 0.0, 0.0]))
        tight = SafetyLimits(arm.safety.joint_limits, arm.safety.ee_box * 0.5)
        arm.safety = tight
        with pytest.raises(SafetyError, match="workspace"):
            arm.command(np.radians([0.0, -30.0, 30.0, 0.0]))
        assert bus.goal_position_writes == before, "Goal Position writes"
        assert {i: bus.servos[i].get("goal_position") for i in IDS} == goals, "goal_position"
        # The servos' own limit registers hold the same joint limits.
        lo = [bus.servos[i].get("min_position_limit") for i in IDS]
        assert lo[1] == 2048 + round(np.radians(-58.0) / (2 * np.pi / 4096)), (
            "min_position_limit of ID 12")
        arm.safety = SafetyLimits.around_workspace(robot)
        state, at_rest, _ = arm.move_and_settle(np.radians([5.0, -30.0, 30.0, 0.0]))
        assert bus.goal_position_writes == before + len(IDS), "Goal Position writes"
        assert at_rest, "at_rest after the move"
        # Joint 1 carries no gravity: it rests where the P loop's torque k*e balances the
        # constant offset plus the friction it can hold, |F| <= f_s*scale + mu*|k*e|, so
        # |e| <= (f_s*scale + |c|) / (k*(1 - mu)), with the log-normal scale at 3 sigma.
        p = default_sim_params()
        fr, sv = p.friction, p.servo
        k_tick = (sv.p_gain[0] / 128 / 885 * sv.supply_voltage[0] / sv.resistance[0]
                  * sv.torque_constant[0])  # [N m per tick of error]
        offset = 0.0 if p.torque_offset is None else abs(p.torque_offset[0])
        hold = fr.static[0] * np.exp(3 * fr.jitter[0]) + offset
        band = float(hold / (k_tick * (1 - fr.load_coefficient[0])))  # [ticks]
        e = (np.radians(5.0) - state.q[0]) / (2 * np.pi / 4096)
        assert abs(e) <= band, f"joint 1 rests {e:.1f} ticks off its goal (band {band:.1f})"


def test_register_gains_map_onto_the_simulator(bus):
    servo = default_sim_params().servo
    with bus._lock:
        for dxl_id in IDS:
            bus.servos[dxl_id].set("position_p_gain", 400)
            bus.servos[dxl_id].set("pwm_limit", 300)
        mapped = bus._servo_params()
        for dxl_id in IDS:
            bus.servos[dxl_id].set("position_p_gain", 800)
            bus.servos[dxl_id].set("pwm_limit", 885)
    np.testing.assert_allclose(mapped.p_gain, np.asarray(servo.p_gain) / 2, rtol=RTOL,
                               err_msg="position_p_gain 400 -> ServoParams.p_gain")
    np.testing.assert_allclose(mapped.pwm_limit, 300.0, rtol=RTOL,
                               err_msg="pwm_limit 300 -> ServoParams.pwm_limit")


def test_virtual_robot_cli_prints_its_device_first(tmp_path):
    with VirtualRobotProcess(["--speed", "2", "--gripper-id", "none"]) as r:
        assert r.path.startswith("/dev/") and os.path.exists(r.path)
        port = PortHandler(r.path)
        assert port.openPort()
        ph = PacketHandler(2.0)
        assert ph.ping(port, 11)[1] == COMM_SUCCESS, "ping ID 11"
        assert ph.ping(port, 15)[1] == COMM_RX_TIMEOUT, "ping ID 15 (no gripper)"
        port.closePort()
    assert r.proc.returncode is not None
