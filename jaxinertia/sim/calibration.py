"""Calibration of the simulated arm to the real OpenMANIPULATOR-X data (lbipe).

Link gravity: the real free-motion torques ``tau_g`` are a static gravity model on the
URDF kinematics with other link masses and first moments (lbipe README). The 8
identifiable base parameters are fitted to them and the simulated arm gets the link
parameters closest to the URDF's that reproduce them exactly; the result ships as
``data/open_manipulator_x_sim.json``.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from jaxinertia.lbipe import find_layout, load_test_file
from jaxinertia.robot import Robot, data_path
from jaxinertia.statics import identify_gravity_base_parameters, robot_with_gravity_parameters

__all__ = ["SIM_CALIBRATION_FILE", "apply_calibration", "fit_link_gravity", "load_calibration"]

SIM_CALIBRATION_FILE = "open_manipulator_x_sim.json"


def fit_link_gravity(robot: Robot, lbipe_dir: str | os.PathLike) -> tuple[Robot, dict]:
    """Fits link masses/first moments to every real test file's ``tau_g``."""
    layout = find_layout(lbipe_dir)
    data = [load_test_file(p, n) for n, p in layout.test_files.items()]
    q = np.concatenate([d.q for d in data])
    tau_g = np.concatenate([d.tau_g for d in data])
    theta, base = identify_gravity_base_parameters(robot, jnp.asarray(q), tau_g)
    fitted = robot_with_gravity_parameters(robot, theta, base)
    info = {
        "source": sorted(layout.test_files),
        "n_samples": int(len(q)),
        "link_mass": np.asarray(fitted.mass).tolist(),
        "link_com": np.asarray(fitted.com).tolist(),
    }
    return fitted, info


def load_calibration(path: str | os.PathLike | None = None) -> dict:
    path = Path(path) if path else data_path(SIM_CALIBRATION_FILE)
    return json.loads(Path(path).read_text())


def apply_calibration(robot: Robot, calibration: dict) -> Robot:
    g = calibration["link_gravity"]
    return robot.replace(mass=jnp.asarray(g["link_mass"], robot.mass.dtype),
                         com=jnp.asarray(g["link_com"], robot.com.dtype))
