"""The virtual SO-101: STS3215 servos (:class:`jaxinertia.virtual.sts_bus.StsBus`, the STS
protocol and its rules) whose joints are the simulated arm holding the object, in the
physics process of :class:`jaxinertia.virtual.robot.VirtualServoBus` (the same design:
compiled before the bus opens, chunks published under the shared lock, the bus thread
never waiting on the physics; the same fault injection).

:class:`VirtualStsBus` is both: the STS bus's protocol and the virtual robot's physics
process. :class:`StsRegisterMap` is how that physics reads and writes an STS3215's memory
table (the servo boundary, :mod:`jaxinertia.hardware.feetech_table`):

* read per chunk: P/I/D Coefficient (21-23; onto the simulator's XM430-scale loop through
  the ratios of :func:`jaxinertia.virtual.physics.loop_ratios`: PWM = P e + D de with a
  1000-step duty), Torque Limit (48, 1000 = 100 % duty) as the PWM limit, Goal Velocity
  (46, ticks/s) and Acceleration (41, 100 ticks/s^2) as the goal's trapezoidal profile
  (0: none);
* published per chunk: Present Position (56, 12-bit, 2048 = 0 rad, clamped to 0..4095),
  Present Speed (58, ticks/s), Present Load (60, the duty in 0.1 %, sign bit 10), Present
  Current (69, 6.5 mA, sign bit 15): sign-magnitude, positive where the servo pushes
  towards increasing ticks; Moving (66).

Moving is 1 while a written goal is not simulated yet, while the goal's profile runs,
at a speed of a tick per second or more, and for :data:`MOVING_HOLD_S` of simulated time
after any tick changed. The STS has no clock register, so the driver times stillness on
the host's clock (:class:`jaxinertia.hardware.feetech.FeetechArm`); the hold keeps a
physics process that a busy host stalls at the turning point of a swing (speed near
zero, ticks still changing) from looking still meanwhile: answers follow simulated time.
"""

from __future__ import annotations

import numpy as np

from jaxinertia.hardware import feetech_table as ft
from jaxinertia.virtual.physics import Present
from jaxinertia.virtual.robot import VirtualServoBus
from jaxinertia.virtual.sts_bus import StsBus, StsMemory
from jaxinertia.xm430 import PWM_FULL_SCALE

__all__ = ["MOVING_HOLD_S", "StsRegisterMap", "VirtualStsBus"]

#: Moving stays 1 this long [s of simulated time] after a tick of Present Position changed.
MOVING_HOLD_S = 0.1
#: The STS duty's full scale (Torque Limit 1000 = 100 %; Present Load in 0.1 %).
STS_FULL_SCALE = 1000.0
_MAGNITUDE_15 = (1 << 15) - 1  # the largest magnitude of a sign-bit-15 register


class StsRegisterMap:
    """The physics' side of the STS3215 memory table (module docstring); keeps, per joint,
    when a tick last changed (Moving's hold)."""

    memory = StsMemory
    reading_lsb = ft.CURRENT_LSB_A  # [A] per LSB of Present Current

    def __init__(self, n_joints: int) -> None:
        self._ticks: np.ndarray | None = None
        self._changed_at = np.full(n_joints, -np.inf)

    @staticmethod
    def registers(servos: list[StsMemory]) -> np.ndarray:
        """(6, N) float64 on the simulator's scales: P, I, D registers, the PWM limit (885 =
        100 %), profile velocity [rad/s] and acceleration [rad/s^2] (0: none)."""
        return np.array([
            [m.get("p_coefficient") for m in servos],
            [m.get("i_coefficient") for m in servos],
            [m.get("d_coefficient") for m in servos],
            [m.get("torque_limit") * PWM_FULL_SCALE / STS_FULL_SCALE for m in servos],
            [abs(m.get("goal_velocity")) * ft.VELOCITY_LSB for m in servos],
            [m.get("acceleration") * ft.ACCELERATION_LSB for m in servos]], np.float64)

    def publish(self, servos: list[StsMemory], p: Present, pending: np.ndarray,
                reading_lsb=ft.CURRENT_LSB_A) -> None:
        """Writes a chunk into the joint servos' tables (under the lock); ``pending``:
        joints with a goal written that the chunk did not simulate yet."""
        lsb = np.broadcast_to(np.asarray(reading_lsb, np.float64), (len(servos),))
        ticks = np.clip(ft.rad_to_ticks(p.q), 0, ft.TICKS_PER_REV - 1)
        if self._ticks is not None:
            self._changed_at[ticks != self._ticks] = p.sim_time
        self._ticks = ticks
        held = p.sim_time - self._changed_at < MOVING_HOLD_S
        for j, m in enumerate(servos):
            speed = int(np.clip(round(p.qd[j] / ft.VELOCITY_LSB), -_MAGNITUDE_15,
                                _MAGNITUDE_15))
            load = int(np.clip(round(p.pwm[j] / PWM_FULL_SCALE * STS_FULL_SCALE),
                               -STS_FULL_SCALE, STS_FULL_SCALE))
            current = int(np.clip(round(p.current[j] / lsb[j]), -_MAGNITUDE_15,
                                  _MAGNITUDE_15))
            moving = bool(pending[j] or p.profile_on[j] or abs(speed) >= 1 or held[j])
            m.set("present_position", int(ticks[j]))
            m.set("present_velocity", speed)
            m.set("present_load", load)
            m.set("present_current", current)
            m.set("moving", int(moving))


class VirtualStsBus(StsBus, VirtualServoBus):
    """STS3215 servos ``ids`` (the joints of ``params.robot``) then ``extra_ids`` (a gripper:
    answering, not moving) on a pty, the joints the simulated arm holding ``obj``: the
    arguments of :class:`~jaxinertia.virtual.robot.VirtualServoBus` (``servo_models``: STS3215
    models, whose supply and current unit each servo reports; ``gain_registers``: the P
    Coefficient each joint's simulated gain belongs to)."""

    register_map = StsRegisterMap
