"""Plans: where the arm stops to take samples (goals ``q_d`` and approach directions).

A plan is two (S, N) arrays: goals [rad] and directions (+1 / -1 per joint: the joint
approaches its goal from below / above). The simulator (:mod:`jaxinertia.sim`) and the
real arm (:mod:`jaxinertia.hardware`) take the same plans. The workspace is a list of
per-joint ``(lo, hi)`` ranges in degrees, handed in from the arm's record
(:attr:`jaxinertia.arm.Arm.workspace_deg`), so the plans are sized from it, not from four
joints; the robot and the clearance of the collision filter come from the record too.
"""

from __future__ import annotations

import itertools
from typing import NamedTuple

import jax
import numpy as np

from jaxinertia.kinematics import ee_positions
from jaxinertia.robot import Robot

__all__ = [
    "Goals",
    "collides",
    "continuous_plan",
    "planning_plan",
    "random_plan",
    "switching_schedule",
]

_DEG = np.pi / 180.0
Workspace = tuple[tuple[float, float], ...]


class Goals(NamedTuple):
    """A plan: where the arm stops and how each joint approaches the stop."""

    q_d: np.ndarray  # (S, N) goals [rad]
    direction: np.ndarray  # (S, N) +1 / -1: the joint approaches its goal from below / above


def _bounds(workspace: Workspace) -> tuple[np.ndarray, np.ndarray]:
    w = np.asarray(workspace, np.float64)
    return w[:, 0] * _DEG, w[:, 1] * _DEG


def collides(q: np.ndarray, *, clearance: float, robot: Robot) -> np.ndarray:
    """(S,) True where the end effector at goals ``q`` (S, N) [rad] comes closer than
    ``clearance`` [m] to the mounting surface (z = 0 of the base frame)."""
    # A few hundred configurations: the host CPU compiles and runs this in a fraction of
    # the time an accelerator takes to compile it (~0.8 s on an H100).
    cpu = jax.devices("cpu")[0]
    robot, q = jax.device_put((robot, np.asarray(q)), cpu)
    return np.asarray(ee_positions(robot, q))[:, 2] < clearance


def planning_plan(step_deg: float, *, clearance: float, robot: Robot,
                  workspace: Workspace) -> Goals:
    """The planning grid (``step_deg`` over the workspace) minus the configurations that
    collide with the mounting surface (:func:`collides`), x all 2^N direction patterns.

    Returns goals (S, N) [rad] and directions (S, N): 721 x 16 = 11,536 per load for the
    OpenMANIPULATOR-X's record (10 deg), so 46,144 over the four training loads as in the
    paper.
    """
    axes = [np.arange(lo, hi + 1e-9, step_deg) * _DEG for lo, hi in workspace]
    grid = np.array(list(itertools.product(*axes)))
    grid = grid[~collides(grid, clearance=clearance, robot=robot)]
    dirs = np.array(list(itertools.product([1.0, -1.0], repeat=len(workspace))))
    q = np.repeat(grid, len(dirs), axis=0)
    d = np.tile(dirs, (len(grid), 1))
    return Goals(q, d)


def random_plan(n: int, seed: int = 0, *,
                workspace: Workspace) -> Goals:
    """``n`` goals uniform in the workspace with random directions."""
    rng = np.random.default_rng(seed)
    lo, hi = _bounds(workspace)
    return Goals(rng.uniform(lo, hi, (n, len(lo))), rng.choice([-1.0, 1.0], (n, len(lo))))


def continuous_plan(n: int, seed: int = 0, *, step_deg: tuple[float, float] = (0.5, 2.0),
                    workspace: Workspace) -> Goals:
    """A random walk of ``n`` nearby goals in the workspace: every joint moves by
    ``step_deg`` (uniform magnitude, random sign, reflected at the workspace bounds) from
    one goal to the next, so every joint has a defined approach direction."""
    rng = np.random.default_rng(seed)
    lo, hi = _bounds(workspace)
    n_joints = len(lo)
    q = np.empty((n, n_joints))
    q[0] = 0.5 * (lo + hi)
    for i in range(1, n):
        d = rng.uniform(*step_deg, n_joints) * _DEG * rng.choice([-1.0, 1.0], n_joints)
        nxt = q[i - 1] + d
        out = (nxt < lo) | (nxt > hi)
        nxt[out] = q[i - 1][out] - d[out]
        q[i] = nxt
    direction = np.sign(np.diff(q, axis=0, prepend=q[:1] - (hi - lo) * 1e-3))
    return Goals(q, direction)


def switching_schedule(n: int, n_objects: int, every: int) -> np.ndarray:
    """(n,) object index per sample: object k from sample k*every on, cycling."""
    return (np.arange(n) // every) % n_objects
