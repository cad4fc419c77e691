"""Servo models as data: one frozen record per servo type, with its datasheet values.

A :class:`ServoModel` says what the servo boundary needs: ticks per turn, the position loop's
law and gain registers, what the servo senses (motor current, or only a "load" estimate)
and in which unit, and the motor's electrical/mechanical constants from which the simulator
builds its per-joint parameters (:meth:`jaxinertia.sim.servo.ServoParams.from_model`).
Nothing here imports the simulator or the hardware layer.

Position loop, as every model here is stepped (the DYNAMIXEL X e-manual's "Position PID
controller"; the Feetech loop is assumed to have the same form, see its gain scales)::

    PWM   = clip(kp P e + ki I sum(e) + kd D (e - e_prev), +-pwm_limit)   [register units]
    duty  = PWM / pwm_full_scale;  V = duty * supply_voltage
    I_m   = (V - k_e qd) / R;  tau = k_t I_m      (k_t = stall torque / stall current,
                                                   R = V / stall current, k_e = V / no-load)

Sources (values marked "estimate" are not on the cited page and are explained in place):
* XM430-W350-T: ROBOTIS e-manual, https://emanual.robotis.com/docs/en/dxl/x/xm430-w350/
  (the numbers the project has always used, unchanged; DESIGN.md "The servo").
* XL430-W250-T: https://emanual.robotis.com/docs/en/dxl/x/xl430-w250/ (and 2xl430-w250,
  the same motor and gear): 1.5 N m at 12.0 V / 1.4 A, 61 rev/min at 12.0 V, 4096 pulse/rev;
  control table: Present Load (126, 0.1 %), no Present Current, no Current Limit; Position
  D/I/P Gain initial 4000/0/640; PWM Limit 885.
* XL330-M288-T: https://emanual.robotis.com/docs/en/dxl/x/xl330-m288/: 0.52 N m at 5.0 V /
  1.47 A, 103 rev/min at 5.0 V, gear 288.4:1; Present Current (126) in 1 mA, Current Limit
  initial 1750 (1 mA); Position D/I/P Gain initial 0/0/400; PWM Limit 885.
* STS3215 (Feetech SMS/STS series; model number 777): 12-bit magnetic encoder (4096 steps),
  gear 1:345; 7.4 V version: 19.5 kg cm stall, no-load 0.192 s/60 deg (52 rev/min) at 7.4 V
  (vendor listing of the Feetech/Waveshare ST3215, DFRobot SER0069); 12 V version (C018):
  30 kg cm stall, 0.222 s/60 deg (45 rev/min) at 12 V (Feetech specification as quoted in
  TheRobotStudio/SO-ARM100 issue 134 and robonine.com's STS3215 test). Present Load (60)
  in 0.1 % (sign bit 10), Present Current (69) in 6.5 mA (Feetech STS memory table, as
  LeRobot's feetech tables use it); P/D/I Coefficient 21/22/23, defaults 32/32/0; LeRobot
  writes P = 16, I = 0, D = 0 on the SO-101 (lerobot/robots/so_follower).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

__all__ = [
    "KG_CM",
    "SERVO_MODELS",
    "STS3215_12V",
    "STS3215_7V4",
    "ServoModel",
    "SensorUnavailableError",
    "XL330_M288",
    "XL430_W250",
    "XM430_W350",
    "servo_model",
]

#: 1 kg cm of torque in N m (Feetech states stall torque in kg cm).
KG_CM = 0.0980665


class SensorUnavailableError(ValueError):
    """A servo that senses no motor current was asked for a current-based torque."""


@dataclass(frozen=True)
class ServoModel:
    """One servo type. Registers in the servo's own units, physics in SI.

    Attributes:
      name: the maker's model name; protocol: ``"dynamixel2"`` or ``"feetech_sts"``;
      model_number: what a ping returns.
      ticks_per_rev: encoder ticks per output turn.
      gain_scale: (kp, ki, kd) register-to-law scales of the position loop (module doc).
      gains: (P, I, D) registers the project sets for collection (I = 0: the method needs
        the rest error that an integrator would remove); default_gains: the maker's initial
        register values.
      pwm_full_scale: PWM register value of 100 % duty; pwm_limit: its default limit.
      sensed: ``"current"`` (Present Current) or ``"load"`` (Present Load only);
      sensed_lsb: its unit: A per LSB for current, fraction of the maximum per LSB for load.
      supply_voltage [V], stall_torque [N m], stall_current [A] (at that supply),
      no_load_rpm [rev/min] (at that supply), gear_ratio.
      current_limit: the motor current limit the simulator applies [A].
      friction: FrictionParams values for this servo (empty: the simulator's defaults).
      estimates: names of fields that are estimates, not datasheet values.
      notes: where the values come from.
    """

    name: str
    protocol: str
    model_number: int
    ticks_per_rev: int
    gain_scale: tuple[float, float, float]
    gains: tuple[float, float, float]
    default_gains: tuple[float, float, float]
    pwm_full_scale: float
    pwm_limit: float
    sensed: str
    sensed_lsb: float
    supply_voltage: float
    stall_torque: float
    stall_current: float
    no_load_rpm: float
    gear_ratio: float
    current_limit: float
    friction: dict = field(default_factory=dict, hash=False, compare=False)
    estimates: tuple[str, ...] = ()
    notes: str = ""

    def __post_init__(self):
        if self.sensed not in ("current", "load"):
            raise ValueError(f"{self.name}: sensed must be 'current' or 'load'")

    def replace_gains(self, gains: tuple[float, float, float]) -> ServoModel:
        """The same servo with other (P, I, D) registers set (an arm's per-joint override)."""
        return dataclasses.replace(self, gains=tuple(float(g) for g in gains))

    @property
    def rad_per_tick(self) -> float:
        return 2.0 * math.pi / self.ticks_per_rev

    @property
    def torque_constant(self) -> float:
        """Output-side torque constant from the stall point [N m/A] (gear and efficiency
        included): what a current-based torque assumes."""
        return self.stall_torque / self.stall_current

    @property
    def no_load_speed(self) -> float:
        """[rad/s] at ``supply_voltage``."""
        return self.no_load_rpm * 2.0 * math.pi / 60.0

    @property
    def has_current_sensor(self) -> bool:
        return self.sensed == "current"

    @property
    def current_lsb(self) -> float:
        """Present Current unit [A]; :class:`SensorUnavailableError` without a sensor."""
        self.require_current_sensor("a Present Current reading")
        return self.sensed_lsb

    def require_current_sensor(self, what: str = "the Sensor baseline") -> None:
        """Raises :class:`SensorUnavailableError`, saying why, if the servo senses no current."""
        if not self.has_current_sensor:
            raise SensorUnavailableError(
                f"{what} is unavailable on the {self.name}: it has no current sensor (it "
                f"reports Present Load only, in {self.sensed_lsb:g} of its maximum), so no "
                "current-based torque can be read")


# Friction of the small servos: the simulator's defaults (fitted to the XM430 on the
# OpenMANIPULATOR-X) scaled by stall torque. Estimates, until a simulator fit on that arm.
_XM430_FRICTION = dict(coulomb=0.03, static=0.05, viscous=0.01)


def _scaled_friction(stall_torque: float) -> dict:
    s = stall_torque / 4.1
    return {k: v * s for k, v in _XM430_FRICTION.items()}


XM430_W350 = ServoModel(
    name="XM430-W350-T", protocol="dynamixel2", model_number=1020, ticks_per_rev=4096,
    gain_scale=(1.0 / 128.0, 1.0 / 65536.0, 1.0 / 16.0),  # e-manual: KP = P/128 ...
    gains=(800.0, 0.0, 0.0), default_gains=(800.0, 0.0, 0.0),
    pwm_full_scale=885.0, pwm_limit=885.0,  # PWM Limit 885 = 100 %
    sensed="current", sensed_lsb=2.69e-3,  # Present Current 2.69 mA
    supply_voltage=12.0, stall_torque=4.1, stall_current=2.3, no_load_rpm=46.0,
    gear_ratio=353.5,
    current_limit=3.2,  # Current Limit 1193 x 2.69 mA = 3.21 A, as the simulator has used
    notes="ROBOTIS e-manual xm430-w350; the project's simulator fit starts here",
)

XL430_W250 = ServoModel(
    name="XL430-W250-T", protocol="dynamixel2", model_number=1060, ticks_per_rev=4096,
    gain_scale=(1.0 / 128.0, 1.0 / 65536.0, 1.0 / 16.0),  # X series, same loop
    gains=(640.0, 0.0, 4000.0), default_gains=(640.0, 0.0, 4000.0),
    pwm_full_scale=885.0, pwm_limit=885.0,
    sensed="load", sensed_lsb=1e-3,  # Present Load 0.1 %; no Present Current
    supply_voltage=12.0, stall_torque=1.5, stall_current=1.4, no_load_rpm=61.0,
    gear_ratio=257.4,  # 2xl430-w250 page (same motor and gear train)
    current_limit=1.4,  # no Current Limit register: the stall current bounds it
    friction=_scaled_friction(1.5), estimates=("friction",),
    notes="ROBOTIS e-manual xl430-w250 (12.0 V point; 11.1 V recommended: 1.4 N m, 1.3 A, "
          "57 rev/min)",
)

XL330_M288 = ServoModel(
    name="XL330-M288-T", protocol="dynamixel2", model_number=1200, ticks_per_rev=4096,
    gain_scale=(1.0 / 128.0, 1.0 / 65536.0, 1.0 / 16.0),
    gains=(400.0, 0.0, 0.0), default_gains=(400.0, 0.0, 0.0),
    pwm_full_scale=885.0, pwm_limit=885.0,
    sensed="current", sensed_lsb=1e-3,  # Present Current 1 mA
    supply_voltage=5.0, stall_torque=0.52, stall_current=1.47, no_load_rpm=103.0,
    gear_ratio=288.4,
    current_limit=1.75,  # Current Limit initial 1750 x 1 mA
    friction=_scaled_friction(0.52), estimates=("friction",),
    notes="ROBOTIS e-manual xl330-m288 (5.0 V recommended)",
)

# The Feetech position loop's register scales are not published: PWM = P e with a
# 1000-step duty (Feetech's torque and PWM registers span 0-1000) is an estimate that gives
# 47 N mm per tick at P = 16 and 12 V, close to the 1.04 N m / 20-30 ticks measured on a
# 12 V STS3215 in SO-ARM100 issue 134 (42 N mm per tick).
_STS_COMMON = dict(
    protocol="feetech_sts", model_number=777, ticks_per_rev=4096,
    gain_scale=(1.0, 1.0 / 65536.0, 1.0), gains=(16.0, 0.0, 0.0),
    default_gains=(32.0, 0.0, 32.0), pwm_full_scale=1000.0, pwm_limit=1000.0,
    sensed="current", sensed_lsb=6.5e-3,  # Present Current 6.5 mA (Present Load: 0.1 %)
    gear_ratio=345.0, current_limit=2.7,
    estimates=("gain_scale", "pwm_full_scale", "stall_current", "current_limit", "friction"),
)

STS3215_7V4 = ServoModel(
    name="STS3215 (7.4 V)", supply_voltage=7.4, stall_torque=19.5 * KG_CM,
    stall_current=2.7,  # estimate: the stall current vendor listings give (not on a
    #                      Feetech page seen here)
    no_load_rpm=52.0, friction=_scaled_friction(19.5 * KG_CM),
    notes="Feetech STS3215 C001 (7.4 V), vendor listing of the ST3215; loop scales estimated",
    **_STS_COMMON,
)

STS3215_12V = ServoModel(
    name="STS3215 (12 V)", supply_voltage=12.0, stall_torque=30.0 * KG_CM,
    stall_current=2.7,  # estimate: the 7.4 V version's (no published 12 V stall current)
    no_load_rpm=45.0, friction=_scaled_friction(30.0 * KG_CM),
    notes="Feetech STS3215 C018 (12 V), as quoted in SO-ARM100 issue 134; loop scales "
          "estimated",
    **_STS_COMMON,
)

#: Registry by short name (what an arm file names).
SERVO_MODELS: dict[str, ServoModel] = {
    "xm430_w350": XM430_W350,
    "xl430_w250": XL430_W250,
    "xl330_m288": XL330_M288,
    "sts3215_7v4": STS3215_7V4,
    "sts3215_12v": STS3215_12V,
}


def servo_model(name: str | ServoModel) -> ServoModel:
    """The model registered as ``name`` (a ServoModel passes through)."""
    if isinstance(name, ServoModel):
        return name
    key = name.lower().replace("-", "_").replace(" ", "_")
    try:
        return SERVO_MODELS[key]
    except KeyError:
        raise KeyError(f"unknown servo model {name!r}; known: {sorted(SERVO_MODELS)}") from None
