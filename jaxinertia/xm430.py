"""The DYNAMIXEL XM430-W350's units: the servo boundary's constants, shared by the
simulated servo (:mod:`jaxinertia.sim.servo`) and the real one
(:mod:`jaxinertia.hardware.control_table`).

Ticks, current LSBs and PWM registers exist only at that boundary; everything past it is
SI. The values are :data:`jaxinertia.servos.XM430_W350`'s (the servo as data); other servo
models are records there.
"""

from __future__ import annotations

import numpy as np

from jaxinertia.servos import XM430_W350

__all__ = [
    "CURRENT_LSB_A",
    "NOMINAL_TORQUE_CONSTANT",
    "PWM_FULL_SCALE",
    "RAD_PER_TICK",
    "TICKS_PER_REV",
]

TICKS_PER_REV = XM430_W350.ticks_per_rev  # 4096
RAD_PER_TICK = 2.0 * np.pi / TICKS_PER_REV
CURRENT_LSB_A = XM430_W350.sensed_lsb  # Present Current unit [A]: 2.69 mA
#: Datasheet torque constant (4.1 N m / 2.3 A): what a current-based torque assumes.
NOMINAL_TORQUE_CONSTANT = XM430_W350.torque_constant
PWM_FULL_SCALE = XM430_W350.pwm_full_scale  # PWM register value for 100 % duty: 885
