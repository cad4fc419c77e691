"""An arm on Feetech STS3215 servos (the SO-101), through scservo_sdk: the same surface,
collection protocol, retries, port lock, status matching and safety checks as
:class:`jaxinertia.hardware.driver.DynamixelArm`, whose bus logic it reuses.

What differs from the DYNAMIXEL path, all at the servo boundary
(:mod:`jaxinertia.hardware.feetech_table`):

* the bus: :class:`~jaxinertia.hardware.feetech_transport.LockedScsPortHandler` and
  :class:`~jaxinertia.hardware.feetech_transport.StsMatchingPacketHandler`;
* registers of one or two bytes, signed ones in sign-magnitude (encoded and decoded here,
  never two's complement);
* the status byte carries hardware errors, not instruction errors: any bit set is a
  hardware alarm, confirmed (or not) by reading Status (65) of each servo on a drained bus,
  as Hardware Error Status is on the DYNAMIXEL bus;
* EEPROM items (position limits, P/D/I Coefficient) are written with the torque off
  between Lock = 0 and Lock = 1, and each is read back: a servo that kept its old value
  is a :class:`CommError`, not a silently different position loop;
* the STS has no clock register: :attr:`ArmState.servo_clock` is the host's monotonic
  clock in ms (mod 32768), so the settling logic of ``wait_until_settled`` is unchanged;
* no REBOOT instruction: ``reboot`` (``--clear-errors``) turns the torque off and on
  again, which ends an STS protection stop.

:func:`feetech_config` builds the driver's configuration from an arm record
(``arms.SO101``): bus IDs, baud rate, the servo model's P/I/D registers (I = 0), joint
limits (workspace widened by the safety margin) and motion timing.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from scservo_sdk import GroupSyncRead, GroupSyncWrite

from jaxinertia.arm import Arm
from jaxinertia.hardware import feetech_table as ft
from jaxinertia.hardware.arm_config import arm_config
from jaxinertia.hardware.driver import (
    ArmConfig,
    ArmState,
    CommError,
    DynamixelArm,
    ServoHardwareError,
)
from jaxinertia.hardware.feetech_transport import LockedScsPortHandler, StsMatchingPacketHandler
from jaxinertia.hardware.safety import SafetyLimits
from jaxinertia.robot import Robot

__all__ = ["FeetechArm", "FeetechState", "StsHardwareError", "feetech_config"]


class StsHardwareError(ServoHardwareError):
    """A servo's Status (65) reports a protection stop (exit code 3)."""

    bit_names = ft.STATUS_NAMES


@dataclass(frozen=True)
class FeetechState(ArmState):
    """One synchronous reading of the joint servos: :class:`ArmState` (``servo_clock`` is
    the host's, in ms; ``load``, Present Load [fraction of the maximum torque], and
    ``current`` both read on every joint)."""


def feetech_config(port: str, arm: Arm, **overrides) -> ArmConfig:
    """The driver's configuration for ``arm`` (``arms.SO101``) on ``port``
    (:func:`jaxinertia.hardware.arm_config.arm_config`: PWM limit 1000, the STS's full
    scale); ``overrides`` replace any field."""
    return arm_config(arm, port, **overrides)


