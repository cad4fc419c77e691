"""The held-out protocol on the real data: fit on one real session, judge on the others.

Real data are scarce (two objects in shared/lbipe, each file its own recording session),
so anything fitted to them is judged on a file the fit did not see: leave one session out.
One fold per real file ``fit_on``:

1. calibrate the simulator from the datasheet start (never the shipped calibration, which
   saw every real file) on ``fit_on``'s real samples only: link gravity from its ``tau_g``,
   then servo, friction and the constant joint torques (:mod:`jaxinertia.app.fold_calibration`,
   :mod:`jaxinertia.sim.real_fit`; on an accelerator every fold's replays in one program);
2. replay every other object's real plan (goals, directions, the object) in that simulator
   and compare its baseline statistics with the real ones (per-joint PE gain and
   intercept): does the load dependence come out of the physics?
3. simulate training data with it, train model pairs, and evaluate them on the held-out
   real objects (Sensor, PE, T, T-A) beside the authors' released models on the same sets;
4. train the physics-structured torque model (``torque_model="physical"``) on the same
   simulated data, fine-tune its servo part on ``fit_on``'s real samples (64, 250, 1000
   of them: a user's few minutes with a known object) beside as many of each simulated
   load, refit the baselines on them, and judge again on the held-out objects. Why the
   servo part: fine-tuning every parameter on one real object teaches the network that
   object's torque as a function of the pose (``experiments/finetune_ablation.py``).

Every model folder is judged on each held-out file at each session strength of
:mod:`jaxinertia.session` (its discrepancy read in the training session, from its own
current gain, or not); :func:`choose_recipe` then picks from these held-out numbers alone
the recipe of ``models_real`` (which candidates, adapted or not, with the attention or not).
"""

from __future__ import annotations

import os
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import replace
from functools import partial
from pathlib import Path

import numpy as np

from jaxinertia.app.ensemble import judge_mean
from jaxinertia.app.fit import EarlyStart
from jaxinertia.app.fold import SESSION_STRENGTHS, Fold, FoldScale
from jaxinertia.app.fold_calibration import fit_simulators
from jaxinertia.app.fold_groups import FoldGroups
from jaxinertia.app.pipeline import RealData, load_real, released_benchmark, train
from jaxinertia.app.programs import folds_side_by_side, side_by_side
from jaxinertia.app.recipe import choose_recipe, pooled_folds
from jaxinertia.app.simdata import simulate_files
from jaxinertia.lbipe import read_released_pairs
from jaxinertia.sim.randomize import session_prior, spread_from_samples

__all__ = ["SESSION_STRENGTHS", "Fold", "FoldScale", "choose_recipe", "run_folds"]


