"""The paper's steps as the command line runs them: train, evaluate, estimate, the released
models' benchmark and sim-to-real.

``train`` turns sample files of known objects into a model folder (orbax checkpoint and
JSON config, see :mod:`jaxinertia.checkpoints`); every evaluation goes through the one
evaluator :func:`jaxinertia.evaluation.evaluate` with sets from
:func:`jaxinertia.evaluation.choose_sets`; ``estimate`` gives the mass and COM of an unknown
object from a sample file.
"""

from __future__ import annotations

import os
import time
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxinertia.app.arm_options import LBIPE_ARM, samples_arm
from jaxinertia.baselines import fit_baselines
from jaxinertia.checkpoints import file_sha256, load_models, save_models
from jaxinertia.errors import FileFormatError, UsageError
from jaxinertia.estimation import ModelPair
from jaxinertia.evaluation import choose_sets, evaluate, l_max_of
from jaxinertia.features import LBIPE_FEATURES
from jaxinertia.fileio import check_output
from jaxinertia.lbipe import (
    LbipeLayout,
    find_layout,
    golden_path,
    load_golden,
    load_released_models,
    test_files,
)
from jaxinertia.networks import torque_model_kind
from jaxinertia.samples import Samples, load_samples
from jaxinertia.session import SessionReference, adapt, servo_session
from jaxinertia.training import (
    TrainConfig,
    feature_config_from,
    per_object_subset,
    split_validation,
    train_attention_models,
    train_torque_models,
)
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

__all__ = ["RealData", "adapt_objects", "copy_models", "estimate", "evaluate_models",
           "evaluate_samples", "load_real", "released_benchmark", "session_reference",
           "sim_to_real", "train"]


def train(sample_files: Sequence[str | os.PathLike], out: str | os.PathLike, cfg: TrainConfig,
          *, progress: bool = True, overwrite: bool = False,
          init: str | os.PathLike | None = None,
          samples_per_object: int | None = None, arm: str | None = None) -> dict:
    """Trains K model pairs and fits the baselines; writes the model folder ``out``
    (atomically; an existing one only with ``overwrite``).

    ``init``: a model folder to fine-tune instead of training from scratch (e.g.
    simulator-trained models adapted on real samples of known objects): its parameters are
    the start (they compete as epoch -1 on the validation split), its feature
    normalisation is kept and its model count wins over ``cfg.n_models``; the baselines are
    fitted on the new data. ``samples_per_object``: use only that many samples of each
    object (seeded random choice; all when it has fewer), to measure how many are needed.
    ``arm``: the arm the samples must come from (the folder records it; default: the one
    the files record).
    """
    check_output(out, overwrite=overwrite)
    parts, metas = [], []
    for f in sample_files:
        d, meta = load_samples(f)
        samples_arm(f, meta, arm)  # another arm's file: one line, before any training
        parts.append(d)
        metas.append(meta)
    # The authors' layout records no robot: it is taken to be the native files' one.
    robots = {m.get("robot") for m in metas} - {None}
    if len(robots) > 1:
        raise FileFormatError(sample_files[0], "metadata", f"files of different robots {robots}")
    robot = robots.pop() if robots else arm
    start = None
    if init is not None:
        pair0, _, fc0, config0 = load_models(init, robot=robot)
        robot = robot or config0.get("robot")
        cfg = cfg.replace(n_models=pair0.n_models,
                          torque_model=torque_model_kind(pair0.torque_model))
        start = (pair0, fc0, config0)
    # Each file is one recording session: read as if recorded in the reference session
    # (the init folder's, else the training data's own pooled current gain), as strongly as
    # cfg.session_strength says.
    reference = None if start is None else session_reference(start[2], cfg.session_strength)
    if reference is None:
        reference = SessionReference(servo_session(parts).current_gain,
                                     strength=float(cfg.session_strength))
    ratios = []
    for i, p in enumerate(parts):
        parts[i], ratio = adapt(p, reference)
        ratios.append(ratio.tolist())
    data = Samples.concatenate(parts)
    if samples_per_object is not None:
        data = per_object_subset(data, samples_per_object, cfg.seed)
    t0 = time.perf_counter()
    train_set, val_set = split_validation(data, cfg.val_fraction, cfg.seed)
    if val_set.n_samples == 0 or train_set.n_samples == 0:
        raise UsageError(f"{data.n_samples} samples and --val-fraction {cfg.val_fraction} leave "
                         f"{train_set.n_samples} for training and {val_set.n_samples} for "
                         "validation: both need samples")
    fc = feature_config_from(train_set) if start is None else start[1]
    key = jax.random.key(cfg.seed)
    k_t, k_a = jax.random.split(key)
    torque = train_torque_models(cfg, fc, train_set, val_set, k_t, progress=progress,
                                 init=None if start is None else start[0].torque_vars,
                                 model=None if start is None else start[0].torque_model)
    t1 = time.perf_counter()
    attention = train_attention_models(
        cfg, fc, torque, train_set, val_set, k_a, progress=progress,
        init=None if start is None else start[0].attention_vars,
        model=None if start is None else start[0].attention_model)
    t2 = time.perf_counter()
    baselines = fit_baselines(train_set.q_d, train_set.q, train_set.direction,
                              train_set.current_tau, train_set.tau)
    pair = ModelPair(torque_vars=torque.variables, attention_vars=attention.variables,
                     tau_scale=np.asarray(fc.tau_scale, np.float32),
                     torque_model=torque.model, attention_model=attention.model)
    info = {
        "training": cfg.to_dict(),
        "data": [{"file": str(Path(f).resolve()), "sha256": file_sha256(f),
                  "objects": m.get("objects"), "scenario": m.get("scenario"),
                  "seed": m.get("seed"), "source": m.get("source"),
                  "session_ratio": r}
                 for f, m, r in zip(sample_files, metas, ratios)],
        "session": None if reference is None else reference.to_dict(),
        "samples_per_object": samples_per_object,
        "simulator": metas[0].get("simulator") or (start[2].get("simulator") if start else None),
        "samples": {"train": train_set.n_samples, "validation": val_set.n_samples},
        "best_epoch": {"torque": torque.best_epoch.tolist(),
                       "attention": attention.best_epoch.tolist()},
        "history": {"torque": torque.history.tolist(), "attention": attention.history.tolist()},
        "wall_time_s": {"torque": t1 - t0, "attention": t2 - t1},
    }
    if start is not None:
        info["fine_tuned_from"] = {"folder": str(Path(init).resolve()),
                                   "data": start[2].get("data"),
                                   "training": start[2].get("training")}
    save_models(out, pair, baselines, fc, robot=robot, extra=info, arm=arm)  # atomic
    return info


