"""The recipe for the models of a new real object, chosen from the held-out folds alone
(:func:`jaxinertia.app.folds.run_folds`): every candidate a fold trained (paper network or
physical model; with the paper's inputs, the current input, drawn sessions; simulator only
or fine-tuned on so many real samples; and their average) at every session strength, with
its attention and without (T-A, T), scored by its error on the held-out files over the
released models' on the same sets; and the two parts, mass and COM, judged apart
(:mod:`jaxinertia.app.by_part`)."""

from __future__ import annotations

from functools import partial

import numpy as np

__all__ = ["ATTENTION", "CURRENT", "ENSEMBLE", "SESSIONS", "candidate_of_folder",
           "candidates", "choose_recipe", "fold_draws", "pooled_folds"]


def candidates(fold: dict) -> dict[str, dict]:
    """A fold's candidate recipes: name -> {strength: held-out objects}."""
    out = {"paper network, simulator only": fold["by_strength"]}
    if fold.get("physical"):
        out["physical, simulator only"] = fold["physical"]["by_strength"]
    for n, ft in (fold.get("fine_tuned") or {}).items():
        out[f"physical, servo part fine-tuned on {n} real samples"] = ft["by_strength"]
    for key, what in (("current", CURRENT), ("current_sessions", f"{CURRENT}, {SESSIONS}")):
        if fold.get(f"physical_{key}"):
            out[f"{what}, simulator only"] = fold[f"physical_{key}"]["by_strength"]
        for n, ft in (fold.get(f"fine_tuned_{key}") or {}).items():
            out[f"{what}, servo part fine-tuned on {n} real samples"] = ft["by_strength"]
    return out


def fold_draws(held: dict) -> list[tuple[str, dict]]:
    """The training draws of :func:`jaxinertia.app.folds.run_folds`' result ``held`` (a
    ``tables.json``'s ``held_out``): ``[(folder under the folds' folder, {fit_on: fold
    result})]``, one item for a run of one draw."""
    return [(d["dir"], d["folds"]) for d in held["draws"]] if held.get("draws") else [
        ("", held["folds"])]


def pooled_folds(held: dict) -> list[tuple[str, dict]]:
    """Every draw's every fold, ``[("[seed<s>/]fit_on", fold result)]``: the folds that
    :func:`choose_recipe` chooses over."""
    return [(f"{d}/{fit}" if d else fit, fold) for d, folds in fold_draws(held)
            for fit, fold in folds.items()]


#: The name of the candidates with the current input (``FoldScale.current_input``).
CURRENT = "physical with the current input"
#: ... and trained on recording sessions drawn (``FoldScale.session_draws``).
SESSIONS = "sessions drawn"
#: Every candidate averaged (:func:`jaxinertia.app.folds._ensemble`): judged and chosen like
#: the others; ``models_real`` then makes every member (:mod:`jaxinertia.app.ensemble`).
ENSEMBLE = "mean of every candidate"

#: A fold's model folder suffix -> the name its candidates carry (:func:`candidates`).
_KINDS = {"": "physical", "_current": CURRENT, "_current_sessions": f"{CURRENT}, {SESSIONS}"}


def candidate_of_folder(folder: str) -> str:
    """The candidate name (:func:`candidates`) of a fold's model folder name: ``models``,
    ``models_physical[_current[_sessions]]``, ``models_finetuned[_current[_sessions]]_N``."""
    if folder == "models":
        return "paper network, simulator only"
    for prefix in ("models_physical", "models_finetuned"):
        if folder.startswith(prefix):
            tag, _, n = folder[len(prefix):].rpartition("_") if prefix == "models_finetuned" \
                else (folder[len(prefix):], "", "")
            if tag in _KINDS and (n.isdigit() or prefix == "models_physical"):
                what = _KINDS[tag]
                return (f"{what}, simulator only" if prefix == "models_physical" else
                        f"{what}, servo part fine-tuned on {n} real samples")
    raise ValueError(f"{folder!r} is no candidate folder of a fold")


