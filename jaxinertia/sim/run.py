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

__all__ = ["SimulationError", "default_chunk", "default_sim_params", "native_fields",
           "run_plan", "simulate_scenario"]

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


def default_chunk() -> int:
    """Samples per compiled call: small on CPU (progress, memory), large on accelerators
    (a 512-sample batch leaves an H100 mostly idle)."""
    return 512 if jax.default_backend() == "cpu" else 16384


def run_plan(params: SimParams, obj: HeldObject, q_d: np.ndarray, direction: np.ndarray,
             key: jax.Array, *, chunk: int | None = None, desc: str = "simulating",
             progress: bool = True) -> dict[str, np.ndarray]:
    """Simulates a plan in chunks of ``chunk`` samples (one compiled program).

    Sample i gets the i-th of ``jax.random.split(key, S)``, so the result does not depend
    on the chunk size (nor on the device's default chunk).
    """
    q_d, direction = _check_plan(params, q_d, direction, desc)
    S = len(q_d)
    chunk = min(chunk or default_chunk(), S)
    keys = jax.random.split(key, S)
    out: dict[str, list] = {}
    with tqdm(total=S, desc=desc, unit="sample", disable=not progress) as bar:
        for start in range(0, S, chunk):
            q = np.asarray(q_d[start:start + chunk])
            d = np.asarray(direction[start:start + chunk])
            k = keys[start:start + chunk]
            n = len(q)
            if n < chunk:  # pad to the compiled size
                q = np.concatenate([q, np.repeat(q[-1:], chunk - n, 0)])
                d = np.concatenate([d, np.repeat(d[-1:], chunk - n, 0)])
                k = jnp.concatenate([k, jnp.repeat(k[-1:], chunk - n, 0)])
            res = _simulate(params, obj, jnp.asarray(q), jnp.asarray(d), k)
            for name, v in res._asdict().items():
                out.setdefault(name, []).append(np.asarray(v)[:n])
            bar.update(n)
    res = {k: np.concatenate(v) for k, v in out.items()}
    # Diverged: a non-finite state, or an arm that ended far from its goal (a settled
    # servo misses by a few ticks; 0.5 rad is a runaway integration).
    with np.errstate(invalid="ignore"):
        bad = ~np.all(np.isfinite(res["q"]) & np.isfinite(res["current_tau"])
                      & (np.abs(res["q"] - q_d) < DIVERGED_RAD), axis=1)
    if bad.any():
        i = np.flatnonzero(bad)
        raise SimulationError(f"{desc}: the integration diverged at sample(s) "
                              f"{i[:10].tolist()}{' ...' if len(i) > 10 else ''} of {S} "
                              f"(non-finite state or more than {DIVERGED_RAD} rad from the "
                              "goal); check the calibration file (gains, dt)")
    return res


#: A sample whose arm ends farther than this from its goal [rad] counts as diverged.
DIVERGED_RAD = 0.5


class SimulationError(ValueError):
    """A plan that cannot be simulated, or a simulation that diverged."""


def _check_plan(params: SimParams, q_d, direction, desc: str):
    """Validates goals (S, N) [rad] and directions (S, N) before anything runs; errors name
    the plan and the first offending sample."""
    q_d = np.asarray(q_d, dtype=np.float64)
    direction = np.asarray(direction, dtype=np.float64)
    n = params.robot.n_joints
    if q_d.ndim != 2 or q_d.shape[1] != n or q_d.shape != direction.shape or not len(q_d):
        raise SimulationError(f"{desc}: goals {q_d.shape} and directions {direction.shape} "
                              f"must both be (S, {n}) with S >= 1")

    def first(mask):
        return int(np.flatnonzero(mask.any(axis=1))[0])

    if not np.all(np.isfinite(q_d)):
        raise SimulationError(f"{desc}: sample {first(~np.isfinite(q_d))}: goal is not finite")
    if not np.all(np.isin(direction, (-1.0, 1.0))):
        i = first(~np.isin(direction, (-1.0, 1.0)))
        raise SimulationError(f"{desc}: sample {i}: direction {direction[i].tolist()} must be "
                              "+1 or -1 per joint")
    lo, hi = np.asarray(params.robot.q_min), np.asarray(params.robot.q_max)
    out = (q_d < lo) | (q_d > hi)
    if out.any():
        i = first(out)
        j = int(np.flatnonzero(out[i])[0])
        raise SimulationError(
            f"{desc}: sample {i}: joint {j + 1} goal {np.degrees(q_d[i, j]):.2f} deg is "
            f"outside its limits [{np.degrees(lo[j]):.1f}, {np.degrees(hi[j]):.1f}] deg")
    return q_d, direction


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
    return {name: (obj, run_plan(params, obj, q_d, d, jax.random.fold_in(key, i),
                                 desc=f"{scenario}/{name}", progress=progress))
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