class RealData(NamedTuple):
    """The real test objects of an lbipe folder, with their evaluation sets."""

    layout: LbipeLayout
    objects: list[Samples]
    sets: list[np.ndarray]
    sources: list[str]  # per object: "golden" or "random (seed s)"
    l_max: list[float]


def load_real(lbipe_dir: str | os.PathLike, *, seed: int = 0, n_sets: int = 1000,
              set_size: int = 64, l_max: dict[str, float] | None = None) -> RealData:
    """Every ``data_test_<name>.npz`` of the folder and its sets: the golden sets when the
    folder has them, else seeded random sets. An object without a bounding-box diagonal
    is an error (``l_max`` supplies one), never silently left out."""
    layout = find_layout(lbipe_dir)
    objects = test_files(layout)
    paths = list(layout.test_files.values())
    diag = [l_max_of([o], l_max, path=p)[0] for o, p in zip(objects, paths)]

    def golden(obj: Samples):
        path = golden_path(layout, obj.name)
        return None if path is None else load_golden(path, obj.n_samples)["sets"]

    sets, sources = choose_sets(objects, n_sets=n_sets, set_size=set_size, seed=seed,
                                golden=golden)
    return RealData(layout, objects, sets, sources, diag)


def released_benchmark(lbipe_dir: str | os.PathLike, *, seed: int = 0,
                       l_max: dict[str, float] | None = None,
                       real: RealData | None = None) -> dict:
    """The authors' released model pairs on the real files (Tables I and III): the result
    of :func:`jaxinertia.evaluation.evaluate` plus ``set_source``, ``timing_s`` and the
    objects."""
    t0 = time.perf_counter()
    real = real or load_real(lbipe_dir, seed=seed, l_max=l_max)
    pair = load_released_models(real.layout.weights_dir, prefer=real.layout.prefer)
    t1 = time.perf_counter()
    res = evaluate(real.objects, real.sets, pair=pair, fc=LBIPE_FEATURES, l_max=real.l_max)
    jax.block_until_ready(res["model_estimates"])
    t2 = time.perf_counter()
    res.update(set_source=dict(zip([o.name for o in real.objects], real.sources)),
               timing_s={"load": t1 - t0, "evaluate_incl_compile": t2 - t1},
               real=real, pair=pair)
    return res


