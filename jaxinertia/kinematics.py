"""Forward kinematics, geometric Jacobians and static gravity torques of a serial chain.

Pure functions of ``(robot, q)``; jit, vmap and grad safe. Shapes are for one
configuration: vmap for batches. Naming: ``R_base_body`` is body's orientation in base,
``p_base_body`` its origin in base coordinates.

Torque sign: a *static* joint torque here is the generalised force that a load exerts on
the joint (gravity pulling the arm), as in the lbipe data. It equals minus MuJoCo's
``qfrc_bias`` at zero velocity, and minus what a gravity-compensating motor applies.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxinertia.robot import Robot

__all__ = [
    "Poses",
    "axis_angle_to_matrix",
    "forward_kinematics",
    "ee_pose",
    "ee_positions",
    "jacobian_at",
    "joint_axes",
    "point_jacobian",
    "ee_jacobian",
    "gravity_torques",
    "point_mass_torques",
    "skew",
]


class Poses(NamedTuple):
    """Frames of the N moving bodies in the base frame: ``rot`` (N, 3, 3), ``pos`` (N, 3)."""

    rot: jnp.ndarray
    pos: jnp.ndarray


def skew(v: jnp.ndarray) -> jnp.ndarray:
    """(3,) -> (3, 3) with ``skew(a) @ b == cross(a, b)``."""
    z = jnp.zeros_like(v[0])
    return jnp.array(
        [[z, -v[2], v[1]], [v[2], z, -v[0]], [-v[1], v[0], z]],
    )


def axis_angle_to_matrix(axis: jnp.ndarray, angle: jnp.ndarray) -> jnp.ndarray:
    """Rodrigues' formula for a unit ``axis`` (3,) and ``angle`` [rad]."""
    K = skew(axis)
    return jnp.eye(3, dtype=K.dtype) + jnp.sin(angle) * K + (1.0 - jnp.cos(angle)) * (K @ K)


def forward_kinematics(robot: Robot, q: jnp.ndarray) -> Poses:
    """Poses of every moving body in the base frame.

    Args:
      q: (N,) joint angles [rad].
    """
    q = jnp.asarray(q)
    # Static check (shapes are known under jit/vmap/grad): JAX clamps out-of-range indices,
    # so a too-short q would otherwise silently reuse its last angle for the missing joints.
    if q.shape != (robot.n_joints,):
        raise ValueError(
            f"q has shape {q.shape}; {robot.name!r} needs ({robot.n_joints},) joint angles "
            "(one configuration; vmap for batches)"
        )
    rots, poss = [], []
    for i in range(robot.n_joints):
        # Body i at q: its rest pose in the parent, then a rotation about the joint axis
        # through the joint anchor (both expressed in body i's own frame).
        R_j = axis_angle_to_matrix(robot.joint_axis[i], q[i])
        a = robot.joint_pos[i]
        R_par_i = robot.body_rot[i] @ R_j
        p_par_i = robot.body_pos[i] + robot.body_rot[i] @ (a - R_j @ a)
        par = robot.parent[i]
        if par < 0:
            rots.append(R_par_i)
            poss.append(p_par_i)
        else:
            rots.append(rots[par] @ R_par_i)
            poss.append(rots[par] @ p_par_i + poss[par])
    return Poses(jnp.stack(rots), jnp.stack(poss))


def joint_axes(robot: Robot, poses: Poses) -> tuple[jnp.ndarray, jnp.ndarray]:
    """World-aligned joint axes (N, 3) and a point on each axis (N, 3), from body poses."""
    z = jnp.einsum("nij,nj->ni", poses.rot, robot.joint_axis)
    anchor = jnp.einsum("nij,nj->ni", poses.rot, robot.joint_pos) + poses.pos
    return z, anchor


def ee_pose(robot: Robot, q: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """End-effector frame in base: ``(R_base_ee (3, 3), p_base_ee (3,))``."""
    poses = forward_kinematics(robot, q)
    R_b, p_b = poses.rot[robot.ee_body], poses.pos[robot.ee_body]
    return R_b @ robot.ee_rot, R_b @ robot.ee_pos + p_b


@jax.jit
def ee_positions(robot: Robot, q: jnp.ndarray) -> jnp.ndarray:
    """(S, 3) end-effector origins in base at configurations ``q`` (S, N): one compiled
    call (an eager ``vmap`` would compile every operation of the kinematics on its own)."""
    return jax.vmap(lambda qi: ee_pose(robot, qi)[1])(q)


def jacobian_at(robot: Robot, poses: Poses, body: int, p_base: jnp.ndarray) -> jnp.ndarray:
    """:func:`point_jacobian` from body poses already computed (one FK pass, many points)."""
    z, anchor = joint_axes(robot, poses)
    mask = jnp.asarray(robot.ancestors(body), dtype=z.dtype)[:, None]
    jv = jnp.cross(z, p_base - anchor) * mask
    jw = z * mask
    return jnp.concatenate([jv.T, jw.T], axis=0)


def point_jacobian(robot: Robot, q: jnp.ndarray, body: int, p_base: jnp.ndarray) -> jnp.ndarray:
    """Geometric Jacobian (6, N) of a point rigidly attached to ``body`` (static index).

    Rows 0-2: linear velocity of the point, rows 3-5: angular velocity of the body, both in
    base-frame axes (MuJoCo's ``mj_jac`` convention).

    Args:
      q: (N,) joint angles [rad].
      p_base: (3,) the point's current position in the base frame [m].
    """
    return jacobian_at(robot, forward_kinematics(robot, q), body, p_base)


def ee_jacobian(robot: Robot, q: jnp.ndarray) -> jnp.ndarray:
    """Geometric Jacobian (6, N) of the end-effector frame origin."""
    _, p_ee = ee_pose(robot, q)
    return point_jacobian(robot, q, robot.ee_body, p_ee)


def gravity_torques(robot: Robot, q: jnp.ndarray) -> jnp.ndarray:
    """Static joint torques (N,) that gravity exerts through the robot's own links [N m]."""
    poses = forward_kinematics(robot, q)
    z, anchor = joint_axes(robot, poses)
    com_base = jnp.einsum("nij,nj->ni", poses.rot, robot.com) + poses.pos
    # tau_j = z_j . sum_{k moved by j} (c_k - a_j) x m_k g: sum first moments per subtree.
    sub = jnp.asarray(robot.subtree(), dtype=z.dtype)
    m_sub = sub @ robot.mass
    mc_sub = sub @ (robot.mass[:, None] * com_base)
    moment = jnp.cross(mc_sub - m_sub[:, None] * anchor, robot.gravity)
    return jnp.einsum("ni,ni->n", z, moment)


def point_mass_torques(
    robot: Robot, q: jnp.ndarray, mass: jnp.ndarray, com_ee: jnp.ndarray
) -> jnp.ndarray:
    """Static joint torques (N,) of a point mass rigidly held in the end-effector frame.

    Args:
      mass: scalar [kg]; com_ee: (3,) its position in the end-effector frame [m].
    """
    R_ee, p_ee = ee_pose(robot, q)
    p = R_ee @ com_ee + p_ee
    jac = point_jacobian(robot, q, robot.ee_body, p)
    return jac[:3].T @ (mass * robot.gravity)

