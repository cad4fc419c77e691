"""DYNAMIXEL hardware path: Protocol 2.0, the driver on dynamixel-sdk, a virtual servo bus."""
