"""Statics of a held object: the load regressor A, link gravity base parameters, tag-pose fit.

For a rigid object of mass m whose COM is ``p`` in its AprilTag frame, held still, the
joint torques it exerts are linear in ``x = [m, m*p]`` (paper eqs. 8-15):

    tau - tau_g = A(q, tag pose) @ x,    A = [J_v(p_tag)^T g | J_w^T [g]_x^T R_base_tag]

``J_v(p_tag)`` is the linear Jacobian of the tag origin, ``J_w`` the angular Jacobian of the
body holding it (both base-aligned), ``g`` gravity in base. This is the paper's
``A_i = J_i^T B_i`` written at the tag origin instead of the end-effector origin; the two
agree because moving the reference point of a wrench is exactly the change between them.
The same regressor with a link's own frame gives that link's gravity torques, which is
how the link gravity parameters are identified.
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxinertia.kinematics import (
    axis_angle_to_matrix,
    ee_pose,
    forward_kinematics,
    jacobian_at,
    skew,
)
from jaxinertia.robot import Robot

__all__ = [
    "BaseParameters",
    "TagFit",
    "fit_tag_pose",
    "gravity_base_parameters",
    "identify_gravity_base_parameters",
    "link_gravity_parameters",
    "link_gravity_regressor",
    "load_regressor",
    "load_regressor_fixed_tag",
    "tag_pose",
    "torque_scale_sensitivity",
]


def _regressor_on_body(robot, poses, body, R_base_f, p_base_f):
    jac = jacobian_at(robot, poses, body, p_base_f)
    g = robot.gravity
    col_m = jac[:3].T @ g
    col_mp = jac[3:].T @ (skew(g).T @ R_base_f)
    return jnp.concatenate([col_m[:, None], col_mp], axis=1)


def load_regressor(
    robot: Robot, q: jnp.ndarray, R_base_tag: jnp.ndarray, p_base_tag: jnp.ndarray
) -> jnp.ndarray:
    """The load regressor A (N, 4) for a tag measured at ``(R_base_tag, p_base_tag)``.

    The tag is rigidly attached to the end-effector body; its pose comes from the camera
    (real robot) or the simulator.

    Args:
      q: (N,) present joint angles [rad] (A is evaluated at q, not at the goal q_d).
      R_base_tag: (3, 3) tag orientation in base; p_base_tag: (3,) tag origin in base [m].
    """
    poses = forward_kinematics(robot, q)
    return _regressor_on_body(robot, poses, robot.ee_body, R_base_tag, p_base_tag)


def tag_pose(
    robot: Robot, q: jnp.ndarray, R_ee_tag: jnp.ndarray, p_ee_tag: jnp.ndarray
) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Pose of a tag fixed in the end-effector frame, in base: ``(R_base_tag, p_base_tag)``."""
    R_ee, p_ee = ee_pose(robot, q)
    return R_ee @ R_ee_tag, R_ee @ p_ee_tag + p_ee


def load_regressor_fixed_tag(
    robot: Robot, q: jnp.ndarray, R_ee_tag: jnp.ndarray, p_ee_tag: jnp.ndarray
) -> jnp.ndarray:
    """A (N, 4) for a tag at a fixed pose in the end-effector frame (no camera needed)."""
    R, p = tag_pose(robot, q, R_ee_tag, p_ee_tag)
    return load_regressor(robot, q, R, p)


def link_gravity_regressor(robot: Robot, q: jnp.ndarray) -> jnp.ndarray:
    """Y (N, 4N) with ``gravity_torques(robot, q) == Y @ link_gravity_parameters(robot)``.

    Columns 4k..4k+3 belong to link k: ``[m_k, m_k * c_k]`` with c_k its COM in body frame.
    """
    poses = forward_kinematics(robot, q)
    cols = [
        _regressor_on_body(robot, poses, k, poses.rot[k], poses.pos[k])
        for k in range(robot.n_joints)
    ]
    return jnp.concatenate(cols, axis=1)


@jax.jit
def _link_gravity_regressors(robot: Robot, q: jnp.ndarray) -> jnp.ndarray:
    """(S, N, 4N) :func:`link_gravity_regressor` at every row of ``q`` (S, N), one program
    (op by op, an accelerator compiles each small kernel of the kinematics on its own:
    13 s of a GPU fold's calibration, against 4 s on a 2-core CPU; jitted, the same numbers
    in 1.3 s there)."""
    return jax.vmap(link_gravity_regressor, in_axes=(None, 0))(robot, q)


