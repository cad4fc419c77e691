"""One simulator step for a whole batch of arms, written batch-last (no ``vmap``).

:func:`jaxinertia.sim.simulator.step` is written for one arm and vmapped. Under ``vmap``
the 3 x 3 products of the kinematics become batched tiny ``dot``s, which XLA:CPU runs
slowly and XLA:GPU compiles into Triton kernels (an H100 steps the batch-last form 1.9x
faster in float32 and 5.5x in float64: docs/benchmarks.md). Here every array keeps the
batch as its LAST (minor, contiguous) axis, so every contraction over a small axis is an
elementwise multiply-add vectorised over the batch:

    joint quantities   (N, B)         q, qd, servo state, friction, goal
    rotations          (3, 3, B)      one per body (Python list over the static chain)
    vectors            (3, B)
    joint-space        N x N entries of (B,) (Python lists)

Parameters (:class:`~jaxinertia.sim.simulator.SimParams`) may be *shared* by the whole
batch (every leaf with its one-arm shape, e.g. ``robot.inertia`` (N, 3, 3)) or *per arm*
(a leaf with the batch appended last, e.g. ``robot.inertia`` (N, 3, 3, B),
``friction.coulomb`` (N, B)); each leaf is judged by its rank, so the two may be mixed
(e.g. a shared servo and a per-arm payload robot and friction).
:func:`params_batch_last` turns per-arm parameters stored batch-first (a leading lane axis,
as ``jax.vmap`` takes them) into this layout.

The step is the same physics and the same numbers as ``simulator.step`` (same servo law,
implicit damping, torque offset, warm-started projected Gauss-Seidel friction sweeps,
``W = dt M~^-1`` by the same unrolled Cholesky solves); only the rigid-body terms are
organised differently, in float64 they agree to rounding (~1e-15 per step):

* forward kinematics uses Rodrigues' formula folded into per-joint constants,
  ``R_parent_i(q) = C0 + sin(q) C1 + (1 - cos(q)) C2`` (``C0 = body_rot``,
  ``C1 = body_rot K``, ``C2 = body_rot K^2``, ``K`` the axis' cross-product matrix), and
  is computed once and shared by the mass matrix and the bias forces;
* the mass matrix is the composite-rigid-body algorithm and the bias forces the recursive
  Newton-Euler algorithm, both with spatial vectors taken about the base origin (no
  per-link anchor recursion): ``M_ij = S_i . I^C_j S_j``, ``c_j = S_j . sum_{k in
  subtree(j)} (I_k a_k + v_k x* I_k v_k)``.

Fusion control (XLA:CPU). XLA:CPU has no multi-output loop fusion, so an array read by
several kernels is either materialised or recomputed in each of them, and it recomputes
whenever it can: written naively, the kinematic chain was recomputed into ~180 kernels
(23,800 fused instructions, 4x slower than the vmapped step). :func:`_barrier` materialises
the few values that everything downstream shares (each body's pose, its spatial inertia,
the velocities and bias accelerations, the composite inertias and wrenches, ``M`` and the
bias forces); the friction sweeps run in a rolled ``fori_loop`` so that ``W``, ``v_free``
and the bounds are computed once. Reductions (``.sum`` over a small axis) are avoided on
purpose: XLA:CPU either hands them to YNNPACK (~100 us per call) or fuses them with the
producers recomputed per reduced element. The barrier is the identity on other backends.

Per-arm robots cost a little more than a shared one: the Rodrigues constants above are
then (N, 3, 3, B) arrays recomputed every step (for a shared robot closed over by ``jit``
they are folded into constants at compile time).

Typical use (convert once, outside the time loop)::

    sb = state_batch_last(state)            # SimState with (B, N) leaves -> (N, B)
    def body(s, _):
        return step_batched(params, s, goal_bl), None
    sb, _ = jax.lax.scan(body, sb, None, length=T)
    state = state_batch_first(sb)
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxinertia.linalg import spd_inverse_rows
from jaxinertia.robot import Robot
from jaxinertia.sim.friction import friction_bound
from jaxinertia.sim.servo import servo_step
from jaxinertia.sim.simulator import SimParams, SimState

__all__ = [
    "batch_first",
    "batch_last",
    "params_batch_last",
    "state_batch_first",
    "state_batch_last",
    "step_batched",
]

# Rank of each Robot leaf for one arm (a per-arm leaf has one more: the batch, last).
_ROBOT_NDIM = dict(body_pos=2, body_rot=3, joint_axis=2, joint_pos=2, mass=1, com=2,
                   inertia=3, armature=1, damping=1, q_min=1, q_max=1, ee_pos=1, ee_rot=2,
                   gravity=1)


def batch_last(tree):
    """Every leaf of ``tree`` with its leading (batch) axis moved last."""
    return jax.tree_util.tree_map(lambda a: jnp.moveaxis(jnp.asarray(a), 0, -1), tree)


def batch_first(tree):
    """The inverse of :func:`batch_last`: every leaf's last axis moved first."""
    return jax.tree_util.tree_map(lambda a: jnp.moveaxis(a, -1, 0), tree)