def copy_models(src: str | os.PathLike, dst: str | os.PathLike, *,
                session_strength: float | None = None) -> Path:
    """A model folder written anew at ``dst`` (replacing it), with the session strength
    changed when given; the weights, baselines and the rest of its record unchanged."""
    pair, baselines, fc, config = load_models(src)
    standard = ("format", "format_version", "robot", "n_models", "torque_model",
                "attention_model", "features", "baselines")
    extra = {k: v for k, v in config.items() if k not in standard}
    ref = session_reference(config, session_strength)
    extra["session"] = None if ref is None else ref.to_dict()
    extra["copied_from"] = str(Path(src).resolve())
    return save_models(dst, pair, baselines, fc, robot=config.get("robot"), extra=extra)


def session_reference(config: dict, strength: float | None = None) -> SessionReference | None:
    """A model folder's session reference (None: the folder predates sessions, or was
    trained without); ``strength`` overrides the recorded one."""
    ref = SessionReference.from_dict(config.get("session"))
    return ref if ref is None or strength is None else ref.replace(strength=float(strength))


def adapt_objects(objects: Sequence[Samples], reference: SessionReference | None
                  ) -> tuple[list[Samples], list[list[float]]]:
    """Each object's samples (one recording session each) read in the reference session,
    from its own current-discrepancy slope; returns them and the per-joint ratios."""
    pairs = [adapt(o, reference) for o in objects]
    return [p[0] for p in pairs], [p[1].tolist() for p in pairs]


def evaluate_models(models: str | os.PathLike, objects: Sequence[Samples],
                    sets: Sequence[np.ndarray], *, l_max: Sequence[float] | None = None,
                    robot: str | None = None, session_strength: float | None = None,
                    arm: str | None = None) -> dict:
    """A model folder (its pairs and baselines) on known objects over the given sets, each
    object adapted to the folder's session (``session_strength``: override, 0 = off)."""
    pair, baselines, fc, config = load_models(models, robot=robot, arm=arm)
    objects, ratios = adapt_objects(objects, session_reference(config, session_strength))
    t = time.perf_counter()
    res = evaluate(objects, sets, pair=pair, baselines=baselines, fc=fc, l_max=l_max)
    res["wall_time_s"] = time.perf_counter() - t
    res["config"] = config
    res["session_ratio"] = {o.name: r for o, r in zip(objects, ratios)}
    return res


def evaluate_samples(models: str | os.PathLike, sample_file: str | os.PathLike, *,
                     n_sets: int = 1000, set_size: int = 64, seed: int = 0,
                     arm: str | None = None) -> dict:
    """A model folder on every object of a sample file (random sets, seed + i); ``arm``:
    the arm the samples must come from."""
    data, meta = load_samples(sample_file)
    arm = samples_arm(sample_file, meta, arm)
    objects = data.by_object()
    sets, _ = choose_sets(objects, n_sets=n_sets, set_size=set_size, seed=seed)
    return evaluate_models(models, objects, sets, l_max=l_max_of(objects, path=sample_file),
                           robot=meta.get("robot"), arm=arm)


def sim_to_real(models: str | os.PathLike, lbipe_dir: str | os.PathLike, *, seed: int = 0,
                n_sets: int = 1000, l_max: dict[str, float] | None = None,
                real: RealData | None = None) -> dict | None:
    """Trained models on every real test file in ``lbipe_dir``, beside the released models
    on the same sets. None when the folder is absent. ``real``: the folder already loaded."""
    if real is None and not Path(lbipe_dir).is_dir():
        return None
    real = real or load_real(lbipe_dir, seed=seed, n_sets=n_sets, l_max=l_max)
    ours = evaluate_models(models, real.objects, real.sets, l_max=real.l_max,
                           arm=LBIPE_ARM)
    names = [o.name for o in real.objects]
    out = {"ours": {"objects": ours["objects"], "torque": ours["torque"]},
           "files": {n: str(p) for n, p in real.layout.test_files.items()},
           "sets": dict(zip(names, real.sources))}
    released = released_benchmark(lbipe_dir, real=real)["objects"]
    out["released"] = {k: {m: v[m] for m in ("T", "T-A")} for k, v in released.items()}
    out["note"] = ("Real files: " + ", ".join(f"{k} ({v} sets)" for k, v in out["sets"].items())
                   + ". The released models were trained on the authors' real training set.")
    return out


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