def link_gravity_parameters(robot: Robot) -> jnp.ndarray:
    """(4N,) the links' ``[m_k, m_k c_k]`` stacked, as ordered by :func:`link_gravity_regressor`."""
    return jnp.concatenate([robot.mass[:, None], robot.mass[:, None] * robot.com], axis=1).ravel()


class BaseParameters(NamedTuple):
    """A minimal set of identifiable gravity parameters.

    ``independent`` (P,) and ``dependent`` (4N - P,) index the columns of
    :func:`link_gravity_regressor`; base parameters are
    ``theta[independent] + K @ theta[dependent]`` and the base regressor is
    ``Y[:, independent]``.
    """

    independent: np.ndarray
    dependent: np.ndarray
    K: np.ndarray

    def regressor(self, Y: jnp.ndarray) -> jnp.ndarray:
        return Y[..., self.independent]

    def from_full(self, theta: jnp.ndarray) -> jnp.ndarray:
        return theta[self.independent] + self.K @ theta[self.dependent]


def gravity_base_parameters(
    robot: Robot, *, n_samples: int = 200, seed: int = 0, rtol: float = 1e-9
) -> BaseParameters:
    """Finds the identifiable combinations of link gravity parameters numerically.

    Stacks the regressor at random configurations and keeps the columns a pivoted QR
    declares independent (structural identifiability does not depend on the samples).
    """
    rng = np.random.default_rng(seed)
    q = rng.uniform(-np.pi, np.pi, size=(n_samples, robot.n_joints))
    r64 = robot.astype(jnp.float64) if jax.config.jax_enable_x64 else robot
    Y = np.asarray(_link_gravity_regressors(r64, jnp.asarray(q)))
    Y = Y.reshape(-1, Y.shape[-1])
    import scipy.linalg  # (a tenth of a second to import: here, not at start)

    _, R, piv = scipy.linalg.qr(Y, mode="economic", pivoting=True)
    d = np.abs(np.diag(R))
    rank = int(np.sum(d > rtol * d[0]))
    ind, dep = np.sort(piv[:rank]), piv[rank:]
    # Dependent columns as combinations of the independent ones: Y_D = Y_I @ K.
    K, *_ = np.linalg.lstsq(Y[:, ind], Y[:, dep], rcond=None)
    K[np.abs(K) < 1e-12] = 0.0
    return BaseParameters(ind, np.sort(dep) if dep.size else dep, K[:, np.argsort(dep)])


def identify_gravity_base_parameters(
    robot: Robot, q: jnp.ndarray, tau_g: jnp.ndarray, base: BaseParameters | None = None
) -> tuple[np.ndarray, BaseParameters]:
    """Least-squares base gravity parameters from static torques ``tau_g`` (S, N) at ``q`` (S, N).

    Returns ``(theta_base, base)``; predict with ``base.regressor(Y) @ theta_base``.
    """
    base = base or gravity_base_parameters(robot)
    Y = _link_gravity_regressors(robot, jnp.asarray(q))
    Yb = np.asarray(base.regressor(Y)).reshape(-1, base.independent.size)
    theta, *_ = np.linalg.lstsq(Yb, np.asarray(tau_g).reshape(-1), rcond=None)
    return theta, base


class TagFit(NamedTuple):
    """A tag pose fixed in the end-effector frame, fitted to measured regressors."""

    R_ee_tag: np.ndarray
    p_ee_tag: np.ndarray
    max_abs_error: np.ndarray
    """(4,) largest |A_fit - A| per column."""
    mean_abs_error: np.ndarray
    """(4,) mean |A_fit - A| per column."""


def fit_tag_pose(robot: Robot, q: jnp.ndarray, A: jnp.ndarray, *, iterations: int = 20) -> TagFit:
    """Fits one fixed tag pose in the end-effector frame to regressors ``A`` (S, N, 4) at ``q``.

    The mass column depends only on the tag position and is linear in it; the other three
    depend only on the orientation. Both start from linear least squares (the rotation is
    projected onto SO(3)) and the orientation is refined by Gauss-Newton.
    """
    R_et, p_et, err = _fit_tag_pose(robot, jnp.asarray(q), jnp.asarray(A), iterations)
    err = np.asarray(err).reshape(-1, 4)
    return TagFit(np.asarray(R_et), np.asarray(p_et), err.max(axis=0), err.mean(axis=0))


