"""DYNAMIXEL XM430-W350-T in position-control mode, as the e-manual defines it.

The servo boundary: registers (ticks, gain registers, PWM and current LSBs) live here and
nowhere else; everything returned to the simulator is SI.

Position loop (e-manual, "Position PID controller"), run every ``control_period``::

    e      = goal_ticks - present_ticks                           [ticks]
    PWM    = clip(KP e + KI sum(e) + KD (e - e_prev), +-PWM Limit) KP = P/128, KI = I/65536,
                                                                   KD = D/16, 885 = 100 %
    V      = PWM / 885 * V_supply                                  [V]
    I      = (V - k_e * qd) / R                                    [A]  (output-side k_e)
    tau    = k_t * I                                               [N m] (output-side k_t,
                                                                          gear and efficiency)

With the default P = 800 at 12 V and the datasheet's stall point (4.1 N m at 2.3 A,
so k_t ~ 1.78 N m/A and R ~ 12 V / 2.3 A ~ 5.2 ohm) this gives ~29 N mm per tick of error,
the stiffness measured on the real arm (25-28 N mm/tick on joints 1-3).
"""

from __future__ import annotations

from collections.abc import Sequence

import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxinertia.servos import XM430_W350, ServoModel
from jaxinertia.xm430 import (
    CURRENT_LSB_A,
    NOMINAL_TORQUE_CONSTANT,
    PWM_FULL_SCALE,
    RAD_PER_TICK,
)

__all__ = [
    "RAD_PER_TICK",
    "CURRENT_LSB_A",
    "NOMINAL_TORQUE_CONSTANT",
    "ServoParams",
    "ServoState",
    "current_reading_share",
    "present_ticks",
    "servo_step",
    "goal_ticks",
]


@struct.dataclass
class ServoParams:
    """Per-joint (N,) servo parameters: registers as the servo holds them, physics in SI."""

    p_gain: jnp.ndarray  # Position P Gain register (default 800)
    i_gain: jnp.ndarray  # Position I Gain register (the method needs 0)
    d_gain: jnp.ndarray  # Position D Gain register
    pwm_limit: jnp.ndarray  # PWM Limit register (885 = 100 %)
    supply_voltage: jnp.ndarray  # [V]
    torque_constant: jnp.ndarray  # output-side, gear ratio and efficiency included [N m/A]
    resistance: jnp.ndarray  # winding [ohm]
    back_emf: jnp.ndarray  # output-side [V s/rad]
    current_limit: jnp.ndarray  # [A]
    current_noise: jnp.ndarray  # std of the Present Current reading [A]
    #: The drive's dead band [ticks of error]: within it Present Current reads 0, beyond it
    #: the reading grows from 0 (:func:`current_reading_share`; 0: none, the datasheet's).
    current_dead_band: jnp.ndarray

    @classmethod
    def xm430_w350(cls, n_joints: int, **overrides) -> ServoParams:
        """Datasheet values for ``n_joints`` servos (``overrides``: per-joint or shared
        values): 12 V, stall 4.1 N m / 2.3 A, no load 46 rpm, gear 353.5."""
        return cls.from_model(XM430_W350, n_joints, **overrides)

    @classmethod
    def from_model(cls, model: ServoModel | Sequence[ServoModel], n_joints: int,
                   **overrides) -> ServoParams:
        """Parameters of ``n_joints`` servos of ``model`` (one, or one per joint: a chain may
        mix models) from their datasheet values, in the register scales that
        :func:`servo_step` uses (the XM430's: KP = P/128, 885 = 100 % PWM); another loop's
        gains are re-expressed so that it applies the same duty per tick of error."""
        models = [model] * n_joints if isinstance(model, ServoModel) else list(model)
        if len(models) != n_joints:
            raise ValueError(f"{len(models)} servo models for {n_joints} joints")

        def values(m: ServoModel) -> dict:
            to_pwm = PWM_FULL_SCALE / m.pwm_full_scale
            (kp, ki, kd), (p, i, d) = m.gain_scale, m.gains
            v = m.supply_voltage
            noise_lsb = m.sensed_lsb if m.has_current_sensor else m.sensed_lsb * m.stall_current
            return dict(
                p_gain=p * (kp * 128.0) * to_pwm, i_gain=i * (ki * 65536.0) * to_pwm,
                d_gain=d * (kd * 16.0) * to_pwm, pwm_limit=m.pwm_limit * to_pwm,
                supply_voltage=v, torque_constant=m.stall_torque / m.stall_current,
                resistance=v / m.stall_current, back_emf=v / m.no_load_speed,
                current_limit=m.current_limit, current_noise=2 * noise_lsb,
                current_dead_band=0.0)

        per_joint = [values(m) for m in models]
        base = {k: np.array([pj[k] for pj in per_joint]) for k in per_joint[0]}
        base.update(overrides)
        return cls(**{k: jnp.asarray(np.broadcast_to(val, (n_joints,)), jnp.result_type(float))
                      for k, val in base.items()})


