"""DYNAMIXEL Protocol 2.0 framing, for the device side (the virtual servo bus).

The client side is dynamixel-sdk's ``Protocol2PacketHandler``; this module is what a servo
does with the bytes, written from the ROBOTIS e-manual ("Protocol 2.0")::

    FF FF FD 00 | ID | LEN_L LEN_H | INST | PARAM ... | CRC_L CRC_H      LEN = n_params + 3

* CRC-16: polynomial 0x8005, initial value 0, not reflected, no final XOR, over every byte
  from the first header byte to the last parameter, *after* byte stuffing.
* Byte stuffing: wherever ``FF FF FD`` occurs from INST to the last parameter an extra
  ``FD`` follows it (``FF FF FD FD``), so that a header never appears inside a packet;
  LEN counts the stuffed bytes.
* A status packet has INST 0x55 followed by an error byte (bit 7: hardware alert, bits
  0-6: the error number) before its parameters.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

__all__ = [
    "BROADCAST_ID",
    "HEADER",
    "Error",
    "Instruction",
    "Packet",
    "PacketParser",
    "add_stuffing",
    "crc16",
    "encode_packet",
    "remove_stuffing",
    "status_packet",
]

HEADER = b"\xff\xff\xfd\x00"
BROADCAST_ID = 0xFE
ERROR_ALERT = 0x80
#: Largest LEN the parser accepts (the SDK's own buffers are 1 KiB).
MAX_LENGTH = 1024


class Instruction(IntEnum):
    PING = 0x01
    READ = 0x02
    WRITE = 0x03
    REG_WRITE = 0x04
    ACTION = 0x05
    FACTORY_RESET = 0x06
    REBOOT = 0x08
    CLEAR = 0x10
    STATUS = 0x55
    SYNC_READ = 0x82
    SYNC_WRITE = 0x83
    FAST_SYNC_READ = 0x8A
    BULK_READ = 0x92
    BULK_WRITE = 0x93


class Error(IntEnum):
    """Error numbers of a status packet (bits 0-6 of its error byte)."""

    NONE = 0
    RESULT_FAIL = 1
    INSTRUCTION = 2
    CRC = 3
    DATA_RANGE = 4
    DATA_LENGTH = 5
    DATA_LIMIT = 6
    ACCESS = 7


def _crc_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005) if crc & 0x8000 else (crc << 1)
        table.append(crc & 0xFFFF)
    return tuple(table)


_CRC_TABLE = _crc_table()


def crc16(data: bytes | bytearray, crc: int = 0) -> int:
    """CRC-16/BUYPASS (poly 0x8005, init 0, MSB first), as the e-manual's ``update_crc``."""
    for b in data:
        crc = ((crc << 8) ^ _CRC_TABLE[((crc >> 8) ^ b) & 0xFF]) & 0xFFFF
    return crc


def add_stuffing(body: bytes) -> bytes:
    """Inserts ``FD`` after every ``FF FF FD`` in ``body`` (INST and parameters)."""
    out = bytearray()
    for b in body:
        out.append(b)
        if b == 0xFD and len(out) >= 3 and out[-3] == 0xFF and out[-2] == 0xFF:
            out.append(0xFD)
    return bytes(out)


def remove_stuffing(body: bytes) -> bytes:
    """Inverse of :func:`add_stuffing`: drops the ``FD`` that follows ``FF FF FD``."""
    out = bytearray()
    i = 0
    while i < len(body):
        b = body[i]
        out.append(b)
        if b == 0xFD and len(out) >= 3 and out[-3] == 0xFF and out[-2] == 0xFF \
                and i + 1 < len(body) and body[i + 1] == 0xFD:
            i += 1  # skip the stuffed byte
        i += 1
    return bytes(out)


def encode_packet(dxl_id: int, instruction: int, params: bytes = b"") -> bytes:
    """A complete packet: header, ID, LEN, stuffed INST + params, CRC."""
    body = add_stuffing(bytes([instruction]) + bytes(params))
    length = len(body) + 2
    head = HEADER + bytes([dxl_id, length & 0xFF, length >> 8])
    crc = crc16(head + body)
    return head + body + bytes([crc & 0xFF, crc >> 8])


def status_packet(dxl_id: int, error: int, params: bytes = b"") -> bytes:
    """A status packet (INST 0x55) with the error byte and parameters."""
    return encode_packet(dxl_id, Instruction.STATUS, bytes([error & 0xFF]) + bytes(params))


@dataclass(frozen=True)
class Packet:
    """A received packet with its parameters un-stuffed."""

    id: int
    instruction: int
    params: bytes
    crc_ok: bool


class PacketParser:
    """Incremental parser of a byte stream into packets (as a servo's receiver).

    Bytes before a header are discarded. A packet whose CRC fails is returned with
    ``crc_ok=False`` (a servo then stays silent); a packet with an impossible length is
    dropped by resynchronising on the next header.
    """

    #: What a subclass for another framing changes: the header, the bytes that must be
    #: in hand to know a packet's size (``_total``) and what a packet is (``_packet``).
    header = HEADER
    head_size = 7

    def __init__(self) -> None:
        self._buf = bytearray()

    def _total(self, buf: bytearray) -> int | None:
        """The size of the packet starting ``buf``, or None when it is not a real header."""
        length = buf[5] | (buf[6] << 8)
        return None if length < 3 or length > MAX_LENGTH else 7 + length

    def _packet(self, raw: bytes) -> Packet:
        crc_ok = crc16(raw[:-2]) == (raw[-2] | (raw[-1] << 8))
        body = remove_stuffing(raw[7:-2])
        return Packet(raw[4], body[0] if body else -1, body[1:], crc_ok)

    def feed(self, data: bytes) -> list[Packet]:
        self._buf.extend(data)
        packets = []
        while True:
            start = self._buf.find(self.header)
            if start < 0:
                # Keep a possible partial header at the end.
                del self._buf[: max(0, len(self._buf) - (len(self.header) - 1))]
                return packets
            del self._buf[:start]
            if len(self._buf) < self.head_size:
                return packets
            total = self._total(self._buf)
            if total is None:
                del self._buf[:1]  # not a real header: resynchronise
                continue
            if len(self._buf) < total:
                return packets
            raw = bytes(self._buf[:total])
            del self._buf[:total]
            packets.append(self._packet(raw))
