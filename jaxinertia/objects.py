"""Held objects: the paper's test objects and training loads, by name, in one place.

An object is a rigid body held with an AprilTag frame fixed in the end-effector frame; the
identification target is ``x = [m, m * p_tag]`` (COM ``p_tag`` in the tag frame). Names
anywhere in the library (``--object``, ``--objects``, sample-file metadata) go through
:func:`resolve`. A new object goes into :data:`TEST_OBJECTS` (mass, COM, bounding-box
diagonal) or is passed as a training load like ``75g``.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxinertia.errors import UsageError

__all__ = [
    "EMPTY",
    "HeldObject",
    "TEST_OBJECTS",
    "TRAINING_LOADS_KG",
    "TestObject",
    "bounding_box_diagonal",
    "known_names",
    "load_name",
    "make_object",
    "resolve",
    "paper_object",
    "training_object",
]


@struct.dataclass
class HeldObject:
    """A rigid object held with an AprilTag frame fixed in the end-effector frame."""

    mass: jnp.ndarray  # [kg]
    com_tag: jnp.ndarray  # (3,) COM in the tag frame [m]
    R_ee_tag: jnp.ndarray  # (3, 3) tag orientation in the end-effector frame
    p_ee_tag: jnp.ndarray  # (3,) tag origin in the end-effector frame [m]
    inertia: jnp.ndarray  # (3, 3) about the COM, tag axes [kg m^2]

    @property
    def x(self) -> jnp.ndarray:
        """The identification target ``[m, m * p_tag]``."""
        return jnp.concatenate([self.mass[None], self.mass * self.com_tag])

    def com_ee(self) -> jnp.ndarray:
        return self.R_ee_tag @ self.com_tag + self.p_ee_tag


class TestObject(NamedTuple):
    mass: float  # [kg], lbipe README
    com_tag: tuple[float, float, float]  # [m]
    diagonal: float  # bounding-box diagonal [m], the COM error's normaliser


#: The paper's test objects. Masses from the lbipe README; COMs (tag frame) from the real
#: data's x for cube and white; red and black are not in the released data, so their COMs
#: are assumed on the tag axis between cube's and white's. Bounding-box diagonals as
#: released with the data.
TEST_OBJECTS: dict[str, TestObject] = {
    "cube": TestObject(0.04150, (0.0, 0.0, -0.0201), 0.0692820),
    "red": TestObject(0.06037, (0.0, 0.002, -0.0198), 0.0665808),  # COM assumed
    "white": TestObject(0.08809, (0.0, 0.004, -0.0195), 0.0755513),
    "black": TestObject(0.13892, (0.0, 0.003, -0.0230), 0.0851880),  # COM assumed
}

#: Training loads of the paper [kg] (0 = empty gripper).
TRAINING_LOADS_KG = (0.0, 0.050, 0.100, 0.150)

#: The empty gripper's name; ``none`` and ``0g`` are accepted for it.
EMPTY = "empty"
_EMPTY_ALIASES = ("empty", "none", "0g")


def make_object(mass: float, com_tag, *, tag_in_ee, l_max: float = 0.07) -> HeldObject:
    """A held object as a uniform solid cube of diagonal ``l_max`` (for its inertia), its
    tag mounted at ``tag_in_ee`` = (R, p) in the end-effector frame (the arm record's
    :attr:`~jaxinertia.arm.Arm.tag_in_ee`)."""
    side = l_max / np.sqrt(3.0)
    inertia = mass * side**2 / 6.0 * np.eye(3)
    R, p = tag_in_ee
    return HeldObject(jnp.asarray(mass, float), jnp.asarray(com_tag, float),
                      jnp.asarray(R), jnp.asarray(p), jnp.asarray(inertia))


def paper_object(name: str, *, tag_in_ee) -> HeldObject:
    """One of :data:`TEST_OBJECTS` by name."""
    t = TEST_OBJECTS[name]
    return make_object(t.mass, t.com_tag, l_max=t.diagonal, tag_in_ee=tag_in_ee)


def training_object(mass: float, *, tag_in_ee) -> HeldObject:
    """A training load: its COM on the tag axis 20 mm below the tag (as the cube's)."""
    return make_object(mass, (0.0, 0.0, -0.020), tag_in_ee=tag_in_ee)


def load_name(mass: float) -> str:
    """The name of a training load: ``0g``, ``50g``, ..."""
    return f"{round(mass * 1000)}g"


def _load_mass(name: str) -> float | None:
    if name in _EMPTY_ALIASES:
        return 0.0
    if name.endswith("g") and name[:-1].isdigit():
        return int(name[:-1]) / 1000.0
    return None


def known_names() -> list[str]:
    """Names :func:`resolve` accepts, for messages."""
    return [*TEST_OBJECTS, EMPTY, *(load_name(m) for m in TRAINING_LOADS_KG[1:]), "<N>g"]


def resolve(name: str, *, tag_in_ee) -> HeldObject:
    """The object called ``name``: a test object, ``empty`` (or ``none``, ``0g``), or a
    load of N grams written ``Ng``, its tag at ``tag_in_ee`` (the arm's mount). Raises
    :class:`UsageError` naming the known ones."""
    if name in TEST_OBJECTS:
        return paper_object(name, tag_in_ee=tag_in_ee)
    mass = _load_mass(name)
    if mass is not None:
        return training_object(mass, tag_in_ee=tag_in_ee)
    raise UsageError(f"unknown object {name!r}; known: {', '.join(known_names())}")


def bounding_box_diagonal(name: str, overrides: dict[str, float] | None = None) -> float | None:
    """The COM error normaliser of object ``name`` [m]; None when it has none."""
    if overrides and name in overrides:
        return float(overrides[name])
    t = TEST_OBJECTS.get(name)
    return None if t is None else t.diagonal
