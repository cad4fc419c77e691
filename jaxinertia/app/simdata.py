"""Simulated data files for the pipeline: simulate what is missing, reuse what an earlier
run made from the same request (scenario, size, seed and simulator parameters). Either way
the file comes back as a :class:`~jaxinertia.samples.SampleFile` (the samples, as a later
read would give them, with the file's SHA-256), so that no caller reads it again."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import jax
import numpy as np

from jaxinertia import __version__
from jaxinertia.app.programs import stream_programs
from jaxinertia.arms import DEFAULT_ARM
from jaxinertia.errors import UsageError
from jaxinertia.samples import SampleFile, Samples, read_sample_file, write_sample_file
from jaxinertia.sim.params import params_to_dict
from jaxinertia.sim.randomize import DomainSpread, SessionSpread, drawn
from jaxinertia.sim.run import ScenarioRequest, native_fields, simulate_scenarios
from jaxinertia.sim.simulator import SimParams

__all__ = ["cached", "params_digest", "reused", "save", "simulate_files"]


def params_digest(params: SimParams) -> str:
    """A short digest of the simulator's parameters (a file made with others is not reused)."""
    d = {"servo_friction": params_to_dict(params), "link_mass": params.robot.mass.tolist(),
         "link_com": params.robot.com.tolist()}
    return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]


def reused(path: Path, request: dict, *, only_at_rest: bool = True) -> SampleFile | None:
    """The file at ``path``, read once, when the same request made it (a re-run reuses it);
    else None."""
    if not path.exists():
        return None
    try:
        f = read_sample_file(path, only_at_rest=only_at_rest)
    except ValueError:
        return None
    return f if f.meta.get("request") == request else None


def save(path: Path, request: dict, fields: dict, meta: dict, *,
         only_at_rest: bool = True) -> SampleFile:
    meta.update(request=request, version=__version__)
    return write_sample_file(path, Samples.from_fields(fields, meta["objects"], need_truth=True),
                             meta, only_at_rest=only_at_rest)


def cached(path: Path, request: dict, make, *, only_at_rest: bool = True) -> SampleFile:
    """Writes ``make() -> (fields, meta)`` to ``path`` unless the file there was made by the
    same request."""
    f = reused(path, request, only_at_rest=only_at_rest)
    if f is not None:
        print(f"reusing {path}")
        return f
    return save(path, request, *make(), only_at_rest=only_at_rest)


def simulate_files(params, wanted: list[tuple[Path, str, int | None, int]], *,
                   spread: DomainSpread | SessionSpread | None = None, draws: int = 4,
                   progress: bool = True, arm=None) -> list[SampleFile]:
    """Simulates the scenarios ``(path, scenario, n, seed)`` whose files are not there yet,
    all in one stream (one compiled program, one settling tail).

    ``spread``: domain randomization: the samples of every file come from ``draws``
    simulated arms drawn around ``params`` (:func:`jaxinertia.sim.randomize.drawn`: other
    arms for a :class:`DomainSpread`, other recording sessions for a
    :class:`SessionSpread`), ``n / draws`` random-scenario samples each (one stream per
    arm). ``progress``: the
    stream's progress bar. ``arm``: the :class:`jaxinertia.arm.Arm` simulated (its
    workspace, planning grid and tag mount; default the OpenMANIPULATOR-X), ``params``
    its simulator."""
    digest = params_digest(params)
    randomized = {} if spread is None else {"spread": spread.to_dict(), "draws": draws}
    other = {} if arm is None or arm.name == DEFAULT_ARM else {"arm": arm.name}

    def request(scenario, n, seed):
        return {"scenario": scenario, "seed": seed, "n": n, "simulator": digest, **randomized,
                **other}

    missing, done = [], {}
    for path, scenario, n, seed in wanted:
        f = reused(path, request(scenario, n, seed))
        if f is not None:
            print(f"reusing {path}")
            done[path] = f
        else:
            missing.append((path, scenario, n, seed))
    results: list = []  # every file reused: nothing to simulate
    if missing and spread is None:
        results = simulate_scenarios(
            params, [ScenarioRequest(scenario, n, None, seed) for _, scenario, n, seed in missing],
            programs=stream_programs(), progress=progress, arm=arm)
    elif missing:
        if any(scenario != "random" or n is None for _, scenario, n, _ in missing):
            raise UsageError("domain randomization splits random-scenario files over the "
                             "simulated arms: give n, scenario 'random'")
        per_arm = []
        for r in range(draws):
            arm_r = drawn(params, jax.random.fold_in(jax.random.key(missing[0][3]), r),
                          spread)
            per_arm.append(simulate_scenarios(arm_r, [
                ScenarioRequest(scenario, -(-n // draws), None, seed + 7919 * (r + 1))
                for _, scenario, n, seed in missing], programs=stream_programs(),
                progress=progress, arm=arm))
        results = [_merge([one[i] for one in per_arm]) for i in range(len(missing))]
    for (path, scenario, n, seed), res in zip(missing, results):
        fields, meta = native_fields(res, params, scenario=scenario, seed=seed,
                                     version=__version__)
        if spread is not None:
            meta["domain_randomization"] = randomized
        done[path] = save(path, request(scenario, n, seed), fields, meta)
    return [done[w[0]] for w in wanted]


def _merge(results: list[dict]) -> dict:
    """One scenario's results of several simulated arms: per object, the arms' samples one
    after the other."""
    return {name: (obj, {k: np.concatenate([r[name][1][k] for r in results])
                         for k in fields})
            for name, (obj, fields) in results[0].items()}
