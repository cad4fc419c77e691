"""The simulated arm: rigid-body dynamics + DYNAMIXEL servos + sticking friction.

One step is one servo control period (1 ms by default)::

    goal (profile) -> servo_step -> motor torque tau_m (held for the period)
    M~ v_free = M~ qd + dt (tau_m - c(q, qd) - D qd)       M~ = M + dt D (implicit damping)
    friction: |f| <= F(q, qd, tau_m), sticks exactly (sim.friction)
    q' = q + dt v'

A sample follows the paper's protocol: every joint first goes to a pre-position
``q_d - s * delta`` so that it approaches its goal from direction ``s``, then to ``q_d``;
the sample is taken once every |qd| stayed below ``rest_velocity`` for ``hold_time``.
A sample that does not come to rest within ``timeout`` is flagged, never silently kept.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from jaxinertia.dynamics import bias_forces, mass_matrix
from jaxinertia.linalg import cholesky_solve
from jaxinertia.objects import HeldObject
from jaxinertia.robot import Robot
from jaxinertia.sim.friction import FrictionParams, friction_bound, solve_box_friction
from jaxinertia.sim.servo import (
    RAD_PER_TICK,
    ServoParams,
    ServoState,
    goal_ticks,
    present_ticks,
    servo_step,
)

__all__ = ["SimParams", "SimState", "attach_payload", "hold", "move_and_settle",
           "physical_params", "step", "trapezoid"]


@struct.dataclass
class SimParams:
    robot: Robot
    servo: ServoParams
    friction: FrictionParams
    dt: float = struct.field(pytree_node=False, default=1e-3)  # servo control period [s]
    rest_velocity: float = struct.field(pytree_node=False, default=1e-3)  # [rad/s]
    hold_time: float = struct.field(pytree_node=False, default=0.2)  # [s]
    timeout: float = struct.field(pytree_node=False, default=6.0)  # per move [s]
    profile_velocity: float = struct.field(pytree_node=False, default=0.5)  # [rad/s]
    profile_acceleration: float = struct.field(pytree_node=False, default=2.0)  # [rad/s^2]
    #: The protocol's pre-position offset: each sample starts at rest at q_d - s * this [rad].
    pre_position: float = struct.field(pytree_node=False, default=3.0 * jnp.pi / 180.0)
    #: Projected Gauss-Seidel sweeps of the friction solve per step. Warm-started from
    #: the previous step's friction, 10 reproduce 30 cold sweeps (same encoder ticks on
    #: 256 random samples, states within 1e-9 rad).
    friction_sweeps: int = struct.field(pytree_node=False, default=10)
    #: (N,) constant joint torque besides the servo (cables, springs) [N m]; None = 0.
    torque_offset: jnp.ndarray | None = None
    #: What each joint's servo reports of its motor current (``sampling.record``): (N,) the
    #: reading's unit [A] and the torque constant of its current-based torque [N m/A], NaN
    #: where the servo senses no current (XL430-W250: the sample's current_tau is then NaN,
    #: as the driver's). None: the XM430's 2.69 mA and datasheet constant on every joint.
    current_lsb: jnp.ndarray | None = None
    current_torque_constant: jnp.ndarray | None = None


@struct.dataclass
class SimState:
    q: jnp.ndarray
    qd: jnp.ndarray
    servo: ServoState
    friction: jnp.ndarray  # last friction torque [N m]

    @classmethod
    def at_rest(cls, q: jnp.ndarray) -> SimState:
        q = jnp.asarray(q)
        return cls(q, jnp.zeros_like(q), ServoState.zeros(q.shape[0], q.dtype), jnp.zeros_like(q))


def attach_payload(robot: Robot, mass, com_ee, inertia_ee=None) -> Robot:
    """The robot with a rigid payload fused into its end-effector body.

    Args:
      mass: [kg]; com_ee: (3,) payload COM in the end-effector frame [m];
      inertia_ee: (3, 3) about the payload COM, end-effector axes (default: point mass).
    """
    b = robot.ee_body
    mass = jnp.asarray(mass, robot.mass.dtype)
    c_p = robot.ee_rot @ jnp.asarray(com_ee) + robot.ee_pos  # in body b's frame
    I_p = jnp.zeros((3, 3)) if inertia_ee is None else robot.ee_rot @ inertia_ee @ robot.ee_rot.T
    m_b, c_b = robot.mass[b], robot.com[b]
    m = m_b + mass
    c = (m_b * c_b + mass * c_p) / m

    def shifted(I, mk, ck):  # parallel axis to the new COM
        d = ck - c
        return I + mk * (jnp.dot(d, d) * jnp.eye(3) - jnp.outer(d, d))

    I = shifted(robot.inertia[b], m_b, c_b) + shifted(I_p, mass, c_p)
    return robot.replace(mass=robot.mass.at[b].set(m), com=robot.com.at[b].set(c),
                         inertia=robot.inertia.at[b].set(I))


def physical_params(params: SimParams, obj: HeldObject | None = None) -> SimParams:
    """The arm as it physically moves, from the parameters of the bare arm in the recorded
    convention (``params.robot``): gravity as felt and the held object (None: none) fused
    into the end effector. The recorded torques follow the opposite of the physical gravity
    (see :func:`jaxinertia.sim.sampling.simulate_samples`), so the arm feels
    ``-robot.gravity``."""
    physical = params.robot.with_gravity(-params.robot.gravity)
    if obj is not None:
        R = obj.R_ee_tag
        physical = attach_payload(physical, obj.mass, obj.com_ee(), R @ obj.inertia @ R.T)
    return params.replace(robot=physical)


def step(params: SimParams, state: SimState, goal: jnp.ndarray) -> SimState:
    """One servo control period with Goal Position ``goal`` [ticks]."""
    robot, dt = params.robot, params.dt
    servo = servo_step(params.servo, state.servo, goal, state.q, state.qd)
    damping = robot.damping + params.friction.viscous
    M = mass_matrix(robot, state.q) + dt * jnp.diag(damping)
    offset = 0.0 if params.torque_offset is None else params.torque_offset
    rhs = servo.torque + offset - damping * state.qd - bias_forces(robot, state.q, state.qd)
    n = state.q.shape[0]
    # W = dt M~^-1 (columns by unrolled Cholesky solves) serves both the free velocity
    # and the friction solve.
    W = dt * cholesky_solve(jnp.broadcast_to(M, (n, n, n)), jnp.eye(n, dtype=M.dtype))
    v_free = state.qd + (W * rhs).sum(-1)
    bound = friction_bound(params.friction, state.q, state.qd, servo.torque)
    f, v = solve_box_friction(W, v_free, bound, params.friction_sweeps, f0=state.friction)
    return SimState(state.q + dt * v, v, servo, f)


def trapezoid(start, end, t, v_max, a_max):
    """Per-joint trapezoidal (or triangular) velocity profile position at time t."""
    d = end - start
    dist = jnp.abs(d)
    t_acc = jnp.minimum(v_max / a_max, jnp.sqrt(dist / a_max))
    v_peak = a_max * t_acc
    d_acc = 0.5 * a_max * t_acc**2
    t_flat = jnp.where(v_peak > 0, (dist - 2 * d_acc) / jnp.where(v_peak > 0, v_peak, 1.0), 0.0)
    t_total = 2 * t_acc + t_flat
    s = jnp.where(
        t < t_acc, 0.5 * a_max * t**2,
        jnp.where(t < t_acc + t_flat, d_acc + v_peak * (t - t_acc),
                  jnp.where(t < t_total, dist - 0.5 * a_max * (t_total - t) ** 2, dist)))
    return start + jnp.sign(d) * s, t_total


def move_and_settle(params: SimParams, state: SimState, start: jnp.ndarray, end: jnp.ndarray):
    """Commands a profiled move of the goal from ``start`` to ``end`` [rad], then holds ``end``
    until the arm is at rest. Returns ``(state, at_rest, time)``; ``at_rest`` is False when
    the timeout came first."""
    dt = params.dt
    hold_steps = int(round(params.hold_time / dt))
    max_steps = int(round(params.timeout / dt))
    _, t_total = trapezoid(start, end, 0.0, params.profile_velocity, params.profile_acceleration)
    t_move = jnp.max(t_total)

    def cond(c):
        _, k, still = c
        return (still < hold_steps) & (k < max_steps)

    def body(c):
        s, k, still = c
        t = k * dt
        q_goal, _ = trapezoid(start, end, t, params.profile_velocity,
                              params.profile_acceleration)
        s = step(params, s, goal_ticks(q_goal))
        resting = (t >= t_move) & jnp.all(jnp.abs(s.qd) < params.rest_velocity)
        return s, k + 1, jnp.where(resting, still + 1, 0)

    state, k, still = jax.lax.while_loop(cond, body, (state, 0, 0))
    return state, still >= hold_steps, k * dt


def rest_ticks_error(state: SimState, q_d: jnp.ndarray) -> jnp.ndarray:
    """Encoder discrepancy q_d - q in ticks (diagnostics)."""
    return (q_d - state.q) / RAD_PER_TICK


def hold(params: SimParams, state: SimState, goal_rad: jnp.ndarray, seconds: float):
    """Holds a constant goal for ``seconds``; returns the final state and the Present
    Position ticks at every step (for checking that nothing creeps)."""
    g = goal_ticks(goal_rad)

    def body(s, _):
        s = step(params, s, g)
        return s, present_ticks(s.q)

    return jax.lax.scan(body, state, None, length=int(round(seconds / params.dt)))
