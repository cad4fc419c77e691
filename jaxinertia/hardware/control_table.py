"""The DYNAMIXEL X control tables (ROBOTIS e-manual) of the XM430-W350-T, XL430-W250-T and
XL330-M288-T, and the conversions at the servo boundary.

Registers are little-endian. Addresses 0-63 are EEPROM (writable only with the torque off),
64 and up RAM. Only the items that the driver and the virtual servo use are listed;
everything else in the table reads as zero on the virtual servo.

Units: position 4096 ticks/rev with 2048 = 0 rad (OpenMANIPULATOR-X's joint zero), present
current 2.69 mA, velocity 0.229 rev/min, profile acceleration 214.577 rev/min^2, input
voltage 0.1 V, temperature 1 degC, PWM 885 = 100 %.

The three models share every address the driver uses (the X series' layout); they differ
in what address 126 holds and in some initial values (:data:`TABLES`, by model number):

* XL430-W250-T (model number 1060; https://emanual.robotis.com/docs/en/dxl/x/xl430-w250/,
  ROBOTIS-GIT/emanual ``docs/en/dxl/x/xl430-w250.md``): **no current sensor**: 126 is
  Present Load (signed, 0.1 % of the maximum torque, -1000..1000), and there is no Current
  Limit (38) or Goal Current (102); Position D/I/P Gain 4000/0/640, Velocity I/P 1000/100,
  Temperature Limit 72, Max/Min Voltage Limit 140/60, Velocity Limit 265, Shutdown 52.
* XL330-M288-T (model number 1200; https://emanual.robotis.com/docs/en/dxl/x/xl330-m288/,
  ``docs/en/dxl/x/xl330-m288.md``): 126 is Present Current in **1 mA**; Current Limit
  1750 (1 mA); Position D/I/P Gain 0/0/400, Velocity I/P 1600/180, Temperature Limit 70,
  Max/Min Voltage Limit 70/35, Velocity Limit 445, Shutdown 53.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from jaxinertia.xm430 import CURRENT_LSB_A, RAD_PER_TICK

__all__ = [
    "ITEMS",
    "TABLES",
    "XL330_M288_MODEL",
    "XL430_W250_MODEL",
    "XM430_W350_MODEL",
    "Item",
    "items_of",
    "current_to_register",
    "rad_to_ticks",
    "register_to_current",
    "ticks_to_rad",
]

XM430_W350_MODEL = 1020
XL430_W250_MODEL = 1060
XL330_M288_MODEL = 1200
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



def _variant(model_number: int, drop: tuple[str, ...] = (), add: dict | None = None,
             **defaults: int) -> dict[str, Item]:
    """The XM430's table with items dropped, added and initial values changed."""
    items = {k: v for k, v in ITEMS.items() if k not in drop}
    items.update(add or {})
    items["model_number"] = items["model_number"]._replace(default=model_number)
    for name, value in defaults.items():
        items[name] = items[name]._replace(default=value)
    return dict(sorted(items.items(), key=lambda kv: kv[1].address))


#: Control table by model number (what a ping returns); initial values from the e-manual
#: pages named in the module docstring.
TABLES: dict[int, dict[str, Item]] = {
    XM430_W350_MODEL: ITEMS,
    XL430_W250_MODEL: _variant(
        XL430_W250_MODEL, drop=("current_limit", "goal_current", "present_current"),
        add={"present_load": Item(126, 2, 0, writable=False, signed=True)},
        temperature_limit=72, max_voltage_limit=140, min_voltage_limit=60,
        velocity_limit=265, shutdown=52, velocity_i_gain=1000, velocity_p_gain=100,
        position_d_gain=4000, position_i_gain=0, position_p_gain=640),
    XL330_M288_MODEL: _variant(
        XL330_M288_MODEL, temperature_limit=70, max_voltage_limit=70, min_voltage_limit=35,
        current_limit=1750, goal_current=1750, velocity_limit=445, shutdown=53,
        velocity_i_gain=1600, velocity_p_gain=180, position_d_gain=0, position_i_gain=0,
        position_p_gain=400),
}


def items_of(model_number: int) -> dict[str, Item]:
    """The control table of the servo that pings as ``model_number``."""
    try:
        return TABLES[model_number]
    except KeyError:
        raise KeyError(f"no DYNAMIXEL control table for model number {model_number} "
                       f"(known: {sorted(TABLES)})") from None


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


def register_to_current(value: np.ndarray, lsb: float | np.ndarray = CURRENT_LSB_A
                        ) -> np.ndarray:
    """Present Current (signed register) -> [A] (``lsb``: the servo's unit, the XM430's
    2.69 mA by default)."""
    return np.asarray(value, np.float64) * lsb


def current_to_register(current: np.ndarray, lsb: float | np.ndarray = CURRENT_LSB_A
                        ) -> np.ndarray:
    return np.round(np.asarray(current) / lsb).astype(np.int64)
