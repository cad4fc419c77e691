"""``jaxinertia estimate``'s work: the mass and COM of each object in a sample file, by every
method, with standard errors, intervals and covariance; what no method can answer is
refused with the reason, never printed as a number."""

from __future__ import annotations

import os
from operator import methodcaller

import jax.numpy as jnp
import numpy as np

from jaxinertia.app.arm_options import samples_arm
from jaxinertia.app.by_part import com_models_of, merge_answers
from jaxinertia.app.ensemble import (
    NETWORK_METHODS,
    map_members,
    mean_estimates,
    mean_uncertainty,
    members_of,
    weights_of,
)
from jaxinertia.app.pipeline import (
    UNIFORM_ATTENTION,
    adapt_objects,
    is_simulated,
    objects_at_rest,
    session_reference,
)
from jaxinertia.app.provenance import seen_by
from jaxinertia.app.with_reference import (
    corrected,
    evaluated,
    read_reference,
    same_session,
    uncertainty,
)
from jaxinertia.checkpoints import load_models
from jaxinertia.errors import UsageError
from jaxinertia.evaluation import choose_sets, evaluate
from jaxinertia.samples import Samples
from jaxinertia.session import servo_session, servo_state_change
from jaxinertia.statics import torque_scale_sensitivity
from jaxinertia.uncertainty import (
    DEFAULT_TORQUE_NOISE_NM,
    LEVELS,
    identifiability,
    intervals,
    mass_com_covariance,
    standard_errors,
    training_validation_error,
    uncertainty_of,
)

__all__ = ["estimate"]


def _gate(x: np.ndarray, *, max_mass: float, max_com: float) -> str | None:
    """Why the estimate ``x`` (4,) is no answer, or None when it is physically possible."""
    if not np.all(np.isfinite(x)):
        return ("singular least squares: the samples do not determine mass and COM (add "
                "configurations that vary all joints)")
    if x[0] <= 0:
        return f"non-physical mass {x[0] * 1e3:.1f} g"
    if x[0] > max_mass:
        return f"mass {x[0] * 1e3:.0f} g above --max-mass {max_mass * 1e3:.0f} g"
    com = np.linalg.norm(x[1:] / x[0])
    if com > max_com:
        return f"COM {com * 1e3:.0f} mm from the tag, beyond --max-com {max_com * 1e3:.0f} mm"
    return None


def _identifiable(obj: Samples, noise: np.ndarray, where: str) -> None:
    """Refuses samples whose poses cannot determine x = [m, m p] at all (singular load
    regressor: e.g. every sample at one pose), before any estimate."""
    ident = identifiability(jnp.asarray(obj.A), jnp.arange(obj.n_samples)[None],
                            jnp.asarray(noise), jnp.asarray([1.0, 0.0, 0.0, 0.0]))
    if bool(ident.rank_deficient[0]):
        n_poses = len(np.unique(np.round(np.asarray(obj.q), 6), axis=0))
        raise UsageError(f"{where}: no method gives a physically possible estimate: the poses "
                         f"do not determine mass and COM (load regressor singular; "
                         f"{n_poses} distinct pose(s) in {obj.n_samples} samples): sample "
                         "configurations that vary joints 2-4 (jaxinertia plan-poses)")


#: The spread's sets: this many samples each, or half an object's samples where it has
#: fewer than twice as many (a short plan, ``plan-poses --n 16``), unless told.
DEFAULT_SET_SIZE = 64


