"""A simulated XM430 servo chain on a pseudo-terminal: the DYNAMIXEL bus protocol in front
of the simulator.

The virtual robot is a simulator with a servo bus in front, so it sits above both
:mod:`jaxinertia.hardware` (control table, protocol framing) and :mod:`jaxinertia.sim`:

* :mod:`jaxinertia.virtual.bus`: the servos' control tables, the Protocol 2.0 replies on
  the pty (bus thread) and fault injection; servos that answer but do not move;
* :mod:`jaxinertia.virtual.physics`: the simulated arm behind the joint servos, one chunk
  at a time, and the loop that publishes it into their control tables;
* :mod:`jaxinertia.virtual.robot`: :class:`~jaxinertia.virtual.robot.VirtualServoBus`,
  the bus with that loop in a process of its own (the bus never waits on the physics);
* :mod:`jaxinertia.virtual.sts_bus`, :mod:`jaxinertia.virtual.sts_robot`: Feetech STS3215
  servos (the SO-101's): the STS protocol, a first-order bus model, and the same simulated
  arm behind them (:class:`~jaxinertia.virtual.sts_robot.VirtualStsBus`);
* :mod:`jaxinertia.virtual.testing`: ``jaxinertia virtual-robot`` in a subprocess.
"""
