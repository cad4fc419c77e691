"""A simulated XM430 servo chain on a pseudo-terminal: the DYNAMIXEL bus protocol in front
of the simulator.

The virtual robot is a simulator with a servo bus in front, so it sits above both
:mod:`jaxinertia.hardware` (control table, protocol framing) and :mod:`jaxinertia.sim`:

* :mod:`jaxinertia.virtual.bus`: the servos' control tables, the Protocol 2.0 replies on
  the pty (bus thread) and fault injection; servos that answer but do not move;
* :mod:`jaxinertia.virtual.physics`: :class:`~jaxinertia.virtual.physics.VirtualServoBus`,
  the bus with the joint servos driven by the simulated arm (physics thread);
* :mod:`jaxinertia.virtual.testing`: ``jaxinertia virtual-robot`` in a subprocess.
"""
