"""jaxinertia: mass and centre of mass of a held object from servo encoder discrepancies.

The library's main names (see docs/architecture.md for the data flow and each module's
job)::

    from jaxinertia import Samples, load_samples, load_regressor, solve_sets, evaluate

Importing the package has no side effect: a program of one's own that runs the batched
evaluation on a CPU calls :func:`apply_xla_workarounds` before its first JAX computation
(the command line does).
"""

from jaxinertia._xla_workarounds import apply as apply_xla_workarounds
from jaxinertia.errors import JaxinertiaError
from jaxinertia.estimation import ModelPair, estimate_sets
from jaxinertia.evaluation import evaluate
from jaxinertia.identification import WLSResult, mass_and_com, solve_sets, wls
from jaxinertia.kinematics import (
    ee_jacobian,
    ee_pose,
    forward_kinematics,
    gravity_torques,
    point_jacobian,
)
from jaxinertia.objects import HeldObject
from jaxinertia.robot import Robot, load_robot, open_manipulator_x
from jaxinertia.samples import Samples, load_samples
from jaxinertia.statics import load_regressor, tag_pose

__version__ = "0.1.0"

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
