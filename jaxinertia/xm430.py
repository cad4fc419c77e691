"""The DYNAMIXEL XM430-W350's units: the servo boundary's constants, shared by the
simulated servo (:mod:`jaxinertia.sim.servo`) and the real one
(:mod:`jaxinertia.hardware.control_table`).

Ticks, current LSBs and PWM registers exist only at that boundary; everything past it is
SI. A second servo family gets a module like this one.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "CURRENT_LSB_A",
    "NOMINAL_TORQUE_CONSTANT",
    "PWM_FULL_SCALE",
    "RAD_PER_TICK",
    "TICKS_PER_REV",
]

TICKS_PER_REV = 4096
RAD_PER_TICK = 2.0 * np.pi / TICKS_PER_REV
CURRENT_LSB_A = 2.69e-3  # Present Current unit [A]
#: Datasheet torque constant (4.1 N m / 2.3 A): what a current-based torque assumes.
NOMINAL_TORQUE_CONSTANT = 4.1 / 2.3
PWM_FULL_SCALE = 885.0  # PWM register value for 100 % duty
