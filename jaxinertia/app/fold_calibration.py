"""A held-out fold's simulator, fitted to the one real file the fold may look at
(:mod:`jaxinertia.app.folds`, step 1): link gravity from its ``tau_g``, then servo,
friction and the constant joint torques (:mod:`jaxinertia.sim.real_fit`), optionally the
per-sample identification; then the held-out objects' real plans replayed in it. Several
folds at once: on an accelerator their replays run together, one program for every fold."""

from __future__ import annotations

import time
from collections.abc import Sequence

import jax
import numpy as np

from jaxinertia.app.programs import stream_programs
from jaxinertia.fileio import write_json
from jaxinertia.sim.identify import ESConfig, identify
from jaxinertia.sim.params import datasheet_sim_params, params_to_dict
from jaxinertia.sim.real_fit import (
    baseline_statistics,
    fit_link_gravity,
    fit_servo_friction,
    fit_servo_friction_many,
    real_plan,
    simulate_real_plan,
    simulate_real_plans,
)

__all__ = ["fit_simulators"]


def _stats(d: dict) -> dict:
    st = baseline_statistics(d["q_d"], d["q"], d["direction"], d["tau"], d["current_tau"])
    return {k: st[k].tolist() for k in ("k", "c", "pe_mae")}


def fit_simulators(folds: Sequence, *, together: bool = False) -> list[tuple]:
    """Each fold's simulator (``folds``: :mod:`jaxinertia.app.folds`' folds) fitted to its
    ``fit_on`` alone (then identified, when asked), written to its ``calibration.json``,
    and its held-out objects' real plans replayed in it: ``[(params, {"replay",
    "identified"})]``. ``together``: every fold's replays in one
    program each (:func:`jaxinertia.sim.real_fit.fit_servo_friction_many`; an accelerator,
    where the folds' replays side by side in threads would wait behind each other's)."""
    scale = folds[0].scale  # (every fold's; the seeds their own: the training draws')
    starts = []
    for fold in folds:
        params = datasheet_sim_params()
        fit = [fold.record(fold.fit_on)]  # the only real samples the fold's fits look at
        robot, gravity = fit_link_gravity(params.robot, fit)
        starts.append((params.replace(robot=robot), fit, gravity))
    kw = dict(iterations=scale.calibration_iterations, fit_offset=True, log=lambda m: None,
              programs=stream_programs())
    if together and len(folds) > 1:
        fitted = fit_servo_friction_many([(p, fit) for p, fit, _ in starts],
                                         seed=[f.seed for f in folds], **kw)
    else:
        fitted = [fit_servo_friction(p, fit, progress=False, seed=f.seed, **kw)
                  for f, (p, fit, _) in zip(folds, starts)]
    params = [p for p, _ in fitted]
    held = [real_plan(p.robot, [fold.record(n) for n in fold.held])
            for fold, p in zip(folds, params)]
    real_held = [_stats({k: np.concatenate([getattr(d, k) for _, _, d in plans])
                         for k in ("q_d", "q", "direction", "tau", "current_tau")})
                 for plans in held]

    def replays(ps) -> list[dict]:  # the held-out objects' real plans replayed in each
        requests = [(p, plans, jax.random.key(f.seed + 7)) for f, p, plans in
                    zip(folds, ps, held)]
        sims = (simulate_real_plans(requests, programs=stream_programs()) if together else
                [simulate_real_plan(*r, programs=stream_programs()) for r in requests])
        return [_stats({k: v[sim["at_rest"]] for k, v in sim.items()}) for sim in sims]

    identified = [None] * len(folds)
    if scale.identify_generations > 0:
        calibrated = replays(params)
        for i in range(len(folds)):
            _, obj_fit, d_fit = real_plan(params[i].robot, starts[i][1])[0]
            if 0 < scale.identify_samples < d_fit.n_samples:
                d_fit = d_fit.take(np.sort(np.random.default_rng(folds[i].seed).choice(
                    d_fit.n_samples, scale.identify_samples, replace=False)))
            t_id = time.perf_counter()
            params[i], ident = identify(params[i], obj_fit, d_fit, config=ESConfig(
                population=scale.identify_population,
                generations=scale.identify_generations, seed=folds[i].seed),
                log=lambda m: None)
            identified[i] = {**ident, "wall_time_s": time.perf_counter() - t_id,
                             "replay_calibrated": calibrated[i]}
    for fold, p, (_, info), (_, _, gravity), ident in zip(folds, params, fitted, starts,
                                                          identified):
        write_json(fold.dir / "calibration.json", {
            "robot": "open_manipulator_x", "fit_on": fold.fit_on,
            "link_gravity": gravity, "servo_friction": params_to_dict(p),
            "fit": {"iterations": scale.calibration_iterations, "real_objects": [fold.fit_on],
                    "seed": fold.seed,
                    "real": info["real"], "final_sim": info["history"][-1]["sim"]},
            "identified": None if ident is None else {
                k: ident[k] for k in ("theta", "parameters", "history")}})
    return [(p, {"replay": {"real": r, "sim": sim}, "identified": ident})
            for p, r, sim, ident in zip(params, real_held, replays(params), identified)]
