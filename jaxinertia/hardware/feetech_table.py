"""The Feetech STS3215 memory table (SMS/STS series), and the conversions at its servo boundary.

Addresses and sizes are those of Feetech's STS/SMS memory table as LeRobot transcribes it
(``lerobot/motors/feetech/tables.py``, ``STS_SMS_SERIES_CONTROL_TABLE``, from
http://doc.feetech.cn FT-SMS-STS-emanual); the project's own summary is DESIGN.md, "Arms and
servos as data". Two-byte registers are little-endian on the STS series (scservo_sdk's
``PacketHandler(0)``; the SCS series is big-endian). Addresses 0-39 are EEPROM, 40 and up
SRAM. EEPROM writes are guarded by **Lock** (55): the driver writes 0 before changing an
EEPROM item and 1 after, as LeRobot does, and reads every EEPROM value back.

Signed registers are **sign-magnitude**, not two's complement: the sign is one bit and the
rest is the magnitude. The sign bit is bit 15 for positions, speeds and current, bit 11 for
the homing offset and bit 10 for the load (DESIGN.md; LeRobot's
``STS_SMS_SERIES_ENCODINGS_TABLE`` lists the homing offset and the speeds).

Units (converted to SI here and nowhere else):

* position: 4096 ticks per turn (12-bit magnetic encoder); 2048 = 0 rad, the middle of the
  range, which is LeRobot's calibration convention for the SO-101 (``arms.SO101``);
* speed: ticks per second (Feetech: 50 steps/s = 0.732 rev/min); acceleration: 100 ticks/s^2;
* load: 0.1 % of the maximum torque (0..1000);
* current: 6.5 mA per LSB (the STS memory table's unit for Protection Current (28) and
  Present Current (69), as ``servos.STS3215_7V4.sensed_lsb`` records it);
* voltage: 0.1 V; temperature: 1 degC.

The status byte of every status packet and the Status register (65) carry the same error
bits (scservo_sdk's ``ERRBIT_*``): input voltage, angle sensor, overheating, overcurrent,
overload.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

__all__ = [
    "EEPROM_END",
    "ITEMS",
    "STATUS_NAMES",
    "STS3215_MODEL",
    "Item",
    "decode",
    "encode",
    "from_sign_magnitude",
    "rad_to_ticks",
    "ticks_to_rad",
    "to_sign_magnitude",
]

#: What a STS3215 reports as its model number (LeRobot's MODEL_NUMBER_TABLE["sts3215"]).
STS3215_MODEL = 777
TICKS_PER_REV = 4096
ZERO_TICKS = 2048
RAD_PER_TICK = 2.0 * math.pi / TICKS_PER_REV
VELOCITY_LSB = RAD_PER_TICK  # [rad/s] per tick/s
#: Acceleration (41) unit [rad/s^2] (Feetech STS manual: 100 steps/s^2; LeRobot writes 254,
#: the largest); 0 means the servo's own default.
ACCELERATION_LSB = 100.0 * RAD_PER_TICK
LOAD_LSB = 1e-3  # fraction of the maximum torque
CURRENT_LSB_A = 6.5e-3  # [A]
VOLTAGE_LSB = 0.1  # [V]
EEPROM_END = 40  # first SRAM address
TABLE_SIZE = 128  # bytes the virtual servo keeps (the table ends below 90)

#: Status (65) / status-packet error bits.
STATUS_VOLTAGE = 1 << 0
STATUS_ANGLE = 1 << 1
STATUS_OVERHEAT = 1 << 2
STATUS_OVERCURRENT = 1 << 3
STATUS_OVERLOAD = 1 << 5
STATUS_NAMES = {STATUS_VOLTAGE: "input voltage", STATUS_ANGLE: "angle sensor",
                STATUS_OVERHEAT: "overheating", STATUS_OVERCURRENT: "overcurrent",
                STATUS_OVERLOAD: "overload"}


class Item(NamedTuple):
    address: int
    size: int
    default: int = 0
    writable: bool = True
    #: The sign bit of a sign-magnitude value (None: unsigned).
    sign_bit: int | None = None

    @property
    def eeprom(self) -> bool:
        return self.address < EEPROM_END


#: name -> Item, ordered by address. Defaults: the factory values of a 7.4 V STS3215 where
#: known (LeRobot's tables give addresses only); the virtual servo starts from them.
ITEMS: dict[str, Item] = {
    "firmware_major_version": Item(0, 1, 3, writable=False),
    "firmware_minor_version": Item(1, 1, 10, writable=False),
    "model_number": Item(3, 2, STS3215_MODEL, writable=False),
    "id": Item(5, 1, 1),
    "baud_rate": Item(6, 1, 0),  # 0 = 1 Mbit/s
    "return_delay_time": Item(7, 1, 0),
    "response_status_level": Item(8, 1, 1),
    "min_position_limit": Item(9, 2, 0),
    "max_position_limit": Item(11, 2, 4095),
    "max_temperature_limit": Item(13, 1, 70),
    "max_voltage_limit": Item(14, 1, 80),
    "min_voltage_limit": Item(15, 1, 40),
    "max_torque_limit": Item(16, 2, 1000),
    "phase": Item(18, 1, 12),
    "unloading_condition": Item(19, 1, 44),
    "led_alarm_condition": Item(20, 1, 47),
    "p_coefficient": Item(21, 1, 32),
    "d_coefficient": Item(22, 1, 32),
    "i_coefficient": Item(23, 1, 0),
    "minimum_startup_force": Item(24, 2, 16),
    "cw_dead_zone": Item(26, 1, 1),
    "ccw_dead_zone": Item(27, 1, 1),
    "protection_current": Item(28, 2, 500),
    "angular_resolution": Item(30, 1, 1),
    "homing_offset": Item(31, 2, 0, sign_bit=11),
    "operating_mode": Item(33, 1, 0),  # 0: position
    "protective_torque": Item(34, 1, 20),
    "protection_time": Item(35, 1, 200),
    "overload_torque": Item(36, 1, 80),
    "torque_enable": Item(40, 1, 0),
    "acceleration": Item(41, 1, 0),
    "goal_position": Item(42, 2, ZERO_TICKS, sign_bit=15),
    "goal_time": Item(44, 2, 0),
    "goal_velocity": Item(46, 2, 0, sign_bit=15),
    "torque_limit": Item(48, 2, 1000),
    "lock": Item(55, 1, 1),
    "present_position": Item(56, 2, ZERO_TICKS, writable=False, sign_bit=15),
    "present_velocity": Item(58, 2, 0, writable=False, sign_bit=15),
    "present_load": Item(60, 2, 0, writable=False, sign_bit=10),
    "present_voltage": Item(62, 1, 74, writable=False),
    "present_temperature": Item(63, 1, 30, writable=False),
    "status": Item(65, 1, 0, writable=False),
    "moving": Item(66, 1, 0, writable=False),
    "present_current": Item(69, 2, 0, writable=False, sign_bit=15),
}

#: The block the driver reads every poll: Present Position (56) .. Present Current (69).
STATE_BLOCK = (56, 69 + 2 - 56)


def to_sign_magnitude(value: int, sign_bit: int) -> int:
    """The register value of ``value``: magnitude in the bits below ``sign_bit``, the sign
    in it. Raises ValueError when the magnitude does not fit."""
    value = int(value)
    if abs(value) >= 1 << sign_bit:
        raise ValueError(f"{value} does not fit a sign-magnitude register with sign bit "
                         f"{sign_bit}")
    return -value | (1 << sign_bit) if value < 0 else value


def from_sign_magnitude(raw: int, sign_bit: int) -> int:
    """The value of a sign-magnitude register (bits above the sign bit are ignored)."""
    raw = int(raw)
    magnitude = raw & ((1 << sign_bit) - 1)
    return -magnitude if raw >> sign_bit & 1 else magnitude


def encode(item: Item, value: int) -> int:
    """The unsigned register value of ``value`` for ``item`` (ValueError if out of range)."""
    raw = int(value) if item.sign_bit is None else to_sign_magnitude(value, item.sign_bit)
    if not 0 <= raw < 1 << (8 * item.size):
        raise ValueError(f"{value} does not fit a {item.size}-byte register")
    return raw


def decode(item: Item, raw: int) -> int:
    return int(raw) if item.sign_bit is None else from_sign_magnitude(raw, item.sign_bit)


def field(item: Item, block: bytes, start: int) -> int:
    """``item``'s value in ``block``, a read of the table from address ``start``."""
    k = item.address - start
    return decode(item, int.from_bytes(block[k:k + item.size], "little"))


def rad_to_ticks(q) -> np.ndarray:
    """Goal Position register values (int) of joint angles [rad] (2048 = 0 rad)."""
    return np.round(np.asarray(q) / RAD_PER_TICK).astype(np.int64) + ZERO_TICKS


def ticks_to_rad(ticks) -> np.ndarray:
    return (np.asarray(ticks, np.float64) - ZERO_TICKS) * RAD_PER_TICK