#: Ours judged with the attention (T-A) and without it (T: every joint weighted alike).
ATTENTION = {"T-A": True, "T": False}


def choose_recipe(folds: dict, method: str = "T-A") -> dict:
    """The candidate, session strength and attention (on: T-A; off: T, every joint of every
    sample weighted alike) with the lowest held-out error, from the folds alone: per fold
    and held-out object, the mass and COM NMAE each divided by the released models' (by
    ``method``, theirs with the attention they were trained with) on the same sets,
    averaged over both and over every fold (a recipe must hold on every session left out,
    not on one). Returns the choice and every score."""
    scores: dict[tuple[str, str, bool], list[float]] = {}
    for f in folds.values():
        ensemble = {ENSEMBLE: f["ensemble"]["by_strength"]} if f.get("ensemble") else {}
        for name, by_strength in {**candidates(f), **ensemble}.items():
            for s, objects in by_strength.items():
                for obj, e in objects.items():
                    ref = f["released"][obj][method]
                    for ours, attention in ATTENTION.items():
                        scores.setdefault((name, s, attention), []).extend(
                            [e[ours][k] / ref[k] for k in ("mass_NMAE_pct", "com_NMAE_pct")])
    n_folds = len(folds)
    # Only recipes that every fold judged compete.
    table = {k: float(np.mean(v)) for k, v in scores.items()
             if len(v) == 2 * sum(len(f["held_out"]) for f in folds.values())}
    members = {tuple(f["ensemble"]["members"]) for f in folds.values() if f.get("ensemble")}
    if len(members) > 1:  # folds that averaged other candidates: no one estimator
        table = {k: v for k, v in table.items() if k[0] != ENSEMBLE}
    recipe = partial(_recipe, members=[candidate_of_folder(n) for n in next(iter(members))]
                     if len(members) == 1 else None)
    (name, strength, attention), best = min(table.items(), key=lambda kv: kv[1])
    return {**recipe(name, strength, attention=attention), "score": best, "method": method,
            "folds": n_folds,
            "scores": [{"candidate": k[0], "session_strength": float(k[1]), "attention": k[2],
                        "score": v} for k, v in sorted(table.items(), key=lambda kv: kv[1])],
            "by_part": _by_part({k: v for k, v in scores.items() if k in table}, recipe)}


def _recipe(name: str, strength, members: list[str] | None = None, *,
            attention: bool = True) -> dict:
    """A candidate's name, strength and attention as the recipe that ``reproduce`` follows;
    the average of every candidate (:data:`ENSEMBLE`) with the recipe of each of its
    ``members`` (candidate names) at the same strength and attention."""
    if name == ENSEMBLE:
        return {"candidate": name, "session_strength": float(strength),
                "finetune_samples": None, "current_input": False, "sessions_drawn": False,
                "attention": attention,
                "members": [_recipe(m, strength, attention=attention) for m in members]}
    finetune = None
    if "fine-tuned on" in name:
        finetune = int(name.split("fine-tuned on ")[1].split()[0])
    return {"candidate": name, "session_strength": float(strength),
            "finetune_samples": finetune, "current_input": name.startswith(CURRENT),
            "sessions_drawn": SESSIONS in name, "attention": attention}


def _by_part(scores: dict[tuple[str, str], list[float]], recipe=_recipe) -> dict:
    """The best candidate for the mass and the best for the COM, judged apart (the ratios
    of :func:`choose_recipe`, mass and COM alternating), and the score of the estimator
    that takes each part from its own models (:mod:`jaxinertia.app.by_part`): the mean of
    the two, exactly what the folds give that estimator (its mass metrics are the mass
    candidate's, its COM metrics the COM candidate's, on the same sets)."""
    part = {}
    for i, what in enumerate(("mass", "com")):
        (name, s, attention), v = min(((k, float(np.mean(r[i::2]))) for k, r in scores.items()),
                                      key=lambda kv: kv[1])
        part[what] = {**recipe(name, s, attention=attention), "score": v}
    return {**part, "score": 0.5 * (part["mass"]["score"] + part["com"]["score"])}
