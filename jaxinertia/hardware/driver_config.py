"""What the DYNAMIXEL driver is configured with, reads and raises: :class:`ArmConfig` (bus,
registers, motion protocol), :class:`ArmState` (one synchronous reading, SI) and the bus
and servo errors. :mod:`jaxinertia.hardware.driver` re-exports them."""

from __future__ import annotations

import termios
from dataclasses import dataclass
from typing import Literal

import numpy as np

from jaxinertia import errors
from jaxinertia.hardware import control_table as ct

__all__ = ["BUS_ERRORS", "ArmConfig", "ArmState", "CommError", "PortError", "ServoHardwareError"]

#: What the serial device raises when it fails or disappears (pyserial's SerialException is
#: an OSError; tcflush on a vanished tty raises termios.error, which is not).
BUS_ERRORS = (OSError, termios.error)


class CommError(errors.HardwareError):
    """The bus failed (no or corrupt status packet) after all retries, or the device went
    away (exit code 3)."""


class PortError(CommError):
    """The serial device cannot be opened or is locked by another program (exit code 3)."""


class ServoHardwareError(errors.HardwareError):
    """A servo reported a hardware error (Hardware Error Status, alert bit; exit code 3)."""

    #: The error register's bits (Hardware Error Status, address 70).
    bit_names = {ct.HW_ERROR_VOLTAGE: "input voltage", ct.HW_ERROR_OVERHEATING: "overheating",
                 ct.HW_ERROR_ENCODER: "encoder", ct.HW_ERROR_ELECTRICAL_SHOCK: "electrical shock",
                 ct.HW_ERROR_OVERLOAD: "overload"}

    def __init__(self, errors: dict[int, int]) -> None:
        self.errors = errors
        text = "; ".join(f"ID {i}: " + ", ".join(n for b, n in self.bit_names.items() if e & b)
                         for i, e in errors.items())
        super().__init__(f"hardware error: {text} (power-cycle or reboot the servo)")


@dataclass(frozen=True)
class ArmConfig:
    """Bus, servo registers and the motion protocol.
    :func:`jaxinertia.hardware.arm_config.arm_config` takes every value from an arm's
    record; the field defaults are the OpenMANIPULATOR-X's registers as the
    paper ran it (PD position loop: I = 0; ROBOTIS' own configuration sets I = 100, which
    would integrate the very discrepancy the method measures). ``joint_limits`` None: the
    safety limits' (:class:`DynamixelArm` is then given them)."""

    port: str
    baudrate: int = 1_000_000
    joint_ids: tuple[int, ...] = (11, 12, 13, 14)
    gripper_id: int | None = 15
    #: Servo model per joint and the gripper's (``jaxinertia.servos.SERVO_MODELS`` names):
    #: what each must ping as, its control table and units (one name: every joint's).
    servo_models: tuple[str, ...] = ("xm430_w350",) * 4
    gripper_model: str | None = "xm430_w350"
    #: Position P/I/D registers: one value for every joint, or one per joint.
    p_gain: int | tuple[int, ...] = 800
    i_gain: int | tuple[int, ...] = 0
    d_gain: int | tuple[int, ...] = 0
    pwm_limit: int = 885
    profile_velocity: float = 0.5  # [rad/s], the simulator's profile
    profile_acceleration: float = 2.0  # [rad/s^2]
    joint_limits: np.ndarray | None = None  # (N, 2) [rad]
    settle_time: float = 0.2  # no tick may change for this long [s]
    move_timeout: float = 6.0  # per move [s]
    poll_period: float = 0.002  # [s]
    max_reading_gap: float = 0.5  # counted of a gap between two readings [s, servo clock]
    retries: int = 10  # per transaction; each retry waits for a quiet bus (~70 ms a try)
    on_stop: Literal["hold", "torque_off"] = "hold"
    #: On connect, REBOOT servos that report a hardware error (after its cause is fixed).
    reboot_on_error: bool = False


@dataclass(frozen=True)
class ArmState:
    """One synchronous reading of the joint servos (N,) each, SI."""

    q: np.ndarray  # Present Position [rad] (integer ticks)
    velocity: np.ndarray  # [rad/s]
    #: Present Current [A] (in the servo's steps: 2.69 mA on the XM430); NaN on a joint
    #: whose servo senses no current (XL430-W250: Present Load only).
    current: np.ndarray
    moving: np.ndarray  # Moving flag (bool)
    temperature: np.ndarray  # [degC]
    voltage: np.ndarray  # [V]
    ticks: np.ndarray  # Present Position register (int)
    servo_clock: int  # Realtime Tick of the first joint servo [ms, mod 32768]
    timestamp: float  # time.time() of the reading [s]
    #: Present Load [fraction of the maximum torque], signed; NaN where the servo reports
    #: no load (the XM430 and XL330 report their current instead).
    load: np.ndarray | None = None
