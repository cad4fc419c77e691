"""The serial transport under the driver: dynamixel-sdk's port and packet handlers, made
safe for a real bus.

* :class:`LockedPortHandler` opens the device with an exclusive lock (``flock``, as
  pyserial's ``exclusive=True``): a second program that uses this class on the same port
  is refused instead of interleaving its packets with ours. While a status packet is
  awaited it sleeps in ``select`` until bytes arrive (or the packet timeout passes)
  instead of the SDK's busy loop of non-blocking reads, which keeps a core busy during
  every transaction (and, on a loaded host, takes it from the servos' simulator).
* :class:`MatchingPacketHandler` matches every status packet to the request it answers.
  dynamixel-sdk's ``rxPacket`` takes the first well-formed status packet on the wire, and
  its callers check only the servo ID; a status packet that arrives after the SDK gave up
  waiting for it (a real bus delivers late packets) is then taken as the answer to the
  *next* request to that servo (a Present Position block read as Hardware Error Status, for
  one). Here the request's instruction and parameters give the answer each servo must
  send (ID and parameter count: PING 3, READ/SYNC_READ/BULK_READ the length asked for,
  WRITE/REBOOT none); any other status packet is discarded and counted as stale, and
  reading goes on within the same timeout. This is the one layer every transaction passes
  through (``txPacket`` sees each request, ``rxPacket`` each answer, for single reads and
  writes and for the group classes alike).
* :func:`drain` discards late bytes after a failed transaction, so that the retry starts
  on a quiet bus.

Protocol 2.0 has no sequence numbers: a late answer of exactly the shape of the next
request's (the same register block of the same servo, asked twice) cannot be told apart
from it; :func:`drain` after every failure is what keeps those out, and once more after
a retry that succeeded (the answer taken may have been the failed attempt's, late, with the
retry's own still on its way: on a loaded host, a test's virtual bus showed it).
"""

from __future__ import annotations

import errno
import select
import time

import serial
from dynamixel_sdk import COMM_SUCCESS, PortHandler, Protocol2PacketHandler
from dynamixel_sdk.port_handler import LATENCY_TIMER
from dynamixel_sdk.robotis_def import (
    BROADCAST_ID,
    INST_BULK_READ,
    INST_CLEAR,
    INST_FACTORY_RESET,
    INST_PING,
    INST_READ,
    INST_REBOOT,
    INST_REG_WRITE,
    INST_SYNC_READ,
    INST_WRITE,
)

__all__ = ["STATUS_TIMEOUT_S", "LockedPort", "LockedPortHandler", "Matching",
           "MatchingPacketHandler", "PortInUse", "drain"]

# Raw packet offsets (Protocol 2.0): FF FF FD 00 ID LEN_L LEN_H INST [ERR] PARAMS.. CRC_L CRC_H
_ID, _LEN_L, _LEN_H, _INST, _ERR, _PARAM = 4, 5, 6, 7, 8, 8
#: The SDK's wait for a short status packet (two USB latency timers + 2 ms) [s].
STATUS_TIMEOUT_S = (2.0 * LATENCY_TIMER + 2.0) / 1000.0
#: Parameters of the status packet that each instruction gets (after the error byte).
_NO_DATA = (INST_WRITE, INST_REG_WRITE, INST_REBOOT, INST_CLEAR, INST_FACTORY_RESET)


class PortInUse(serial.SerialException):
    """The device is locked by another program (another ``collect``)."""


class LockedPort:
    """A vendor SDK's ``PortHandler`` (dynamixel-sdk's, scservo_sdk's: the same class)
    that holds an exclusive lock on the device while open. Raises :class:`PortInUse` when
    another holder has it, and pyserial's ``SerialException`` (an ``OSError``) when the
    device cannot be opened. A mixin: put it before the SDK's class."""

    def setupPort(self, cflag_baud):  # noqa: N802 (the SDK's name)
        if self.is_open:
            self.closePort()
        try:
            self.ser = serial.Serial(port=self.port_name, baudrate=self.baudrate,
                                     bytesize=serial.EIGHTBITS, timeout=0, exclusive=True)
        except serial.SerialException as e:
            if e.errno in (errno.EAGAIN, errno.EWOULDBLOCK) and "lock" in str(e):
                raise PortInUse(e.errno, f"{self.port_name} is in use by another program "
                                "(another collect?)") from None
            raise
        self.is_open = True
        self.ser.reset_input_buffer()
        self.tx_time_per_byte = (1000.0 / self.baudrate) * 10.0
        return True

    def closePort(self):  # noqa: N802
        if self.ser is not None:
            self.ser.close()  # releases the lock
        self.is_open = False

    def readPort(self, length):  # noqa: N802
        """Up to ``length`` bytes; when none are waiting, first sleeps until some arrive or
        the packet timeout (``setPacketTimeout``) passes. Never waits longer than the SDK
        would have spun."""
        if not self.ser.in_waiting:
            left_ms = self.packet_timeout - self.getTimeSinceStart()
            if left_ms > 0:
                select.select([self.ser.fileno()], [], [], left_ms / 1000.0)
        return self.ser.read(length)