@partial(jax.jit, static_argnums=3)
def _fit_tag_pose(robot: Robot, q: jnp.ndarray, A: jnp.ndarray, iterations: int):
    """:func:`fit_tag_pose` as one program (the robot an argument): ``(R, p, |A_fit - A|)``."""
    zero = jnp.zeros(3, dtype=A.dtype)
    eye = jnp.eye(3, dtype=A.dtype)

    def regress(R_et, p_et):
        return jax.vmap(load_regressor_fixed_tag, in_axes=(None, 0, None, None))(
            robot, q, R_et, p_et
        )

    # Mass column: affine in p_ee_tag. Its Jacobian is exact (affine), taken at zero.
    col0 = lambda p: regress(eye, p)[..., 0].ravel()  # noqa: E731
    J0 = jax.jacfwd(col0)(zero)
    p_et, *_ = jnp.linalg.lstsq(J0, A[..., 0].ravel() - col0(zero))

    # Orientation columns: linear in the entries of R_ee_tag.
    def cols(Rflat):
        return regress(Rflat.reshape(3, 3), p_et)[..., 1:].ravel()

    Jr = jax.jacfwd(cols)(jnp.zeros(9, dtype=A.dtype))
    r_lin, *_ = jnp.linalg.lstsq(Jr, A[..., 1:].ravel())
    U, _, Vt = jnp.linalg.svd(r_lin.reshape(3, 3))
    R0 = U @ jnp.diag(jnp.array([1.0, 1.0, jnp.linalg.det(U @ Vt)], dtype=A.dtype)) @ Vt

    def rotation(w):
        n = jnp.sqrt(jnp.sum(w**2) + 1e-30)
        return R0 @ axis_angle_to_matrix(w / n, n)

    def resid(w):
        return cols(rotation(w).ravel()) - A[..., 1:].ravel()

    def step(_, w):  # Gauss-Newton
        return w - jnp.linalg.lstsq(jax.jacfwd(resid)(w), resid(w))[0]

    w = jax.lax.fori_loop(0, iterations, step, jnp.full(3, 1e-9, dtype=A.dtype))
    R_et = rotation(w)
    return R_et, p_et, jnp.abs(regress(R_et, p_et) - A)


def robot_with_gravity_parameters(
    robot: Robot, theta_base: np.ndarray, base: BaseParameters
) -> Robot:
    """The robot whose link masses and first moments reproduce identified base parameters.

    Of all link parameters ``theta`` with ``base.from_full(theta) == theta_base``, takes the
    one closest to the robot's own (minimum-norm correction), so unidentifiable parts keep
    their nominal values. Raises ``ValueError`` if a link mass would not stay positive.
    """
    theta0 = np.asarray(link_gravity_parameters(robot), np.float64)
    n = theta0.size
    C = np.zeros((base.independent.size, n))
    C[:, base.independent] = np.eye(base.independent.size)
    if base.dependent.size:
        C[:, base.dependent] = base.K
    delta, *_ = np.linalg.lstsq(C, np.asarray(theta_base) - C @ theta0, rcond=None)
    theta = (theta0 + delta).reshape(-1, 4)
    if np.any(theta[:, 0] <= 0):
        raise ValueError(f"identified gravity parameters imply link masses {theta[:, 0]}")
    return robot.replace(mass=jnp.asarray(theta[:, 0], robot.mass.dtype),
                         com=jnp.asarray(theta[:, 1:] / theta[:, :1], robot.com.dtype))


def torque_scale_sensitivity(A, tau_g, x, weights=None, rel: float = 0.01) -> np.ndarray:
    """How far a least-squares answer moves when one joint's torques are all read ``rel``
    (a fraction) off: a servo whose torque per tick differs from what the models learnt
    (another recording session: its supply, its temperature) scales every torque it reads,
    most of it the arm's own weight, not the object's. ``A`` (S, N, 4) and ``tau_g``
    (S, N) of the samples, ``x`` (4,) the answer ``[m, m p]``, ``weights`` (S, N) the
    solve's (None: every row alike). Returns (N, 4): per joint, the change of ``x``. Exact
    for the weighted least squares (linear in the torques) at the torques the answer
    explains, ``tau_g + A x`` (docs/results.md, "What one per cent of joint 2 costs the
    answer": on the OpenMANIPULATOR-X 1 % of joint 2 is 4.6-5.1 g)."""
    A, tau_g, x = (np.asarray(a, np.float64) for a in (A, tau_g, x))
    w = np.ones(tau_g.shape) if weights is None else np.asarray(weights, np.float64)
    tau = tau_g + A @ x
    gram = np.einsum("snk,sn,snl->kl", A, w, A)
    return np.linalg.solve(gram, rel * np.einsum("snk,sn,sn->kn", A, w, tau)).T
