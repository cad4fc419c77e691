"""``models_real``: the models ``reproduce`` leaves for a real object none of them saw,
made as the held-out folds' recipe says (:mod:`jaxinertia.app.recipe`; mass and COM from
their own models where the folds judge them apart, :mod:`jaxinertia.app.by_part`).

Where the folds ran, ``models_real`` *is* the folds' own models (:func:`models_from_folds`):
for each part, the chosen candidate's folder of every fold, each calibrated, trained and
fine-tuned on one real file (one recording session) and judged on the others, averaged over
the folds. Without folds (fewer than two real files), :func:`models_real` makes the default
recipe's models on the shipped calibration and every real file. The ``scale`` arguments are
the run's :class:`jaxinertia.app.reproduce.Scale` (not imported: ``reproduce`` imports this
module)."""

from __future__ import annotations

import contextlib
from pathlib import Path

from jaxinertia.app.by_part import attach_com_models
from jaxinertia.app.ensemble import attach_members
from jaxinertia.app.pipeline import RealData, copy_models, evaluate_models, train
from jaxinertia.app.provenance import record_fitted_on
from jaxinertia.app.recipe import candidate_of_folder, fold_draws
from jaxinertia.fileio import replacing_dir
from jaxinertia.open_manipulator_x import load_sim_fit
from jaxinertia.session import ServoSession, servo_session
from jaxinertia.training import FINETUNE_DEFAULTS, TrainConfig

__all__ = ["DEFAULT_RECIPE", "models_from_folds", "models_real", "recipe_of",
           "sim_fit_files", "sim_fit_session"]

#: The recipe for the models of a new real object when no held-out folds chose one: the
#: physical model fine-tuned on every real file, sessions adapted.
DEFAULT_RECIPE = {"candidate": "physical, servo part fine-tuned", "session_strength": 1.0,
                  "current_input": False,
                  "finetune_samples": None, "chosen_by": "default (no held-out folds)"}


def sim_fit_session(real: RealData | None) -> ServoSession | None:
    """The session of the real files the shipped simulator fit was fitted on (its
    ``link_gravity.source``), pooled, when the folder has them: the servo state that the
    simulated data imitate, the reference of models trained on them."""
    used = [o for o, _ in _sim_fit_files(real)]
    return servo_session(used) if used else None


def sim_fit_files(real: RealData | None) -> list[dict]:
    """Those files, as a model folder records what it was fitted on
    (:func:`jaxinertia.app.provenance.record_fitted_on`)."""
    return [{"file": f.path.name, "sha256": f.meta.get("sha256")}
            for _, f in _sim_fit_files(real)]


def _sim_fit_files(real: RealData | None) -> list:
    names = set(load_sim_fit()["link_gravity"].get("source", ()))
    return [(o, f) for o, f in zip(real.objects, real.files) if o.name in names] if real else []


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


def models_real(out: Path, train_files: list[Path], real: RealData, scale,
                recipe: dict, seed: int, progress: bool,
                session: ServoSession | None) -> dict:
    """``out/models_real`` where no folds ran (fewer than two real files, or none asked
    for): ``recipe`` (:data:`DEFAULT_RECIPE`) on the shipped calibration. The physical
    model trained on the run's simulated files (``out/models_physical``), its servo part
    fine-tuned on every real file (``out/models_real_finetuned_<n>``), written with the
    recipe's session strength. Its fine-tuning also sees as many samples of each load of
    the run's simulated random data (``train_files[0]``) as of each real file, as the
    folds' fine-tunings do (``FoldScale.finetune_anchor``; docs/results.md, "The
    simulator's loads beside the real one"). Evaluated on the real files (not held out)."""
    start = out / "models_physical"
    train(train_files, start, scale.train.replace(seed=seed, torque_model="physical"),
          overwrite=True, progress=progress, session=session)
    record_fitted_on(start, sim_fit_files(real))  # its simulator's real files, passed on
    n = recipe.get("finetune_samples") or scale.real_finetune_samples
    tuned = out / f"models_real_finetuned_{n}"
    anchor = train_files[:1]
    info = train([*real.files, *anchor], tuned, TrainConfig(**FINETUNE_DEFAULTS, seed=seed,
                                                            trainable="servo"),
                 overwrite=True, progress=progress, init=start, samples_per_object=n)
    dst = copy_models(tuned, out / "models_real",
                      session_strength=float(recipe["session_strength"]))
    res = evaluate_models(dst, real.objects, real.sets, l_max=real.l_max)
    return {"objects": res["objects"], "files": [str(f.path) for f in real.files],
            "samples": info["samples"], "real_samples": n,
            "anchor": [Path(getattr(f, "path", f)).name for f in anchor], "models": str(dst),
            "recipe": recipe,
            "session_ratio": res["session_ratio"]}