def run_folds(out: str | os.PathLike, lbipe_dir: str | os.PathLike, scale: FoldScale, *,
              seed: int = 0, draws: int = 1, progress: bool = True, log=print,
              real: RealData | None = None, keep: dict | None = None) -> dict | None:
    """Every fold into ``out/fit_<object>/`` (calibration.json, data, models); returns the
    held-out results and the recipe they choose (None when there is no real data, or only
    one object). ``draws`` > 1: the folds of that many training draws (seeds ``seed``,
    ``seed + 1``, ...; each draw's calibrations, simulated data and trainings its own, as
    ``--seed`` would make them; the later draws' under ``out/seed<s>/``), all side by side
    (on an accelerator their trainings in the same groups) and judged on the same sets;
    the recipe is chosen over every draw's folds (:func:`jaxinertia.app.recipe.pooled_folds`).
    ``real``: the folder's real data when already loaded. ``keep``: filled with the
    estimates the folds judged (``estimates``: fold -> one per draw: (folder, strength) ->
    {method: (held objects, K, B, 4)}; ``released``: the released models' {method:
    (objects, K, B, 4)}),
    for judgements made after the recipe (:func:`jaxinertia.app.with_released.judge_draws`)."""
    if draws < 1:
        raise ValueError(f"draws must be 1 or more, not {draws}")
    if real is None and not Path(lbipe_dir).is_dir():
        return None
    real = real or load_real(lbipe_dir, seed=seed)
    names = [o.name for o in real.objects]
    if len(names) < 2:
        return None
    seeds = [seed + k for k in range(draws)]
    # The released models' benchmark is needed only once a fold judges: it runs beside the
    # calibrations instead of before them (on an accelerator 7 s of tracing and compiling
    # off the folds' critical path: docs/benchmarks.md, "Session 33"). Their weights are
    # read here, before any fold starts: a torn or missing file stops the run at once, not
    # after every fold has trained.
    released = read_released_pairs(real.layout.weights_dir, prefer=real.layout.prefer)
    with ThreadPoolExecutor(1, thread_name_prefix="jaxinertia-released") as pool:
        benchmark = pool.submit(released_benchmark, lbipe_dir, real=real, pairs=released)
        by_draw, todo, workers = _run_all(out, names, real, scale, seeds, progress, log,
                                          benchmark)
    if keep is not None:
        keep.update(estimates={n: [f.estimates for f in todo if f.fit_on == n] for n in names},
                    released={m: np.asarray(x)
                              for m, x in benchmark.result()["estimates"].items()})
    res = {"folds": by_draw[0], "sets": dict(zip(names, real.sources)), "seeds": seeds,
           "side_by_side": workers}
    if draws > 1:
        res["draws"] = [{"seed": s, "dir": _draw_dir(k, s), "folds": f}
                        for k, (s, f) in enumerate(zip(seeds, by_draw))]
    return {**res, "recipe": choose_recipe(dict(pooled_folds(res)))}


def _draw_dir(k: int, seed: int) -> str:
    """The k-th training draw's folder under the folds' (the first: the folds' own)."""
    return "" if k == 0 else f"seed{seed}"


def _run_all(out, names, real, scale, seeds, progress, log, benchmark: Future
             ) -> tuple[list[dict[str, dict]], list[Fold], int]:
    """Every draw's folds' stages: their results by name (one dict per draw), the folds,
    and how many ran side by side; ``benchmark``: the released models' on the real files,
    awaited when judged."""
    todo = [Fold(Path(out) / _draw_dir(k, s) / f"fit_{fit_on}", fit_on,
                  [n for n in names if n != fit_on], real, scale, s, progress,
                  draw=_draw_dir(k, s))
            for k, s in enumerate(seeds) for fit_on in names]
    groups = FoldGroups.of([f.key for f in todo], scale)
    todo = [replace(f, groups=groups) for f in todo]

    def announce(fold: Fold) -> None:
        log(f"-- fold{f' ({fold.draw})' if fold.draw else ''}: calibrate on {fold.fit_on}, "
            f"judge on {', '.join(fold.held)}")

    # Side by side (an accelerator), the folds' calibrations run first, together: each of
    # their replays one program for every fold (on a CPU each fold calibrates in its own
    # thread, on its own core).
    calibrated: list = [None] * len(todo)
    if groups is not None:
        for fold in todo:
            announce(fold)
        t = time.perf_counter()
        fitted = fit_simulators(todo, together=True)
        calibrated = [(*c, time.perf_counter() - t) for c in fitted]

    def run(fold: Fold, calibration) -> dict:
        if calibration is None:
            announce(fold)
        res = _run_fold(fold, calibration)
        released = benchmark.result()["objects"]
        return {**res, "released": {n: {m: released[n][m] for m in ("T", "T-A")}
                                    for n in fold.held}}

    # The folds share nothing but the real data they read: side by side (on an
    # accelerator their trainings grouped into few programs; on a CPU one fold per core).
    calls = [fold.branch(partial(run, fold, c)) for fold, c in zip(todo, calibrated)]
    workers = todo[0].workers(len(calls)) or folds_side_by_side(len(calls))
    done = side_by_side(calls, workers)
    n = len(names)
    return [dict(zip(names, done[k:k + n])) for k in range(0, len(done), n)], todo, workers


