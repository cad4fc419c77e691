"""Feetech SCS/STS framing, for the device side (the virtual STS bus).

The client side is scservo_sdk's ``protocol_packet_handler``; this module is what a servo
does with the bytes::

    instruction  FF FF | ID | LEN | INST | PARAM ... | CHK      LEN = n_params + 2
    status       FF FF | ID | LEN | ERR  | PARAM ... | CHK

* CHK = ~(ID + LEN + INST/ERR + params) & 0xFF; no byte stuffing, so a header may occur
  inside a packet and a receiver resynchronises on the next ``FF FF`` after a bad one.
* Instructions: PING 0x01, READ 0x02 (address, length), WRITE 0x03 (address, data),
  REG_WRITE 0x04, ACTION 0x05, SYNC_READ 0x82 (address, length, IDs; each servo answers
  in turn), SYNC_WRITE 0x83 (address, length, then ID + data per servo; no answer).
* ERR carries the servo's error bits (``feetech_table.STATUS_*``); bit 7 is never set
  (scservo_sdk drops a status packet whose error byte exceeds 0x7F).
"""

from __future__ import annotations

from dataclasses import dataclass

# The instruction codes and the broadcast ID are DYNAMIXEL's (Protocol 1.0, which the SCS
# protocol follows); STS uses PING, READ, WRITE, REG_WRITE, ACTION, SYNC_READ, SYNC_WRITE.
from jaxinertia.hardware.protocol import BROADCAST_ID, Instruction, PacketParser

__all__ = ["BROADCAST_ID", "Instruction", "Packet", "StsPacketParser", "checksum",
           "encode_packet"]

#: Largest LEN scservo_sdk sends or accepts (its buffers hold 250 bytes).
MAX_LENGTH = 250


def checksum(body: bytes) -> int:
    """CHK of ID, LEN, INST/ERR and parameters."""
    return ~sum(body) & 0xFF


def encode_packet(scs_id: int, inst_or_error: int, params: bytes = b"") -> bytes:
    """A complete packet (instruction, or status with the error byte in INST's place)."""
    body = bytes([scs_id, len(params) + 2, inst_or_error & 0xFF]) + bytes(params)
    return b"\xff\xff" + body + bytes([checksum(body)])


@dataclass(frozen=True)
class Packet:
    id: int
    instruction: int
    params: bytes
    checksum_ok: bool


class StsPacketParser(PacketParser):
    """Incremental parser of a byte stream into instruction packets (a servo's receiver;
    :class:`jaxinertia.hardware.protocol.PacketParser` with this framing).

    Bytes before a header are discarded; a packet whose checksum fails is returned with
    ``checksum_ok=False`` (a servo then stays silent); an impossible ID or length drops one
    byte and resynchronises."""

    header = b"\xff\xff"
    head_size = 4

    def _total(self, buf: bytearray) -> int | None:
        scs_id, length = buf[2], buf[3]
        return None if scs_id == 0xFF or length < 2 or length > MAX_LENGTH else 4 + length

    def _packet(self, raw: bytes) -> Packet:
        return Packet(raw[2], raw[4], raw[5:-1], checksum(raw[2:-1]) == raw[-1])
