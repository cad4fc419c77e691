"""Running plans and scenarios: checked, streamed (:mod:`jaxinertia.sim.stream`), with a
progress bar; scenario results as native-format fields."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxinertia.arm import Arm
from jaxinertia.errors import SimulationError, UsageError
from jaxinertia.objects import (
    TEST_OBJECTS,
    TRAINING_LOADS_KG,
    HeldObject,
    load_name,
    paper_object,
    training_object,
)
from jaxinertia.open_manipulator_x import ARM as OMX_ARM
from jaxinertia.plans import Goals, planning_plan, random_plan
from jaxinertia.sim.params import params_to_dict
from jaxinertia.sim.simulator import SimParams
from jaxinertia.sim.stream import (
    LanePlan,
    StreamPrograms,
    stream_jobs,
    stream_lanes,
    stream_plans,
)

__all__ = ["as_float64", "native_fields", "run_jobs", "run_plan", "run_plans", "ScenarioRequest",
           "simulate_scenario", "simulate_scenarios"]


def run_plan(params: SimParams, obj: HeldObject, q_d: np.ndarray, direction: np.ndarray,
             key: jax.Array, *, lanes: int | None = None, desc: str = "simulating",
             programs: StreamPrograms | None = None,
             progress: bool = True) -> dict[str, np.ndarray]:
    """Simulates one object's plan; returns the sample fields (numpy, leading axis S).

    Sample i gets the i-th of ``jax.random.split(key, S)``, so the result depends neither
    on the lane count (nor on the device's default) nor on the scheduling.
    """
    return run_plans(params, [(obj, q_d, direction, key)], lanes=lanes, descs=[desc],
                     desc=desc, programs=programs, progress=progress)[0]


def run_plans(params: SimParams, plans: list, *, lanes: int | None = None,
              tail_lanes: int | None = None, batch_last: bool | None = None,
              descs: list[str] | None = None, desc: str = "simulating",
              programs: StreamPrograms | None = None,
              progress: bool = True) -> list[dict[str, np.ndarray]]:
    """Simulates several plans ``(object, q_d, direction, key)`` in one stream of lanes
    (:mod:`jaxinertia.sim.stream`; ``programs``: the caller's compiled programs, None: the
    stream's own); every plan is checked first and every result after, errors naming
    ``descs[i]`` and the sample."""
    descs = descs or [f"{desc}[{i}]" for i in range(len(plans))]
    checked = [LanePlan(obj, *_check_plan(params, q_d, d, name), key)
               for (obj, q_d, d, key), name in zip(plans, descs)]
    results = stream_plans(params, checked, lanes=lanes, tail_lanes=tail_lanes,
                           batch_last=batch_last, programs=programs, desc=desc,
                           progress=progress)
    out = []
    for plan, res, name in zip(checked, results, descs):
        res = res._asdict()
        _check_diverged(res, plan.q_d, name, params)
        out.append(res)
    return out


def run_jobs(jobs: list, *, programs: StreamPrograms | None = None
             ) -> list[list[dict[str, np.ndarray]]]:
    """Several simulators' plans as one program (:func:`jaxinertia.sim.stream.stream_jobs`):
    ``jobs`` is ``[(params, plans, descs)]`` with ``plans`` as :func:`run_plans` takes them;
    returns each job's results per plan, checked as :func:`run_plans` checks them."""
    checked = [(params, [LanePlan(obj, *_check_plan(params, q_d, d, name), key)
                         for (obj, q_d, d, key), name in zip(plans, descs)], descs)
               for params, plans, descs in jobs]
    results = stream_jobs([(params, plans) for params, plans, _ in checked],
                          programs=programs)
    out = []
    for (params, plans, descs), job in zip(checked, results):
        out.append([])
        for plan, res, name in zip(plans, job, descs):
            res = res._asdict()
            _check_diverged(res, plan.q_d, name, params)
            out[-1].append(res)
    return out


def _check_diverged(res: dict, q_d: np.ndarray, desc: str, params: SimParams) -> None:
    # Diverged: a non-finite state, or an arm that ended far from its goal (a settled
    # servo misses by a few ticks; 0.5 rad is a runaway integration). A joint without a
    # current sensor has no current-based torque (NaN by design).
    unsensed = (np.zeros(q_d.shape[1], bool) if params.current_torque_constant is None
                else np.isnan(np.asarray(params.current_torque_constant)))
    with np.errstate(invalid="ignore"):
        bad = ~np.all(np.isfinite(res["q"]) & (np.isfinite(res["current_tau"]) | unsensed)
                      & (np.abs(res["q"] - q_d) < DIVERGED_RAD), axis=1)
    if bad.any():
        i = np.flatnonzero(bad)
        raise SimulationError(f"{desc}: the integration diverged at sample(s) "
                              f"{i[:10].tolist()}{' ...' if len(i) > 10 else ''} of {len(q_d)} "
                              f"(non-finite state or more than {DIVERGED_RAD} rad from the "
                              "goal); check the calibration file (gains, dt)")


#: A sample whose arm ends farther than this from its goal [rad] counts as diverged.
DIVERGED_RAD = 0.5


def _check_plan(params: SimParams, q_d, direction, desc: str) -> Goals:
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
    return Goals(q_d, direction)


def simulate_scenario(params: SimParams, scenario: str, *, n: int | None = None,
                      objects: list[str] | None = None, seed: int = 0,
                      lanes: int | None = None, plan: tuple | None = None,
                      programs: StreamPrograms | None = None,
                      progress: bool = True, arm: Arm | None = None
                      ) -> dict[str, tuple[HeldObject, dict]]:
    """Runs a scenario; returns ``{object name: (object, fields)}``.

    planning: the 10 deg grid x 16 direction patterns per training load (``n`` caps it);
    random: ``n`` (default 1000) random goals and directions per training load;
    test: ``n`` (default 1000) per test object (``objects``: default all four).
    ``plan``: the goals and directions every object visits instead (``n`` samples: the
    plan repeated cyclically; default once). ``arm``: the arm record whose workspace,
    planning grid and tag mount the scenario uses (default: the OpenMANIPULATOR-X's);
    ``params`` must be that arm's (:func:`jaxinertia.sim.params.arm_sim_params`).
    """
    return simulate_scenarios(params, [ScenarioRequest(scenario, n, objects, seed, plan)],
                              lanes=lanes, programs=programs, progress=progress, arm=arm)[0]


class ScenarioRequest(NamedTuple):
    scenario: str
    n: int | None = None
    objects: list[str] | None = None
    seed: int = 0
    #: Goals ``(q_d (P, N), direction (P, N))`` every object visits instead of the
    #: scenario's own (e.g. ``jaxinertia plan-poses``), repeated cyclically to ``n`` samples.
    plan: Goals | None = None


def simulate_scenarios(params: SimParams, requests: list[ScenarioRequest], *,
                       lanes: int | None = None, tail_lanes: int | None = None,
                       batch_last: bool | None = None, programs: StreamPrograms | None = None,
                       progress: bool = True, arm: Arm | None = None
                       ) -> list[dict[str, tuple[HeldObject, dict]]]:
    """Several scenarios in one stream of lanes (one compiled program, one tail); each
    result is what :func:`simulate_scenario` returns for its request. ``programs``: the
    caller's compiled stream programs (None: compiled for this call alone)."""
    for r in requests:  # bad requests fail before anything compiles
        _check_request(r.scenario, r.objects)
    if programs is None:
        with StreamPrograms() as own:
            return simulate_scenarios(params, requests, lanes=lanes, tail_lanes=tail_lanes,
                                      batch_last=batch_last, programs=own, progress=progress,
                                      arm=arm)
    # The stepping program needs no plans: it compiles while they are built (for the lanes
    # the stream will step, where the requests tell how many samples they make).
    arm = OMX_ARM if arm is None else arm
    counts = [_request_samples(r) for r in requests]
    programs.precompile(params, training_object(0.0, tag_in_ee=arm.tag_in_ee),
                        lanes=lanes or (None if None in counts else stream_lanes(sum(counts))),
                        batch_last=batch_last)
    jobs, descs, plans = [], [], []
    for r in requests:
        named = _scenario_jobs(r.scenario, r.n, r.objects, r.seed, r.plan, arm=arm,
                               robot=params.robot)
        with jax.default_device(jax.devices("cpu")[0]):  # tiny: no accelerator kernels
            key = jax.random.key(r.seed)
            keys = [jax.random.fold_in(key, i) for i in range(len(named))]
        for (name, obj, (q_d, d)), k in zip(named, keys):
            plans.append((obj, q_d, d, k))
            descs.append(f"{r.scenario}/{name}")
        jobs.append(named)
    results = iter(run_plans(params, plans, lanes=lanes, tail_lanes=tail_lanes,
                             batch_last=batch_last, descs=descs, programs=programs,
                             desc="+".join(r.scenario for r in requests), progress=progress))
    return [{name: (obj, next(results)) for name, obj, _ in named} for named in jobs]


def _check_request(scenario: str, objects: list[str] | None) -> None:
    if scenario not in ("planning", "random", "test"):
        raise UsageError(f"unknown scenario {scenario!r}; known: planning, random, test")
    unknown = [o for o in objects or [] if o not in TEST_OBJECTS]
    if scenario == "test" and unknown:
        raise UsageError(f"unknown test object(s) {unknown}; known: {list(TEST_OBJECTS)}")


def _request_samples(r: ScenarioRequest) -> int | None:
    """How many samples :func:`_scenario_jobs` makes of ``r`` (None for a planning grid
    whose size only the grid tells)."""
    objects = len(r.objects or TEST_OBJECTS) if r.scenario == "test" else len(TRAINING_LOADS_KG)
    if r.plan is not None:
        return objects * (r.n or len(r.plan[0]))
    if r.scenario == "planning":
        return None
    return objects * (r.n or 1000)


def _scenario_jobs(scenario: str, n: int | None, objects: list[str] | None, seed: int,
                   given: Goals | None = None, *,
                   arm: Arm | None = None, robot=None):
    """``[(object name, object, (q_d, direction))]`` of a scenario (``given``: one plan
    for every object, repeated cyclically to ``n`` samples; ``arm``: its workspace,
    planning grid and tag mount, ``robot`` its bare robot; default the OpenMANIPULATOR-X)."""
    _check_request(scenario, objects)
    arm = OMX_ARM if arm is None else arm
    tag, ws = {"tag_in_ee": arm.tag_in_ee}, {"workspace": arm.workspace_deg}
    grid_kw = dict(step_deg=arm.planning_step_deg, clearance=arm.mount_clearance_m,
                   robot=robot if robot is not None else arm.robot(), **ws)
    if given is not None:
        q_d, d = (np.asarray(a, np.float64) for a in given)
        reps = np.arange(n or len(q_d)) % len(q_d)
        given = (q_d[reps], d[reps])
    if scenario == "test":
        names = objects or list(TEST_OBJECTS)
        return [(o, paper_object(o, **tag), given or random_plan(n or 1000, seed + i, **ws))
                for i, o in enumerate(names)]
    jobs = []  # planning or random
    grid = planning_plan(**grid_kw) if scenario == "planning" else None
    for i, m in enumerate(TRAINING_LOADS_KG):
        if given is not None:
            plan = given
        elif scenario == "planning":
            plan = tuple(a[:n] for a in grid) if n else grid
        else:
            plan = random_plan(n or 1000, seed + i, **ws)
        jobs.append((load_name(m), training_object(m, **tag), plan))
    return jobs


def as_float64(a: np.ndarray) -> np.ndarray:
    """Floating arrays as float64 (files store float64 whatever the simulation's precision)."""
    return a.astype(np.float64) if np.issubdtype(a.dtype, np.floating) else a


def native_fields(results: dict[str, tuple[HeldObject, dict]], params: SimParams, *,
                  scenario: str, seed: int, version: str) -> tuple[dict, dict]:
    """Concatenates per-object results into native-format fields and metadata."""
    names = list(results)
    fields = {k: as_float64(np.concatenate([results[n][1][k] for n in names]))
              for k in results[names[0]][1]}
    fields["object_id"] = np.concatenate(
        [np.full(len(results[n][1]["q"]), i) for i, n in enumerate(names)])
    fields["x"] = as_float64(np.stack([np.asarray(results[n][0].x) for n in names]))
    simulator = {k: v for k, v in params_to_dict(params).items() if k != "torque_offset"}
    meta = {
        "version": version, "scenario": scenario, "seed": seed, "source": "simulator",
        "objects": names, "robot": params.robot.name,
        "arm": params.robot.name,  # an arm's robot is named after it (jaxinertia.arms)
        "simulator": {"precision": str(jnp.dtype(jnp.result_type(float))), **simulator},
    }
    return fields, meta