def _run_fold(fold: Fold, calibration: tuple | None = None) -> dict:
    """One fold's stages; ``calibration``: its simulator already fitted (an item of
    :func:`~jaxinertia.app.fold_calibration.fit_simulators`' result and the seconds it
    took), else fitted here."""
    wall: dict[str, float] = {}

    def timed(name, fn, *args):
        t = time.perf_counter()
        try:
            return fn(*args)
        finally:
            wall[name] = time.perf_counter() - t

    if calibration is None:
        params, replay = timed("calibrate", lambda: fit_simulators([fold])[0])
    else:
        params, replay, wall["calibrate"] = calibration
    wanted = [(fold.dir / "data" / "train_random.npz", "random", fold.scale.random_per_load,
               fold.seed)]
    if fold.scale.planning:
        wanted.append((fold.dir / "data" / "train_planning.npz", "planning", None, fold.seed))
    # The sessions-drawn data (when the scale has them) simulate beside the fold's own: their
    # candidates' trainings meet the others' in one group, which would wait for them.
    sims = [partial(simulate_files, params, wanted, progress=fold.progress)]
    if fold.scale.current_input and fold.scale.session_draws > 0:
        sims.append(partial(_draw_sessions, fold, params))
    files, *drawn = timed("simulate", side_by_side, sims, fold.workers(len(sims)))

    def paper() -> dict:
        with fold.member("scratch", "paper"):
            timed("train", partial(train, overwrite=True, progress=fold.progress,
                                   session=fold.session,
                                   samples_per_object=fold.scale.per_load),
                  files, fold.dir / "models", fold.scale.train.replace(seed=fold.seed))
        return timed("evaluate", fold.judge, fold.dir / "models")

    # The candidates trained on the fold's simulated data are independent of each other: side
    # by side on an accelerator (their trainings share programs), in this order on a CPU.
    calls = [fold.branch(paper, "paper"),
             lambda: (timed("randomized", _randomized, fold, params, files)
                      if fold.scale.randomize_draws > 0 else None),
             fold.branch(lambda: timed("fine-tune", _finetuned, fold, files), "physical"),
             fold.branch(lambda: (timed("current input", _finetuned, fold, files, True)
                                  if fold.scale.current_input else (None, {})),
                         "physical_current"),
             fold.branch(lambda: (timed("sessions drawn", _finetuned, fold,
                                        drawn[0] + files[1:], True, "_current_sessions")
                                  if drawn else (None, {})), "physical_current_sessions")]
    ours, randomized, (physical, fine), (physical_c, fine_c), (physical_s, fine_s) = \
        side_by_side(calls, fold.workers(len(calls)))
    return {"held_out": fold.held, "ours": ours["objects"], "torque": ours["torque"],
            "session_ratio": ours["session_ratio"], "by_strength": ours["by_strength"],
            "physical": physical, "fine_tuned": fine, "randomized": randomized,
            "physical_current": physical_c, "fine_tuned_current": fine_c,
            "physical_current_sessions": physical_s, "fine_tuned_current_sessions": fine_s,
            "ensemble": _ensemble(fold), **replay,
            "wall_time_s": {k: wall.get(k, 0.0) for k in (
                "calibrate", "simulate", "train", "evaluate", "randomized", "fine-tune",
                "current input", "sessions drawn")}}


#: Judged folders that are no candidate of the recipe (:func:`jaxinertia.app.recipe.candidates`).
_NOT_CANDIDATES = ("models_randomized",)


def _ensemble(fold: Fold) -> dict | None:
    """Every candidate of the fold averaged (:func:`jaxinertia.app.ensemble.judge_mean`)
    on its held-out objects; the recipe may choose it (``models_real`` then makes every
    member on the real files)."""
    idx = fold.held_index
    return judge_mean({k: v for k, v in fold.estimates.items() if k[0] not in _NOT_CANDIDATES},
                      [fold.real.objects[i] for i in idx], [fold.real.l_max[i] for i in idx],
                      fold.scale.session_strengths)


