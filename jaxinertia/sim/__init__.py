"""Simulated OpenMANIPULATOR-X on DYNAMIXEL XM430-W350-T servos (pure JAX)."""
