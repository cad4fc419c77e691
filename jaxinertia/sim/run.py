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

__all__ = ["default_sim_params", "native_fields", "run_plan", "simulate_scenario"]

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


def simulate_scenario(params: SimParams, scenario: str, *, n: int | None = None,
                      objects: list[str] | None = None, seed: int = 0,
                      progress: bool = True) -> dict[str, tuple[HeldObject, dict]]:
    """Runs a scenario; returns ``{object name: (object, fields)}``.

    planning: the 10 deg grid x 16 direction patterns per training load (``n`` caps it);
    random: ``n`` (default 1000) random goals and directions per training load;
    test: ``n`` (default 1000) per test object (``objects``: default all four).
    """
    from jaxinertia.sim import scenarios as sc

    if scenario == "test":
        names = objects or list(sc.OBJECTS)
        unknown = [o for o in names if o not in sc.OBJECTS]
        if unknown:
            raise ValueError(f"unknown test object(s) {unknown}; known: {list(sc.OBJECTS)}")
        jobs = [(o, sc.lbipe_object(o), sc.random_plan(n or 1000, seed + i))
                for i, o in enumerate(names)]
    elif scenario in ("planning", "random"):
        jobs = []
        for i, m in enumerate(sc.TRAINING_LOADS_KG):
            if scenario == "planning":
                plan = sc.planning_plan()
                if n:
                    plan = tuple(a[:n] for a in plan)
            else:
                plan = sc.random_plan(n or 1000, seed + i)
            jobs.append((f"{round(m * 1000)}g", sc.training_object(m), plan))
    else:
        raise ValueError(f"unknown scenario {scenario!r}")
    key = jax.random.key(seed)
    return {name: (obj, run_plan(params, obj, q_d, d, jax.random.fold_in(key, i), desc=name,
                                 progress=progress))
            for i, (name, obj, (q_d, d)) in enumerate(jobs)}


def native_fields(results: dict[str, tuple[HeldObject, dict]], params: SimParams, *,
                  scenario: str, seed: int, version: str) -> tuple[dict, dict]:
    """Concatenates per-object results into native-format fields and metadata."""
    names = list(results)
    fields = {k: np.concatenate([results[n][1][k] for n in names]) for k in results[names[0]][1]}
    fields["object_id"] = np.concatenate(
        [np.full(len(results[n][1]["q"]), i) for i, n in enumerate(names)])
    fields["x"] = np.stack([np.asarray(results[n][0].x) for n in names])
    meta = {
        "version": version, "scenario": scenario, "seed": seed, "source": "simulator",
        "objects": names, "robot": params.robot.name,
        "simulator": {"dt": params.dt, "armature": np.asarray(params.robot.armature).tolist(),
                      "servo": {k: np.asarray(v).tolist()
                                for k, v in params.servo.__dict__.items()},
                      "friction": {k: np.asarray(v).tolist()
                                   for k, v in params.friction.__dict__.items()}},
    }
    return fields, meta
