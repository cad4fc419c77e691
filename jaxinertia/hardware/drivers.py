"""The driver of each servo bus: an arm record's :attr:`jaxinertia.arm.Arm.bus` (the protocol
its servo models speak) names the class that drives it, so that a command picks the driver
from the record, never from the arm's name."""

from __future__ import annotations

from jaxinertia.arm import Arm
from jaxinertia.hardware.driver import DynamixelArm
from jaxinertia.hardware.feetech import FeetechArm

__all__ = ["DRIVERS", "driver_class"]

#: Driver class by bus protocol (``ServoModel.protocol``).
DRIVERS: dict[str, type[DynamixelArm]] = {"dynamixel2": DynamixelArm, "feetech_sts": FeetechArm}


def driver_class(arm: Arm) -> type[DynamixelArm]:
    """The driver of ``arm``'s bus: :class:`DynamixelArm` (DYNAMIXEL Protocol 2.0) or
    :class:`FeetechArm` (Feetech STS)."""
    return DRIVERS[arm.bus]
