"""A simulated XM430 servo chain on a pseudo-terminal: the DYNAMIXEL bus protocol in front of the simulator."""
