"""Running scenarios in chunks with a progress bar, and the default simulated arm."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from jaxinertia.robot import open_manipulator_x
from jaxinertia.sim.friction import FrictionParams
from jaxinertia.sim.sampling import HeldObject, simulate_samples
from jaxinertia.sim.servo import ServoParams
from jaxinertia.sim.simulator import SimParams

__all__ = ["default_sim_params", "run_plan"]

#: One compiled program per (parameters structure, chunk size); objects are arguments.
_simulate = jax.jit(simulate_samples, static_argnames=("delta",))

#: Reflected rotor inertia of the XM430 gear train [kg m^2] (assumed until calibrated).
DEFAULT_ARMATURE = 0.01


def default_sim_params(calibration_file=None) -> SimParams:
    """The simulated OpenMANIPULATOR-X as calibrated to the real arm
    (``data/open_manipulator_x_sim.json``: link gravity, servo and friction), falling back
    to datasheet servos and default friction where the file has no servo calibration."""
    from jaxinertia.sim.calibration import (
        apply_calibration,
        apply_servo_friction,
        load_calibration,
    )

    calibration = load_calibration(calibration_file)
    robot = apply_calibration(open_manipulator_x(), calibration)
    robot = robot.replace(armature=jnp.full(4, DEFAULT_ARMATURE))
    params = SimParams(robot, ServoParams.xm430_w350(), FrictionParams.create())
    return apply_servo_friction(params, calibration)


def run_plan(params: SimParams, obj: HeldObject, q_d: np.ndarray, direction: np.ndarray,
             key: jax.Array, *, chunk: int = 512, desc: str = "simulating",
             progress: bool = True) -> dict[str, np.ndarray]:
    """Simulates a plan in chunks of ``chunk`` samples (one compiled program)."""
    S = len(q_d)
    chunk = min(chunk, S)
    out: dict[str, list] = {}
    with tqdm(total=S, desc=desc, unit="sample", disable=not progress) as bar:
        for i, start in enumerate(range(0, S, chunk)):
            q = np.asarray(q_d[start:start + chunk])
            d = np.asarray(direction[start:start + chunk])
            n = len(q)
            if n < chunk:  # pad to the compiled size
                q = np.concatenate([q, np.repeat(q[-1:], chunk - n, 0)])
                d = np.concatenate([d, np.repeat(d[-1:], chunk - n, 0)])
            res = _simulate(params, obj, jnp.asarray(q), jnp.asarray(d),
                            jax.random.fold_in(key, i))
            for k, v in res._asdict().items():
                out.setdefault(k, []).append(np.asarray(v)[:n])
            bar.update(n)
    return {k: np.concatenate(v) for k, v in out.items()}
