"""``models_real_with_released``: ``models_real`` averaged with the authors' released
models, half and half (the OpenMANIPULATOR-X only: the released models are its).

Why (docs/results.md, "The authors' models averaged in"): on each held-out real file, the
two estimators err on opposite sides. ``models_real``'s parts (trained on the simulator,
fine-tuned on one known real object) miss both files' mass low; the released models
(trained by the authors on 82k real samples of other objects, never on cube or white) miss
it high. Their mean is judged by the held-out folds exactly as ``models_real``'s parts are
(:func:`judge_with_released`: each fold's own models of the recipe's parts, the released
models' estimates on the same sets, averaged per model pair and set), so the half-and-half
share is fixed before any number and nothing is fitted on the file it is judged on. It is
a second folder beside ``models_real``, never a candidate of the recipe: ``models_real``
stays the project's own models, judged against the released ones.

The released models are written as a model folder (:func:`released_folder`: their
weights, the authors' input scaling, no session: a file is read as recorded) and added to
each part of a copy of ``models_real`` as a member whose share is one half
(:data:`jaxinertia.app.ensemble.ENSEMBLE_WEIGHTS`).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from jaxinertia.app.by_part import com_models_of
from jaxinertia.app.ensemble import (
    ENSEMBLE_MEMBERS,
    attach_members,
    finite_estimates,
    mean_estimates,
)
from jaxinertia.app.pipeline import RealData, evaluate_models
from jaxinertia.app.recipe import candidate_of_folder
from jaxinertia.checkpoints import load_models, read_config, save_models
from jaxinertia.features import LBIPE_FEATURES
from jaxinertia.fileio import replacing_dir
from jaxinertia.lbipe import load_released_models
from jaxinertia.metrics import inertial_metrics

__all__ = ["RELEASED", "RELEASED_SHARE", "drop_with_released", "judge_draws",
           "judge_each_draw", "judge_with_released", "models_with_released", "released_folder"]

#: The released models' share of the mean (the rest: ``models_real``'s members alike).
RELEASED_SHARE = 0.5
#: The released models' member folder inside each part.
RELEASED = "released"


def released_folder(dst: Path, real: RealData, like) -> Path:
    """The authors' released model pairs of ``real``'s lbipe folder written as a model
    folder at ``dst`` (the baselines, robot and arm of ``like``, a loaded model folder:
    the member of an ensemble answers only with its networks)."""
    pair = load_released_models(real.layout.weights_dir, prefer=real.layout.prefer)
    return save_models(dst, pair, like.baselines, LBIPE_FEATURES, robot=like.config["robot"],
                       arm=like.config.get("arm"),
                       extra={"source": f"the authors' released models "
                                        f"({real.layout.weights_dir})", "session": None})


def models_with_released(out: Path, real: RealData, share: float = RELEASED_SHARE, *,
                         src: Path | None = None, dst: Path | None = None) -> dict:
    """``out/models_real_with_released``: a copy of ``out/models_real`` whose parts (the
    mass's and the COM's) each answer with ``share`` of the released models and the rest
    of their own members alike; evaluated on the real files (**not held out**: each file
    was seen by ``models_real``'s members of its own fold). ``src``, ``dst``: another
    ``models_real`` and where its average goes (:mod:`jaxinertia.app.draws`' judges)."""
    src = src or out / "models_real"
    dst = dst or out / "models_real_with_released"
    with replacing_dir(dst) as tmp:  # in place once complete, never half written
        shutil.copytree(src, tmp, dirs_exist_ok=True)
        like = load_models(tmp)
        com = com_models_of(tmp, like.config)
        written = released_folder(tmp / RELEASED, real, like)  # loaded and written once
        if com is not None:
            shutil.copytree(written, com / RELEASED)
        for part in [tmp] + ([com] if com is not None else []):
            members = read_config(part).get(ENSEMBLE_MEMBERS) or []
            n = len(members) + 1
            attach_members(part, [*members, RELEASED], [(1 - share) / n] * n + [share])
    res = evaluate_models(dst, real.objects, real.sets, l_max=real.l_max)
    return {"objects": res["objects"], "models": str(dst), "released_share": share}


def drop_with_released(out: Path) -> Path | None:
    """Removes ``out/models_real_with_released`` when there is one (a run that remade
    ``models_real`` without the folds has no average of it to write: an older one would
    average the *previous* ``models_real``); returns the folder removed, else None."""
    dst = out / "models_real_with_released"
    if not dst.exists():
        return None
    shutil.rmtree(dst)
    return dst


def judge_with_released(folds: dict, estimates: dict, released: dict, real: RealData,
                        recipe: dict, share: float = RELEASED_SHARE) -> dict:
    """The held-out folds' judgement of ``models_real_with_released``: per fold and
    held-out object, each part of ``recipe`` (``models_real``'s: the mass's, and the COM's
    under ``com``) from that fold's own models of every training draw, as the fold judged
    them (``estimates``: fold -> one per draw: (folder name, strength) -> {method: (held
    objects, K, B, 4)}), averaged with ``released`` (the released models' estimates
    ``{method: (objects, K, B, 4)}`` on the same sets) at ``share``; scored as the recipe
    is (NMAE over the released models' T-A)."""
    return {"released_share": share,
            **judge_draws(folds, estimates, real, recipe, released=released, share=share)}


def judge_draws(folds: dict, estimates: dict, real: RealData, recipe: dict, *,
                released: dict | None = None, share: float = 0.0) -> dict:
    """``models_real`` judged by the held-out folds from their estimates in memory
    (:func:`jaxinertia.app.folds.run_folds`' ``keep``): on each held-out file, each part of
    ``recipe`` averaged over the members that did not see it (its candidates, of every
    training draw's fold fitted on the other file), as :func:`jaxinertia.app.models_real.
    models_from_folds` averages them; with ``released``, that mean and the released models'
    at ``share``. Scored as the recipe is (NMAE over the released models' T-A): with one
    draw and no released models, the recipe's own score."""
    names = [o.name for o in real.objects]
    parts = {"mass": recipe, "com": recipe.get("com") or recipe}
    ratios: dict[str, list[float]] = {"mass": [], "com": []}
    out: dict = {}
    for fit_on, fold in folds["folds"].items():
        draws = estimates[fit_on]
        folder_of = {}
        for folder, _ in draws[0]:
            try:
                folder_of[candidate_of_folder(folder)] = folder
            except ValueError:  # not a candidate (the randomized models)
                pass
        for i, held in enumerate(fold["held_out"]):
            g = names.index(held)
            row = {}
            for part, r in parts.items():
                s = next(k for _, k in draws[0] if float(k) == float(r["session_strength"]))
                method = "T-A" if r.get("attention", True) else "T"
                units = r.get("members") or [r]
                ours = [est[(folder_of[u["candidate"]], s)][method][i] for est in draws
                        for u in units]
                x = mean_estimates(ours, [u["candidate"] for _ in draws for u in units])
                if released is not None:
                    x = mean_estimates([x, released["T-A"][g]], ["models_real", "released"],
                                       [1 - share, share])
                row[part] = inertial_metrics(finite_estimates(x), real.objects[g].x[0],
                                             real.l_max[g])
                ref = fold["released"][held]["T-A"][f"{part}_NMAE_pct"]
                ratios[part].append(row[part][f"{part}_NMAE_pct"] / ref)
            out.setdefault(fit_on, {})[held] = {
                "mass_NMAE_pct": row["mass"]["mass_NMAE_pct"],
                "com_NMAE_pct": row["com"]["com_NMAE_pct"], "mass_part": row["mass"],
                "com_part": row["com"]}
    mass, com = float(np.mean(ratios["mass"])), float(np.mean(ratios["com"]))
    return {"draws": len(next(iter(estimates.values()))), "folds": out, "mass_score": mass,
            "com_score": com, "score": 0.5 * (mass + com)}


def judge_each_draw(folds: dict, estimates: dict, real: RealData, recipe: dict) -> list[dict]:
    """Each training draw of ``folds`` alone (:func:`judge_draws` of its folds and its
    estimates only), the same ``recipe``: what one draw would have scored beside the
    draws' mean. ``[{"seed", "score", "mass_score", "com_score"}]``, one per draw."""
    out = []
    for k, draw in enumerate(folds.get("draws") or [{"seed": folds["seeds"][0],
                                                     "folds": folds["folds"]}]):
        alone = judge_draws({"folds": draw["folds"]}, {f: [e[k]] for f, e in estimates.items()},
                            real, recipe)
        out.append({"seed": draw["seed"],
                    **{key: alone[key] for key in ("score", "mass_score", "com_score")}})
    return out
