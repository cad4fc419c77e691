"""Rigid-body dynamics of a serial chain in pure JAX (jit, vmap and grad safe).

    M(q) qdd + c(q, qd) = tau + tau_ext,   c = Coriolis/centrifugal + gravity

``bias_forces`` follows MuJoCo's ``qfrc_bias`` (it contains *minus* the gravity torques of
:func:`jaxinertia.kinematics.gravity_torques`), ``mass_matrix`` MuJoCo's ``qM`` (armature
on the diagonal). Viscous joint damping is a passive force, ``-damping * qd``, kept apart as
in MuJoCo. Both are checked against MuJoCo C in tests/test_dynamics.py.
"""

from __future__ import annotations

import jax.numpy as jnp

from jaxinertia.kinematics import Poses, forward_kinematics, joint_axes
from jaxinertia.linalg import cholesky_solve
from jaxinertia.robot import Robot

__all__ = ["bias_forces", "euler_step", "forward_dynamics", "inverse_dynamics", "mass_matrix"]


def _com_and_inertia(robot: Robot, poses: Poses):
    com = jnp.einsum("nij,nj->ni", poses.rot, robot.com) + poses.pos
    I_w = jnp.einsum("nij,njk,nlk->nil", poses.rot, robot.inertia, poses.rot)
    return com, I_w


def mass_matrix(robot: Robot, q: jnp.ndarray) -> jnp.ndarray:
    """Joint-space inertia matrix (N, N) [kg m^2], armature included.

    ``M = sum_k m_k Jv_k^T Jv_k + Jw_k^T I_k Jw_k`` with the COM Jacobians of every link.
    """
    poses = forward_kinematics(robot, q)
    z, anchor = joint_axes(robot, poses)
    com, I_w = _com_and_inertia(robot, poses)
    sub = jnp.asarray(robot.subtree(), dtype=z.dtype)  # [j, k]: link k moves with joint j
    # Jv[k, j] = z_j x (c_k - a_j) for ancestors j of link k, else 0; Jw[k, j] = z_j.
    Jv = jnp.cross(z[None, :, :], com[:, None, :] - anchor[None, :, :]) * sub.T[:, :, None]
    Jw = z[None, :, :] * sub.T[:, :, None]
    M = jnp.einsum("k,kix,kjx->ij", robot.mass, Jv, Jv)
    M = M + jnp.einsum("kia,kab,kjb->ij", Jw, I_w, Jw)
    return M + jnp.diag(robot.armature)


def inverse_dynamics(
    robot: Robot, q: jnp.ndarray, qd: jnp.ndarray, qdd: jnp.ndarray, *, gravity: bool = True
) -> jnp.ndarray:
    """Joint torques (N,) for motion (q, qd, qdd), recursive Newton-Euler in base axes.

    Armature is included (``armature * qdd``), damping is not (MuJoCo's convention).
    With ``qdd = 0`` this is ``bias_forces``.
    """
    poses = forward_kinematics(robot, q)
    z, anchor = joint_axes(robot, poses)
    com, I_w = _com_and_inertia(robot, poses)
    n = robot.n_joints
    g = robot.gravity if gravity else jnp.zeros_like(robot.gravity)
    zero = jnp.zeros_like(g)
    w, dw, acc = [None] * n, [None] * n, [None] * n  # acc: linear acc. of anchor point k
    for k in range(n):
        p = robot.parent[k]
        if p < 0:
            w_p, dw_p, a_p, r_p = zero, zero, -g, anchor[k]  # base "accelerates" against g
        else:
            w_p, dw_p, a_p, r_p = w[p], dw[p], acc[p], anchor[p]
        d = anchor[k] - r_p
        acc[k] = a_p + jnp.cross(dw_p, d) + jnp.cross(w_p, jnp.cross(w_p, d))
        w[k] = w_p + z[k] * qd[k]
        dw[k] = dw_p + z[k] * qdd[k] + jnp.cross(w_p, z[k] * qd[k])
    F, N = [None] * n, [None] * n  # force on link k's subtree, moment about anchor k
    tau = []
    for k in reversed(range(n)):
        d = com[k] - anchor[k]
        a_c = acc[k] + jnp.cross(dw[k], d) + jnp.cross(w[k], jnp.cross(w[k], d))
        f = robot.mass[k] * a_c
        nk = I_w[k] @ dw[k] + jnp.cross(w[k], I_w[k] @ w[k]) + jnp.cross(d, f)
        for c in range(k + 1, n):
            if robot.parent[c] == k:
                f = f + F[c]
                nk = nk + N[c] + jnp.cross(anchor[c] - anchor[k], F[c])
        F[k], N[k] = f, nk
    tau = jnp.stack([z[k] @ N[k] for k in range(n)])
    return tau + robot.armature * qdd


def bias_forces(robot: Robot, q: jnp.ndarray, qd: jnp.ndarray) -> jnp.ndarray:
    """Coriolis, centrifugal and gravity forces (N,) [N m]: MuJoCo's ``qfrc_bias``."""
    return inverse_dynamics(robot, q, qd, jnp.zeros_like(qd))


def forward_dynamics(
    robot: Robot, q: jnp.ndarray, qd: jnp.ndarray, tau: jnp.ndarray
) -> jnp.ndarray:
    """Joint accelerations (N,) under applied joint torques ``tau`` and joint damping."""
    rhs = tau - robot.damping * qd - bias_forces(robot, q, qd)
    return cholesky_solve(mass_matrix(robot, q), rhs)


def euler_step(
    robot: Robot, q: jnp.ndarray, qd: jnp.ndarray, tau: jnp.ndarray, dt: float
) -> tuple[jnp.ndarray, jnp.ndarray]:
    """One semi-implicit Euler step with implicit joint damping (MuJoCo's ``Euler``).

    ``qdd = (M + dt D)^-1 (tau - c - D qd)``, ``qd' = qd + dt qdd``, ``q' = q + dt qd'``:
    the damping term is integrated implicitly, so stiff servo damping stays stable at the
    servo's own control period.
    """
    M = mass_matrix(robot, q) + dt * jnp.diag(robot.damping)
    rhs = tau - robot.damping * qd - bias_forces(robot, q, qd)
    qd = qd + dt * cholesky_solve(M, rhs)
    return q + dt * qd, qd
