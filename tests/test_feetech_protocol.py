"""The Feetech STS3215 servo boundary without a bus: the memory table against the published
addresses (DESIGN.md, LeRobot's STS_SMS_SERIES_CONTROL_TABLE), sign-magnitude values,
the framing against scservo_sdk's own packets, and which status packets the matching
handler accepts. Pure Python, milliseconds."""

from __future__ import annotations

import numpy as np
import pytest
from scservo_sdk import protocol_packet_handler as sdk_handler
from scservo_sdk import scservo_def as sdk
from scservo_sdk.scservo_def import SCS_TOHOST, SCS_TOSCS

from jaxinertia.hardware import feetech_table as ft
from jaxinertia.hardware.feetech_protocol import (
    Instruction,
    StsPacketParser,
    encode_packet,
)
from jaxinertia.hardware.feetech_transport import StsMatchingPacketHandler, expected_answers


def test_table_has_the_published_addresses_sizes_and_sign_bits():
    # DESIGN.md, "Arms and servos as data", and LeRobot's STS_SMS_SERIES_CONTROL_TABLE.
    published = {"model_number": (3, 2), "id": (5, 1), "min_position_limit": (9, 2),
                 "max_position_limit": (11, 2), "p_coefficient": (21, 1),
                 "d_coefficient": (22, 1), "i_coefficient": (23, 1), "homing_offset": (31, 2),
                 "operating_mode": (33, 1), "torque_enable": (40, 1), "acceleration": (41, 1),
                 "goal_position": (42, 2), "goal_velocity": (46, 2), "lock": (55, 1),
                 "present_position": (56, 2), "present_velocity": (58, 2),
                 "present_load": (60, 2), "present_voltage": (62, 1),
                 "present_temperature": (63, 1), "status": (65, 1), "moving": (66, 1),
                 "present_current": (69, 2)}
    for name, (address, size) in published.items():
        assert ft.ITEMS[name][:2] == (address, size), name
    signs = {"present_position": 15, "goal_position": 15, "present_velocity": 15,
             "goal_velocity": 15, "present_current": 15, "homing_offset": 11,
             "present_load": 10}
    assert {n: i.sign_bit for n, i in ft.ITEMS.items() if i.sign_bit is not None} == signs
    assert ft.ITEMS["model_number"].default == ft.STS3215_MODEL == 777
    assert [n for n, i in ft.ITEMS.items() if i.eeprom][-1] == "overload_torque"
    addresses = [i.address for i in ft.ITEMS.values()]
    assert addresses == sorted(addresses)
    for a, b in zip(ft.ITEMS.values(), list(ft.ITEMS.values())[1:]):
        assert a.address + a.size <= b.address, (a, b)  # no overlap
    # The status bits are the SDK's.
    assert (ft.STATUS_VOLTAGE, ft.STATUS_ANGLE, ft.STATUS_OVERHEAT, ft.STATUS_OVERCURRENT,
            ft.STATUS_OVERLOAD) == (1, 2, 4, 8, 32)


@pytest.mark.parametrize("bit", [10, 11, 15])
def test_sign_magnitude_round_trips_and_matches_the_sdk(bit):
    values = [0, 1, -1, 7, -7, (1 << bit) - 1, -((1 << bit) - 1), 1000, -1000]
    for v in values:
        raw = ft.to_sign_magnitude(v, bit)
        assert 0 <= raw < 1 << (bit + 1)
        assert ft.from_sign_magnitude(raw, bit) == v
        assert raw == SCS_TOSCS(v, bit) and SCS_TOHOST(raw, bit) == v  # the vendor's
    assert ft.to_sign_magnitude(-5, bit) == (1 << bit) | 5  # not two's complement
    with pytest.raises(ValueError):
        ft.to_sign_magnitude(1 << bit, bit)
    # Every raw value decodes, and re-encodes to itself (negative zero aside).
    for raw in range(1 << (bit + 1)):
        v = ft.from_sign_magnitude(raw, bit)
        if raw != 1 << bit:
            assert ft.to_sign_magnitude(v, bit) == raw


