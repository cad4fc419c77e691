"""jaxinertia: mass and centre of mass of a held object from servo encoder discrepancies.

The library's main names (see docs/architecture.md for the data flow and each module's
job)::

    from jaxinertia import Samples, load_samples, load_regressor, solve_sets, evaluate

They are imported when first used (PEP 562), not with the package: ``import jaxinertia``
(and the command line's ``--help``) does not start JAX, flax or optax. Importing the
package has no side effect: a program of one's own that runs the batched evaluation on a
CPU calls :func:`apply_xla_workarounds` before its first JAX computation (the command line
does).
"""

import importlib

from jaxinertia._xla_workarounds import apply as apply_xla_workarounds  # noqa: F401

__version__ = "0.1.0"

#: Each public name and the module it comes from.
_NAMES = {
    "JaxinertiaError": "errors",
    "ModelPair": "estimation", "estimate_sets": "estimation",
    "evaluate": "evaluation",
    "WLSResult": "identification", "mass_and_com": "identification",
    "solve_sets": "identification", "wls": "identification",
    "ee_jacobian": "kinematics", "ee_pose": "kinematics",
    "forward_kinematics": "kinematics", "gravity_torques": "kinematics",
    "point_jacobian": "kinematics",
    "HeldObject": "objects",
    "Robot": "robot", "load_robot": "robot", "open_manipulator_x": "robot",
    "Samples": "samples", "load_samples": "samples",
    "load_regressor": "statics", "tag_pose": "statics",
}

__all__ = [
    "HeldObject",
    "JaxinertiaError",
    "ModelPair",
    "Robot",
    "Samples",
    "WLSResult",
    "apply_xla_workarounds",
    "ee_jacobian",
    "ee_pose",
    "estimate_sets",
    "evaluate",
    "forward_kinematics",
    "gravity_torques",
    "load_regressor",
    "load_robot",
    "load_samples",
    "mass_and_com",
    "open_manipulator_x",
    "point_jacobian",
    "solve_sets",
    "tag_pose",
    "wls",
]


def __getattr__(name: str):
    if name in _NAMES:
        value = getattr(importlib.import_module(f"jaxinertia.{_NAMES[name]}"), name)
        globals()[name] = value  # once
        return value
    try:  # a submodule used as an attribute (``jaxinertia.samples``) before its import
        return importlib.import_module(f"jaxinertia.{name}")
    except ModuleNotFoundError:
        raise AttributeError(f"module 'jaxinertia' has no attribute {name!r}") from None


def __dir__():
    return sorted(set(globals()) | set(_NAMES))
