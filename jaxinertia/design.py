"""The most informative poses: D-optimal choice of where the arm stops.

For independent torque errors of level ``sigma_j`` per joint the covariance of the WLS
estimate of ``x = [m, m p]`` is ``(sum_s A_s^T W A_s)^-1`` with ``W = diag(w_j)``,
``w_j = 1 / sigma_j^2`` (unit weights: the T estimate's identity weights). A D-optimal set
of n poses maximises ``log det sum_s A_s^T W A_s``: the volume of the confidence ellipsoid
of x shrinks the most. The criterion does not depend on where the tag (the COM's
reference point) sits on the end effector nor how it is turned: moving or rotating the
reference point is ``x' = T x`` with ``det T = 1``. Nor does it depend on the units of x
(column scaling adds a constant), so the candidates' regressors need only the arm.

:func:`select` is greedy forward selection (each step adds the candidate with the largest
``log det``) followed by Fedorov exchanges (swap a chosen pose for a candidate while that
raises ``log det``), every step one batched evaluation of 4 x 4 determinants in one jitted
program; :func:`select_pools` vmaps it over many candidate pools (the experiments' 1000
repeats). The approach directions do not enter A; :func:`balance_directions` picks them so
that an error of fixed size whose sign follows the approach direction on each joint
(unmodelled friction) cancels in x to first order.

:func:`plan_poses` plans from the collision-free planning grid (:mod:`jaxinertia.plans`);
:func:`save_plan` / :func:`load_plan` write and read the JSON plan (``q_d`` (n, N) [rad],
``direction`` (n, N) of +1 / -1) that ``simulate --plan`` / ``collect --plan`` can take.
"""

from __future__ import annotations

import json
import os
from functools import partial
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxinertia.errors import FileFormatError, UsageError
from jaxinertia.fileio import write_text
from jaxinertia.linalg import gram, logdet_spd
from jaxinertia.plans import Goals, planning_plan
from jaxinertia.robot import Robot
from jaxinertia.statics import load_regressor_fixed_tag

__all__ = [
    "PLAN_FORMAT",
    "Plan",
    "DEFAULT_MARGIN_DEG",
    "arm_plan_kwargs",
    "balance_directions",
    "inner_workspace",
    "information",
    "load_plan",
    "plan_poses",
    "random_logdets",
    "regressors",
    "save_plan",
    "select",
    "select_pools",
    "subset_logdets",
]

PLAN_FORMAT = "jaxinertia-plan"
PLAN_FORMAT_VERSION = 1

#: Ridge on the column-scaled information matrix while fewer poses than unknowns are
#: chosen: it makes greedy selection first raise the rank, then the volume.
RIDGE = 1e-8


def information(A: jnp.ndarray, joint_weights: jnp.ndarray | None = None) -> jnp.ndarray:
    """Per-sample information ``A_s^T W A_s`` (S, P, P) of regressors A (S, N, P);
    ``joint_weights`` (N,) (None: ones)."""
    A = jnp.asarray(A)
    return gram(A, None if joint_weights is None else jnp.asarray(joint_weights, A.dtype))


def _scaled(C: jnp.ndarray) -> jnp.ndarray:
    """Candidates' information scaled to unit mean diagonal (the ridge's reference)."""
    d = jnp.sqrt(jnp.maximum(jnp.mean(jnp.diagonal(C, axis1=-2, axis2=-1), axis=0), 1e-300))
    return C / (d[:, None] * d[None, :])


