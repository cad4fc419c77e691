"""jaxinertia: mass and centre of mass of a held object from servo encoder discrepancies.

The core is importable from the top level::

    from jaxinertia import open_manipulator_x, load_regressor, solve_sets, mass_and_com
"""

from jaxinertia import _xla_workarounds

_xla_workarounds.apply()  # before JAX creates its CPU backend

from jaxinertia.identification import WLSResult, mass_and_com, solve_sets, wls  # noqa: E402
from jaxinertia.kinematics import (  # noqa: E402
    ee_jacobian,
    ee_pose,
    forward_kinematics,
    gravity_torques,
    point_jacobian,
)
from jaxinertia.robot import Robot, load_robot, open_manipulator_x  # noqa: E402
from jaxinertia.statics import load_regressor, tag_pose  # noqa: E402

__version__ = "0.1.0"

__all__ = [
    "Robot",
    "WLSResult",
    "ee_jacobian",
    "ee_pose",
    "forward_kinematics",
    "gravity_torques",
    "load_regressor",
    "load_robot",
    "mass_and_com",
    "open_manipulator_x",
    "point_jacobian",
    "solve_sets",
    "tag_pose",
    "wls",
]
