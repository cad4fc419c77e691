"""``virtual-robot --arm so101`` (and any arm whose record names Feetech STS servos): the
virtual STS bus (:class:`jaxinertia.virtual.sts_bus.StsServoBus`) on a pseudo-terminal.

The SO-101's virtual robot is, for now, the bus model: six STS3215 servos (the arm's bus
IDs and its gripper's) answering scservo_sdk with the same fault injection as the
DYNAMIXEL virtual robot, the joints following the first-order servo model of
:mod:`jaxinertia.virtual.sts_bus`. It is not yet the simulated SO-101 holding an object:
``--object``, ``--calibration`` and ``--q0`` are not used (said on stderr when given).
"""

from __future__ import annotations

import sys

from jaxinertia.arm import Arm
from jaxinertia.virtual.bus import Faults
from jaxinertia.virtual.sts_bus import StsServoBus

__all__ = ["virtual_sts_robot"]


def virtual_sts_robot(args, arm: Arm, faults: Faults, serve) -> int:
    """Serves ``arm``'s STS servos on a pty with ``faults``; ``serve(bus, what)`` prints
    the device path first and runs until SIGTERM or Ctrl-C."""
    ignored = [o for o, given in (("--object", args.object != "none"),
                                  ("--calibration", args.calibration is not None))
               if given]
    if ignored:
        print(f"virtual-robot --arm {arm.name}: the STS bus model does not simulate the arm; "
              f"{', '.join(ignored)} not used", file=sys.stderr)
    extra = () if arm.gripper_id is None else (arm.gripper_id,)
    bus = StsServoBus(tuple(arm.bus_ids), extra, faults=faults,
                      input_voltage=arm.servo_models[0].supply_voltage, speed=args.speed)
    return serve(bus, f"virtual STS3215 servos {list(bus.servos)} on {bus.path} ({arm.name}, "
                      "bus model)")
