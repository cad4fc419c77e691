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
from jaxinertia.app.ensemble import attach_members
from jaxinertia.app.pipeline import RealData, copy_models, evaluate_models, train
from jaxinertia.app.programs import side_by_side, side_by_side_workers
from jaxinertia.app.simdata import simulate_files
from jaxinertia.open_manipulator_x import load_sim_fit
from jaxinertia.session import ServoSession, servo_session
from jaxinertia.sim.params import arm_sim_params
from jaxinertia.sim.randomize import session_prior
from jaxinertia.training import FINETUNE_DEFAULTS, TrainConfig
from jaxinertia.training_group import TrainingGroup

__all__ = ["DEFAULT_RECIPE", "fold_kinds", "models_real", "recipe_of", "sim_fit_session",
           "train_starts"]

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
            part["mass"].get(k) == part["com"].get(k)
            for k in ("candidate", "session_strength", "attention")):
        return {**best, "chosen_by": "held-out folds"}
    return {**part["mass"], "com": part["com"], "score": part["score"],
            "single_model_recipe": {k: v for k, v in best.items() if k not in ("scores",
                                                                               "by_part")},
            "chosen_by": "held-out folds, mass and COM judged apart"}


def fold_kinds(scale) -> list[tuple[bool, bool]]:
    """The kinds (current input, drawn sessions) of simulator-trained physical model that
    the folds' candidates start from at ``scale`` (a :class:`jaxinertia.app.reproduce.Scale`):
    what ``models_real`` may need, whatever the recipe."""
    if not scale.fold_finetune_samples:
        return []
    kinds = [(False, False)]
    if scale.fold_current_input:
        kinds.append((True, False))
        if scale.fold_session_draws > 0:
            kinds.append((True, True))
    return kinds


def train_starts(out: Path, train_files: list[Path], scale, kinds, seed: int,
                 progress: bool, session: ServoSession | None) -> dict[tuple, Path]:
    """The simulator-trained physical models of ``kinds`` (current input, drawn sessions)
    that ``models_real``'s candidates start from, trained on the run's simulated files
    (drawn sessions: the random scenario simulated over them, once), at the folds' training
    strength, in ``out/models_physical[_current[_sessions]]``; on an accelerator side by
    side. Returns their folders by kind."""
    kinds = sorted(set(kinds))
    files = train_files
    if any(drawn for _, drawn in kinds):  # the random scenario over drawn sessions, once
        params = arm_sim_params()
        files = simulate_files(params, [
            (out / "data" / "train_random_sessions.npz", "random", scale.random_per_load,
             seed)], spread=session_prior(params.robot.n_joints),
            draws=scale.fold_session_draws or 4, progress=progress) + train_files[1:]
    start_dir = {k: out / f"models_physical{_TAGS[k]}" for k in kinds}

    def train_start(kind):
        current, drawn = kind
        cfg = scale.train.replace(seed=seed, torque_model="physical", current_input=current)
        train(files if drawn else train_files, start_dir[kind], cfg, overwrite=True,
              progress=progress, session=session)

    _trainings({start_dir[k].name: partial(train_start, k) for k in kinds})
    return start_dir