class FeetechArm(DynamixelArm):
    """The joint servos of an arm on Feetech STS3215s; a context manager as
    :class:`DynamixelArm` is (``connect`` and ``configure`` on entry, :meth:`stop` and
    close on exit)."""

    sync_read_class = GroupSyncRead
    refused_bits = 0  # the STS status byte has hardware-error bits only
    error_register = "status"
    hardware_error = StsHardwareError

    def __init__(self, config: ArmConfig, *, robot: Robot | None = None,
                 safety: SafetyLimits | None = None) -> None:
        super().__init__(config, robot=robot, safety=safety)
        self.port = LockedScsPortHandler(config.port)
        self.packet = StsMatchingPacketHandler()

    # ---- bus primitives ----------------------------------------------------------------

    def _write(self, dxl_id: int, name: str, value: int, *, alarm: bool = True) -> None:
        """Writes one item; an error bit in the answer is confirmed (``alarm``) or, while
        clearing it, expected."""
        item = ft.ITEMS[name]
        fn = {1: self.packet.write1ByteTxRx, 2: self.packet.write2ByteTxRx}[item.size]
        raw = ft.encode(item, value)
        _, error = self._retry(f"write {name} = {value} to ID {dxl_id}",
                               lambda: (None, *fn(self.port, dxl_id, item.address, raw)))
        if error and alarm:  # a hardware alarm in the status byte: confirmed (or not) by Status
            self._confirm_hardware_errors({*self.config.joint_ids, dxl_id})

    def _read(self, dxl_id: int, name: str) -> int:
        item = ft.ITEMS[name]
        fn = {1: self.packet.read1ByteTxRx, 2: self.packet.read2ByteTxRx}[item.size]
        raw, _ = self._retry(f"read {name} of ID {dxl_id}",
                             lambda: fn(self.port, dxl_id, item.address))
        return ft.decode(item, raw)

    def _write_eeprom(self, name: str, values) -> None:
        """Writes an EEPROM item of every joint servo (unlocked: :meth:`configure`) and
        reads it back."""
        values = np.broadcast_to(values, (self.n_joints,))
        self._write_all(name, values)
        for dxl_id, v in zip(self.config.joint_ids, values):
            got = self._read(dxl_id, name)
            if got != int(v):
                raise CommError(f"ID {dxl_id}: {name} reads {got} after writing {int(v)} "
                                "(EEPROM locked?)")

    def _goal_group(self, ticks) -> GroupSyncWrite:
        item = ft.ITEMS["goal_position"]
        group = GroupSyncWrite(self.port, self.packet, item.address, item.size)
        for dxl_id, t in zip(self.config.joint_ids, ticks):
            group.addParam(dxl_id, list(ft.encode(item, int(t)).to_bytes(2, "little")))
        return group

    # ---- lifecycle ---------------------------------------------------------------------

    def reboot(self, dxl_id: int, wait: float = 2.0) -> None:  # noqa: ARG002 (no reboot)
        """Ends a protection stop of one servo (``connect`` with ``reboot_on_error``):
        torque off, on (holding where it is), off."""
        for value in (0, 1, 0):
            self._write(dxl_id, "torque_enable", value, alarm=False)

    def configure(self) -> None:
        """Torque off; position mode, position limits and P/D/I Coefficient in EEPROM
        (unlocked, read back, locked again); speed and acceleration; goal = present
        position; torque on."""
        c = self.config
        limits = self.safety.joint_limits if c.joint_limits is None else c.joint_limits
        ticks = ft.rad_to_ticks(np.asarray(limits, np.float64))
        self._write_all("torque_enable", 0)
        self._write_all("lock", 0)
        self._write_eeprom("operating_mode", 0)  # position
        self._write_eeprom("min_position_limit", np.clip(ticks[:, 0], 0, 4095))
        self._write_eeprom("max_position_limit", np.clip(ticks[:, 1], 0, 4095))
        self._write_eeprom("p_coefficient", c.p_gain)
        self._write_eeprom("i_coefficient", c.i_gain)
        self._write_eeprom("d_coefficient", c.d_gain)
        self._write_all("lock", 1)
        self._write_all("goal_velocity",
                        max(1, round(c.profile_velocity / ft.VELOCITY_LSB)))
        self._write_all("acceleration",
                        min(254, max(1, round(c.profile_acceleration / ft.ACCELERATION_LSB))))
        self._write_goals(self.read_state().ticks)  # hold where it is
        self._write_all("torque_enable", 1)

    # ---- state and motion --------------------------------------------------------------

    def check_hardware_errors(self) -> None:
        """Raises :class:`StsHardwareError` if any joint servo's Status is set (confirmed
        first, on its own)."""
        item = ft.ITEMS["status"]
        data = self._sync_read(item.address, item.size)
        suspects = [i for i, d in data.items() if d[0]]
        if suspects:
            self._confirm_hardware_errors(suspects)

    def read_state(self) -> FeetechState:
        start, length = ft.STATE_BLOCK
        data = self._sync_read(start, length)
        t = time.time()

        def field_of(name: str) -> np.ndarray:
            return np.array([ft.field(ft.ITEMS[name], data[i], start)
                             for i in self.config.joint_ids])

        ticks = field_of("present_position")
        return FeetechState(
            q=ft.ticks_to_rad(ticks),
            velocity=field_of("present_velocity") * ft.VELOCITY_LSB,
            current=field_of("present_current") * ft.CURRENT_LSB_A,
            moving=field_of("moving").astype(bool),
            temperature=field_of("present_temperature").astype(np.float64),
            voltage=field_of("present_voltage") * ft.VOLTAGE_LSB,
            ticks=ticks, servo_clock=int(time.monotonic() * 1000.0) % 32768, timestamp=t,
            load=field_of("present_load") * ft.LOAD_LSB)
