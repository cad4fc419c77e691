"""The XM430-W350-T control table (ROBOTIS e-manual), and the conversions at the servo boundary.

Registers are little-endian. Addresses 0-63 are EEPROM (writable only with the torque off),
64 and up RAM. Only the items that the driver and the virtual servo use are listed;
everything else in the table reads as zero on the virtual servo.

Units: position 4096 ticks/rev with 2048 = 0 rad (OpenMANIPULATOR-X's joint zero), present
current 2.69 mA, velocity 0.229 rev/min, profile acceleration 214.577 rev/min^2, input
voltage 0.1 V, temperature 1 degC, PWM 885 = 100 %.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from jaxinertia.xm430 import CURRENT_LSB_A, RAD_PER_TICK

__all__ = [
    "ITEMS",
    "XM430_W350_MODEL",
    "Item",
    "current_to_register",
    "rad_to_ticks",
    "register_to_current",
    "ticks_to_rad",
]

XM430_W350_MODEL = 1020
ZERO_TICKS = 2048
VELOCITY_LSB = 0.229 * 2.0 * np.pi / 60.0  # [rad/s]
ACCELERATION_LSB = 214.577 * 2.0 * np.pi / 3600.0  # [rad/s^2]
VOLTAGE_LSB = 0.1  # [V]
EEPROM_END = 64  # first RAM address


class Item(NamedTuple):
    address: int
    size: int
    default: int = 0
    writable: bool = True
    signed: bool = False


#: name -> Item, ordered by address. Defaults are the factory values of the e-manual.
ITEMS: dict[str, Item] = {
    "model_number": Item(0, 2, XM430_W350_MODEL, writable=False),
    "model_information": Item(2, 4, 0, writable=False),
    "firmware_version": Item(6, 1, 48, writable=False),
    "id": Item(7, 1, 1),
    "baud_rate": Item(8, 1, 1),
    "return_delay_time": Item(9, 1, 250),
    "drive_mode": Item(10, 1, 0),
    "operating_mode": Item(11, 1, 3),
    "secondary_id": Item(12, 1, 255),
    "protocol_type": Item(13, 1, 2),
    "homing_offset": Item(20, 4, 0, signed=True),
    "moving_threshold": Item(24, 4, 10),
    "temperature_limit": Item(31, 1, 80),
    "max_voltage_limit": Item(32, 2, 160),
    "min_voltage_limit": Item(34, 2, 95),
    "pwm_limit": Item(36, 2, 885),
    "current_limit": Item(38, 2, 1193),
    "velocity_limit": Item(44, 4, 200),
    "max_position_limit": Item(48, 4, 4095),
    "min_position_limit": Item(52, 4, 0),
    "shutdown": Item(63, 1, 0x34),
    "torque_enable": Item(64, 1, 0),
    "led": Item(65, 1, 0),
    "status_return_level": Item(68, 1, 2),
    "registered_instruction": Item(69, 1, 0, writable=False),
    "hardware_error_status": Item(70, 1, 0, writable=False),
    "velocity_i_gain": Item(76, 2, 1920),
    "velocity_p_gain": Item(78, 2, 100),
    "position_d_gain": Item(80, 2, 0),
    "position_i_gain": Item(82, 2, 0),
    "position_p_gain": Item(84, 2, 800),
    "feedforward_2nd_gain": Item(88, 2, 0),
    "feedforward_1st_gain": Item(90, 2, 0),
    "bus_watchdog": Item(98, 1, 0),
    "goal_pwm": Item(100, 2, 885, signed=True),
    "goal_current": Item(102, 2, 1193, signed=True),
    "goal_velocity": Item(104, 4, 0, signed=True),
    "profile_acceleration": Item(108, 4, 0),
    "profile_velocity": Item(112, 4, 0),
    "goal_position": Item(116, 4, ZERO_TICKS, signed=True),
    "realtime_tick": Item(120, 2, 0, writable=False),
    "moving": Item(122, 1, 0, writable=False),
    "moving_status": Item(123, 1, 0, writable=False),
    "present_pwm": Item(124, 2, 0, writable=False, signed=True),
    "present_current": Item(126, 2, 0, writable=False, signed=True),
    "present_velocity": Item(128, 4, 0, writable=False, signed=True),
    "present_position": Item(132, 4, ZERO_TICKS, writable=False, signed=True),
    "velocity_trajectory": Item(136, 4, 0, writable=False, signed=True),
    "position_trajectory": Item(140, 4, ZERO_TICKS, writable=False, signed=True),
    "present_input_voltage": Item(144, 2, 120, writable=False),
    "present_temperature": Item(146, 1, 30, writable=False),
}

#: Hardware Error Status bits (address 70).
HW_ERROR_VOLTAGE = 1 << 0
HW_ERROR_OVERHEATING = 1 << 2
HW_ERROR_ENCODER = 1 << 3
HW_ERROR_ELECTRICAL_SHOCK = 1 << 4
HW_ERROR_OVERLOAD = 1 << 5

#: The block the driver reads every poll: Realtime Tick (120) .. Present Temperature (146).
STATE_BLOCK = (120, 146 + 1 - 120)
#: Realtime Tick: the servo's clock, 1 ms, wraps at 32768.
REALTIME_TICK_S = 1e-3
REALTIME_TICK_WRAP = 32768


def to_unsigned(value: int, size: int) -> int:
    return int(value) & ((1 << (8 * size)) - 1)


def to_signed(value: int, size: int) -> int:
    bits = 8 * size
    value = int(value) & ((1 << bits) - 1)
    return value - (1 << bits) if value >> (bits - 1) else value


def rad_to_ticks(q: np.ndarray) -> np.ndarray:
    """Goal Position register (int) of joint angles [rad] (rounded as the simulator does)."""
    return np.round(np.asarray(q) / RAD_PER_TICK).astype(np.int64) + ZERO_TICKS


def ticks_to_rad(ticks: np.ndarray) -> np.ndarray:
    return (np.asarray(ticks, np.float64) - ZERO_TICKS) * RAD_PER_TICK


def register_to_current(value: np.ndarray) -> np.ndarray:
    """Present Current (signed register) -> [A]."""
    return np.asarray(value, np.float64) * CURRENT_LSB_A


def current_to_register(current: np.ndarray) -> np.ndarray:
    return np.round(np.asarray(current) / CURRENT_LSB_A).astype(np.int64)