def state_batch_last(state: SimState) -> SimState:
    """A batch-first ``SimState`` (leaves (B, N)) in the batch-last layout (N, B)."""
    return batch_last(state)


def state_batch_first(state: SimState) -> SimState:
    """The inverse of :func:`state_batch_last`: (N, B) leaves back to (B, N)."""
    return batch_first(state)


def params_batch_last(params: SimParams, per_arm: bool = True) -> SimParams:
    """Per-arm ``SimParams`` stored batch-first (every array leaf with a leading batch axis,
    as ``jax.vmap(step, (0, 0, 0))`` takes them) in the batch-last layout of
    :func:`step_batched` (the batch axis moved last). ``per_arm=False`` returns ``params``
    (shared parameters need no conversion)."""
    return batch_last(params) if per_arm else params


def _lane(x, ndim: int):
    """A parameter leaf broadcastable against batch-last arrays: a shared leaf (one-arm
    rank ``ndim``) gets a trailing axis of 1, a per-arm leaf (rank ``ndim + 1``) is kept."""
    x = jnp.asarray(x)
    if x.ndim == ndim:
        return x[..., None]
    if x.ndim == ndim + 1:
        return x
    raise ValueError(f"parameter of rank {x.ndim}: expected {ndim} (shared) or {ndim + 1} "
                     "(per arm, batch last)")


# ---------------------------------------------------------------- small batch-last algebra
def _mv(R, v):
    """(3, 3, B) @ (3, B) -> (3, B)."""
    return R[:, 0] * v[0] + R[:, 1] * v[1] + R[:, 2] * v[2]


def _mm(A, C):
    """(3, 3, B) @ (3, 3, B) -> (3, 3, B)."""
    return A[:, 0, None] * C[0][None] + A[:, 1, None] * C[1][None] + A[:, 2, None] * C[2][None]


def _mmT(A, C):
    """A @ C^T for (3, 3, B) arrays."""
    return (A[:, None, 0] * C[None, :, 0] + A[:, None, 1] * C[None, :, 1]
            + A[:, None, 2] * C[None, :, 2])


def _cross(a, b):
    """Cross product of (3, B) arrays."""
    return jnp.stack([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2],
                      a[0] * b[1] - a[1] * b[0]])