def test_items_encode_and_convert_to_si():
    load = ft.ITEMS["present_load"]
    assert ft.encode(load, -250) == 0x400 | 250 and ft.decode(load, 0x400 | 250) == -250
    with pytest.raises(ValueError):
        ft.encode(ft.ITEMS["id"], 256)
    with pytest.raises(ValueError):
        ft.encode(load, 1024)
    block = bytes(ft.TABLE_SIZE)
    assert ft.field(ft.ITEMS["present_current"], block, 0) == 0
    q = np.radians([-90.0, 0.0, 45.0])
    np.testing.assert_array_equal(ft.rad_to_ticks(q), [1024, 2048, 2560])
    np.testing.assert_allclose(ft.ticks_to_rad(ft.rad_to_ticks(q)), q, atol=ft.RAD_PER_TICK)
    assert ft.CURRENT_LSB_A == 6.5e-3 and ft.LOAD_LSB == 1e-3 and ft.VOLTAGE_LSB == 0.1


class _Capture:
    """A port that keeps what the SDK writes."""

    is_using = False

    def __init__(self):
        self.sent = b""

    def clearPort(self):  # noqa: N802
        pass

    def writePort(self, packet):  # noqa: N802
        self.sent += bytes(packet)
        return len(packet)

    def setPacketTimeout(self, length):  # noqa: N802
        pass


def _sdk_bytes(send) -> bytes:
    port = _Capture()
    send(sdk_handler(), port)
    return port.sent


def test_framing_matches_the_sdk_and_the_parser_resynchronises():
    assert [Instruction.PING, Instruction.READ, Instruction.WRITE, Instruction.REG_WRITE,
            Instruction.ACTION, Instruction.SYNC_READ, Instruction.SYNC_WRITE] == [
        sdk.INST_PING, sdk.INST_READ, sdk.INST_WRITE, sdk.INST_REG_WRITE, sdk.INST_ACTION,
        sdk.INST_SYNC_READ, sdk.INST_SYNC_WRITE]
    ping = _sdk_bytes(lambda h, p: h.txPacket(p, [0, 0, 3, 2, Instruction.PING, 0]))
    assert ping == encode_packet(3, Instruction.PING)
    write = _sdk_bytes(lambda h, p: h.writeTxOnly(p, 1, 42, 2, [0x00, 0x08]))
    assert write == encode_packet(1, Instruction.WRITE, bytes([42, 0x00, 0x08]))
    sync = _sdk_bytes(lambda h, p: h.syncReadTx(p, 56, 15, [1, 2, 3], 3))
    assert sync == encode_packet(0xFE, Instruction.SYNC_READ, bytes([56, 15, 1, 2, 3]))
    parser = StsPacketParser()
    bad = bytearray(write)
    bad[-1] ^= 0x5A
    stream = b"\x00\xff" + bytes(bad) + b"\xff\xff\xff" + ping + sync[:5]
    packets = parser.feed(stream)
    assert [(p.id, p.instruction, p.checksum_ok) for p in packets] == [
        (1, Instruction.WRITE, False), (3, Instruction.PING, True)]
    (rest,) = parser.feed(sync[5:])
    assert (rest.id, rest.params, rest.checksum_ok) == (0xFE, bytes([56, 15, 1, 2, 3]), True)


def test_matching_handler_accepts_only_the_answers_due():
    assert expected_answers(list(encode_packet(0xFE, Instruction.SYNC_READ,
                                               bytes([56, 15, 1, 2])))) == {1: 15, 2: 15}
    assert expected_answers(list(encode_packet(4, Instruction.READ, bytes([3, 2])))) == {4: 2}
    assert expected_answers(list(encode_packet(4, Instruction.PING))) == {4: 0}
    assert expected_answers(list(encode_packet(4, Instruction.WRITE, bytes([40, 1])))) == {4: 0}
    assert expected_answers(list(encode_packet(0xFE, Instruction.SYNC_WRITE,
                                               bytes([42, 2, 1, 0, 8])))) == {}
    h = StsMatchingPacketHandler()
    h._expected = {4: 2}
    assert h._matches(list(encode_packet(4, 0, bytes([9, 3]))))
    assert not h._matches(list(encode_packet(4, 0, bytes([9]))))  # a late 1-byte answer
    assert not h._matches(list(encode_packet(5, 0, bytes([9, 3]))))  # another servo