class LockedPortHandler(LockedPort, PortHandler):
    """dynamixel-sdk's ``PortHandler``, locked (:class:`LockedPort`)."""


def _word(lo: int, hi: int) -> int:
    return lo | (hi << 8)


def expected_answers(txpacket) -> dict[int, int] | None:
    """``{servo ID: parameter count of its status packet}`` for an (unstuffed) instruction
    packet; ``{}`` when no status packet is due, None when this class does not know the
    instruction (then any packet is taken, as the SDK does)."""
    dxl_id, inst = txpacket[_ID], txpacket[_INST]
    n_params = _word(txpacket[_LEN_L], txpacket[_LEN_H]) - 3
    params = list(txpacket[_PARAM:_PARAM + n_params])
    if inst == INST_SYNC_READ:
        length = _word(params[2], params[3])
        return {i: length for i in params[4:]}
    if inst == INST_BULK_READ:
        return {params[k]: _word(params[k + 3], params[k + 4])
                for k in range(0, len(params) - 4, 5)}
    if dxl_id == BROADCAST_ID:
        return {} if inst != INST_PING else None  # broadcast ping: the SDK's own reader
    if inst == INST_PING:
        return {dxl_id: 3}  # model number (2), firmware version (1)
    if inst == INST_READ:
        return {dxl_id: _word(params[2], params[3])}
    if inst in _NO_DATA:
        return {dxl_id: 0}
    return None


class Matching:
    """A vendor SDK's packet handler (dynamixel-sdk's, scservo_sdk's) that accepts only the
    status packets its last request is answered with (see the module docstring);
    ``stale_packets`` counts the others. A mixin: put it before the SDK's class; a
    subclass says which answers a request gets (``expected_answers``, a static method)
    and which packet is one (``_answers``)."""

    expected_answers = staticmethod(lambda txpacket: None)  # None: any packet is taken
    id_offset = _ID  # of the servo ID in a raw packet

    def __init__(self) -> None:
        self._expected: dict[int, int] | None = None
        self.stale_packets = 0

    def txPacket(self, port, txpacket):  # noqa: N802 (the SDK's name)
        # Before the SDK stuffs the packet in place.
        self._expected = self.expected_answers(txpacket)
        return super().txPacket(port, txpacket)

    def _answers(self, rxpacket, n_params: int) -> bool:
        """Whether ``rxpacket`` is a status packet with ``n_params`` parameters."""
        raise NotImplementedError

    def _matches(self, rxpacket) -> bool:
        expected = self._expected
        if expected is None:
            return True
        want = expected.get(rxpacket[self.id_offset])
        return want is not None and self._answers(rxpacket, want)

    def rxPacket(self, port, *fast_option):  # noqa: N802 (dynamixel-sdk's takes one more)
        while True:
            rxpacket, result = super().rxPacket(port, *fast_option)
            if result != COMM_SUCCESS or any(fast_option) or self._matches(rxpacket):
                return rxpacket, result
            self.stale_packets += 1  # a late answer to an earlier request: keep reading


class MatchingPacketHandler(Matching, Protocol2PacketHandler):
    """Protocol 2.0 packet handler that accepts only the status packets its last request
    is answered with (:class:`Matching`)."""

    expected_answers = staticmethod(expected_answers)

    def _answers(self, rxpacket, n_params: int) -> bool:
        n = _word(rxpacket[_LEN_L], rxpacket[_LEN_H]) - 4  # INST, ERR, CRC
        # A servo that refuses an instruction (error number set) may answer without data.
        return n == n_params or (rxpacket[_ERR] & 0x7F != 0 and n == 0)


def drain(port: PortHandler, quiet_s: float = STATUS_TIMEOUT_S, max_s: float = 0.5) -> int:
    """Reads and discards bytes until none arrived for ``quiet_s`` (at most ``max_s``);
    returns how many were discarded. Call it after a failed transaction: the answer the
    SDK stopped waiting for may still be on its way."""
    discarded = 0
    start = last = time.monotonic()
    while True:
        now = time.monotonic()
        if now - last >= quiet_s or now - start >= max_s:
            return discarded
        n = port.getBytesAvailable()
        if n:
            discarded += len(port.readPort(n))
            last = time.monotonic()
        else:
            time.sleep(min(0.002, quiet_s / 4))
