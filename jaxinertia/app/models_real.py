"""``models_real``: the models ``reproduce`` leaves for a real object none of them saw,
made as the held-out folds' recipe says (:mod:`jaxinertia.app.recipe`; mass and COM from
their own models where the folds judge them apart, :mod:`jaxinertia.app.by_part`). The
``scale`` arguments are the run's :class:`jaxinertia.app.reproduce.Scale` (not imported:
``reproduce`` imports this module)."""

from __future__ import annotations

import contextlib
import shutil
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

from jaxinertia.app.by_part import attach_com_models
from jaxinertia.app.pipeline import RealData, copy_models, evaluate_models, train
from jaxinertia.app.programs import side_by_side, side_by_side_workers
from jaxinertia.app.simdata import simulate_files
from jaxinertia.open_manipulator_x import load_sim_fit
from jaxinertia.session import ServoSession, servo_session
from jaxinertia.sim.params import arm_sim_params
from jaxinertia.sim.randomize import session_prior
from jaxinertia.training import FINETUNE_DEFAULTS, TrainConfig
from jaxinertia.training_group import TrainingGroup

__all__ = ["DEFAULT_RECIPE", "models_real", "recipe_of", "sim_fit_session"]

#: The recipe for the models of a new real object when no held-out folds chose one: the
#: physical model fine-tuned on every real file, sessions adapted.
DEFAULT_RECIPE = {"candidate": "physical, servo part fine-tuned", "session_strength": 1.0,
                  "current_input": False,
                  "finetune_samples": None, "chosen_by": "default (no held-out folds)"}


def sim_fit_session(real: RealData | None) -> ServoSession | None:
    """The session of the real files the shipped simulator fit was fitted on (its
    ``link_gravity.source``), pooled, when the folder has them: the servo state that the
    simulated data imitate, the reference of models trained on them."""
    names = set(load_sim_fit()["link_gravity"].get("source", ()))
    used = [o for o in (real.objects if real else ()) if o.name in names]
    return servo_session(used) if used else None


def recipe_of(folds: dict | None, scale) -> dict:
    """The recipe of ``models_real``: the folds' best candidate, or, with
    ``scale.recipe_by_part`` and where the folds' best for the mass and for the COM differ,
    the mass's with the COM's under ``com`` (:mod:`jaxinertia.app.by_part`)."""
    if not folds:
        return DEFAULT_RECIPE
    best, part = folds["recipe"], folds["recipe"]["by_part"]
    if not scale.recipe_by_part or part["score"] >= best["score"] or all(
            part["mass"][k] == part["com"][k] for k in ("candidate", "session_strength")):
        return {**best, "chosen_by": "held-out folds"}
    return {**part["mass"], "com": part["com"], "score": part["score"],
            "single_model_recipe": {k: v for k, v in best.items() if k not in ("scores",
                                                                               "by_part")},
            "chosen_by": "held-out folds, mass and COM judged apart"}


def models_real(out: Path, train_files: list[Path], real: RealData, scale,
                 recipe: dict, seed: int, progress: bool,
                 session: ServoSession | None) -> dict:
    """``out/models_real``, the models for a new real object, made as ``recipe`` says (the
    held-out folds' choice; with the COM's recipe under ``com``, its models in
    ``models_real/com``, the COM's source, :mod:`jaxinertia.app.by_part`). Evaluated on
    the real files (not held out).

    Each folder is made as the folds made the candidate they judged: the physical model
    trained on the simulated files, and fine-tuned, at the folds' training strength
    (``scale.train``'s and :data:`FINETUNE_DEFAULTS`' ``session_strength``: with both real
    files, each read in the models' reference session), then written with the strength the
    recipe chose, the strength it was judged at. A simulator-trained model that the mass's
    and the COM's candidates share is trained once (``models_physical``; another one:
    ``models_physical_com``), a fine-tuning lands in ``models_real_finetuned[_com]`` and is
    copied from there."""
    dst = out / "models_real"
    recipes = {"mass": recipe, "com": recipe["com"]} if recipe.get("com") else {"mass": recipe}
    starts: dict[tuple, list[str]] = {}  # the simulator-trained models the parts start from
    for part, r in recipes.items():
        if not r["candidate"].startswith("paper"):
            starts.setdefault((bool(r.get("current_input")), bool(r.get("sessions_drawn"))),
                              []).append(part)
    files = train_files
    if any(drawn for _, drawn in starts):  # the random scenario over drawn sessions, once
        params = arm_sim_params()
        files = simulate_files(params, [
            (out / "data" / "train_random_sessions.npz", "random", scale.random_per_load,
             seed)], spread=session_prior(params.robot.n_joints),
            draws=scale.fold_session_draws or 4, progress=progress) + train_files[1:]
    start_dir = {key: out / ("models_physical" + ("" if i == 0 else "_com"))
                 for i, key in enumerate(starts)}

    def train_start(key):
        current, drawn = key
        cfg = scale.train.replace(seed=seed, torque_model="physical", current_input=current)
        train(files if drawn else train_files, start_dir[key], cfg, overwrite=True,
              progress=progress, session=session)

    _trainings({parts[0]: partial(train_start, key) for key, parts in starts.items()})
    start_of = {part: start_dir[key] for key, parts in starts.items() for part in parts}
    tuned = {part: out / ("models_real_finetuned" + ("" if part == "mass" else f"_{part}"))
             for part, r in recipes.items() if "fine-tuned" in r["candidate"]}

    def finetune(part):
        n = recipes[part].get("finetune_samples") or scale.real_finetune_samples
        return train(real.files, tuned[part], TrainConfig(**FINETUNE_DEFAULTS, seed=seed,
                                                          trainable="servo"),
                     overwrite=True, progress=progress, init=start_of[part],
                     samples_per_object=n)

    info = _trainings({part: partial(finetune, part) for part in tuned}).get("mass")
    # Each part's folder, read at its recipe's strength; the COM's inside the mass's.
    where = {"mass": dst, "com": out / "models_real_com"}
    for part, r in recipes.items():
        src = tuned.get(part) or start_of.get(part) or out / "models"
        copy_models(src, where[part], session_strength=float(r["session_strength"]))
    if "com" in recipes:
        shutil.rmtree(dst / "com", ignore_errors=True)
        shutil.move(where["com"], dst / "com")
        attach_com_models(dst, "com")
    res = evaluate_models(dst, real.objects, real.sets, l_max=real.l_max)
    return {"objects": res["objects"], "files": [str(f.path) for f in real.files],
            "samples": None if info is None else info["samples"], "models": str(dst),
            "recipe": recipe, "session_ratio": res["session_ratio"]}


def _trainings(calls: dict[str, Callable[[], Any]]) -> dict:
    """``{name: call()}``; on an accelerator side by side, their trainings of one shape as
    one program (:class:`TrainingGroup`); on a CPU in order."""
    names = list(calls)
    group = TrainingGroup(names) if len(names) > 1 and side_by_side_workers() > 1 else None

    def run(name):
        with group.member(name) if group else contextlib.nullcontext():
            return calls[name]()

    results = side_by_side([partial(run, n) for n in names], len(names) if group else 1)
    return dict(zip(names, results))