def models_from_folds(out: Path, folds: dict, real: RealData, recipe: dict, *,
                      fold_dirs: list[Path] | None = None, dst: Path | None = None) -> dict:
    """``out/models_real`` made of the held-out folds' own model folders
    (``out/folds/fit_<object>/models*``): for each part of ``recipe`` (the mass's, and the
    COM's under ``com``), every candidate it names (one, or every member of the folds'
    average), from every fold, written at the recipe's strength and with or without the
    attention as the recipe says; the first in ``models_real`` (or ``models_real/com``),
    the others as members (``members/<i>``) that it answers with the mean of
    (:mod:`jaxinertia.app.ensemble`). Each member is the very folder a fold judged on the
    real files it did not see: calibrated from the datasheet, trained and fine-tuned on
    one real file, so each keeps that file's session as its reference. Evaluated on the
    real files (not held out: each was seen by its own fold's members). ``fold_dirs``: the
    folds' folders (default: every training draw's of ``folds`` in ``out/folds``; several
    runs' folds, :mod:`jaxinertia.app.draws`); ``dst``: the folder written (default
    ``out/models_real``)."""
    dst = dst or out / "models_real"
    if fold_dirs is None:  # every training draw's (the first's under out/folds itself)
        fold_dirs = [out / "folds" / d / f"fit_{name}" for d, by_fit in fold_draws(folds)
                     for name in by_fit]
    by_candidate = []
    for d in fold_dirs:
        found = {}
        for p in sorted(d.glob("models*")):
            if (p / "config.json").is_file():
                with contextlib.suppress(ValueError):  # not a candidate (randomized ones)
                    found[candidate_of_folder(p.name)] = p
        by_candidate.append(found)
    parts = {"mass": recipe, "com": recipe["com"]} if recipe.get("com") else {"mass": recipe}
    # The real file each fold was calibrated, trained and fine-tuned on, for every copy.
    seen = {f"fit_{o.name}": {"file": f.path.name, "sha256": f.meta.get("sha256")}
            for o, f in zip(real.objects, real.files)}
    made = {}
    # Written beside and put in place once complete: an interrupted run leaves the previous
    # models_real (or none), never one that answers without its members or COM part.
    with replacing_dir(dst) as tmp:
        where = {"mass": tmp, "com": tmp / "com"}
        for part, r in parts.items():
            units = [r] if not r.get("members") else r["members"]
            sources = []
            for u in units:
                for d, found in zip(fold_dirs, by_candidate):
                    if u["candidate"] not in found:
                        raise FileNotFoundError(f"{d}: no folder of the candidate "
                                                f"{u['candidate']!r} that the recipe names")
                    sources.append(found[u["candidate"]])
            names = [""] + [f"members/{i}" for i in range(1, len(sources))]
            for name, src in zip(names, sources):
                copy_models(src, where[part] / name,
                            session_strength=float(r["session_strength"]),
                            uniform=not r.get("attention", True))
                record_fitted_on(where[part] / name, [seen[src.parent.name]])
            if len(names) > 1:
                attach_members(where[part], names[1:])
            made[part] = [str(s.relative_to(out)) if s.is_relative_to(out) else str(s)
                          for s in sources]
        if "com" in parts:
            attach_com_models(tmp, "com")
    res = evaluate_models(dst, real.objects, real.sets, l_max=real.l_max)
    return {"objects": res["objects"], "files": [str(f.path) for f in real.files],
            "samples": None, "models": str(dst), "recipe": recipe,
            "session_ratio": res["session_ratio"], "from_folds": made}
