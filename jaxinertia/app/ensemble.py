"""A model folder that answers with the mean of several: ``config.json`` names member
folders inside it (``ensemble_members``, written by :func:`attach_members`); the folder's
own models are the first member.

Why: the held-out folds judge, beside every candidate, the mean of all of them
(:func:`judge_mean`), and where the recipe chooses it ``models_real``
is that mean (docs/results.md, "Every candidate averaged"). For the network methods (T,
T-A), per model pair k and set, the estimate ``x = [m, m p]`` is the mean of the members'
(their model counts must agree): Table I pools the K pairs' sets as for one folder. Each
member reads a file in its own session (its reference and strength). The baselines (Sensor,
PE), the attention weights and the torque metrics are the first member's. ``estimate``'s
covariance of the mean: the members' residual covariances averaged (their errors are not
independent, so not divided by their number) plus the covariance of every member's pair
estimates around the mean (as one folder's pairs give theirs). A folder may give its members
shares (``ensemble_weights``; :mod:`jaxinertia.app.with_released` weighs the authors'
released models half against every model of ``models_real``): the means are then weighted.
"""

from __future__ import annotations

import copy
import json
import os
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from jaxinertia.app.by_part import COM_MODELS
from jaxinertia.checkpoints import CONFIG
from jaxinertia.errors import ModelFolderError, UsageError
from jaxinertia.fileio import write_json
from jaxinertia.metrics import inertial_metrics
from jaxinertia.samples import Samples
from jaxinertia.uncertainty import SetUncertainty

__all__ = ["ENSEMBLE_KEYS", "ENSEMBLE_MEMBERS", "ENSEMBLE_WEIGHTS", "NETWORK_METHODS",
           "attach_members", "finite_estimates", "judge_mean", "map_members", "mean_estimates",
           "mean_evaluation", "mean_uncertainty", "members_of", "weights_of"]

#: The ``config.json`` key naming the further members (relative to the folder).
ENSEMBLE_MEMBERS = "ensemble_members"
#: The ``config.json`` key giving each member's share of the mean (the folder's own models
#: first; absent: equal shares). With shares given, a member of another model count than
#: the folder's enters with its pairs' mean on each set, for every pair of the folder.
ENSEMBLE_WEIGHTS = "ensemble_weights"
#: Both: what a copy of the folder's own models leaves out (``pipeline.copy_models``).
ENSEMBLE_KEYS = (ENSEMBLE_MEMBERS, ENSEMBLE_WEIGHTS)
#: The methods whose estimates are averaged.
NETWORK_METHODS = ("T", "T-A")
#: At most this many members read and judged at once (:func:`map_members`).
MEMBER_THREADS = 8


def members_of(models: str | os.PathLike, config: dict) -> list[Path]:
    """The further members that a model folder (its ``config``) names (none: [])."""
    return [Path(models) / name for name in config.get(ENSEMBLE_MEMBERS) or ()]


def map_members(fn: Callable, members: Sequence) -> list:
    """``[fn(m) for m in members]``, the members side by side in threads (at most
    :data:`MEMBER_THREADS`, one a core): each member's checkpoint is read one at a time
    (orbax, ``checkpoints._ORBAX``) while the others' objects are adapted, their programs
    compiled and run. The results in the members' order; a member's error is raised as
    the loop would raise it (the first failing member's, in order)."""
    workers = min(MEMBER_THREADS, len(members), os.cpu_count() or 1)
    if workers < 2:
        return [fn(m) for m in members]
    with ThreadPoolExecutor(workers, thread_name_prefix="jaxinertia-member") as pool:
        return list(pool.map(fn, members))


def _checked_shares(weights, n: int, where: str) -> np.ndarray:
    """``n`` shares, finite, >= 0, not all zero, normalised; else the error says so."""
    # A hand-edited record may hold anything: a string, a mapping, numbers written as
    # strings or booleans (which numpy would convert), an integer too large for a float.
    numbers = (isinstance(weights, (list, tuple, np.ndarray)) and np.ndim(weights) == 1
               and all(isinstance(v, (int, float, np.integer, np.floating))
                       and not isinstance(v, (bool, np.bool_)) for v in weights))
    try:
        w = np.asarray(weights, float) if numbers else np.full(0, np.nan)
    except OverflowError:
        w = np.full(0, np.nan)
    with np.errstate(over="ignore"):
        total = w.sum()
    if (w.shape != (n,) or not np.all(np.isfinite(w)) or np.any(w < 0) or total <= 0
            or not np.isfinite(total)):
        raise ModelFolderError(f"{where}: {n} shares >= 0 (the folder's own first) are "
                               f"needed, not {weights!r}")
    return w / total


