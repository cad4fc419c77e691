"""Protocol 2.0 conformance of the virtual servo bus, checked with dynamixel-sdk's own
packet handler through the pseudo-terminal; the driver's safety checks; the transport
(status packets matched to their request, the port lock); hardware errors confirmed
before they are reported; the physics compiled before the bus opens and reporting a
moving arm as moving until it has simulated the move.

Registers are integers and compared exactly; failures name the register and the servo.
Nothing here depends on the host's speed: the SDK's port waits generously for a status
packet (:class:`PatientPort`), and waits for bytes are conditions with generous
deadlines, never sleeps.
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
from support.compiles import compile_counter
from support.hardware import RETRIES

from jaxinertia.hardware import control_table as ct
from jaxinertia.hardware.arm_config import arm_config, safety_limits
from jaxinertia.hardware.driver import DynamixelArm, ServoHardwareError
from jaxinertia.hardware.protocol import (
    Instruction,
    PacketParser,
    add_stuffing,
    crc16,
    encode_packet,
    remove_stuffing,
    status_packet,
)
from jaxinertia.hardware.safety import SafetyError, SafetyLimits
from jaxinertia.hardware.transport import LockedPortHandler, MatchingPacketHandler, PortInUse
from jaxinertia.objects import resolve
from jaxinertia.open_manipulator_x import ARM as OMX
from jaxinertia.open_manipulator_x import sim_fit_robot
from jaxinertia.sim.params import default_sim_params
from jaxinertia.virtual.bus import open_pty
from jaxinertia.virtual.physics import ArmPhysics, PhysicsLoop, publish
from jaxinertia.virtual.robot import VirtualServoBus
from jaxinertia.virtual.testing import VirtualRobotProcess

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"),
                                reason="the virtual servo bus needs a Linux pseudo-terminal")

IDS = (11, 12, 13, 14)
#: The one tolerance of this module: register gains mapped onto the simulator's (float64
#: arithmetic on the same numbers).
RTOL = 1e-7
#: How long a test waits for bytes that must come [s] (a deadline, not a pace).
PATIENCE_S = 60.0
Q0 = np.radians([0.0, -30.0, 30.0, 0.0])


class PatientPort(PortHandler):
    """dynamixel-sdk's port, waiting ``patience_ms`` for a status packet instead of ~35 ms:
    these tests check what the bus answers, not how fast a busy host lets it answer. (A
    check that nothing comes waits less: a reply that a slow host delays past it can only
    make such a check pass, never fail.)"""

    patience_ms = PATIENCE_S * 1000.0

    def setPacketTimeout(self, packet_length):  # noqa: N802 (the SDK's name)
        super().setPacketTimeout(packet_length)
        self.packet_timeout = self.patience_ms

    def setPacketTimeoutMillis(self, msec):  # noqa: N802
        super().setPacketTimeoutMillis(max(msec, 1000.0))  # broadcast ping waits it out


def wait_for_bytes(port, n: int) -> int:
    """Waits until at least ``n`` bytes are in ``port`` (deadline ``PATIENCE_S``)."""
    deadline = time.monotonic() + PATIENCE_S
    while port.getBytesAvailable() < n and time.monotonic() < deadline:
        time.sleep(0.001)
    return port.getBytesAvailable()


@pytest.fixture(scope="module")
def bus():
    b = VirtualServoBus(default_sim_params(), resolve("cube", tag_in_ee=OMX.tag_in_ee),
                        q0=Q0, speed=5.0)
    with b:
        yield b


@pytest.fixture()
def sdk(bus):
    port = PatientPort(bus.path)
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
    port.patience_ms = 500.0
    assert ph.ping(port, 99)[1] == COMM_RX_TIMEOUT, "ping ID 99"  # no such servo: silence
    port.patience_ms = PatientPort.patience_ms
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
    ping = encode_packet(12, Instruction.PING)
    port.clearPort()
    # The bus answers in order: whatever the corrupted packet got would come before the
    # ping's 14-byte status packet.
    port.writePort(bad + ping)
    got = wait_for_bytes(port, 14)
    assert got - 14 == 0, "reply bytes to a corrupted packet"
    port.clearPort()
    assert ph.read4ByteTxRx(port, 12, 112)[0] == 0, "profile_velocity of ID 12"
    port.writePort(good)  # the same packet with its CRC intact is executed and answered
    assert wait_for_bytes(port, 11) == 11, "reply bytes to the intact packet"
    port.clearPort()
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
    robot = sim_fit_robot()
    arm = DynamixelArm(arm_config(OMX, bus.path, retries=RETRIES), robot=robot,
                       safety=safety_limits(OMX, robot))
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
        arm.safety = safety_limits(OMX, robot)
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
        port = PatientPort(r.path)
        assert port.openPort()
        ph = PacketHandler(2.0)
        assert ph.ping(port, 11)[1] == COMM_SUCCESS, "ping ID 11"
        port.patience_ms = 500.0
        assert ph.ping(port, 15)[1] == COMM_RX_TIMEOUT, "ping ID 15 (no gripper)"
        port.closePort()
    assert r.proc.returncode is not None


# ---- the transport: status packets matched to their request, the port lock --------------


@pytest.fixture()
def wire():
    """A pseudo-terminal with dynamixel-sdk on one side and the test on the other."""
    master, slave, path = open_pty()
    port = LockedPortHandler(path)
    assert port.openPort()
    yield port, master
    port.closePort()
    os.close(master)
    os.close(slave)


def test_a_late_status_packet_is_not_the_answer_to_the_next_request(wire):
    port, master = wire
    # ID 11 answers a Present Position block read (27 bytes) too late: the master has
    # already asked for Hardware Error Status (1 byte), whose answer (0) follows.
    late = status_packet(11, 0, bytes(range(8, 35)))  # first data byte 8: "encoder"
    answer = status_packet(11, 0, bytes([0]))
    sdk = PacketHandler(2.0)
    assert sdk.readTx(port, 11, 70, 1) == COMM_SUCCESS
    os.write(master, late + answer)
    data, result, _ = sdk.readRx(port, 11, 1)
    assert result == COMM_SUCCESS and data == [8], "the SDK alone takes the late packet"
    matching = MatchingPacketHandler()
    assert matching.readTx(port, 11, 70, 1) == COMM_SUCCESS
    os.write(master, late + answer)
    data, result, _ = matching.readRx(port, 11, 1)
    assert result == COMM_SUCCESS and data == [0], "Hardware Error Status of ID 11"
    assert matching.stale_packets == 1, "late packets discarded"
    # A status packet of another servo, or of the right servo and the wrong length, is no
    # answer either; an error status without data is.
    assert matching.readTx(port, 12, 132, 4) == COMM_SUCCESS
    os.write(master, status_packet(13, 0, bytes(4)) + status_packet(12, 0, bytes(1))
             + status_packet(12, 7))
    data, result, error = matching.readRx(port, 12, 4)
    assert (result, error) == (COMM_SUCCESS, 7), "access error of ID 12"
    assert matching.stale_packets == 3, "late packets discarded"


def test_the_port_is_locked_while_open(wire):
    port, _ = wire
    with pytest.raises(PortInUse, match="in use"):
        LockedPortHandler(port.getPortName()).openPort()
    port.closePort()
    again = LockedPortHandler(port.getPortName())
    assert again.openPort(), "the lock is released on close"
    again.closePort()


# ---- hardware errors are confirmed by register 70 ----------------------------------------


def test_a_hardware_error_reading_is_confirmed_before_it_is_reported(bus, monkeypatch):
    arm = DynamixelArm(arm_config(OMX, bus.path, gripper_id=None, retries=RETRIES))
    with arm:
        real = arm._sync_read

        def garbled(address, length):  # as a late packet taken for the answer would be
            data = real(address, length)
            if address == ct.ITEMS["hardware_error_status"].address:
                data = {i: bytes([ct.HW_ERROR_ENCODER | ct.HW_ERROR_OVERLOAD]) for i in data}
            return data

        monkeypatch.setattr(arm, "_sync_read", garbled)
        arm.check_hardware_errors()  # register 70 reads 0 on every servo: no error
        assert arm.unconfirmed_alarms == 1, "unconfirmed hardware-error readings"
        with bus._lock:  # a real one: ID 13 overloaded
            bus.servos[13].set("hardware_error_status", ct.HW_ERROR_OVERLOAD)
        try:
            with pytest.raises(ServoHardwareError, match="ID 13: overload") as e:
                arm.check_hardware_errors()
            assert e.value.errors == {13: ct.HW_ERROR_OVERLOAD}, "confirmed errors"
        finally:
            with bus._lock:
                bus.servos[13].set("hardware_error_status", 0)
            monkeypatch.undo()


# ---- the physics: compiled before the bus opens, moving until simulated -------------------


@pytest.fixture()
def stepped():
    """A virtual servo bus whose physics the test steps itself, in this process (no
    physics process, no threads): the bus answers through ``handle``."""
    b = VirtualServoBus(default_sim_params(), resolve("cube", tag_in_ee=OMX.tag_in_ee),
                        q0=Q0, speed=1.0)
    arm = ArmPhysics(b._spec.params, q0=Q0, chunk=b._spec.chunk, seed=0)
    loop = PhysicsLoop(arm, [b.servos[i] for i in IDS], b._lock, b._events_in,
                       b._shared_goal_writes)
    yield b, loop
    b.close()


def write(bus, dxl_id: int, name: str, value: int) -> None:
    item = ct.ITEMS[name]
    params = item.address.to_bytes(2, "little") + ct.to_unsigned(value, item.size).to_bytes(
        item.size, "little")
    (packet,) = PacketParser().feed(encode_packet(dxl_id, Instruction.WRITE, params))
    (reply,) = bus.handle(packet)
    assert reply[8] == 0, f"write {name} of ID {dxl_id}: error {reply[8]}"


def test_every_physics_path_is_compiled_before_the_bus_opens(stepped):
    bus, loop = stepped
    loop.arm.compile()
    with compile_counter("_advance", "at_rest") as seen:
        loop.step()  # torque off
        for i in IDS:
            write(bus, i, "torque_enable", 1)
        loop.step()  # torque on, hold
        write(bus, 11, "goal_position", 2048 + 40)
        for _ in range(5):
            loop.step()
        write(bus, 12, "torque_enable", 0)
        loop.step()
    assert not seen.traces and not seen.compiles, f"compiled after the bus opened: {seen}"


def test_a_moving_arm_reports_moving_until_simulated_time_has_caught_up(stepped):
    bus, loop = stepped
    for i in IDS:
        write(bus, i, "profile_velocity", 20)  # 0.48 rad/s
        write(bus, i, "profile_acceleration", 20)
        write(bus, i, "torque_enable", 1)
    loop.step()
    m = bus.servos[11]
    before = m.get("present_position")
    write(bus, 11, "goal_position", before + 100)  # 8.8 deg: a profile of ~0.4 s
    # Written, not simulated yet: moving, where it was.
    assert m.get("moving") == 1, "moving of ID 11 right after the goal write"
    assert m.get("moving_status") & 0x02, "moving_status profile bit of ID 11"
    assert m.get("present_position") == before, "present_position of ID 11"
    t0 = loop.arm.sim_time
    moving_at = []
    while loop.arm.sim_time < t0 + 3.0:
        p = loop.step()
        moving_at.append((p.sim_time, m.get("moving"), m.get("present_position")))
    t_end = next(t for t, moving, _ in moving_at if not moving)
    # Until the profile has run in simulated time (~0.4 s) the arm reports moving; it
    # never reports rest half-way.
    assert t_end - t0 > 0.3, f"moving reported 0 after {t_end - t0:.2f} s of simulated time"
    resting = [pos for t, _, pos in moving_at if t >= t_end]
    assert abs(resting[0] - (before + 100)) < 15, "present_position of ID 11 at rest"
    # A goal written while a chunk was being computed is pending: reported moving.
    pending = np.array([True, False, False, False])
    with bus._lock:
        publish([bus.servos[i] for i in IDS], p, pending)
    assert m.get("moving") == 1, "moving of ID 11 with its goal pending"


def test_a_physics_whose_bus_died_holding_the_lock_ends(stepped, monkeypatch):
    """A bus process killed while it held the tables' lock never releases it: the physics
    waits for the lock in slices and ends once its parent is gone, instead of waiting
    for ever (as a physics process left behind by a killed virtual robot once did)."""
    import threading

    from jaxinertia.virtual import physics

    b, loop = stepped
    parent = os.getppid()
    calls = []

    def getppid():  # the parent lives for the loop's first check, then is gone
        calls.append(1)
        return parent if len(calls) == 1 else 1

    monkeypatch.setattr(physics.os, "getppid", getppid)
    assert b._lock.acquire(timeout=PATIENCE_S)  # the dead bus's hold, never released
    try:
        runner = threading.Thread(target=loop.run, args=(1.0, threading.Event(), parent))
        runner.start()
        runner.join(PATIENCE_S)
        assert not runner.is_alive(), "the physics still waits for the lock"
        assert len(calls) >= 2, "the loop checked its parent while it waited"
    finally:
        b._lock.release()


def test_the_physics_process_serves_the_bus_and_stops_with_it():
    b = VirtualServoBus(default_sim_params(), None, q0=Q0, speed=5.0)
    with b:
        port = PatientPort(b.path)
        assert port.openPort()
        clock = [PacketHandler(2.0).read2ByteTxRx(port, 11, 120)[0] for _ in range(2)]
        deadline = time.monotonic() + PATIENCE_S
        while clock[-1] == clock[0] and time.monotonic() < deadline:
            clock.append(PacketHandler(2.0).read2ByteTxRx(port, 11, 120)[0])
        assert clock[-1] != clock[0], "realtime_tick of ID 11 advances"
        port.closePort()
        process = b._process
    assert not process.is_alive(), "the physics process ended with the bus"