def spread_set_size(n_samples: int, set_size: int | None) -> int:
    """Samples per set of the spread over sample sets for an object of ``n_samples``:
    ``set_size`` when given, else :data:`DEFAULT_SET_SIZE` or half the samples where
    fewer (sets of all the samples would all be one set, and their spread zero)."""
    return set_size if set_size is not None else max(1, min(DEFAULT_SET_SIZE, n_samples // 2))


def _refuse_unanswerable(objects, sample_file, set_size: int | None, noise) -> None:
    """Refuses, object by object, samples no estimate can come from."""
    for obj in objects:
        where = f"{sample_file}" + (f" [{obj.name}]" if len(objects) > 1 else "")
        if set_size is not None and obj.n_samples < set_size:
            raise UsageError(f"{where}: {obj.n_samples} sample(s), fewer than one set of "
                             f"--set-size {set_size} (leave --set-size out: sets of half the "
                             "samples)")
        if set_size is None and obj.n_samples < 2:
            raise UsageError(f"{where}: {obj.n_samples} sample(s): an answer and its spread "
                             "over sample sets need at least 2 (collect more)")
        if np.all(obj.q_d == obj.q):
            raise UsageError(f"{where}: q_d - q is zero on every sample: no discrepancy to "
                             "read a load from (torque off, or q_d recorded as q?)")
        _identifiable(obj, noise, where)


def _method_answer(x_all, x_sets, unc, *, max_mass: float, max_com: float) -> dict:
    """One method's answer for one object: from all its samples (``x_all``, per model
    pair), the spread over the random sets (``x_sets``, of the object's ``set_size``), the
    uncertainty; or why not."""
    x_models = np.asarray(x_all).reshape(-1, 4)  # (K, 4) or (1, 4)
    x = np.mean(x_models, axis=0)
    why = _gate(x, max_mass=max_mass, max_com=max_com)
    if why is not None:
        return {"ok": False, "reason": why}
    xs = np.asarray(x_sets).reshape(-1, 4)
    good = np.array([_gate(v, max_mass=max_mass, max_com=max_com) is None for v in xs])
    return {
        "ok": True, "mass_kg": float(x[0]), "com_tag_m": (x[1:] / x[0]).tolist(),
        **_uncertainty_fields(unc, 0),
        "mass_std_across_models_kg": float(np.std(x_models[:, 0])),
        "mass_std_over_sample_sets_kg": float(np.std(xs[good, 0])),
        "com_std_over_sample_sets_m":
            np.std(xs[good, 1:] / xs[good, :1], axis=0).tolist(),
        "failed_sets": int(np.sum(~good)), "n_sets": int(len(xs)),
    }


#: The servo-state step of :func:`_servo_state`: 1 % of a joint's torque.
SERVO_STATE_STEP = 0.01


def _servo_state(methods: dict, obj, weights: list[np.ndarray],
                 shares: list[float] | None = None) -> None:
    """Adds to each network method's answer how far it moves when one joint's torques are
    read 1 % off (:func:`jaxinertia.statics.torque_scale_sensitivity`): a servo in another
    state than the models learnt (supply, temperature) is a bias the intervals do not
    hold. ``weights``: per folder answering (the folder, then an ensemble's further
    members) its attention weights (K, S, N) for T-A; ``shares``: the folders' shares of
    the answer (None: alike). The answer is their mean, and so is its shift."""
    shares = np.full(len(weights), 1 / len(weights)) if shares is None else np.asarray(shares)
    for m, folders in (("T", [(1.0, [None])]), ("T-A", list(zip(shares, weights)))):
        r = methods.get(m)
        if not (r and r["ok"]):
            continue
        p = np.asarray(r["com_tag_m"])
        x = np.r_[r["mass_kg"], r["mass_kg"] * p]
        dx = sum(share * np.mean([torque_scale_sensitivity(obj.A, obj.tau_g, x, wk,
                                                           SERVO_STATE_STEP) for wk in w],
                                 axis=0) for share, w in folders)  # (N, 4)
        moved = (x[1:] + dx[:, 1:]) / (x[0] + dx[:, :1]) - p
        r["servo_state_sensitivity"] = {"torque_fraction": SERVO_STATE_STEP,
                                        "mass_kg": dx[:, 0].tolist(),
                                        "com_m": np.linalg.norm(moved, axis=1).tolist()}


def _uncertainty_fields(u, o: int) -> dict:
    """One object's answer of one method: standard errors, intervals, covariance."""
    x, cov = np.asarray(u.x[o, 0]), np.asarray(u.cov[o, 0])
    se = np.asarray(standard_errors(x, cov))
    out = {"mass_se_kg": float(se[0]), "com_se_m": se[1:].tolist()}
    for level in LEVELS:
        _, lo, hi = (np.asarray(a) for a in intervals(x, cov, level))
        out[f"interval_{round(level * 100)}"] = {
            "mass_kg": [float(lo[0]), float(hi[0])],
            "com_tag_m": np.stack([lo[1:], hi[1:]], axis=-1).tolist()}
    out.update(covariance_x=cov.tolist(),
               covariance_mass_com=np.asarray(mass_com_covariance(x, cov)[1]).tolist(),
               covariance_terms={"noise": np.asarray(u.cov_noise[o, 0]).tolist(),
                                 "ensemble": np.asarray(u.cov_ensemble[o, 0]).tolist()},
               torque_error_level_Nm=np.asarray(u.noise_std[o, 0]).tolist())
    return out


def estimate(models: str | os.PathLike, sample_file: str | os.PathLike, *,
             set_size: int | None = None,
             n_sets: int = 200, seed: int = 0, max_mass: float = 5.0,
             max_com: float = 0.5, max_com_se: float | None = None,
             session_strength: float | None = None, arm: str | None = None,
             reference: str | os.PathLike | None = None) -> dict:
    """Mass and COM of each object in a sample file (ground truth, if any, is not used),
    by every method, with standard errors, intervals and covariance.

    Per object: all its samples in one WLS (the estimate) and ``n_sets`` random sets of
    ``set_size`` samples for a spread (None: :func:`spread_set_size`). A method whose
    estimate is singular or physically impossible (mass not in (0, ``max_mass``], COM
    farther than ``max_com`` from the tag) is reported as failed, with the reason, never
    as a number; an object no method can estimate is an error.

    Session (:mod:`jaxinertia.session`): each object's discrepancy is first rescaled per
    joint by its own current-discrepancy slope against the model folder's (the ratio is in
    the answer; ``session_strength`` overrides the folder's strength, 0 = off).

    Uncertainty (:mod:`jaxinertia.uncertainty`): residual scatter with a floor at the
    torque models' validation error (recomputed from the training files the model folder
    names, when they are still there; else residuals only, said in ``torque_error_floor``)
    plus the spread over the model pairs. Identifiability: poses whose load regressor is
    singular are refused before any estimate; with ``max_com_se`` [m], so is an object
    whose COM the poses alone determine worse than that (predicted standard error at the
    estimated mass, for the floor's torque error level, else
    :data:`~jaxinertia.uncertainty.DEFAULT_TORQUE_NOISE_NM`).

    A model folder that names COM models (:mod:`jaxinertia.app.by_part`) answers the mass
    from its own models and the COM of the network methods from those; one that names
    ensemble members (:mod:`jaxinertia.app.ensemble`), by their mean with its own.

    ``reference``: a sample file of known loads (their truth recorded: a known weight)
    recorded in the same session as ``sample_file``. Each folder (and member) fits, on it
    read in its session, a gain and an offset per joint between its torques and the known
    ones, and reads the unknown object's torques through them
    (:mod:`jaxinertia.reference`); the network methods only, the baselines as they are.
    """
    ref = None if reference is None else read_reference(reference, arm)
    kw = dict(set_size=set_size, n_sets=n_sets, seed=seed, max_mass=max_mass,
              max_com=max_com, max_com_se=max_com_se, session_strength=session_strength,
              arm=arm, reference=ref)
    out, config = _estimate(models, sample_file, **kw)
    com = com_models_of(models, config)
    if com is not None:
        com_out = _estimate(com, sample_file, **kw)[0]
        out = merge_answers(out, com_out)
        out.update(com_models=str(com), com_session_strength=com_out["session_strength"])
        if ref is not None:  # the COM's folders fitted their own on the reference
            out["reference"]["com_models"] = {k: com_out["reference"][k]
                                              for k in ("correction", "members")}
    # Were the models fitted on this very file? (Then its answer is no held-out number.)
    out["fitted_on_this_file"] = {p: {"folders": k, "of": n}
                                  for p, (k, n) in seen_by(models, out["sha256"]).items()}
    return out


def _estimate(models, sample_file, *, set_size, n_sets, seed, max_mass, max_com, max_com_se,
              session_strength, arm, reference=None) -> tuple[dict, dict]:
    """:func:`estimate` by one model folder: the answer and the folder's config."""
    objects, meta = objects_at_rest(sample_file, need_truth=False)
    objects = [o.without_truth() for o in objects]
    arm = samples_arm(sample_file, meta, arm)  # the folder's and every member's
    folder = load_models(models, robot=meta.get("robot"), arm=arm)
    baselines, fc = folder.baselines, folder.features
    session = session_reference(folder.config, session_strength,
                                simulated=is_simulated(meta))
    # An ensemble's further members (app.ensemble): each reads the objects in its session.
    members = map_members(lambda m: _Member(m, objects, meta, session_strength, arm,
                                            reference), members_of(models, folder.config))
    weights = weights_of(folder.config, models)  # checked before any estimate
    # Each file's servo state against the folder's (and the reference's), as recorded.
    states = [servo_state_change(session, servo_session(o)) for o in objects]
    against = [None if reference is None else same_session(reference, o) for o in objects]
    objects, ratios = adapt_objects(objects, session)
    raw = objects  # the baselines read the objects as they are
    pair, objects, corr = corrected(folder, objects, reference, session, str(models))
    floor, floor_source = training_validation_error(folder.config)
    noise = floor if floor is not None else np.full(objects[0].n_joints,
                                                    DEFAULT_TORQUE_NOISE_NM)
    noise_source = ("torque models' validation error" if floor is not None else
                    f"nominal {DEFAULT_TORQUE_NOISE_NM * 1e3:.0f} N mm per joint")
    _refuse_unanswerable(objects, sample_file, set_size, noise)  # before any estimate
    out: dict = {"file": str(sample_file), "sha256": meta.get("sha256"), "objects": {},
                 "session_strength": 0.0 if session is None else session.strength,
                 "torque_error_floor": {"Nm": None if floor is None else floor.tolist(),
                                        "source": floor_source}}
    for o, (obj, ratio, state) in enumerate(zip(objects, ratios, states)):
        all_samples = [np.arange(obj.n_samples)[None]]
        kw = dict(pair=pair, baselines=baselines, fc=fc, raw=raw[o])
        res = evaluated(obj, all_samples, **kw)
        unc = uncertainty(obj, all_samples, floor=floor, **kw)
        size = spread_set_size(obj.n_samples, set_size)
        sets, _ = choose_sets([obj], n_sets=n_sets, set_size=size, seed=seed)
        spread = evaluated(obj, sets, **kw)
        member_parts = map_members(methodcaller("parts", o, all_samples, sets), members)
        if members:
            _average_members(res, unc, spread, member_parts,
                             [models, *(m.path for m in members)], weights)
        methods = {m: _method_answer(x_all, spread["estimates"][m], unc[m],
                                     max_mass=max_mass, max_com=max_com)
                   for m, x_all in res["estimates"].items()}
        _servo_state(methods, obj, [np.asarray(res["model_estimates"].weights[0]),
                                    *(p[3] for p in member_parts)], weights)
        if not any(r["ok"] for r in methods.values()):
            raise UsageError(f"{sample_file} [{obj.name}]: no method gives a physically possible "
                             "estimate (" + "; ".join(f"{m}: {r['reason']}"
                                                      for m, r in methods.items()) + ")")
        best = next(methods[m] for m in ("T-A", "T", "PE", "Sensor")
                    if methods.get(m, {}).get("ok"))
        x_best = np.r_[best["mass_kg"], best["mass_kg"] * np.asarray(best["com_tag_m"])]
        ident = identifiability(jnp.asarray(obj.A), jnp.asarray(all_samples[0]),
                                jnp.asarray(noise), jnp.asarray(x_best))
        pred_se = np.asarray(ident.se[0])
        out["objects"][obj.name] = {
            "n_samples": obj.n_samples, "set_size": size, "methods": methods,
            "session_ratio": ratio, "servo_state": state,
            **({} if against[o] is None else {"reference_session": against[o]}),
            "unavailable": res["unavailable"],
            "identifiability": {"condition": float(ident.condition[0]),
                                "predicted_mass_se_kg": float(pred_se[0]),
                                "predicted_com_se_m": pred_se[1:].tolist(),
                                "torque_error_Nm": np.asarray(noise).tolist(),
                                "torque_error_source": noise_source}}
        if max_com_se is not None and np.max(pred_se[1:]) > max_com_se:
            raise UsageError(
                f"{sample_file} [{obj.name}]: the poses determine the COM only to "
                f"+-{np.max(pred_se[1:]) * 1e3:.1f} mm (predicted standard error at "
                f"{x_best[0] * 1e3:.0f} g, torque error {noise_source}), above --max-com-se "
                f"{max_com_se * 1e3:.1f} mm: sample more varied poses (jaxinertia plan-poses)")
    if members:
        out["ensemble_members"] = [str(m.path) for m in members]
        if weights is not None:
            out["ensemble_weights"] = weights
    if reference is not None:
        out["reference"] = {
            **reference.record(), "correction": corr.to_dict(),
            "members": [m.correction.to_dict() for m in members]}
    # (T-A answers as T only where no member has its attention: models_real_with_released's
    # released member keeps the authors')
    out["uniform_attention"] = all(bool(f.config.get(UNIFORM_ATTENTION))
                                   for f in (folder, *(m.folder for m in members)))
    return out, folder.config


class _Member:
    """A further member of an ensemble folder (:mod:`jaxinertia.app.ensemble`): its models,
    the objects read in its session and its torque error floor."""

    def __init__(self, path, objects, meta, session_strength, arm, reference=None):
        self.path = path
        self.folder = load_models(path, robot=meta.get("robot"), arm=arm)
        session = session_reference(self.folder.config, session_strength,
                                    simulated=is_simulated(meta))
        objects, _ = adapt_objects(objects, session)
        self.pair, self.objects, self.correction = corrected(self.folder, objects, reference,
                                                              session, str(path))
        self.floor, _ = training_validation_error(self.folder.config)

    def parts(self, o: int, all_samples, sets) -> tuple[dict, dict, dict, np.ndarray]:
        """Object ``o``'s network estimates on all its samples, their uncertainty, the
        estimates on the ``sets`` (as :func:`_estimate` computes them), and its attention
        weights on all the samples (K, S, N)."""
        obj, f = self.objects[o], self.folder
        kw = dict(pair=self.pair, fc=f.features)
        every = evaluate([obj], all_samples, l_max=[np.nan], **kw)
        return (every["estimates"], uncertainty_of([obj], all_samples, floor=self.floor, **kw),
                evaluate([obj], sets, l_max=[np.nan], **kw)["estimates"],
                np.asarray(every["model_estimates"].weights[0]))


def _average_members(res: dict, unc: dict, spread: dict, parts: list, folders: list,
                     weights: list[float] | None) -> None:
    """The network methods' estimates and uncertainty of one object replaced, in place, by
    the mean over the folder and its further members (``parts``: :meth:`_Member.parts`;
    ``weights``: their shares, :data:`~jaxinertia.app.ensemble.ENSEMBLE_WEIGHTS`)."""
    for m in NETWORK_METHODS:
        if m not in res["estimates"]:
            continue
        x_all = [res["estimates"][m], *(p[0][m] for p in parts)]
        unc[m] = mean_uncertainty([unc[m], *(p[1][m] for p in parts)], x_all, weights)
        res["estimates"][m] = mean_estimates(x_all, folders, weights)
        spread["estimates"][m] = mean_estimates(
            [spread["estimates"][m], *(p[2][m] for p in parts)], folders, weights)
