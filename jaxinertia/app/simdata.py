"""Simulated data files for the pipeline: simulate what is missing, reuse what an earlier
run made from the same request (scenario, size, seed and simulator parameters). Either way
the file comes back as a :class:`~jaxinertia.samples.SampleFile` (the samples, as a later
read would give them, with the file's SHA-256), so that no caller reads it again."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import NamedTuple

import jax
import numpy as np

from jaxinertia import __version__
from jaxinertia.app.programs import side_by_side, stream_programs
from jaxinertia.arms import DEFAULT_ARM
from jaxinertia.errors import UsageError
from jaxinertia.samples import SampleFile, Samples, read_sample_file, write_sample_file
from jaxinertia.sim.params import params_to_dict
from jaxinertia.sim.randomize import DomainSpread, SessionSpread, drawn
from jaxinertia.sim.run import (
    ScenarioRequest,
    native_fields,
    simulate_scenarios,
    simulate_scenarios_many,
)
from jaxinertia.sim.simulator import SimParams

__all__ = ["FilesRequest", "cached", "params_digest", "reused", "save", "simulate_files",
           "simulate_many"]


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


class FilesRequest(NamedTuple):
    """One :func:`simulate_files` call's simulator, files and domain randomization."""

    params: SimParams
    wanted: list[tuple[Path, str, int | None, int]]
    spread: DomainSpread | SessionSpread | None = None
    draws: int = 4


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
    return simulate_many([FilesRequest(params, wanted, spread, draws)], progress=progress,
                         arm=arm, together=False)[0]


def simulate_many(calls: list[FilesRequest], *, progress: bool = True, arm=None,
                  together: bool = True) -> list[list[SampleFile]]:
    """Several :func:`simulate_files` calls; each call's files as it returns them.

    ``together``: the streams of every call (a call's own, or one per simulated arm of a
    domain-randomized call) that make plans of the same shapes (the same scenarios and
    sizes) run as one program (:func:`jaxinertia.sim.run.simulate_scenarios_many`), those
    of other shapes side by side: for an accelerator, where many small streams in threads
    would queue behind each other's programs (the held-out folds' training files). The
    files are those the calls make one by one, up to the last bits of the simulator's
    state (no settling tail on fewer lanes). Else one stream after the other."""
    pending = [_Pending.of(c, arm) for c in calls]
    streams = [(k, r, params, requests) for k, p in enumerate(pending)
               for r, (params, requests) in enumerate(p.streams())]
    results: dict = {}
    if together:
        shapes: dict = {}
        for st in streams:
            shapes.setdefault(tuple((q.scenario, q.n) for q in st[3]), []).append(st)

        def run(group):
            if len(group) == 1:
                return [simulate_scenarios(group[0][2], group[0][3], programs=stream_programs(),
                                           progress=progress, arm=arm)]
            return simulate_scenarios_many([(params, requests) for *_, params, requests in group],
                                           programs=stream_programs(), arm=arm)

        groups = list(shapes.values())
        for group, res in zip(groups, side_by_side([partial(run, g) for g in groups],
                                                   len(groups))):
            results.update({(k, r): one for (k, r, _, _), one in zip(group, res)})
    else:
        for k, r, params, requests in streams:
            results[k, r] = simulate_scenarios(params, requests, programs=stream_programs(),
                                               progress=progress, arm=arm)
    return [p.save([results[k, r] for r in range(p.n_streams)])
            for k, p in enumerate(pending)]


@dataclass
class _Pending:
    """A call's files: those reused, those to simulate and how (its streams), then saved."""

    call: FilesRequest
    request: Callable
    missing: list
    done: dict

    @classmethod
    def of(cls, call: FilesRequest, arm) -> _Pending:
        digest = params_digest(call.params)
        randomized = ({} if call.spread is None else
                      {"spread": call.spread.to_dict(), "draws": call.draws})
        other = {} if arm is None or arm.name == DEFAULT_ARM else {"arm": arm.name}

        def request(scenario, n, seed):
            return {"scenario": scenario, "seed": seed, "n": n, "simulator": digest,
                    **randomized, **other}

        missing, done = [], {}
        for path, scenario, n, seed in call.wanted:
            f = reused(path, request(scenario, n, seed))
            if f is not None:
                print(f"reusing {path}")
                done[path] = f
            else:
                missing.append((path, scenario, n, seed))
        if missing and call.spread is not None and any(
                scenario != "random" or n is None for _, scenario, n, _ in missing):
            raise UsageError("domain randomization splits random-scenario files over the "
                             "simulated arms: give n, scenario 'random'")
        return cls(call, request, missing, done)

    @property
    def n_streams(self) -> int:
        if not self.missing:
            return 0  # every file reused: nothing to simulate
        return 1 if self.call.spread is None else self.call.draws

    def streams(self) -> list[tuple[SimParams, list[ScenarioRequest]]]:
        """``(simulator, requests)`` of each stream the missing files need."""
        if not self.missing:
            return []
        c = self.call
        if c.spread is None:
            return [(c.params, [ScenarioRequest(scenario, n, None, seed)
                                for _, scenario, n, seed in self.missing])]
        key = jax.random.key(self.missing[0][3])
        return [(drawn(c.params, jax.random.fold_in(key, r), c.spread),
                 [ScenarioRequest(scenario, -(-n // c.draws), None, seed + 7919 * (r + 1))
                  for _, scenario, n, seed in self.missing])
                for r in range(c.draws)]

    def save(self, per_stream: list[list]) -> list[SampleFile]:
        """Writes the missing files from each stream's results; every wanted file."""
        c = self.call
        for i, (path, scenario, n, seed) in enumerate(self.missing):
            res = _merge([one[i] for one in per_stream])
            fields, meta = native_fields(res, c.params, scenario=scenario, seed=seed,
                                         version=__version__)
            if c.spread is not None:
                meta["domain_randomization"] = {"spread": c.spread.to_dict(),
                                                "draws": c.draws}
            self.done[path] = save(path, self.request(scenario, n, seed), fields, meta)
        return [self.done[w[0]] for w in c.wanted]


def _merge(results: list[dict]) -> dict:
    """One scenario's results of several simulated arms: per object, the arms' samples one
    after the other."""
    return {name: (obj, {k: np.concatenate([r[name][1][k] for r in results])
                         for k in fields})
            for name, (obj, fields) in results[0].items()}
