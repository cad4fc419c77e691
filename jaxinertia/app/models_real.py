"""``models_real``: the models ``reproduce`` leaves for a real object none of them saw,
made as the held-out folds' recipe says (:mod:`jaxinertia.app.recipe`; mass and COM from
their own models where the folds judge them apart, :mod:`jaxinertia.app.by_part`). The
``scale`` arguments are the run's :class:`jaxinertia.app.reproduce.Scale` (not imported:
``reproduce`` imports this module)."""

from __future__ import annotations

from pathlib import Path

from jaxinertia.app.by_part import attach_com_models
from jaxinertia.app.pipeline import RealData, copy_models, evaluate_models, train
from jaxinertia.app.simdata import simulate_files
from jaxinertia.open_manipulator_x import load_sim_fit
from jaxinertia.session import ServoSession, servo_session
from jaxinertia.sim.params import arm_sim_params
from jaxinertia.sim.randomize import session_prior
from jaxinertia.training import FINETUNE_DEFAULTS, TrainConfig

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
    info = _make_models(out, dst, train_files, real, scale, recipe, seed, progress, session)
    if recipe.get("com"):
        _make_models(out, dst / "com", train_files, real, scale, recipe["com"], seed,
                     progress, session)
        attach_com_models(dst, "com")
    res = evaluate_models(dst, real.objects, real.sets, l_max=real.l_max)
    return {"objects": res["objects"], "files": [str(f.path) for f in real.files],
            "samples": None if info is None else info["samples"], "models": str(dst),
            "recipe": recipe, "session_ratio": res["session_ratio"]}


def _make_models(out: Path, dst: Path, train_files: list[Path], real: RealData,
                 scale, recipe: dict, seed: int, progress: bool,
                 session: ServoSession | None) -> dict | None:
    """One model folder at ``dst`` as ``recipe`` says: the run's simulator-trained paper
    models, the physical model trained on the simulated files (the random scenario's drawn
    over recording sessions when the recipe says so), or that model's servo part
    fine-tuned on every real file of the folder; the session strength the recipe chose.
    Returns the fine-tuning's record (None without one)."""
    strength = float(recipe["session_strength"])
    info = None
    if recipe.get("sessions_drawn"):
        params = arm_sim_params()
        train_files = simulate_files(params, [
            (out / "data" / "train_random_sessions.npz", "random", scale.random_per_load, seed)],
            spread=session_prior(params.robot.n_joints),
            draws=scale.fold_session_draws or 4, progress=progress) + train_files[1:]
    if recipe["candidate"].startswith("paper"):
        copy_models(out / "models", dst, session_strength=strength)
    else:
        start = out / "models_physical"
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
