"""Samples as the paper takes them, from the simulated arm, vmapped over many samples.

Each sample: the arm rests at the pre-position ``q_d - s * delta`` (so that every joint
approaches its goal from its direction ``s``), moves to ``q_d`` with the servo's profile,
and is recorded once at rest. The record has the lbipe fields, computed as on the real arm
from what the servo reports (``q`` in integer ticks, the current in 2.69 mA steps with
noise), plus the tag pose and the simulator's true state for diagnostics.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxinertia.kinematics import gravity_torques
from jaxinertia.objects import HeldObject
from jaxinertia.robot import Robot
from jaxinertia.sim.servo import (
    CURRENT_LSB_A,
    NOMINAL_TORQUE_CONSTANT,
    RAD_PER_TICK,
    current_reading_share,
    present_ticks,
)
from jaxinertia.sim.simulator import SimParams, SimState, move_and_settle, physical_params
from jaxinertia.statics import load_regressor, tag_pose

__all__ = ["Record", "jitter_friction", "record", "simulate_samples"]


class Record(NamedTuple):
    """What the simulator records per sample: the lbipe fields, the tag pose and the
    simulator's true state (the raw output; :class:`jaxinertia.samples.Samples` is the
    library's sample container). Leading axis S. Angles [rad], torques [N m]."""

    q_d: jnp.ndarray  # (S, N) commanded goal (continuous, as recorded on the real arm)
    q: jnp.ndarray  # (S, N) Present Position (integer ticks, in rad)
    current_tau: jnp.ndarray  # (S, N) torque from Present Current (datasheet k_t * I; NaN:
    #                            no current sensor, SimParams.current_torque_constant)
    direction: jnp.ndarray  # (S, N) +1 / -1
    tau: jnp.ndarray  # (S, N) load torque of arm + object at q (statics)
    tau_g: jnp.ndarray  # (S, N) load torque of the bare arm at q
    A: jnp.ndarray  # (S, N, 4) load regressor at q and the tag pose
    R_base_tag: jnp.ndarray  # (S, 3, 3)
    p_base_tag: jnp.ndarray  # (S, 3)
    at_rest: jnp.ndarray  # (S,) False: timed out (never silently used)
    settle_time: jnp.ndarray  # (S,) [s]
    q_true: jnp.ndarray  # (S, N) simulator state at the sample
    servo_tau: jnp.ndarray  # (S, N) true motor output torque
    friction_tau: jnp.ndarray  # (S, N) true friction torque


def jitter_friction(params: SimParams, key: jax.Array, n_joints: int) -> SimParams:
    """Friction varies from sample to sample (temperature, lubricant, gear mesh)."""
    scale = jnp.exp(params.friction.jitter * jax.random.normal(key, (n_joints,)))
    fr = params.friction
    return params.replace(friction=fr.replace(coulomb=fr.coulomb * scale,
                                              static=fr.static * scale))


def record(params: SimParams, bare: Robot, obj: HeldObject, q_d, direction, state: SimState,
           key: jax.Array, *, at_rest, settle_time) -> Record:
    """What the servos and the statics report for the arm in ``state`` (one sample)."""
    q = present_ticks(state.q) * RAD_PER_TICK
    noise = jax.random.normal(key, q.shape) * params.servo.current_noise
    # Each servo's reading unit and torque constant (NaN: no current sensor, no
    # current-based torque); the XM430's unless the parameters say otherwise.
    lsb, k_t = ((CURRENT_LSB_A, NOMINAL_TORQUE_CONSTANT) if params.current_lsb is None
                else (params.current_lsb, params.current_torque_constant))
    # Within the drive's dead band the reading is 0, noise and all (ServoParams).
    share = current_reading_share(state.servo.prev_error, params.servo.current_dead_band)
    current = jnp.where(share > 0, jnp.round((state.servo.current * share + noise) / lsb) * lsb,
                        0.0)
    R_bt, p_bt = tag_pose(bare, q, obj.R_ee_tag, obj.p_ee_tag)
    A = load_regressor(bare, q, R_bt, p_bt)
    tau_g = gravity_torques(bare, q)
    return Record(
        q_d=q_d, q=q, current_tau=k_t * current,
        direction=direction, tau=tau_g + A @ obj.x, tau_g=tau_g, A=A, R_base_tag=R_bt,
        p_base_tag=p_bt, at_rest=at_rest, settle_time=settle_time, q_true=state.q,
        servo_tau=state.servo.torque, friction_tau=state.friction,
    )


def _one_sample(params: SimParams, bare: Robot, obj: HeldObject, q_d, direction, delta, key):
    key_f, key = jax.random.split(key)
    params = jitter_friction(params, key_f, q_d.shape[0])
    pre = q_d - direction * delta
    state = SimState.at_rest(pre)
    state, ok1, _ = move_and_settle(params, state, pre, pre)
    state, ok2, t = move_and_settle(params, state, pre, q_d)
    return record(params, bare, obj, q_d, direction, state, key, at_rest=ok1 & ok2,
                  settle_time=t)


# Compiled as one program (the parameters, object and plan are arguments): run eagerly, each
# call compiled its settling loops again.
@jax.jit
def simulate_samples(
    params: SimParams,
    obj: HeldObject,
    q_d: jnp.ndarray,
    direction: jnp.ndarray,
    key: jax.Array,
    *,
    delta: float | None = None,
) -> Record:
    """Simulates S samples (vmapped): goals ``q_d`` and directions (S, N); ``delta``: the
    pre-position offset [rad] (default: ``params.pre_position``, the arm's).

    ``params.robot`` is the bare arm in the lbipe convention; the object is attached here.

    Sign convention. In the real data the recorded torque (``tau``, the torque gravity
    exerts on the joints with gravity [-9.81, 0, 0] in the base frame) rises with the
    discrepancy ``q_d - q`` and with the servo's current (correlations 0.8-0.9 on joints
    1, 3, 4: ``tau ~ k (q_d - q) - s f``). A servo at rest pushes *against* the load, so
    the physical gravity on the real arm is the opposite of that convention's vector.
    The simulated arm therefore feels ``-robot.gravity``; every recorded field (tau,
    tau_g, A) uses the convention, so ``tau - tau_g = A x`` holds as in the real data and
    the servo's holding torque equals ``+tau`` at rest.
    """
    delta = params.pre_position if delta is None else delta
    bare = params.robot
    loaded = physical_params(params, obj)
    # One key per sample (or a single key, split here): samples do not depend on batching.
    keys = key if key.ndim == 1 else jax.random.split(key, q_d.shape[0])
    return jax.vmap(_one_sample, (None, None, None, 0, 0, None, 0))(
        loaded, bare, obj, q_d, direction, delta, keys)
