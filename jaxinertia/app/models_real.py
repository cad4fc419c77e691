"""``models_real``: the models ``reproduce`` leaves for a real object none of them saw,
made as the held-out folds' recipe says (:mod:`jaxinertia.app.recipe`; mass and COM from
their own models where the folds judge them apart, :mod:`jaxinertia.app.by_part`). The
``scale`` arguments are the run's :class:`jaxinertia.app.reproduce.Scale` (not imported:
``reproduce`` imports this module)."""

from __future__ import annotations

import contextlib
import shutil
from functools import partial
from pathlib import Path

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
    the real files (not held out)."""
    dst = out / "models_real"
    recipes = {"mass": recipe, "com": recipe["com"]} if recipe.get("com") else {"mass": recipe}
    files = {part: train_files for part in recipes}
    drawn = [part for part, r in recipes.items() if r.get("sessions_drawn")]
    if drawn:  # the random scenario over drawn recording sessions, simulated once
        params = arm_sim_params()
        sessions = simulate_files(params, [
            (out / "data" / "train_random_sessions.npz", "random", scale.random_per_load,
             seed)], spread=session_prior(params.robot.n_joints),
            draws=scale.fold_session_draws or 4, progress=progress) + train_files[1:]
        files.update(dict.fromkeys(drawn, sessions))
    # The COM's folder is written beside and moved into the mass's once both exist (the
    # mass's is written whole, replacing any folder there), each fine-tuning from its own
    # start. On an accelerator the two train side by side, their trainings of one shape as
    # one program.
    where = {"mass": (dst, out / "models_physical"),
             "com": (out / "models_real_com", out / "models_physical_com")}
    group = (TrainingGroup(recipes) if len(recipes) > 1 and side_by_side_workers() > 1
             else None)

    def make(part: str):
        with group.member(part) if group else contextlib.nullcontext():
            return _make_models(*where[part], files[part], real, scale, recipes[part],
                                seed, progress, session, out)

    info, *_ = side_by_side([partial(make, part) for part in recipes],
                            len(recipes) if group else 1)
    if "com" in recipes:
        shutil.rmtree(dst / "com", ignore_errors=True)
        shutil.move(where["com"][0], dst / "com")
        attach_com_models(dst, "com")
    res = evaluate_models(dst, real.objects, real.sets, l_max=real.l_max)
    return {"objects": res["objects"], "files": [str(f.path) for f in real.files],
            "samples": None if info is None else info["samples"], "models": str(dst),
            "recipe": recipe, "session_ratio": res["session_ratio"]}


def _make_models(dst: Path, start: Path, train_files: list[Path], real: RealData,
                 scale, recipe: dict, seed: int, progress: bool,
                 session: ServoSession | None, out: Path) -> dict | None:
    """One model folder at ``dst`` as ``recipe`` says: the run's simulator-trained paper
    models, the physical model trained on the simulated files (``train_files``: with the
    random scenario drawn over recording sessions when a recipe says so), or that model's
    servo part fine-tuned on every real file of the folder; the session strength the
    recipe chose; a fine-tuning starts from the physical model trained at ``start``.
    Returns the fine-tuning's record (None without one)."""
    strength = float(recipe["session_strength"])
    info = None
    if recipe["candidate"].startswith("paper"):
        copy_models(out / "models", dst, session_strength=strength)
    else:
        physical_cfg = scale.train.replace(seed=seed, torque_model="physical",
                                           current_input=bool(recipe.get("current_input")),
                                           session_strength=strength)
        if "fine-tuned" not in recipe["candidate"]:
            train(train_files, dst, physical_cfg, overwrite=True, progress=progress,
                  session=session)
        else:
            train(train_files, start, physical_cfg, overwrite=True, progress=progress,
                  session=session)
            n = recipe.get("finetune_samples") or scale.real_finetune_samples
            info = train(real.files, dst,
                         TrainConfig(**FINETUNE_DEFAULTS, seed=seed, trainable="servo",
                                     session_strength=strength),
                         overwrite=True, progress=progress, init=start, samples_per_object=n)
    return info
