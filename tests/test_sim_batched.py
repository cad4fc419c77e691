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
from jaxinertia.sim.params import default_sim_params
from jaxinertia.sim.servo import ServoState, goal_ticks, present_ticks
from jaxinertia.sim.simulator import SimState, attach_payload, step

B, STEPS = 64, 300

#: Agreement with the reference ``jax.vmap(simulator.step)`` in float64 (relative to each
#: field's magnitude, at least 1): rounding only, accumulated over ``STEPS`` steps.
TOL = 1e-12


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


#: Traces of the rollouts below (the counts rise only while JAX traces them).
_TRACES = {"vmap": 0, "batch-last": 0}


def _copies(tree):
    """``tree`` with every leaf repeated for the B arms (leading axis)."""
    return jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (B,) + jnp.shape(a)), tree)


@jax.jit
def _reference_rollout(params, state, goal):
    """``STEPS`` steps of ``jax.vmap(step)``, every arm with its own robot and friction
    (``params.robot`` and ``params.friction`` have a leading axis B; the servo and the
    torque offset are shared), (T, B, N). One compiled program, the parameters as arguments,
    for every test here (~10 s to compile on the 2-core CI machine): a robot shared by all
    arms is given to it as B copies (:func:`_copies`), the same arithmetic per arm."""
    _TRACES["vmap"] += 1
    in_axes = params.replace(robot=0, servo=None, friction=0, torque_offset=None)

    def body(s, _):
        s = jax.vmap(step, (in_axes, 0, 0))(params, s, goal)
        return s, s

    return jax.lax.scan(body, state, None, length=STEPS)[1]


@jax.jit
def _batch_last_rollout(params_bl, state, goal):
    """The same steps batch-last, returned batch-first (T, B, N)."""
    _TRACES["batch-last"] += 1
    g = goal.T

    def body(s, _):
        s = step_batched(params_bl, s, g)
        return s, s

    traj = jax.lax.scan(body, state_batch_last(state), None, length=STEPS)[1]
    return jax.tree_util.tree_map(lambda a: jnp.moveaxis(a, -1, 1), traj)


def _rollouts(params_ref, params_bl, state, goal):
    return (_reference_rollout(params_ref, state, goal),
            _batch_last_rollout(params_bl, state, goal))


def _shared(params):
    """The reference's parameters for a robot and friction shared by all arms."""
    return params.replace(robot=_copies(params.robot), friction=_copies(params.friction))


def _assert_same(traj_ref, traj_bl):
    """Every field of the trajectories agrees to ``TOL``; the failure names the field
    (``.servo.integral``, ...)."""
    ref = dict(jax.tree_util.tree_flatten_with_path(traj_ref)[0])
    for path, b in jax.tree_util.tree_flatten_with_path(traj_bl)[0]:
        name, a = jax.tree_util.keystr(path), ref[path]
        assert a.shape == b.shape, f"mismatch: {name} shape {b.shape} != {a.shape}"
        scale = max(1.0, float(jnp.max(jnp.abs(a))))
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=0, atol=TOL * scale,
                                   err_msg=f"mismatch: {name}")
    np.testing.assert_array_equal(present_ticks(traj_bl.q), present_ticks(traj_ref.q),
                                  err_msg="mismatch: present ticks")
    assert float(jnp.max(jnp.abs(traj_ref.qd))) > 1e-2  # the arms did move


@pytest.mark.parametrize("gains", ["default", "pid"])
def test_batched_step_matches_vmapped_step_with_a_shared_robot(gains):
    params = default_sim_params()
    if gains == "pid":  # every term of the servo law, and a constant torque offset
        def full(v):  # float64, not weak-typed: the default's types (one compiled program)
            return jnp.full(4, v, jnp.float64)

        params = params.replace(
            servo=params.servo.replace(i_gain=full(30.0), d_gain=full(200.0)),
            friction=params.friction.replace(ripple_amplitude=full(0.01),
                                             ripple_frequency=full(3.0)),
            torque_offset=jnp.array([0.02, -0.05, 0.03, 0.0]))
    state, goal = _random_states(jax.random.PRNGKey(0))
    traj_ref, traj_bl = _rollouts(_shared(params), params, state, goal)
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
    params_bl = per_arm.replace(robot=params_batch_last(robots),
                                friction=params_batch_last(friction))
    state, goal = _random_states(key_s)
    traj_ref, traj_bl = _rollouts(per_arm, params_bl, state, goal)
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


def test_the_steps_trace_and_compile_once_for_new_data_of_the_same_shapes():
    """New states, goals and parameter values of the same shapes reuse the compiled steps
    (one arm vmapped, and batch-last; inside the rollouts above, whose programs the other
    tests of this module may have compiled already): the parameters' static fields (dt,
    tolerances) and the leaves' dtypes do not change between calls, so after the first call
    nothing is traced again."""
    params = default_sim_params()
    programs = (_reference_rollout, _batch_last_rollout)
    for i in range(3):
        p = params.replace(friction=params.friction.replace(
            coulomb=params.friction.coulomb * (1.0 + 0.1 * i)))
        state, goal = _random_states(jax.random.PRNGKey(10 + i))
        jax.block_until_ready(_rollouts(_shared(p), p, state, goal))
        if i == 0:
            traced, sizes = dict(_TRACES), [f._cache_size() for f in programs]
    assert traced["vmap"] >= 1 and traced["batch-last"] >= 1, traced  # the counter counts
    assert _TRACES == traced, (traced, _TRACES)
    assert [f._cache_size() for f in programs] == sizes


def test_the_cpu_barrier_holds_under_vmap():
    """On the CPU the batch-last step keeps its values materialised through conditionals
    (``batched._barrier``). Under ``vmap`` (several streams as one program,
    ``sim.stream.stream_jobs``) they must stay conditionals, not become selects of both
    branches (which XLA then fuses through: the step ran 9x slower); and the vmapped step
    is the step of each stream."""
    params = default_sim_params()
    state, goal = _random_states(jax.random.key(5))
    state, goal = state_batch_last(state), goal.T

    def conditionals(fn, *args):
        return jax.jit(fn).lower(*args).compile().as_text().count("conditional(")

    plain = conditionals(lambda s, g: step_batched(params, s, g), state, goal)
    two = jax.tree_util.tree_map(lambda a: jnp.stack([a, a + 0.01]), state)
    vmapped = jax.vmap(lambda s, g: step_batched(params, s, g))
    assert plain > 0 and conditionals(vmapped, two, jnp.stack([goal, goal])) == plain
    got = jax.jit(vmapped)(two, jnp.stack([goal, goal]))
    for i in range(2):
        alone = step_batched(params, jax.tree_util.tree_map(lambda a, i=i: a[i], two), goal)
        for a, b in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(alone)):
            np.testing.assert_allclose(np.asarray(a)[i], np.asarray(b), rtol=1e-12, atol=1e-15)
