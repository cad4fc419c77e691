"""The serial transport under the Feetech driver: scservo_sdk's port and packet handlers,
made safe for a real bus as :mod:`jaxinertia.hardware.transport` makes dynamixel-sdk's.

* :class:`LockedScsPortHandler`: the device locked while open, status packets awaited in
  ``select`` (:class:`jaxinertia.hardware.transport.LockedPort`).
* :class:`StsMatchingPacketHandler`: scservo_sdk's packet handler (STS, little-endian:
  what ``PacketHandler(0)`` returns) that accepts only the status packets its last request
  is answered with: the servo IDs it addressed, each with the parameter count its
  instruction gets (PING none, READ and SYNC_READ the length asked for, WRITE, REG_WRITE
  and ACTION none). The SDK's readers match the servo ID only, so a status packet that
  arrives after the SDK gave up waiting for it would be taken as the answer to the next
  request to that servo; here it is discarded and counted (``stale_packets``), and
  reading goes on within the same timeout.

The SCS/STS protocol (Feetech's memory-table manual; scservo_sdk)::

    request  FF FF | ID | LEN | INST | PARAM ... | CHK      LEN = n_params + 2
    status   FF FF | ID | LEN | ERR  | PARAM ... | CHK      CHK = ~(ID + LEN + ... ) & 0xFF

Like Protocol 2.0 it has no sequence numbers: a late answer of exactly the shape of the
next request's cannot be told apart from it, and the driver drains the bus after every
failed transaction (:func:`jaxinertia.hardware.transport.drain`).
"""

from __future__ import annotations

from scservo_sdk import PortHandler, protocol_packet_handler
from scservo_sdk.scservo_def import (
    BROADCAST_ID,
    INST_ACTION,
    INST_PING,
    INST_READ,
    INST_REG_WRITE,
    INST_SYNC_READ,
    INST_WRITE,
    SCS_SETEND,
)

from jaxinertia.hardware.transport import LockedPort, Matching

__all__ = ["LockedScsPortHandler", "StsMatchingPacketHandler", "expected_answers"]

# Raw packet offsets: FF FF ID LEN INST|ERR PARAMS.. CHK
_ID, _LEN, _INST, _PARAM = 2, 3, 4, 5
_NO_DATA = (INST_PING, INST_WRITE, INST_REG_WRITE, INST_ACTION)


class LockedScsPortHandler(LockedPort, PortHandler):
    """scservo_sdk's ``PortHandler``, locked (:class:`LockedPort`)."""


def expected_answers(txpacket) -> dict[int, int] | None:
    """``{servo ID: parameter count of its status packet}`` for an instruction packet;
    ``{}`` when no status packet is due, None when the instruction is not known here (then
    any packet is taken, as the SDK does)."""
    scs_id, inst = txpacket[_ID], txpacket[_INST]
    params = list(txpacket[_PARAM:_PARAM + txpacket[_LEN] - 2])
    if inst == INST_SYNC_READ:
        return {i: params[1] for i in params[2:]}
    if scs_id == BROADCAST_ID:
        return {}
    if inst == INST_READ:
        return {scs_id: params[1]}
    if inst in _NO_DATA:
        return {scs_id: 0}
    return None


class StsMatchingPacketHandler(Matching, protocol_packet_handler):
    """STS packet handler (little-endian registers) that accepts only the status packets
    its last request is answered with (module docstring; :class:`Matching`)."""

    expected_answers = staticmethod(expected_answers)
    id_offset = _ID

    def __init__(self) -> None:
        SCS_SETEND(0)  # what PacketHandler(0) does: STS byte order (a global of the SDK)
        super().__init__()

    def _answers(self, rxpacket, n_params: int) -> bool:
        return rxpacket[_LEN] - 2 == n_params
