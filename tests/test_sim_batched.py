"""The batch-last simulator step against ``jax.vmap(simulator.step)`` (float64)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxinertia.sim.batched import (
    params_batch_last,
    state_batch_first,
    state_batch_last,
    step_batched,
)
from jaxinertia.sim.run import default_sim_params
from jaxinertia.sim.servo import ServoState, goal_ticks, present_ticks
from jaxinertia.sim.simulator import SimState, attach_payload, step

B, STEPS = 64, 300


def _random_states(key, n=4):
    k = jax.random.split(key, 8)
    q = jax.random.uniform(k[0], (B, n), minval=-1.5, maxval=1.5)
    qd = jax.random.uniform(k[1], (B, n), minval=-1.0, maxval=1.0)
    servo = ServoState(
        integral=jnp.round(jax.random.uniform(k[2], (B, n), minval=-50, maxval=50)),
        prev_error=jnp.round(jax.random.uniform(k[3], (B, n), minval=-20, maxval=20)),
        torque=jax.random.uniform(k[4], (B, n), minval=-0.5, maxval=0.5),
        current=jax.random.uniform(k[5], (B, n), minval=-0.3, maxval=0.3),
    )
    friction = jax.random.uniform(k[6], (B, n), minval=-0.05, maxval=0.05)
    goal = goal_ticks(q + jax.random.uniform(k[7], (B, n), minval=-0.1, maxval=0.1))
    return SimState(q, qd, servo, friction), goal


def _rollouts(params_ref, in_axes, params_bl, state, goal):
    @jax.jit
    def ref(s):
        def body(s, _):
            s = jax.vmap(step, (in_axes, 0, 0))(params_ref, s, goal)
            return s, s

        return jax.lax.scan(body, s, None, length=STEPS)[1]

    @jax.jit
    def bl(s):
        g = goal.T

        def body(s, _):
            s = step_batched(params_bl, s, g)
            return s, s

        traj = jax.lax.scan(body, state_batch_last(s), None, length=STEPS)[1]
        return jax.tree_util.tree_map(lambda a: jnp.moveaxis(a, -1, 1), traj)  # (T, B, N)

    return ref(state), bl(state)


def _assert_same(traj_ref, traj_bl):
    for a, b in zip(jax.tree_util.tree_leaves(traj_ref), jax.tree_util.tree_leaves(traj_bl)):
        assert a.shape == b.shape
        scale = max(1.0, float(jnp.max(jnp.abs(a))))
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=0, atol=1e-12 * scale)
    np.testing.assert_array_equal(present_ticks(traj_bl.q), present_ticks(traj_ref.q))
    assert float(jnp.max(jnp.abs(traj_ref.qd))) > 1e-2  # the arms did move


@pytest.mark.parametrize("gains", ["default", "pid"])
def test_batched_step_matches_vmapped_step_with_a_shared_robot(gains):
    params = default_sim_params()
    if gains == "pid":  # every term of the servo law, and a constant torque offset
        params = params.replace(
            servo=params.servo.replace(i_gain=jnp.full(4, 30.0), d_gain=jnp.full(4, 200.0)),
            friction=params.friction.replace(ripple_amplitude=jnp.full(4, 0.01),
                                             ripple_frequency=jnp.full(4, 3.0)),
            torque_offset=jnp.array([0.02, -0.05, 0.03, 0.0]))
    state, goal = _random_states(jax.random.PRNGKey(0))
    traj_ref, traj_bl = _rollouts(params, None, params, state, goal)
    _assert_same(traj_ref, traj_bl)


def test_batched_step_matches_vmapped_step_with_per_arm_robots_and_friction():
    params = default_sim_params()
    key_m, key_c, key_f, key_s = jax.random.split(jax.random.PRNGKey(1), 4)
    masses = jax.random.uniform(key_m, (B,), minval=0.0, maxval=0.3)
    coms = jax.random.uniform(key_c, (B, 3), minval=-0.03, maxval=0.03)
    robots = jax.vmap(attach_payload, (None, 0, 0))(params.robot, masses, coms)
    scale = jax.random.uniform(key_f, (B, 1), minval=0.5, maxval=1.5)
    friction = jax.tree_util.tree_map(lambda a: scale * a[None], params.friction)
    per_arm = params.replace(robot=robots, friction=friction)  # servo shared
    in_axes = params.replace(robot=0, servo=None, friction=0, torque_offset=None)
    params_bl = per_arm.replace(robot=params_batch_last(robots),
                                friction=params_batch_last(friction))
    state, goal = _random_states(key_s)
    traj_ref, traj_bl = _rollouts(per_arm, in_axes, params_bl, state, goal)
    _assert_same(traj_ref, traj_bl)


def test_layout_helpers_round_trip_and_reject_batch_first_states():
    state, goal = _random_states(jax.random.PRNGKey(2))
    bl = state_batch_last(state)
    assert bl.q.shape == (4, B) and bl.servo.integral.shape == (4, B)
    back = state_batch_first(bl)
    for a, b in zip(jax.tree_util.tree_leaves(state), jax.tree_util.tree_leaves(back)):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="batch last"):
        step_batched(default_sim_params(), state, goal)