def _dot(a, b):
    """(3, B) . (3, B) -> (B,)."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _skew(k):
    """(3, ...) -> (3, 3, ...) with skew(k) @ b = k x b."""
    z = jnp.zeros_like(k[0])
    return jnp.stack([jnp.stack([z, -k[2], k[1]]), jnp.stack([k[2], z, -k[0]]),
                      jnp.stack([-k[1], k[0], z])])


@jax.custom_batching.custom_vmap
def _cond_barrier(tree, key):
    pred = (key == key) | (key != key)  # always True
    return jax.lax.cond(pred, lambda t: t,
                        lambda t: jax.tree_util.tree_map(jnp.zeros_like, t), tree)


@_cond_barrier.def_vmap
def _cond_barrier_vmap(axis_size, in_batched, tree, key):
    # Under vmap (several streams as one program, sim.stream.stream_jobs) the values stay
    # batched and the predicate need not be: a batched one would turn the conditional into
    # a select of both branches, and the barrier would be gone (a step 9x slower).
    tree_batched, key_batched = in_batched
    return _cond_barrier(tree, key[0] if key_batched else key), tree_batched


def _barrier(tree, key):
    """``tree`` unchanged, but materialised: XLA:CPU fuses nothing across this point.

    XLA:CPU has no multi-output loop fusion: each array that several consumers read is
    either its own kernel or recomputed inside every consumer's kernel, and it prefers to
    recompute (``lax.optimization_barrier`` is dropped before fusion). Recomputing the
    kinematic chain in every consumer made this step ~10x slower, so the values pass here
    through a ``lax.cond`` on an always-true predicate that XLA cannot fold
    (``key == key | key != key``; the other branch, never taken, returns zeros so that the
    two branches differ and the conditional is kept), unbatched under ``vmap``. Other
    backends get the identity.
    """
    return jax.lax.platform_dependent(tree, key, cpu=_cond_barrier,
                                      default=lambda t, k: t)


# ----------------------------------------------------------------------- rigid-body terms
def _chain_constants(robot: Robot):
    """Per-joint constants (batch-last; trailing axis 1 for a shared robot):
    R_parent_i(q) = C0 + s C1 + c C2, p_parent_i(q) = P0 - s P1 - c P2, with
    s = sin q_i, c = 1 - cos q_i; plus the joint axis and a point on it in the parent's
    frame (both constant)."""
    rob = {k: _lane(getattr(robot, k), nd) for k, nd in _ROBOT_NDIM.items()}
    out = []
    for i in range(robot.n_joints):
        R0 = rob["body_rot"][i]  # (3, 3, b)
        K = _skew(rob["joint_axis"][i])
        C1 = _mm(R0, K)
        C2 = _mm(C1, K)
        a = rob["joint_pos"][i]
        out.append(dict(
            C0=R0, C1=C1, C2=C2, P0=rob["body_pos"][i], P1=_mv(C1, a), P2=_mv(C2, a),
            z=_mv(R0, rob["joint_axis"][i]),  # joint axis in the parent's frame
            anchor=rob["body_pos"][i] + _mv(R0, a),  # joint anchor in the parent's frame
        ))
    return rob, out


def _dynamics(robot: Robot, q, qd):
    """Mass matrix (N x N nested lists of (B,)) and bias forces (N, B) of the chain."""
    n = robot.n_joints
    parent = robot.parent
    rob, cst = _chain_constants(robot)
    s, c = jnp.sin(q), 1.0 - jnp.cos(q)
    rot, pos, z, anc = [None] * n, [None] * n, [None] * n, [None] * n
    for i in range(n):
        k = cst[i]
        R_loc = k["C0"] + s[i] * k["C1"] + c[i] * k["C2"]
        p_loc = k["P0"] - s[i] * k["P1"] - c[i] * k["P2"]
        p = parent[i]
        if p < 0:
            rot[i], pos[i], z[i], anc[i] = R_loc, p_loc, k["z"], k["anchor"]
        else:
            rot[i] = _mm(rot[p], R_loc)
            pos[i] = _mv(rot[p], p_loc) + pos[p]
            z[i] = _mv(rot[p], k["z"])
            anc[i] = _mv(rot[p], k["anchor"]) + pos[p]
        rot[i], pos[i], z[i], anc[i] = _barrier((rot[i], pos[i], z[i], anc[i]), q[0, 0])
    # Spatial inertia of each link about the base origin: (I_O, h = m c, m).
    mass = rob["mass"]
    I_O, h = [None] * n, [None] * n
    eye = jnp.eye(3, dtype=q.dtype)[:, :, None]
    for k in range(n):
        com = _mv(rot[k], rob["com"][k]) + pos[k]
        I_w = _mmT(_mm(rot[k], rob["inertia"][k]), rot[k])
        h[k] = mass[k] * com
        I_O[k] = I_w + mass[k] * (_dot(com, com) * eye - com[:, None] * com[None, :])

    def inertia_times(I, hh, m, w, v):  # spatial inertia (I, h, m) @ motion (w, v)
        return _mv(I, w) + _cross(hh, v), m * v - _cross(hh, w)

    # Motion subspaces S_j = (z_j, a_j x z_j); velocities and (bias) accelerations.
    Sv = [_cross(anc[j], z[j]) for j in range(n)]
    I_O, h, Sv = _barrier((I_O, h, Sv), q[0, 0])
    g = rob["gravity"]
    zero = jnp.zeros_like(q[:3])
    vel_w, vel_v, acc_w, acc_v = [None] * n, [None] * n, [None] * n, [None] * n
    for k in range(n):
        p = parent[k]
        if p < 0:
            w_p, v_p, aw_p, av_p = zero, zero, zero, -g + zero
        else:
            w_p, v_p, aw_p, av_p = vel_w[p], vel_v[p], acc_w[p], acc_v[p]
        sw, sv = z[k] * qd[k], Sv[k] * qd[k]
        vel_w[k], vel_v[k] = w_p + sw, v_p + sv
        # a_k = a_p + v_k x S_k qd_k  (motion cross product)
        acc_w[k] = aw_p + _cross(vel_w[k], sw)
        acc_v[k] = av_p + _cross(vel_w[k], sv) + _cross(vel_v[k], sw)
    vel_w, vel_v, acc_w, acc_v = _barrier((vel_w, vel_v, acc_w, acc_v), q[0, 0])
    # Per-link bias wrench F_k = I_k a_k + v_k x* (I_k v_k).
    Fn, Ff = [None] * n, [None] * n
    for k in range(n):
        an, af = inertia_times(I_O[k], h[k], mass[k], acc_w[k], acc_v[k])
        pn, pf = inertia_times(I_O[k], h[k], mass[k], vel_w[k], vel_v[k])
        Fn[k] = an + _cross(vel_w[k], pn) + _cross(vel_v[k], pf)
        Ff[k] = af + _cross(vel_w[k], pf)
    # Composite (subtree) inertias and bias wrenches, leaves first.
    cI, ch, cFn, cFf = list(I_O), list(h), list(Fn), list(Ff)
    cm = [mass[k] for k in range(n)]
    for k in reversed(range(n)):
        p = parent[k]
        if p >= 0:
            cI[p], ch[p], cm[p] = cI[p] + cI[k], ch[p] + ch[k], cm[p] + cm[k]
            cFn[p], cFf[p] = cFn[p] + cFn[k], cFf[p] + cFf[k]
    cI, ch, cFn, cFf = _barrier((cI, ch, cFn, cFf), q[0, 0])
    bias = jnp.stack([_dot(z[j], cFn[j]) + _dot(Sv[j], cFf[j]) for j in range(n)])
    # CRBA: M_ij = S_i . (I^C_j S_j) for i an ancestor of j (or j itself).
    anc_mask = robot.subtree()  # [i, j]: body j moves with joint i
    armature = rob["armature"]
    M = [[None] * n for _ in range(n)]
    for j in range(n):
        Fw, Fv = inertia_times(cI[j], ch[j], cm[j], z[j], Sv[j])
        for i in range(n):
            if anc_mask[i, j]:
                M[i][j] = M[j][i] = _dot(z[i], Fw) + _dot(Sv[i], Fv)
    zero_b = jnp.zeros_like(q[0])
    for i in range(n):
        M[i][i] = M[i][i] + armature[i]
        for j in range(n):
            if M[i][j] is None:
                M[i][j] = zero_b
    return _barrier((M, bias), q[0, 0])


def step_batched(params: SimParams, state: SimState, goal: jnp.ndarray) -> SimState:
    """``simulator.step`` for B arms at once, batch-last.

    Args:
      params: shared or per-arm (batch-last) parameters, see the module docstring.
      state: ``SimState`` with every leaf (N, B) (see :func:`state_batch_last`).
      goal: (N, B) Goal Position [ticks].
    Returns the next ``SimState``, leaves (N, B).
    """
    robot, dt = params.robot, params.dt
    n = robot.n_joints
    q, qd = state.q, state.qd
    if q.ndim != 2 or q.shape[0] != n:
        raise ValueError(f"state.q has shape {q.shape}; expected ({n}, B) (batch last)")
    sp = jax.tree_util.tree_map(lambda a: _lane(a, 1), params.servo)
    fp = jax.tree_util.tree_map(lambda a: _lane(a, 1), params.friction)
    servo = servo_step(sp, state.servo, goal, q, qd)
    damping = _lane(robot.damping, 1) + fp.viscous
    M, bias = _dynamics(robot, q, qd)
    for i in range(n):
        M[i][i] = M[i][i] + dt * damping[i]
    offset = 0.0 if params.torque_offset is None else _lane(params.torque_offset, 1)
    rhs = servo.torque + offset - damping * qd - bias
    Minv = spd_inverse_rows(M, q.dtype)
    W = [[dt * Minv[r][c] for c in range(n)] for r in range(n)]
    v_free = [qd[r] + sum((W[r][c] * rhs[c] for c in range(n)), start=0.0) for r in range(n)]
    bound = friction_bound(fp, q, qd, servo.torque)
    lo = [-bound[i] for i in range(n)]
    hi = [bound[i] for i in range(n)]
    f = [jnp.clip(state.friction[i], lo[i], hi[i]) for i in range(n)]

    def sweep(_, f):
        f = list(f)
        for i in range(n):
            v_i = v_free[i] + sum(W[i][j] * f[j] for j in range(n))
            f[i] = jnp.clip(f[i] - v_i / W[i][i], lo[i], hi[i])
        return tuple(f)

    f = list(jax.lax.fori_loop(0, params.friction_sweeps, sweep, tuple(f)))
    v = jnp.stack([v_free[i] + sum(W[i][j] * f[j] for j in range(n)) for i in range(n)])
    return SimState(q + dt * v, v, servo, jnp.stack(f))