def models_real(out: Path, train_files: list[Path], real: RealData, scale,
                 recipe: dict, seed: int, progress: bool,
                 session: ServoSession | None,
                 starts: dict[tuple, Path] | None = None) -> dict:
    """``out/models_real``, the models for a new real object, made as ``recipe`` says (the
    held-out folds' choice; with the COM's recipe under ``com``, its models in
    ``models_real/com``, the COM's source, :mod:`jaxinertia.app.by_part`). Evaluated on
    the real files (not held out).

    Each folder is made as the folds made the candidate they judged: the physical model
    trained on the simulated files, and fine-tuned, at the folds' training strength
    (``scale.train``'s and :data:`FINETUNE_DEFAULTS`' ``session_strength``: with both real
    files, each read in the models' reference session), then written with the strength the
    recipe chose, the strength it was judged at, and without their attention where the
    recipe says so (every joint weighted alike: T-A answers as T, the way the folds judged
    it: :func:`jaxinertia.networks.uniform_attention`). Where the recipe is the folds' average of
    every candidate (:mod:`jaxinertia.app.ensemble`), each of its members is made so, and
    lands in ``models_real/members/<i>`` (the first in ``models_real`` itself). A
    simulator-trained model is trained once per kind, as the folds name theirs
    (``models_physical[_current[_sessions]]``), shared by every candidate that starts from
    it, a fine-tuning once per kind and sample count (``models_real_finetuned<kind>_<n>``);
    the folders are copied from there (``starts``: those already trained by
    :func:`train_starts`, by kind). The paper network from the simulator alone is the
    run's ``models``."""
    dst = out / "models_real"
    parts = {"mass": recipe, "com": recipe["com"]} if recipe.get("com") else {"mass": recipe}
    # Each part is one folder, or the mean of several (the folds' average of every
    # candidate: app.ensemble): the folders to make, by name, each a single candidate.
    units = {part: [r] if not r.get("members") else
             [{**m, "session_strength": r["session_strength"],
               "attention": r.get("attention", True)} for m in r["members"]]
             for part, r in parts.items()}
    every = [u for us in units.values() for u in us]
    kinds = sorted({_kind(u) for u in every if not u["candidate"].startswith("paper")})
    # The simulator-trained models the candidates start from: one per kind, shared.
    start_dir = {k: v for k, v in (starts or {}).items() if k in kinds}
    start_dir.update(train_starts(out, train_files, scale, [k for k in kinds
                                                            if k not in start_dir],
                                  seed, progress, session))
    # The fine-tunings on every real file: one per kind and sample count, shared.
    tunings = sorted({(_kind(u), _samples(u, scale)) for u in every
                      if "fine-tuned" in u["candidate"]})
    tuned = {t: out / f"models_real_finetuned{_TAGS[t[0]]}_{t[1]}" for t in tunings}

    def finetune(t):
        return train(real.files, tuned[t], TrainConfig(**FINETUNE_DEFAULTS, seed=seed,
                                                       trainable="servo"),
                     overwrite=True, progress=progress, init=start_dir[t[0]],
                     samples_per_object=t[1])

    infos = _trainings({tuned[t].name: partial(finetune, t) for t in tunings})

    def source(u):
        if "fine-tuned" in u["candidate"]:
            return tuned[(_kind(u), _samples(u, scale))]
        return out / "models" if u["candidate"].startswith("paper") else start_dir[_kind(u)]

    # Each part's folder, read at its recipe's strength (an ensemble's members inside its
    # folder); the COM's inside the mass's.
    where = {"mass": dst, "com": out / "models_real_com"}
    def copy(u, dst):  # read at the recipe's strength, with its attention or without
        copy_models(source(u), dst, session_strength=float(u["session_strength"]),
                    uniform=not u.get("attention", True))

    for part, us in units.items():
        copy(us[0], where[part])
        names = [f"members/{i}" for i in range(1, len(us))]
        for name, u in zip(names, us[1:]):
            copy(u, where[part] / name)
        if names:
            attach_members(where[part], names)
    if "com" in parts:
        shutil.rmtree(dst / "com", ignore_errors=True)
        shutil.move(where["com"], dst / "com")
        attach_com_models(dst, "com")
    res = evaluate_models(dst, real.objects, real.sets, l_max=real.l_max)
    mass = units["mass"][0]
    info = infos.get(tuned[(_kind(mass), _samples(mass, scale))].name) \
        if "fine-tuned" in mass["candidate"] else None
    return {"objects": res["objects"], "files": [str(f.path) for f in real.files],
            "samples": None if info is None else info["samples"], "models": str(dst),
            "recipe": recipe, "session_ratio": res["session_ratio"]}


#: A simulator-trained physical model's folder suffix by its kind (current input, drawn
#: sessions), as the folds name theirs.
_TAGS = {(False, False): "", (True, False): "_current", (True, True): "_current_sessions",
         (False, True): "_sessions"}


def _kind(recipe: dict) -> tuple[bool, bool]:
    """A single candidate's simulator-trained start: (current input, drawn sessions)."""
    return bool(recipe.get("current_input")), bool(recipe.get("sessions_drawn"))


def _samples(recipe: dict, scale) -> int:
    """The real samples per file a fine-tuned candidate takes."""
    return recipe.get("finetune_samples") or scale.real_finetune_samples


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
