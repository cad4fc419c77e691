"""The paper's data-collection scenarios and objects for the simulated OpenMANIPULATOR-X."""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np

from jaxinertia.kinematics import ee_pose
from jaxinertia.lbipe import BOUNDING_BOX_DIAGONALS
from jaxinertia.sim.sampling import HeldObject

__all__ = [
    "OBJECTS",
    "TAG_IN_EE",
    "TRAINING_LOADS_KG",
    "MOUNT_CLEARANCE_M",
    "WORKSPACE_DEG",
    "collides",
    "lbipe_object",
    "make_object",
    "planning_plan",
    "random_plan",
    "training_object",
]

_DEG = np.pi / 180.0

#: Tag frame in the end-effector frame: the offset fitted on the real cube data
#: (README: about [9.3, -0.4, 23.2] mm), orientation identity.
TAG_IN_EE = (np.eye(3), np.array([0.00925, -0.00043, 0.0232]))

#: Training loads of the paper [kg] (0 = empty gripper).
TRAINING_LOADS_KG = (0.0, 0.050, 0.100, 0.150)

#: Test objects: masses from the lbipe README; COMs (tag frame) from the real data's x
#: for cube and white; red and black are not in the released data, so their COMs are
#: assumed on the tag axis between cube's and white's. Bounding-box diagonals as released.
OBJECTS = {
    "cube": (0.04150, (0.0, 0.0, -0.0201)),
    "red": (0.06037, (0.0, 0.002, -0.0198)),  # COM assumed
    "white": (0.08809, (0.0, 0.004, -0.0195)),
    "black": (0.13892, (0.0, 0.003, -0.0230)),  # COM assumed
}


def make_object(mass: float, com_tag, *, l_max: float = 0.07) -> HeldObject:
    """A held object as a uniform solid cube of diagonal ``l_max`` (for its inertia)."""
    side = l_max / np.sqrt(3.0)
    inertia = mass * side**2 / 6.0 * np.eye(3)
    R, p = TAG_IN_EE
    return HeldObject(jnp.asarray(mass, float), jnp.asarray(com_tag, float),
                      jnp.asarray(R), jnp.asarray(p), jnp.asarray(inertia))


def lbipe_object(name: str) -> HeldObject:
    mass, com = OBJECTS[name]
    return make_object(mass, com, l_max=BOUNDING_BOX_DIAGONALS[name])


def training_object(mass: float) -> HeldObject:
    """Training loads: the load's COM on the tag axis 20 mm below the tag (as the cube)."""
    return make_object(mass, (0.0, 0.0, -0.020))


WORKSPACE_DEG = ((-30.0, 30.0), (-50.0, -10.0), (10.0, 50.0), (-20.0, 20.0))


#: Clearance of the end-effector point from the mounting surface (the plane z = 0 of the
#: base frame, which is vertical on the paper's wall-mounted arm) below which a planning
#: configuration counts as colliding: gripper and held object (up to ~70 mm) need it.
#: Any value between 97.8 and 102.5 mm removes the same 22 of the 125 (q2, q3, q4) grid
#: points and leaves 721 configurations, i.e. the paper's 46,144 planning samples.
MOUNT_CLEARANCE_M = 0.10


def collides(q: np.ndarray, *, clearance: float = MOUNT_CLEARANCE_M, robot=None) -> np.ndarray:
    """(S,) True where the end effector at goals ``q`` (S, 4) [rad] comes closer than
    ``clearance`` [m] to the mounting surface (z = 0 of the base frame)."""
    from jaxinertia.robot import open_manipulator_x

    robot = open_manipulator_x() if robot is None else robot
    # A few hundred configurations: the host CPU compiles and runs this in a fraction of
    # the time an accelerator takes to compile it (~0.8 s on an H100).
    cpu = jax.devices("cpu")[0]
    robot, q = jax.device_put((robot, np.asarray(q)), cpu)
    return np.asarray(_ee_positions(robot, q))[:, 2] < clearance


@jax.jit
def _ee_positions(robot, q):
    """(S, 3) end-effector positions at goals (S, N), in one compiled call."""
    return jax.vmap(lambda qi: ee_pose(robot, qi)[1])(q)


def planning_plan(step_deg: float = 10.0, *, clearance: float = MOUNT_CLEARANCE_M,
                  robot=None) -> tuple[np.ndarray, np.ndarray]:
    """The planning grid (10 deg over the authors' workspace) minus the configurations
    that collide with the mounting surface (:func:`collides`), x all 16 direction patterns.

    Returns goals (S, 4) [rad] and directions (S, 4): 721 x 16 = 11,536 per load at the
    defaults, so 46,144 over the four training loads as in the paper.
    """
    axes = [np.arange(lo, hi + 1e-9, step_deg) * _DEG for lo, hi in WORKSPACE_DEG]
    grid = np.array(list(itertools.product(*axes)))
    grid = grid[~collides(grid, clearance=clearance, robot=robot)]
    dirs = np.array(list(itertools.product([1.0, -1.0], repeat=4)))
    q = np.repeat(grid, len(dirs), axis=0)
    d = np.tile(dirs, (len(grid), 1))
    return q, d


def random_plan(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """n goals uniform in the workspace with random directions."""
    rng = np.random.default_rng(seed)
    lo = np.array([w[0] for w in WORKSPACE_DEG]) * _DEG
    hi = np.array([w[1] for w in WORKSPACE_DEG]) * _DEG
    return rng.uniform(lo, hi, (n, 4)), rng.choice([-1.0, 1.0], (n, 4))