def estimate(models: str | os.PathLike, sample_file: str | os.PathLike, *, set_size: int = 64,
             n_sets: int = 200, seed: int = 0, max_mass: float = 5.0,
             max_com: float = 0.5, max_com_se: float | None = None,
             session_strength: float | None = None, arm: str | None = None) -> dict:
    """Mass and COM of each object in a sample file (ground truth, if any, is not used),
    by every method, with standard errors, intervals and covariance.

    Per object: all its samples in one WLS (the estimate) and ``n_sets`` random sets of
    ``set_size`` samples for a spread. A method whose estimate is singular or physically
    impossible (mass not in (0, ``max_mass``], COM farther than ``max_com`` from the tag)
    is reported as failed, with the reason, never as a number; an object no method can
    estimate is an error.

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
    """
    data, meta = load_samples(sample_file, need_truth=False)
    pair, baselines, fc, config = load_models(models, robot=meta.get("robot"),
                                              arm=samples_arm(sample_file, meta, arm))
    objects, ratios = adapt_objects(data.without_truth().by_object(),
                                    session_reference(config, session_strength))
    floor, floor_source = training_validation_error(pair, fc, config)
    noise = floor if floor is not None else np.full(data.n_joints, DEFAULT_TORQUE_NOISE_NM)
    noise_source = ("torque models' validation error" if floor is not None else
                    f"nominal {DEFAULT_TORQUE_NOISE_NM * 1e3:.0f} N mm per joint")
    for obj in objects:  # every refusal before any estimate
        where = f"{sample_file}" + (f" [{obj.name}]" if len(objects) > 1 else "")
        if obj.n_samples < set_size:
            raise UsageError(f"{where}: {obj.n_samples} sample(s); an estimate needs at least "
                             f"one set of --set-size {set_size}")
        if np.all(obj.q_d == obj.q):
            raise UsageError(f"{where}: q_d - q is zero on every sample: no discrepancy to "
                             "read a load from (torque off, or q_d recorded as q?)")
        _identifiable(obj, noise, where)
    out: dict = {"file": str(sample_file), "objects": {},
                 "torque_error_floor": {"Nm": None if floor is None else floor.tolist(),
                                        "source": floor_source}}
    for obj, ratio in zip(objects, ratios):
        all_samples = [np.arange(obj.n_samples)[None]]
        res = evaluate([obj], all_samples, pair=pair, baselines=baselines, fc=fc,
                       l_max=[np.nan])
        unc = uncertainty_of([obj], all_samples, pair=pair, fc=fc, baselines=baselines,
                             floor=floor)
        sets, _ = choose_sets([obj], n_sets=n_sets, set_size=set_size, seed=seed)
        spread = evaluate([obj], sets, pair=pair, baselines=baselines, fc=fc, l_max=[np.nan])
        methods = {}
        for m, x_all in res["estimates"].items():
            x_models = np.asarray(x_all).reshape(-1, 4)  # (K, 4) or (1, 4)
            x = np.mean(x_models, axis=0)
            why = _gate(x, max_mass=max_mass, max_com=max_com)
            if why is not None:
                methods[m] = {"ok": False, "reason": why}
                continue
            xs = np.asarray(spread["estimates"][m]).reshape(-1, 4)
            good = np.array([_gate(v, max_mass=max_mass, max_com=max_com) is None for v in xs])
            methods[m] = {
                "ok": True, "mass_kg": float(x[0]), "com_tag_m": (x[1:] / x[0]).tolist(),
                **_uncertainty_fields(unc[m], 0),
                "mass_std_across_models_kg": float(np.std(x_models[:, 0])),
                f"mass_std_over_{set_size}_sample_sets_kg": float(np.std(xs[good, 0])),
                f"com_std_over_{set_size}_sample_sets_m":
                    np.std(xs[good, 1:] / xs[good, :1], axis=0).tolist(),
                "failed_sets": int(np.sum(~good)), "n_sets": int(len(xs)),
            }
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
            "n_samples": obj.n_samples, "methods": methods, "session_ratio": ratio,
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
    return out
