"""Rigid-body dynamics against MuJoCo C: qM, qfrc_bias, inverse dynamics, a PD trajectory."""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from jax.test_util import check_grads

from jaxinertia.dynamics import (
    bias_forces,
    euler_step,
    forward_dynamics,
    inverse_dynamics,
    mass_matrix,
)
from jaxinertia.robot import compile_mujoco, data_path, load_robot

ASSETS = Path(__file__).parent / "assets"

#: Agreement with MuJoCo C (float64) per evaluation: rounding only. A trajectory
#: accumulates it over its steps (1000x over 2,000 steps, below).
TOL = 1e-9

ARMS = {
    "open_manipulator_x": (data_path("open_manipulator_x.xml"), "end_effector"),
    "arm6": (ASSETS / "arm6.xml", "tool"),
}


@pytest.fixture(params=list(ARMS), scope="module")
def arm(request):
    path, site = ARMS[request.param]
    model = compile_mujoco(path)
    rng = np.random.default_rng(0)
    # Non-zero armature and damping, the same on both sides.
    model.dof_armature[:] = rng.uniform(1e-4, 1e-3, model.nv)
    model.dof_damping[:] = rng.uniform(0.01, 0.1, model.nv)
    robot = load_robot(path, ee_site=site).replace(
        armature=jnp.asarray(model.dof_armature.copy()),
        damping=jnp.asarray(model.dof_damping.copy()),
    )
    return model, robot


#: The mass matrix, bias forces and inverse dynamics of a batch of states, one compiled
#: program per arm (three took ~1 s longer to compile on the 2-core CI machine).
_dynamics_batch = jax.jit(jax.vmap(
    lambda robot, q, qd, qdd: (mass_matrix(robot, q), bias_forces(robot, q, qd),
                               inverse_dynamics(robot, q, qd, qdd)), (None, 0, 0, 0)))


def _states(robot, n, seed=1):
    rng = np.random.default_rng(seed)
    q = rng.uniform(robot.q_min, robot.q_max, (n, robot.n_joints))
    qd = rng.normal(scale=2.0, size=(n, robot.n_joints))
    qdd = rng.normal(scale=5.0, size=(n, robot.n_joints))
    return q, qd, qdd


def _assert_eq(got, want, name: str, *, atol: float = TOL, rtol: float = 0.0):
    """``got`` agrees with the reference ``want``; the failure names the field."""
    np.testing.assert_allclose(np.asarray(got), np.asarray(want), atol=atol, rtol=rtol,
                               err_msg=f"mismatch: {name}")


def test_mass_matrix_bias_and_inverse_dynamics_equal_mujoco(arm):
    model, robot = arm
    data = mujoco.MjData(model)
    q, qd, qdd = _states(robot, 100)
    M, c, tau = _dynamics_batch(robot, q, qd, qdd)
    for i in range(len(q)):
        data.qpos[:], data.qvel[:] = q[i], qd[i]
        mujoco.mj_forward(model, data)
        M_ref = np.zeros((model.nv, model.nv))
        mujoco.mj_fullM(model, data, M_ref)
        _assert_eq(M[i], M_ref, f"qM (state {i})")
        _assert_eq(c[i], data.qfrc_bias, f"qfrc_bias (state {i})")
        data.qacc[:] = qdd[i]
        mujoco.mj_inverse(model, data)
        # qfrc_inverse = M qdd + c - passive (damping); ours excludes damping.
        _assert_eq(tau[i], data.qfrc_inverse + data.qfrc_passive,
                   f"qfrc_inverse + qfrc_passive (state {i})")


def test_forward_dynamics_equals_mujoco_qacc(arm):
    model, robot = arm
    data = mujoco.MjData(model)
    q, qd, _ = _states(robot, 20, seed=2)
    ctrl = np.random.default_rng(3).normal(size=(20, robot.n_joints))
    for i in range(len(q)):
        data.qpos[:], data.qvel[:], data.qfrc_applied[:] = q[i], qd[i], ctrl[i]
        mujoco.mj_forward(model, data)
        # qacc = M^-1 (...): the solve scales the rounding by M's conditioning.
        _assert_eq(forward_dynamics(robot, q[i], qd[i], ctrl[i]), data.qacc,
                   f"qacc (state {i})", atol=10 * TOL, rtol=TOL / 10)


def test_frictionless_pd_trajectory_matches_mujoco_euler(arm):
    """2 s of a joint-space PD law, MuJoCo's Euler integrator (implicit damping), 1 ms."""
    model, robot = arm
    model.opt.integrator = mujoco.mjtIntegrator.mjINT_EULER
    model.opt.timestep = dt = 1e-3
    # The chain itself only: no joint-limit or contact constraints.
    off = mujoco.mjtDisableBit
    model.opt.disableflags |= off.mjDSBL_LIMIT | off.mjDSBL_CONTACT
    data = mujoco.MjData(model)
    rng = np.random.default_rng(4)
    q0 = rng.uniform(robot.q_min, robot.q_max)
    goal = rng.uniform(robot.q_min, robot.q_max)
    kp, kd = 4.0, 0.05

    def pd(q, qd):
        return kp * (goal - q) - kd * qd

    data.qpos[:] = q0
    ref = []
    for _ in range(2000):
        data.qfrc_applied[:] = pd(data.qpos, data.qvel)
        mujoco.mj_step(model, data)
        ref.append(data.qpos.copy())

    def step(state, _):
        q, qd = state
        q, qd = euler_step(robot, q, qd, pd(q, qd), dt)
        return (q, qd), q

    _, traj = jax.jit(lambda s: jax.lax.scan(step, s, None, length=2000))(
        (jnp.asarray(q0), jnp.zeros(robot.n_joints)))
    ref = np.asarray(ref)
    assert np.max(np.abs(ref[-1] - q0)) > 0.05  # it moved
    _assert_eq(traj, ref, "qpos trajectory", atol=1e3 * TOL)


def test_dynamics_are_jit_vmap_and_grad_safe(arm):
    _, robot = arm
    q, qd, qdd = _states(robot, 3, seed=5)
    eager = [inverse_dynamics(robot, q[i], qd[i], qdd[i]) for i in range(3)]
    batched = jax.jit(jax.vmap(inverse_dynamics, (None, 0, 0, 0)))(robot, q, qd, qdd)
    # The same program jitted and vmapped as run eagerly: to the last bits.
    _assert_eq(batched, np.stack(eager), "inverse dynamics, jit(vmap) vs eager",
               atol=TOL / 1e5, rtol=TOL / 1e3)
    # d(tau)/d(qdd) is the mass matrix.
    J = jax.jacfwd(inverse_dynamics, argnums=3)(robot, q[0], qd[0], qdd[0])
    _assert_eq(J, mass_matrix(robot, q[0]), "d tau / d qdd", atol=TOL / 1e3)

    check_grads(lambda x: bias_forces(robot, x, jnp.asarray(qd[0])), (jnp.asarray(q[0]),),
                order=2, atol=1e-5, rtol=1e-5)
