"""DYNAMIXEL hardware path: the XM430 control table, Protocol 2.0 framing, the transport
(a locked port, status packets matched to their request), the driver on dynamixel-sdk,
safety checks and sample collection. The virtual servo bus (a simulator
behind the same protocol) is :mod:`jaxinertia.virtual`; the commands are
:mod:`jaxinertia.app.hardware_commands`."""