def _check_member(models: Path, name: str) -> None:
    """A member is a plain model folder inside ``models``: not the folder itself, not one
    that answers with members or COM models of its own (``evaluate`` and ``estimate``
    would then disagree on what it answers)."""
    path = models / name
    if not (path / CONFIG).is_file():
        raise FileNotFoundError(f"{path}: no model folder to average")
    if path.resolve() == models.resolve() or models.resolve() not in path.resolve().parents:
        raise UsageError(f"{path}: a member must be a model folder inside {models}")
    nested = [k for k in (ENSEMBLE_MEMBERS, COM_MODELS)
              if json.loads((path / CONFIG).read_text()).get(k)]
    if nested:
        raise UsageError(f"{path}: a member answers with its own models only, not with "
                         f"{' and '.join(nested)}")


def attach_members(models: str | os.PathLike, names: Sequence[str],
                   weights: Sequence[float] | None = None) -> None:
    """Records in ``models/config.json`` that ``models`` answers with the mean of its own
    models and those of ``models/<name>`` for each name (model folders already there);
    ``weights``: each one's share (the folder's own first; normalised), else equal."""
    models = Path(models)
    path = models / CONFIG
    if len(set(names)) != len(names):
        raise UsageError(f"{models}: a member named twice in {list(names)}")
    for name in names:
        _check_member(models, name)
    config = {k: v for k, v in json.loads(path.read_text()).items() if k != ENSEMBLE_WEIGHTS}
    config[ENSEMBLE_MEMBERS] = list(names)
    if weights is not None:
        try:
            w = _checked_shares(weights, len(names) + 1, str(models))
        except ModelFolderError as e:
            raise UsageError(str(e)) from None
        config[ENSEMBLE_WEIGHTS] = w.tolist()
    write_json(path, config)


def weights_of(config: dict, models: str | os.PathLike = "the model folder"
               ) -> list[float] | None:
    """The members' shares that a folder's ``config`` records (None: equal), checked
    against its members (a hand-edited record is an error naming the folder)."""
    weights = config.get(ENSEMBLE_WEIGHTS)
    if weights is None:
        return None
    n = len(config.get(ENSEMBLE_MEMBERS) or ()) + 1
    return _checked_shares(weights, n, f"{models} [{ENSEMBLE_WEIGHTS}]").tolist()


def mean_estimates(estimates: Sequence[np.ndarray], folders: Sequence,
                   weights: Sequence[float] | None = None) -> np.ndarray:
    """The members' estimates (..., K, B, 4) averaged per model pair and set; ``weights``:
    each member's share, and then a member of another model count K than the first's
    enters with its pairs' mean (:data:`ENSEMBLE_WEIGHTS`)."""
    xs = [np.asarray(x) for x in estimates]
    if weights is not None:
        k = xs[0].shape[-3]
        xs = [x if x.shape[-3] == k else np.broadcast_to(
            x.mean(axis=-3, keepdims=True), x.shape[:-3] + (k,) + x.shape[-2:]) for x in xs]
    shapes = {x.shape for x in xs}
    if len(shapes) > 1:
        raise UsageError("the members of an ensemble must have as many model pairs each: "
                         + ", ".join(f"{f}: {np.shape(x)}" for f, x in zip(folders, estimates)))
    return np.average(np.stack(xs), axis=0, weights=weights)


def finite_estimates(x: np.ndarray) -> np.ndarray:
    """The estimates ``x`` (..., 4) as rows, without those a failed solve left non-finite."""
    x = np.asarray(x).reshape(-1, 4)
    return x[np.all(np.isfinite(x), axis=-1)]


