"""The vendor SDK (scservo_sdk, LeRobot's client) against the virtual SO-101 bus: six
STS3215 servos (IDs 1-6) on a pseudo-terminal (:class:`jaxinertia.virtual.sts_bus.StsServoBus`,
in this process, no simulator).

* A clean bus: every servo pings as model 777, reads and writes (one and two bytes,
  sign-magnitude), sync read and sync write, EEPROM behind the lock, a goal reached and
  held short of it by the joint's load: **no failed transaction**.
* A faulty bus (status packets dropped, checksum-corrupted and late beyond the SDK's
  timeout): the transport as the driver uses it (status matching, drain after a failure,
  retry) meets the faults, and **no successful transaction returns a wrong value or an
  error bit** (no false alarm).

No wall-clock assertions: waits are for conditions with generous deadlines.
"""

from __future__ import annotations

import sys
import time

import pytest
from scservo_sdk import (
    COMM_SUCCESS,
    GroupSyncRead,
    GroupSyncWrite,
    PacketHandler,
    PortHandler,
)
from support.hardware import Client as SdkClient

from jaxinertia.hardware import feetech_table as ft
from jaxinertia.hardware.feetech_protocol import encode_packet
from jaxinertia.hardware.feetech_transport import LockedScsPortHandler, StsMatchingPacketHandler
from jaxinertia.hardware.transport import drain
from jaxinertia.virtual.bus import Faults
from jaxinertia.virtual.sts_bus import StsServoBus

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"),
                                reason="the virtual servo bus needs a Linux pseudo-terminal")

IDS = (1, 2, 3, 4, 5, 6)
JOINTS = IDS[:5]
LOADS = (0.0, 0.12, -0.08, 0.03, 0.0)  # external load per joint [fraction of max torque]
DEADLINE_S = 120.0  # for a condition on a busy host


class PatientPort(PortHandler):
    """The SDK's port, waiting up to 2 s for a status packet instead of ~34 ms: on a clean
    bus a failure is then the bus's, never a busy host's scheduling (the faulty-bus tests
    keep the SDK's own timeout, which late packets must outlast)."""

    def setPacketTimeout(self, packet_length):  # noqa: N802 (the SDK's name)
        super().setPacketTimeout(packet_length)
        self.packet_timeout = max(self.packet_timeout, 2000.0)


def Client(path: str, packet=None, port_class=PortHandler) -> SdkClient:  # noqa: N802
    """scservo_sdk on a port, counting transactions (``attempted``, ``failed``)."""
    return SdkClient(port_class(path), PacketHandler(0) if packet is None else packet)


@pytest.fixture
def clean():
    with StsServoBus(loads=LOADS) as bus:
        client = Client(bus.path, port_class=PatientPort)
        yield bus, client
        client.close()


def test_every_servo_pings_reads_and_writes(clean):
    bus, c = clean
    for i in IDS:
        assert c.call(c.ph.ping, i) == (ft.STS3215_MODEL, COMM_SUCCESS, 0)
        assert c.call(c.ph.read1ByteTxRx, i, ft.ITEMS["id"].address) == (i, COMM_SUCCESS, 0)
    # One and two bytes; a sign-magnitude register read back through the SDK's decoding.
    assert c.call(c.ph.write1ByteTxRx, 3, 41, 20) == (COMM_SUCCESS, 0)
    assert c.call(c.ph.read1ByteTxRx, 3, 41)[0] == 20
    raw = ft.to_sign_magnitude(-300, 15)
    assert c.call(c.ph.write2ByteTxRx, 3, 46, raw) == (COMM_SUCCESS, 0)  # Goal Velocity
    value, _, _ = c.call(c.ph.read2ByteTxRx, 3, 46)
    assert value == raw and ft.from_sign_magnitude(value, 15) == -300
    # EEPROM: locked by default (the write is answered and ignored), then unlocked.
    p = ft.ITEMS["p_coefficient"].address
    assert c.call(c.ph.write1ByteTxRx, 2, p, 16) == (COMM_SUCCESS, 0)
    assert c.call(c.ph.read1ByteTxRx, 2, p)[0] == 32
    c.call(c.ph.write1ByteTxRx, 2, ft.ITEMS["lock"].address, 0)
    c.call(c.ph.write1ByteTxRx, 2, p, 16)
    assert c.call(c.ph.read1ByteTxRx, 2, p)[0] == 16
    # Read-only: ignored.
    c.call(c.ph.write2ByteTxRx, 2, ft.ITEMS["model_number"].address, 1)
    assert c.call(c.ph.ping, 2)[0] == ft.STS3215_MODEL
    assert (c.attempted, c.failed) == (23, 0), "no failed transaction on a clean bus"