def _greedy_exchange(C: jnp.ndarray, n: int, max_exchanges: int):
    """Greedy forward selection of n of the (scaled) candidates C (S, P, P), then Fedorov
    exchanges until none raises ``log det`` (or ``max_exchanges``). Returns (indices (n,),
    log det, exchanges made)."""
    S, P, _ = C.shape
    ridge = RIDGE * jnp.eye(P, dtype=C.dtype)

    def add(t, carry):
        G, chosen, idx = carry
        scores = jnp.where(chosen, -jnp.inf, logdet_spd(G[None] + C))
        i = jnp.argmax(scores)
        return G + C[i], chosen.at[i].set(True), idx.at[t].set(i.astype(jnp.int32))

    G, chosen, idx = jax.lax.fori_loop(
        0, n, add, (ridge, jnp.zeros(S, bool), jnp.zeros(n, jnp.int32)))

    def gain(state):
        G, chosen, idx, _, _ = state
        without = G[None] - C[idx]  # (n, P, P)
        scores = logdet_spd(without[:, None] + C[None])  # (n, S)
        scores = jnp.where(chosen[None], -jnp.inf, scores)
        flat = jnp.argmax(scores)
        i, s = (flat // S).astype(jnp.int32), (flat % S).astype(jnp.int32)
        return scores[i, s] - logdet_spd(G), i, s

    def cond(state):
        return (state[3] < max_exchanges) & (state[4] > 1e-9)

    def body(state):
        G, chosen, idx, k, _ = state
        g, i, s = gain(state)
        take = g > 1e-9
        old = idx[i]
        G = jnp.where(take, G - C[old] + C[s], G)
        chosen = jnp.where(take, chosen.at[old].set(False).at[s].set(True), chosen)
        idx = jnp.where(take, idx.at[i].set(s), idx)
        return G, chosen, idx, k + take.astype(jnp.int32), jnp.where(take, g, 0.0)

    G, _, idx, k, _ = jax.lax.while_loop(
        cond, body, (G, chosen, idx, jnp.int32(0), jnp.asarray(jnp.inf, C.dtype)))
    return idx, logdet_spd(G - ridge), k


@partial(jax.jit, static_argnames=("n", "max_exchanges"))
def select(C: jnp.ndarray, n: int, max_exchanges: int = 200):
    """D-optimal choice of n of S candidates with information C (S, P, P) (see
    :func:`information`): ``(indices (n,), log det, exchanges)``; the log det is of the
    information scaled to the candidates' unit mean diagonal (compare only within one
    candidate set)."""
    if n > C.shape[0]:
        raise UsageError(f"cannot choose {n} of {C.shape[0]} candidates")
    return _greedy_exchange(_scaled(C), n, max_exchanges)


@partial(jax.jit, static_argnames=("n", "max_exchanges"))
def select_pools(C: jnp.ndarray, pools: jnp.ndarray, n: int, max_exchanges: int = 200):
    """:func:`select` in each of R candidate pools (R, Q) of the candidates C (S, P, P), in
    one program: ``(indices into S (R, n), log det (R,), exchanges (R,))``. The pools'
    scaling is the whole candidate set's, so their log dets compare."""
    Cs = _scaled(C)
    # lax.map, not vmap: the exchange loop of one pool is (n, Q) determinants; all R at once
    # would hold R times that.
    idx, ld, k = jax.lax.map(lambda pool: _greedy_exchange(Cs[pool], n, max_exchanges), pools)
    return jnp.take_along_axis(pools, idx, axis=1), ld, k


def random_logdets(C: jnp.ndarray, n: int, n_draws: int = 1000, seed: int = 0) -> np.ndarray:
    """(n_draws,) log det (same scaling as :func:`select`) of uniformly random n-subsets
    of the candidates: the reference a plan is measured against."""
    rng = np.random.default_rng(seed)
    S = C.shape[0]
    subsets = np.stack([rng.choice(S, n, replace=False) for _ in range(n_draws)])
    return np.asarray(subset_logdets(jnp.asarray(C), jnp.asarray(subsets)))


@jax.jit
def subset_logdets(C: jnp.ndarray, subsets: jnp.ndarray) -> jnp.ndarray:
    """(R,) log det of the candidates' subsets (R, n), scaled as :func:`select` scales."""
    return logdet_spd(_scaled(C)[subsets].sum(axis=1))


@jax.jit
def balance_directions(A: jnp.ndarray, joint_weights: jnp.ndarray | None = None) -> jnp.ndarray:
    """(n, N) approach directions for the chosen poses' regressors A (n, N, P): pose by
    pose, each joint takes the sign that keeps ``sum_s d_sj w_j A_s[j]`` smallest, so an
    error ``d_sj f_j`` (friction-like: its sign follows the approach) cancels in x."""
    n, N, P = A.shape
    w = jnp.ones(N, A.dtype) if joint_weights is None else jnp.asarray(joint_weights, A.dtype)
    rows = A * w[None, :, None]

    def step(u, a):
        d = jnp.where(jnp.einsum("np,np->n", u, a) > 0, -1.0, 1.0).astype(A.dtype)
        return u + d[:, None] * a, d

    _, d = jax.lax.scan(step, jnp.zeros((N, P), A.dtype), rows)
    return d


@jax.jit
def _regressors(robot, q, R_ee_tag, p_ee_tag):
    return jax.vmap(lambda qi: load_regressor_fixed_tag(robot, qi, R_ee_tag, p_ee_tag))(q)


def regressors(q: np.ndarray, *, robot: Robot, tag) -> np.ndarray:
    """(S, N, 4) load regressors of ``robot`` at goals q (S, N) [rad], the tag at
    ``tag = (R, p)`` in the end-effector frame (the arm record's ``tag_in_ee``; any tag
    gives the same plan, see the module's docstring)."""
    dtype = jnp.float64 if jax.config.jax_enable_x64 else jnp.float32
    R, p = (jnp.asarray(t, dtype) for t in tag)
    return np.asarray(_regressors(robot.astype(dtype), jnp.asarray(q, dtype), R, p))


class Plan(NamedTuple):
    """n planned poses."""

    q_d: np.ndarray  # (n, N) goals [rad]
    direction: np.ndarray  # (n, N) approach directions, +1 / -1
    A: np.ndarray  # (n, N, 4) regressors at the goals (tag as planned)
    logdet: float  # log det of the plan's scaled information
    random_logdet: np.ndarray  # (draws,) the same for random n-subsets of the grid
    n_candidates: int  # collision-free grid configurations
    exchanges: int


#: Default distance of planned poses from the workspace limits [deg]. D-optimal poses sit at
#: the limits, where the torque models (trained on poses uniform in the workspace) are least
#: accurate: on the simulator (1000 repeats) 16 grid poses at the limits gave a T-A mass /
#: COM error of 9.4 g / 27.6 mm against 8.0 g / 17.5 mm for 16 random poses, and 10 deg
#: inside them 6.0 g / 11.2 mm (docs/results.md, "The most informative poses"), with the
#: quick run's models. Models trained on the planning grid (which includes the limits) are
#: accurate there: with the full-scale ones the limits gave 3.0 g / 9.7 mm, 10 deg inside
#: 4.0 g / 9.0 mm; ``--margin-deg 0`` suits such models.
DEFAULT_MARGIN_DEG = 10.0


def inner_workspace(workspace, margin_deg: float):
    """The workspace shrunk by ``margin_deg`` at both ends of every joint range."""
    inner = tuple((lo + margin_deg, hi - margin_deg) for lo, hi in workspace)
    if any(lo >= hi for lo, hi in inner):
        raise UsageError(f"a margin of {margin_deg:g} deg leaves no room in the workspace "
                         f"{[tuple(w) for w in workspace]} (deg)")
    return inner


def plan_poses(n: int, *, robot: Robot, step_deg: float, workspace, clearance: float, tag,
               margin_deg: float = DEFAULT_MARGIN_DEG, joint_weights=None,
               n_random: int = 1000, seed: int = 0) -> Plan:
    """n D-optimal poses of ``robot`` from the collision-free planning grid (``step_deg``
    over ``workspace`` shrunk by ``margin_deg``; ``clearance`` and the ``tag`` mount: the
    arm record's values, :func:`arm_plan_kwargs`), approach directions balanced
    (:func:`balance_directions`)."""
    if len(workspace) != robot.n_joints:
        raise UsageError(f"the workspace has {len(workspace)} joint ranges, the robot "
                         f"{robot.name!r} {robot.n_joints} joints")
    q, _ = planning_plan(step_deg, clearance=clearance, robot=robot,
                         workspace=inner_workspace(workspace, margin_deg))
    q = np.unique(q, axis=0)  # the directions repeat each configuration
    if n > len(q):
        raise UsageError(f"`n` {n}: the grid has only {len(q)} collision-free configurations "
                         "(use a finer `step_deg`)")
    A = regressors(q, robot=robot, tag=tag)
    C = information(A, joint_weights)
    idx, ld, k = select(C, n)
    idx = np.asarray(idx)
    direction = np.asarray(balance_directions(jnp.asarray(A[idx]), joint_weights))
    return Plan(q[idx], direction, A[idx], float(ld),
                random_logdets(C, n, n_random, seed), len(q), int(k))


def arm_plan_kwargs(arm, robot: Robot | None = None) -> dict:
    """:func:`plan_poses`'s arm-specific arguments from an :class:`jaxinertia.arm.Arm`
    record (``robot``: its bare robot, default ``arm.robot()``)."""
    return dict(robot=arm.robot() if robot is None else robot, step_deg=arm.planning_step_deg,
                workspace=arm.workspace_deg, clearance=arm.mount_clearance_m,
                tag=arm.tag_in_ee)


def save_plan(path: str | os.PathLike, plan: Plan, *, robot: str, extra: dict | None = None,
              ) -> Path:
    """The plan as JSON (atomically): ``q_d`` [rad] and ``direction`` per pose."""
    doc = {"format": PLAN_FORMAT, "format_version": PLAN_FORMAT_VERSION, "robot": robot,
           "n": int(len(plan.q_d)), "q_d": np.asarray(plan.q_d).tolist(),
           "direction": np.asarray(plan.direction).astype(int).tolist(),
           "q_d_deg": np.round(np.degrees(plan.q_d), 6).tolist(),
           "criterion": {"logdet": plan.logdet,
                         "random_logdet_median": float(np.median(plan.random_logdet)),
                         "random_logdet_max": float(np.max(plan.random_logdet)),
                         "n_random": int(len(plan.random_logdet)),
                         "n_candidates": plan.n_candidates, "exchanges": plan.exchanges},
           **(extra or {})}
    return write_text(path, json.dumps(doc, indent=2) + "\n")


def load_plan(path: str | os.PathLike, *, arm: str | None = None) -> Goals:
    """A plan file -> :class:`~jaxinertia.plans.Goals` (``q_d`` (n, N) [rad], ``direction``
    (n, N) of +1 / -1), checked;
    ``arm``: the arm it is for (a plan made for another arm is refused)."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except OSError as e:
        raise FileFormatError(path, None, f"unreadable ({e.strerror or e})") from None
    except ValueError as e:  # not UTF-8 or not JSON
        raise FileFormatError(path, None, f"not JSON ({e})") from None
    if not isinstance(doc, dict) or doc.get("format") != PLAN_FORMAT:
        raise FileFormatError(path, "format", f"not a {PLAN_FORMAT} file")
    if doc.get("format_version") != PLAN_FORMAT_VERSION:
        raise FileFormatError(path, "format_version", f"{doc.get('format_version')!r}; this "
                              f"version reads {PLAN_FORMAT_VERSION}")
    planned_for = doc.get("arm") or doc.get("robot")
    if arm is not None and planned_for is not None and planned_for != arm:
        raise UsageError(f"{path}: a plan for the arm {planned_for!r}, not for {arm!r} "
                         f"(plan poses for it with `arm` {arm})")
    out = []
    for key in ("q_d", "direction"):
        try:
            a = np.asarray(doc.get(key), np.float64)
        except (TypeError, ValueError):
            raise FileFormatError(path, key, "not a numeric table") from None
        if a.ndim != 2 or a.shape[0] == 0 or a.shape[1] == 0:
            raise FileFormatError(path, key, f"must be (n, joints), got shape {a.shape}")
        if not np.all(np.isfinite(a)):
            raise FileFormatError(path, key, "non-finite values")
        out.append(a)
    q_d, direction = out
    if q_d.shape != direction.shape:
        raise FileFormatError(path, "direction", f"shape {direction.shape} differs from q_d's "
                              f"{q_d.shape}")
    if not np.all(np.abs(direction) == 1):
        raise FileFormatError(path, "direction", "entries must be +1 or -1")
    return Goals(q_d, direction)