@struct.dataclass
class ServoState:
    """The servo's own memory between control periods."""

    integral: jnp.ndarray  # sum of errors [ticks]
    prev_error: jnp.ndarray  # [ticks]
    torque: jnp.ndarray  # output torque held until the next control period [N m]
    current: jnp.ndarray  # [A]

    @classmethod
    def zeros(cls, n_joints: int, dtype=jnp.float64) -> ServoState:
        z = jnp.zeros(n_joints, dtype)
        return cls(z, z, z, z)


def goal_ticks(q_d: jnp.ndarray) -> jnp.ndarray:
    """Goal Position register from a commanded angle [rad] (rounded to ticks)."""
    return jnp.round(q_d / RAD_PER_TICK)


def present_ticks(q: jnp.ndarray) -> jnp.ndarray:
    """Present Position register (integer ticks) of the true joint angle [rad]."""
    return jnp.round(q / RAD_PER_TICK)


def servo_step(
    params: ServoParams, state: ServoState, goal: jnp.ndarray, q: jnp.ndarray, qd: jnp.ndarray
) -> ServoState:
    """One control period: new PWM from the tick error, then motor current and torque.

    Args:
      goal: Goal Position [ticks]; q, qd: true joint angle [rad] and velocity [rad/s].
    """
    e = goal - present_ticks(q)
    integral = state.integral + e
    pwm = (params.p_gain / 128.0) * e + (params.i_gain / 65536.0) * integral + (
        params.d_gain / 16.0) * (e - state.prev_error)
    pwm = jnp.clip(pwm, -params.pwm_limit, params.pwm_limit)
    voltage = pwm / PWM_FULL_SCALE * params.supply_voltage
    current = (voltage - params.back_emf * qd) / params.resistance
    current = jnp.clip(current, -params.current_limit, params.current_limit)
    return ServoState(integral, e, params.torque_constant * current, current)


def current_reading_share(error_ticks, dead_band):
    """The share of the motor current that Present Current shows at a position error
    [ticks]: ``max(|e| - d, 0) / |e|``, so that the reading grows by the same gain per
    tick beyond the drive's dead band ``d`` [ticks] and is 0 within it (the real XM430s of
    the OpenMANIPULATOR-X read no current within 1-3 ticks: ``experiments/servo_dead_band.py``,
    docs/results.md "The dead band"). Exactly 1 where ``d`` is 0. The reading alone: the
    torque the servo holds is the simulator's, whose calibration matches the real torques
    (a dead band in the torque too was tried and made the arm sag where friction holds the
    real one)."""
    e = jnp.abs(error_ticks)
    return jnp.where(dead_band > 0, jnp.clip(1.0 - dead_band / jnp.maximum(e, 1e-6), 0.0, 1.0),
                     1.0)