def test_sync_read_sync_write_and_a_goal_reached(clean):
    bus, c = clean
    start, length = ft.STATE_BLOCK
    group = GroupSyncRead(c.port, c.ph, start, length)
    for i in IDS:
        group.addParam(i)
    assert c.call(lambda _port: group.txRxPacket()) == COMM_SUCCESS
    for i in IDS:
        assert group.getData(i, 56, 2) == ft.ZERO_TICKS
        assert group.getData(i, 62, 1) == 74  # 7.4 V
    for i in JOINTS:
        c.call(c.ph.write1ByteTxRx, i, ft.ITEMS["torque_enable"].address, 1)
    goals = {i: 2048 + 150 * k for k, i in enumerate(JOINTS, start=-2)}
    write = GroupSyncWrite(c.port, c.ph, ft.ITEMS["goal_position"].address, 2)
    for i, g in goals.items():
        write.addParam(i, [g & 0xFF, g >> 8])
    assert c.call(lambda _port: write.txPacket()) == COMM_SUCCESS
    # Each joint comes to rest short of its goal by load * 1000 / P ticks (P = 32).
    rest = {i: goals[i] - LOADS[k] * 1000 / 32 for k, i in enumerate(JOINTS)}
    deadline = time.monotonic() + DEADLINE_S
    while True:
        assert c.call(lambda _port: group.txRxPacket()) == COMM_SUCCESS
        ticks = {i: ft.from_sign_magnitude(group.getData(i, 56, 2), 15) for i in JOINTS}
        moving = [group.getData(i, 66, 1) for i in JOINTS]
        if not any(moving) and all(abs(ticks[i] - rest[i]) <= 1 for i in JOINTS):
            break
        assert time.monotonic() < deadline, (ticks, rest, moving)
        time.sleep(0.01)
    loads = {i: ft.from_sign_magnitude(group.getData(i, 60, 2), 10) for i in JOINTS}
    for k, i in enumerate(JOINTS):  # the loop's output holds the load (0.1 %)
        assert abs(loads[i] - LOADS[k] * 1000) <= 32, (i, loads[i])
        current = ft.from_sign_magnitude(group.getData(i, 69, 2), 15)
        assert (current > 0) == (loads[i] > 0) or current == 0
    assert group.getData(6, 56, 2) == ft.ZERO_TICKS  # the gripper does not move
    assert bus.goal_position_writes == len(JOINTS)
    assert c.failed == 0, f"{c.failed} of {c.attempted} transactions failed on a clean bus"


def test_a_faulty_bus_is_retried_and_never_misread():
    faults = Faults(drop_rate=0.02, corrupt_rate=0.02, delay_rate=0.03, delay_s=0.05, seed=5)
    # What each request must read: (servo, address, length) -> bytes.
    with StsServoBus(faults=faults) as bus:
        expected = {}
        for i in IDS:
            mem = bus.servos[i]
            for address, length in ((3, 2), (5, 1), (9, 4), (56, 2)):
                expected[i, address, length] = mem.read(address, length)
        c = Client(bus.path, StsMatchingPacketHandler(), LockedScsPortHandler)
        retried = 0
        for n in range(120):
            i = IDS[n % len(IDS)]
            address, length = list(expected)[n % 4][1:]
            if n % 3 == 2:  # a sync read of every servo
                group = GroupSyncRead(c.port, c.ph, address, length)
                for k in IDS:
                    group.addParam(k)
                for attempt in range(200):
                    if c.call(lambda _port, g=group: g.txRxPacket()) == COMM_SUCCESS:
                        if attempt:  # as the driver does: a retry's own answer may be late
                            drain(c.port)
                        break
                    retried += 1
                    drain(c.port)
                for k in IDS:
                    assert bytes(group.data_dict[k]) == expected[k, address, length], (n, k)
                continue
            for attempt in range(200):
                data, result, error = c.call(c.ph.readTxRx, i, address, length)
                if result == COMM_SUCCESS:
                    if attempt:  # as the driver does (DynamixelArm._retry)
                        drain(c.port)
                    break
                retried += 1
                drain(c.port)
            assert bytes(data) == expected[i, address, length], (n, i, address)
            assert error == 0, "an error bit that no servo set: a false alarm"
        c.close()
    print(f"faulty bus: {c.attempted} transactions, {c.failed} failed and retried, "
          f"{c.ph.stale_packets} late status packets discarded")
    assert c.failed == retried > 0, "the injected faults must have been met"


def test_a_late_status_packet_is_not_the_answer_to_the_next_request(clean):
    """The SDK matches an answer by servo ID only: a late 1-byte answer of servo 1 on the
    wire would be read as its Model Number. The matching handler discards it."""
    bus, _ = clean
    for handler, port_class in ((PacketHandler(0), PortHandler),
                                (StsMatchingPacketHandler(), LockedScsPortHandler)):
        c = Client(bus.path, handler, port_class)
        bus._write_out(encode_packet(1, 0, bytes([7])))  # late: ID 1's answer to a 1-byte read
        deadline = time.monotonic() + DEADLINE_S
        while not c.port.getBytesAvailable():
            assert time.monotonic() < deadline
            time.sleep(0.001)
        data, result, _ = c.ph.readTxRx(c.port, 1, ft.ITEMS["model_number"].address, 2)
        assert result == COMM_SUCCESS
        if isinstance(handler, StsMatchingPacketHandler):
            assert bytes(data) == ft.STS3215_MODEL.to_bytes(2, "little")
            assert handler.stale_packets == 1
        else:
            # The vendor's handler takes the late packet (its checksum as the second byte).
            assert data[0] == 7 and bytes(data) != ft.STS3215_MODEL.to_bytes(2, "little")
        drain(c.port)
        c.close()
