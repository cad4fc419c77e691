"""Held objects by name: the paper's test objects and training loads (jaxinertia.sim.scenarios)."""

from __future__ import annotations

from jaxinertia.sim.sampling import HeldObject

__all__ = ["OBJECT_NAMES", "resolve_object"]

#: Names accepted by ``--object``: test objects, training loads, and ``unknown`` (collect
#: only: no ground truth) / ``none`` (virtual robot: empty gripper, same as ``0g``).
OBJECT_NAMES = ("cube", "red", "white", "black", "0g", "50g", "100g", "150g")


def resolve_object(name: str) -> HeldObject | None:
    """The object called ``name``; None for ``unknown``. Raises ValueError otherwise."""
    from jaxinertia.sim import scenarios as sc

    if name == "unknown":
        return None
    if name == "none":
        name = "0g"
    if name in sc.OBJECTS:
        return sc.lbipe_object(name)
    loads = {f"{round(m * 1000)}g": m for m in sc.TRAINING_LOADS_KG}
    if name in loads:
        return sc.training_object(loads[name])
    raise ValueError(f"unknown object {name!r}; known: {', '.join(OBJECT_NAMES)}, unknown")