def _randomized(fold: Fold, params, files: list[Path]) -> dict:
    """Models trained on domain-randomized data, judged like the others."""
    obj = fold.record(fold.fit_on)
    spread = spread_from_samples(obj.q_d, obj.q, obj.direction, obj.tau)
    dr_files = simulate_files(params, [
        (fold.dir / "data" / "train_random_randomized.npz", "random",
         fold.scale.random_per_load, fold.seed)], spread=spread,
        draws=fold.scale.randomize_draws, progress=fold.progress)
    train(dr_files + files[1:], fold.dir / "models_randomized",
          fold.scale.train.replace(seed=fold.seed), overwrite=True, progress=fold.progress,
          session=fold.session, samples_per_object=fold.scale.per_load)
    res = fold.judge(fold.dir / "models_randomized")
    return {**res, "spread": spread.to_dict(), "draws": fold.scale.randomize_draws}


def _draw_sessions(fold: Fold, params) -> list[Path]:
    """The random scenario simulated over ``session_draws`` recording sessions drawn around
    the fold's calibration, for the current-input candidates trained on them (with the
    planning grid as simulated)."""
    return simulate_files(params, [
        (fold.dir / "data" / "train_random_sessions.npz", "random", fold.scale.random_per_load,
         fold.seed)], spread=session_prior(params.robot.n_joints),
        draws=fold.scale.session_draws, progress=fold.progress)


def _finetuned(fold: Fold, files: list[Path], current_input: bool = False,
               tag: str | None = None) -> tuple[dict | None, dict]:
    """The physical model trained on the simulated files (``current_input``: with the
    servo's current as a fifth input), then its servo part fine-tuned on each number of
    ``fit_on``'s real samples (beside as many of each load of ``files[0]``: the anchor); all
    judged on the held-out objects. ``tag``: the folders' suffix (default: ``_current``
    with the current input, none without)."""
    if not fold.scale.finetune_samples:
        return None, {}
    if tag is None:
        tag = "_current" if current_input else ""
    start = fold.dir / f"models_physical{tag}"
    # On an accelerator the fine-tunings start from the start's torque models while its
    # attention trains (they keep it: app.fit.EarlyStart); on a CPU from its folder.
    early = EarlyStart(start) if fold.groups is not None else None

    def fit_start() -> None:
        with fold.member("scratch", f"physical{tag}"):
            train(files, start, fold.scale.train.replace(
                seed=fold.seed, torque_model="physical", current_input=current_input),
                  overwrite=True, progress=fold.progress, session=fold.session, early=early,
                  samples_per_object=fold.scale.per_load)
    anchor = files[:1] if fold.scale.finetune_anchor else []
    data = [fold.real.files[fold.index(fold.fit_on)], *anchor]

    def finetune(n: int) -> dict:
        models = fold.dir / f"models_finetuned{tag}_{n}"
        with fold.member("finetune", f"physical{tag}/{n}"):
            info = train(data, models, fold.scale.finetune.replace(seed=fold.seed),
                         overwrite=True, progress=fold.progress, init=early or start,
                         samples_per_object=n)
        return {**fold.judge(models), "samples": info["samples"], "real_samples": n,
                "anchor": [Path(getattr(f, "path", f)).name for f in anchor],
                "best_epoch": info["best_epoch"],
                "fit_session_ratio": info["data"][0]["session_ratio"]}

    def judged_start() -> dict:
        if early is not None:  # trained here, beside the fine-tunings
            with early.resolving():  # a failure anywhere fails the waiting fine-tunings
                fit_start()
        return fold.judge(start)

    # Each fine-tuning has its own shapes (its own programs): they compile side by side,
    # and each runs in one program with the other branches' and folds' of its shapes.
    sizes = fold.scale.finetune_samples
    if early is None:
        fit_start()
    calls = [judged_start] + [partial(finetune, n) for n in sizes]
    physical, *fine = side_by_side(calls, fold.workers(len(calls)))
    return physical, {str(n): f for n, f in zip(sizes, fine)}