def judge_mean(estimates: dict, objects: Sequence[Samples], l_max: Sequence[float],
               strengths: Sequence[float]) -> dict | None:
    """The held-out folds' average of every candidate (issue 30: the recipe's near ties):
    ``estimates`` maps (folder name, strength) to each folder's network estimates
    ``{method: (O, K, B, 4)}`` on the held-out ``objects``; at each strength, per model pair
    k and set, the mean over the folders, judged like one folder (Table I over the K pairs'
    sets pooled, as a candidate's; the pairs are not averaged). No choice among the
    candidates is made, so nothing is tuned on the files it is judged on. Returns
    ``{"members": folder names, "by_strength": {str(s): {object: {method: metrics}}}}``;
    None with fewer than two folders, or folders of unequal model counts."""
    names = sorted({n for n, _ in estimates})
    if len(names) < 2:
        return None
    by_strength = {}
    for s in strengths:
        members = [estimates[(n, s)] for n in names]
        if len({np.shape(e["T-A"]) for e in members}) > 1:
            return None
        by_strength[str(s)] = {
            obj.name: {m: inertial_metrics(
                finite_estimates(np.mean([e[m][o] for e in members], axis=0)), obj.x[0],
                l_max[o]) for m in NETWORK_METHODS}
            for o, obj in enumerate(objects)}
    return {"members": names, "by_strength": by_strength}


def mean_evaluation(evaluations: Sequence[dict], objects: Sequence[Samples],
                    folders: Sequence, weights: Sequence[float] | None = None) -> dict:
    """An evaluation (``pipeline.evaluate_models``) of the members' mean: the first
    member's, with the network methods' estimates averaged (``weights``: the members'
    shares) and their Table I metrics computed again from them. ``evaluations`` and
    ``folders``: the folder's own and each further member's, in that order."""
    out = copy.copy(evaluations[0])
    out["objects"] = copy.deepcopy(out["objects"])
    out["estimates"] = dict(out["estimates"])
    for m in NETWORK_METHODS:
        if m not in out["estimates"]:
            continue
        x = mean_estimates([e["estimates"][m] for e in evaluations], folders, weights)
        out["estimates"][m] = x
        for o, obj in enumerate(objects):
            entry = out["objects"][obj.name]
            if m in entry:
                entry[m] = inertial_metrics(finite_estimates(x[o]), obj.x[0], entry["L_max_m"])
    out["ensemble_members"] = [str(f) for f in folders[1:]]  # the further members
    if weights is not None:
        out["ensemble_weights"] = list(weights)
    return out


def mean_uncertainty(uncertainties: Sequence[SetUncertainty],
                     pair_estimates: Sequence[np.ndarray],
                     weights: Sequence[float] | None = None) -> SetUncertainty:
    """The answer and covariance of the members' mean, for one set (leading axes (1, 1) as
    :func:`jaxinertia.uncertainty.uncertainty_of` gives them); ``pair_estimates``: each
    member's K pairs' estimates (K, 4) on that set; ``weights``: the members' shares (each
    member's pairs then weigh its share between them in the spread)."""
    us = [SetUncertainty(*(np.asarray(a, np.float64) for a in u)) for u in uncertainties]
    w = None if weights is None else np.asarray(weights, float)
    x = np.average([u.x for u in us], axis=0, weights=w)
    cov_noise = np.average([u.cov_noise for u in us], axis=0, weights=w)
    pairs = [np.reshape(p, (-1, 4)) for p in pair_estimates]
    # Equal shares: every pair alike (as before shares existed); else each member's share.
    aw = (None if w is None else
          np.concatenate([np.full(len(p), wi / len(p)) for p, wi in zip(pairs, w)]))
    pairs = np.concatenate(pairs)
    spread = (np.cov(pairs, rowvar=False, ddof=1, aweights=aw) if len(pairs) > 1
              else np.zeros((4, 4)))[None, None]
    return SetUncertainty(
        x=x, cov=cov_noise + spread, cov_noise=cov_noise, cov_ensemble=spread,
        noise_std=np.sqrt(np.average([u.noise_std ** 2 for u in us], axis=0, weights=w)),
        floor_used=np.average([u.floor_used for u in us], axis=0, weights=w))
