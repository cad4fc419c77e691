"""The simulated arm's parameters: the default fitted to the real arm, a simulator-fit
file's servo, friction and armature values applied, and the parameters as plain data.

``default_sim_params`` reads the simulator-fit file that ``jaxinertia calibrate`` writes
(:mod:`jaxinertia.sim.real_fit` fits it; ``--calibration FILE`` on the command line); the
arm's constants and the file's link gravity come from :mod:`jaxinertia.open_manipulator_x`.
Every per-joint array is sized from the robot (``robot.n_joints``).
"""

from __future__ import annotations

import os

import jax.numpy as jnp
import numpy as np

from jaxinertia.arm import Arm
from jaxinertia.errors import ConfigError, UsageError
from jaxinertia.open_manipulator_x import ARM as OMX_ARM
from jaxinertia.open_manipulator_x import (
    DEFAULT_ARMATURE,
    SIM_FIT_FILE,
    load_sim_fit,
    sim_fit_robot,
)
from jaxinertia.robot import Robot, open_manipulator_x
from jaxinertia.sim.friction import FrictionParams
from jaxinertia.sim.servo import ServoParams
from jaxinertia.sim.simulator import SimParams

__all__ = ["apply_servo_friction", "arm_sim_params", "datasheet_sim_params",
           "default_sim_params", "params_to_dict", "session_params"]


def default_sim_params(sim_fit_file: str | os.PathLike | None = None) -> SimParams:
    """The simulated OpenMANIPULATOR-X as fitted to the real arm (default: the shipped
    ``data/open_manipulator_x_sim.json``: link gravity, servo and friction), falling back
    to datasheet servos and default friction where the file has no servo fit."""
    fit = load_sim_fit(sim_fit_file)
    where = sim_fit_file or SIM_FIT_FILE
    try:
        robot = sim_fit_robot(fit)
        n = robot.n_joints
        params = SimParams(robot, ServoParams.xm430_w350(n), FrictionParams.create(n))
        params = apply_servo_friction(params, fit)
    except (KeyError, TypeError, ValueError) as e:  # a field missing or of the wrong shape
        raise ConfigError(where, None, f"not a usable calibration ({type(e).__name__}: "
                          f"{e})") from None
    for name, leaf in (("servo", params.servo), ("friction", params.friction)):
        for k, v in leaf.__dict__.items():
            if np.shape(v) != (n,) or not np.all(np.isfinite(np.asarray(v, np.float64))):
                raise ConfigError(where, f"servo_friction.{name}.{k}",
                                  f"must be {n} finite values, got {np.asarray(v).tolist()}")
    return params


def datasheet_sim_params(robot: Robot | None = None) -> SimParams:
    """The arm before any simulator fit: the description's link parameters (the embedded
    OpenMANIPULATOR-X by default), the default armature, datasheet XM430 servos and default
    friction; the start of a simulator fit that must not see the shipped one (a held-out
    fold)."""
    robot = open_manipulator_x() if robot is None else robot
    n = robot.n_joints
    robot = robot.replace(armature=jnp.full(n, DEFAULT_ARMATURE, robot.mass.dtype))
    return SimParams(robot, ServoParams.xm430_w350(n), FrictionParams.create(n))


def arm_sim_params(arm: Arm | None = None,
                   sim_fit_file: str | os.PathLike | None = None) -> SimParams:
    """The simulated ``arm`` (an :class:`jaxinertia.arm.Arm`; default the
    OpenMANIPULATOR-X), its motion timing and pre-position from the record.

    An arm with a simulator fit (``sim_fit_file``, else the record's shipped one) gets
    :func:`default_sim_params` of it (the OpenMANIPULATOR-X: exactly what it always got);
    one without is simulated from its description's links and its servos' datasheet
    values (:meth:`ServoParams.from_model`, the record's gain overrides; each servo model's
    friction, else the simulator's defaults)."""
    arm = OMX_ARM if arm is None else arm
    if sim_fit_file is not None or arm.sim_fit_file is not None:
        params = default_sim_params(sim_fit_file)
        if params.robot.name != arm.name:
            raise ConfigError(sim_fit_file or arm.sim_fit_file, None,
                              f"calibrates {params.robot.name!r}, not the arm {arm.name!r}")
    else:
        robot = arm.robot()
        n = robot.n_joints
        robot = robot.replace(armature=jnp.full(n, arm.armature, robot.mass.dtype))
        models = arm.servo_models
        gains = [g or m.gains for g, m in zip(arm.gains or (None,) * n, models)]
        servo = ServoParams.from_model([m.replace_gains(g) for m, g in zip(models, gains)], n)
        keys = sorted({k for m in models for k in m.friction})
        base = FrictionParams.create(1)
        friction = {k: [m.friction.get(k, float(getattr(base, k)[0])) for m in models]
                    for k in keys}
        # What each servo reports (the XL430: Present Load, no current-based torque).
        params = SimParams(robot, servo, FrictionParams.create(n, **friction),
                           current_lsb=jnp.asarray([m.sensed_lsb if m.has_current_sensor
                                                    else m.sensed_lsb * m.stall_current
                                                    for m in models]),
                           current_torque_constant=jnp.asarray(
                               [m.torque_constant if m.has_current_sensor else np.nan
                                for m in models]))
    t = arm.timing
    return params.replace(profile_velocity=t.profile_velocity,
                          profile_acceleration=t.profile_acceleration,
                          hold_time=t.settle_time, timeout=t.move_timeout,
                          pre_position=arm.pre_position)


def apply_servo_friction(params: SimParams, fit: dict) -> SimParams:
    """Sets the servo, friction and armature values of a simulator-fit file, where present."""
    c = fit.get("servo_friction")
    if not c:
        return params
    n = params.robot.n_joints
    robot = params.robot.replace(armature=jnp.asarray(c["armature"]))
    offset = c.get("torque_offset")
    return params.replace(robot=robot, servo=ServoParams.xm430_w350(n, **c["servo"]),
                          friction=FrictionParams.create(n, **c["friction"]),
                          torque_offset=None if offset is None else jnp.asarray(offset))


def session_params(params: SimParams, fit: dict, name: str) -> SimParams:
    """``params`` (a simulator fit's common servo) in the fit's recording session ``name``
    (``calibrate --sessions``: the file's ``sessions.per_session``): each joint's P gain
    times the session's electrical term, its torque constant times its torque term."""
    per = {p["name"]: p for p in (fit.get("sessions") or {}).get("per_session", [])}
    if name not in per:
        raise UsageError(f"`name` {name!r}: the simulator fit has the recording sessions "
                         f"{sorted(per)} (a fit made with sessions records them)")
    sv = params.servo
    return params.replace(servo=sv.replace(
        p_gain=sv.p_gain * jnp.asarray(per[name]["electrical"]),
        torque_constant=sv.torque_constant * jnp.asarray(per[name]["torque"])))


def params_to_dict(params: SimParams) -> dict:
    """The servo, friction and armature values as a simulator-fit file stores them
    (``servo_friction``; :func:`apply_servo_friction` reads them back)."""
    return {
        "dt": params.dt,
        "armature": np.asarray(params.robot.armature).tolist(),
        "torque_offset": (None if params.torque_offset is None
                          else np.asarray(params.torque_offset).tolist()),
        "servo": {k: np.asarray(v).tolist() for k, v in params.servo.__dict__.items()},
        "friction": {k: np.asarray(v).tolist() for k, v in params.friction.__dict__.items()},
    }
