"""The paper's steps as the command line runs them: train, evaluate, the released models'
benchmark and sim-to-real (``estimate``: :mod:`jaxinertia.app.estimate`).

``train`` turns sample files of known objects into a model folder (orbax checkpoint and
JSON config, see :mod:`jaxinertia.checkpoints`); every evaluation goes through the one
evaluator :func:`jaxinertia.evaluation.evaluate` with sets from
:func:`jaxinertia.evaluation.choose_sets`, each object first read in the model folder's
session (:mod:`jaxinertia.session`).
"""

from __future__ import annotations

import os
import time
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import jax
import numpy as np

from jaxinertia.app.arm_options import LBIPE_ARM, samples_arm
from jaxinertia.app.by_part import COM_MODELS, com_models_of, merge_evaluations
from jaxinertia.app.ensemble import (
    ENSEMBLE_KEYS,
    map_members,
    mean_evaluation,
    members_of,
    weights_of,
)
from jaxinertia.app.fit import EarlyStart, fit_pairs
from jaxinertia.app.provenance import FITTED_ON, fitted_on
from jaxinertia.checkpoints import (
    UNIFORM_ATTENTION,
    copy_folder,
    load_models,
    read_config,
    save_models,
)
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
    read_test_files,
)
from jaxinertia.networks import torque_model_kind
from jaxinertia.reference import corrected, evaluate_corrected
from jaxinertia.samples import SampleFile, Samples, load_samples, read_sample_file
from jaxinertia.session import (
    ServoSession,
    SessionReference,
    adapt,
    adapt_objects,
    servo_session,
    session_reference,
)
from jaxinertia.session_terms import with_session_terms
from jaxinertia.training import (
    TrainConfig,
    feature_config_from,
    split_validation,
    subset_per_object,
)
from jaxinertia.uncertainty import validation_torque_error

__all__ = ["UNIFORM_ATTENTION", "RealData", "adapt_objects", "copy_models", "evaluate_models",
           "evaluate_samples", "is_simulated", "load_real", "objects_at_rest",
           "released_benchmark", "session_reference", "sim_to_real", "train"]


def train(sample_files: Sequence[str | os.PathLike | SampleFile], out: str | os.PathLike,
          cfg: TrainConfig, *, progress: bool = True, overwrite: bool = False,
          init: str | os.PathLike | None = None,
          samples_per_object: int | Sequence[int] | None = None,
          session: ServoSession | None = None, arm: str | None = None,
          early: EarlyStart | None = None) -> dict:
    """Trains K model pairs and fits the baselines; writes the model folder ``out``
    (atomically; an existing one only with ``overwrite``). ``sample_files``: paths, or
    records already read (:class:`~jaxinertia.samples.SampleFile`).

    ``init``: a model folder to fine-tune instead of training from scratch (e.g.
    simulator-trained models adapted on real samples of known objects): its parameters are
    the start (they compete as epoch -1 on the validation split), its feature normalisation
    is kept and its model count wins over ``cfg.n_models``; the baselines are fitted on the
    new data. ``samples_per_object``: use only that many samples of each object (seeded
    random choice; all when it has fewer; a sequence: of each file's objects, in order).

    ``session``: the models' reference session (:mod:`jaxinertia.session`): the real
    files a simulator was calibrated on, whose servo state the simulated data imitate;
    default: the init folder's, else the training data's own (pooled). Every real training
    file is read in it (simulated files in the simulator's own); the folder records it, and
    evaluation and estimation read every file in it. ``arm``: the arm the samples must
    come from (the folder records it; default: the one the files record). ``early``: told
    the torque models as soon as they are trained, and the folder once written, for
    fine-tunings that start from it meanwhile (``init`` may be such an
    :class:`~jaxinertia.app.fit.EarlyStart`; one that fails, at any step, fails them too).
    """
    try:
        info, pair = _train(sample_files, out, cfg, progress=progress, overwrite=overwrite,
                            init=init, samples_per_object=samples_per_object,
                            session=session, arm=arm, early=early)
    except BaseException as e:
        if early is not None:
            early.failed(e)
        raise
    if early is not None:
        early.written(pair)
    return info


def _train(sample_files, out, cfg: TrainConfig, *, progress, overwrite, init,
           samples_per_object, session, arm, early) -> tuple[dict, ModelPair]:
    check_output(out, overwrite=overwrite, folder=True)
    files, robot = _training_files(sample_files, arm)
    parts, metas = [f.samples for f in files], [f.meta for f in files]
    start = (None if init is None else init.start() if isinstance(init, EarlyStart)
             else load_models(init, robot=robot))
    init = getattr(init, "path", init)
    if start is not None and members_of(init, start.config):
        raise UsageError(f"{init}: the mean of {len(members_of(init, start.config)) + 1} model "
                         "folders (app.ensemble), no one set of models to start from: "
                         f"fine-tune one of them ({init} itself or its members/...) instead")
    if start is not None:
        robot = robot or start.config.get("robot")
        cfg = cfg.replace(n_models=start.pair.n_models,
                          torque_model=torque_model_kind(start.pair.torque_model))
    parts, (reference, sim_reference), ratios = _sessions_read(
        parts, metas, float(cfg.session_strength), start and start.config, session)
    data = subset_per_object(parts, samples_per_object, cfg.seed)
    t0 = time.perf_counter()
    train_set, val_set = split_validation(data, cfg.val_fraction, cfg.seed)
    if val_set.n_samples == 0 or train_set.n_samples == 0:
        raise UsageError(f"{data.n_samples} samples and --val-fraction {cfg.val_fraction} leave "
                         f"{train_set.n_samples} for training and {val_set.n_samples} for "
                         "validation: both need samples")
    fc = (feature_config_from(train_set, current_input=cfg.current_input) if start is None
          else start.features)
    terms = None
    if cfg.session_terms:
        train_set, val_set, terms = with_session_terms(start, parts, train_set, val_set)
    cfg = cfg.replace(current_input=fc.current_scale is not None)  # fine-tuning: the folder's
    info = {
        "training": cfg.to_dict(),
        "data": [{"file": str(f.path.resolve()), "sha256": f.meta["sha256"],
                  **{k: f.meta.get(k) for k in ("objects", "scenario", "seed", "source")},
                  "session_ratio": r} for f, r in zip(files, ratios)],
        "session": reference.to_dict(),
        "simulator_session": None if sim_reference is None else sim_reference.to_dict(),
        "samples_per_object": (samples_per_object if not isinstance(samples_per_object,
                               Sequence) else [int(n) for n in samples_per_object]),
        "session_terms": terms,
        "simulator": metas[0].get("simulator") or (start and start.config.get("simulator")),
        "samples": {"train": train_set.n_samples, "validation": val_set.n_samples},
    }
    if start is not None:
        info["fine_tuned_from"] = {"folder": str(Path(init).resolve()),
                                   "data": start.config.get("data"),
                                   "training": start.config.get("training")}
        info[FITTED_ON] = [{"sha256": s} for s in sorted(fitted_on(start.config))]
    pair, baselines, torque, attention, t1 = fit_pairs(
        cfg, fc, train_set, val_set, None if start is None else start.pair, progress,
        early and (lambda t: early.torque_trained(t, fc, {"robot": robot, **info})))
    t2 = time.perf_counter()
    info.update({
        # What the uncertainty's floor needs: the torque models' error on this run's own
        # validation split (per joint, RMS over the pairs) [N m].
        "torque_validation_error_Nm": validation_torque_error(pair, fc, val_set).tolist(),
        "best_epoch": {"torque": torque.best_epoch.tolist(),
                       "attention": attention.best_epoch.tolist()},
        "history": {"torque": torque.history.tolist(), "attention": attention.history.tolist()},
        "wall_time_s": {"torque": t1 - t0, "attention": t2 - t1}})
    save_models(out, pair, baselines, fc, robot=robot, extra=info, arm=arm)  # atomic
    return info, pair


def _training_files(sample_files, arm: str | None) -> tuple[list[SampleFile], str | None]:
    """The training files, each read once (a record already read is not read again), all
    of one arm and robot; returns them and the robot's name."""
    files = [f if isinstance(f, SampleFile) else read_sample_file(f) for f in sample_files]
    for f in files:
        samples_arm(f.path, f.meta, arm)  # another arm's file: one line, before any training
    # The authors' layout records no robot: it is taken to be the native files' one.
    robots = {f.meta.get("robot") for f in files} - {None}
    if len(robots) > 1:
        raise FileFormatError(files[0].path, "metadata", f"files of different robots {robots}")
    return files, (robots.pop() if robots else arm)


def _sessions_read(parts, metas, strength: float, init_config: dict | None,
                   session: ServoSession | None):
    """Each file is one recording session, read in the reference session as strongly as
    ``strength`` says: a real file in the models' reference (``session``, else the init
    folder's, else the data's own), a simulated one in the simulator's own (the pooled
    simulated files: the calibration that made them stands for the reference). Returns the
    files' records, the two references (real files', simulated files') and each file's
    per-joint ratio."""
    simulated = [is_simulated(m) for m in metas]
    sim_ref = (SessionReference.of(servo_session([p for p, s in zip(parts, simulated) if s]),
                                   strength) if any(simulated) else None)
    if sim_ref is None and init_config is not None:
        sim_ref = session_reference(init_config, strength, simulated=True)
    reference = None if init_config is None else session_reference(init_config, strength)
    if session is not None:
        reference = SessionReference.of(session, strength)
    if reference is None:
        reference = sim_ref or SessionReference.of(servo_session(parts), strength)
    read = [adapt(p, sim_ref if sim else reference) for p, sim in zip(parts, simulated)]
    return [r[0] for r in read], (reference, sim_ref), [r[1].tolist() for r in read]


def is_simulated(meta: dict) -> bool:
    """Whether a sample file's metadata says the simulator made it (its recording session
    is the simulator's own)."""
    return meta.get("source") == "simulator"


class RealData(NamedTuple):
    """The real test objects of an lbipe folder, with their evaluation sets."""

    layout: LbipeLayout
    objects: list[Samples]
    sets: list[np.ndarray]
    sources: list[str]  # per object: "golden" or "random (seed s)"
    l_max: list[float]
    files: list[SampleFile]  # per object: its file as read once (path, SHA-256)


def load_real(lbipe_dir: str | os.PathLike, *, seed: int = 0, n_sets: int = 1000,
              set_size: int = 64, l_max: dict[str, float] | None = None) -> RealData:
    """Every ``data_test_<name>.npz`` of the folder and its sets: the golden sets when the
    folder has them, else seeded random sets. An object without a bounding-box diagonal
    is an error (``l_max`` supplies one), never silently left out."""
    layout = find_layout(lbipe_dir)
    files = read_test_files(layout)  # each real file read once, for the whole command
    objects = [f.samples for f in files]
    paths = [f.path for f in files]
    diag = [l_max_of([o], l_max, path=p)[0] for o, p in zip(objects, paths)]

    def golden(obj: Samples):
        path = golden_path(layout, obj.name)
        return None if path is None else load_golden(path, obj.n_samples)["sets"]

    sets, sources = choose_sets(objects, n_sets=n_sets, set_size=set_size, seed=seed,
                                golden=golden)
    return RealData(layout, objects, sets, sources, diag, files)


def released_benchmark(lbipe_dir: str | os.PathLike, *, seed: int = 0,
                       l_max: dict[str, float] | None = None,
                       real: RealData | None = None, pairs: list | None = None) -> dict:
    """The authors' released model pairs on the real files (Tables I and III): the result
    of :func:`jaxinertia.evaluation.evaluate` plus ``set_source``, ``timing_s`` and the
    objects. ``pairs``: as :func:`jaxinertia.lbipe.read_released_pairs` read them."""
    t0 = time.perf_counter()
    real = real or load_real(lbipe_dir, seed=seed, l_max=l_max)
    pair = load_released_models(real.layout.weights_dir, prefer=real.layout.prefer,
                                pairs=pairs)
    t1 = time.perf_counter()
    res = evaluate(real.objects, real.sets, pair=pair, fc=LBIPE_FEATURES, l_max=real.l_max)
    jax.block_until_ready(res["model_estimates"])
    t2 = time.perf_counter()
    res.update(set_source=dict(zip([o.name for o in real.objects], real.sources)),
               timing_s={"load": t1 - t0, "evaluate_incl_compile": t2 - t1},
               real=real, pair=pair)
    return res


def copy_models(src: str | os.PathLike, dst: str | os.PathLike, *,
                session_strength: float | None = None, uniform: bool = False) -> Path:
    """A model folder written anew at ``dst`` (replacing it), with the session strength
    changed when given; ``uniform``: answering without its attention (the attention models'
    last layer zeroed when loaded, :data:`~jaxinertia.checkpoints.UNIFORM_ATTENTION`: T-A
    then answers as T), recorded; the weights (their files copied as they are), baselines
    and the rest of its record unchanged."""
    config = read_config(src)
    # A folder's COM models (app.by_part) and ensemble members (app.ensemble) live inside
    # it and are not copied: neither are the keys that name them.
    config = {k: v for k, v in config.items() if k not in (COM_MODELS, *ENSEMBLE_KEYS)}
    for key, simulated in (("session", False), ("simulator_session", True)):
        ref = session_reference(config, session_strength, simulated=simulated)
        config[key] = None if ref is None else ref.to_dict()
    config["copied_from"] = str(Path(src).resolve())
    if uniform:
        config[UNIFORM_ATTENTION] = True
    return copy_folder(src, dst, config)


def evaluate_models(models: str | os.PathLike, objects: Sequence[Samples],
                    sets: Sequence[np.ndarray], *, l_max: Sequence[float] | None = None,
                    robot: str | None = None, session_strength: float | None = None,
                    simulated: bool = False, arm: str | None = None,
                    known: Sequence[Samples] | None = None) -> dict:
    """A model folder (its pairs and baselines) on known objects over the given sets, each
    object read in the folder's session (``simulated``: objects the simulator made, read in
    its session; ``session_strength``: override, 0 = off). A folder that names COM models
    (:mod:`jaxinertia.app.by_part`) is judged with the network methods' COM from those; one
    that names ensemble members (:mod:`jaxinertia.app.ensemble`), by their mean. ``known``:
    known loads recorded in the objects' session, through whose gain and offset per joint
    each folder's networks read them (:mod:`jaxinertia.reference`; the baselines do not)."""
    folder = load_models(models, robot=robot, arm=arm)
    reference = session_reference(folder.config, session_strength, simulated=simulated)
    adapted, ratios = adapt_objects(objects, reference)
    t, members = time.perf_counter(), members_of(models, folder.config)
    pair, read, corr = corrected(folder.pair, folder.features, adapted, known, reference)
    res = evaluate_corrected(read, adapted, sets, pair=pair, baselines=folder.baselines,
                             fc=folder.features, l_max=l_max)
    kw = dict(l_max=l_max, robot=robot, session_strength=session_strength,
              simulated=simulated, arm=arm, known=known)
    if members:  # each member reads the objects in its own session
        res = mean_evaluation(
            [res, *map_members(lambda m: evaluate_models(m, objects, sets, **kw), members)],
            objects, [Path(models), *members], weights_of(folder.config, models))
    com = com_models_of(models, folder.config)
    if com is not None:
        part = evaluate_models(com, objects, sets, **kw)
        res = {**merge_evaluations(res, part), "com_models": str(com), "com_session": {
            "strength": part["session_strength"], "ratio": part["session_ratio"]}}
    res.update({} if corr is None else {"reference_correction": corr.to_dict()})
    res["wall_time_s"] = time.perf_counter() - t
    res["config"] = folder.config
    res["session_ratio"] = {o.name: r for o, r in zip(adapted, ratios)}
    res["session_strength"] = 0.0 if reference is None else reference.strength
    return res


def evaluate_samples(models: str | os.PathLike, sample_file: str | os.PathLike | SampleFile,
                     *, n_sets: int = 1000, set_size: int = 64, seed: int = 0,
                     l_max: dict[str, float] | None = None, arm: str | None = None,
                     session_strength: float | None = None,
                     known: Sequence[Samples] | None = None) -> dict:
    """A model folder on every object of a sample file (random sets, seed + i); ``l_max``
    gives the bounding-box diagonal of objects without a built-in one. ``sample_file``: a
    path, or a file already read (its samples at rest); ``arm``: the arm the samples must
    come from; ``session_strength``: overrides the folder's (:func:`evaluate_models`)."""
    if isinstance(sample_file, SampleFile):
        objects, meta, sample_file = (sample_file.samples.by_object(), sample_file.meta,
                                      sample_file.path)
    else:
        objects, meta = objects_at_rest(sample_file, need_truth=True)
    arm = samples_arm(sample_file, meta, arm)
    massless = [o.name for o in objects if not o.mass > 0]
    if massless:
        raise UsageError(f"{sample_file} [{massless[0]}]: mass 0 (the empty gripper): mass and "
                         "COM errors need a held object; leave it out of the file")
    diag = l_max_of(objects, l_max, path=sample_file)
    sets, _ = choose_sets(objects, n_sets=n_sets, set_size=set_size, seed=seed)
    return {**evaluate_models(models, objects, sets, l_max=diag, robot=meta.get("robot"),
                              simulated=is_simulated(meta), arm=arm,
                              session_strength=session_strength, known=known),
            "sha256": {o.name: meta.get("sha256") for o in objects}}  # (each object's file)


def objects_at_rest(sample_file, *, need_truth: bool) -> tuple[list[Samples], dict]:
    """Each object of a sample file with its samples at rest, and the metadata; a file with
    no such sample, or an object that has none, is an error (an object is never dropped
    from an answer silently)."""
    data, meta = load_samples(sample_file, need_truth=need_truth, only_at_rest=False)
    kept = data.at_rest_only()
    if kept.n_samples == 0:
        raise UsageError(f"{sample_file}: no sample to use: " + (
            "the file holds none" if data.n_samples == 0 else
            f"all {data.n_samples} timed out before rest (at_rest = False)"))
    present = set(np.unique(kept.object_id).tolist())
    for o, name in enumerate(data.names):
        n_all = int(np.sum(data.object_id == o))
        if o not in present and n_all:
            raise UsageError(f"{sample_file} [{name}]: all {n_all} samples of this object "
                             "timed out before rest (at_rest = False): nothing to answer from")
    return kept.by_object(), meta


def sim_to_real(models: str | os.PathLike, lbipe_dir: str | os.PathLike, *, seed: int = 0,
                n_sets: int = 1000, l_max: dict[str, float] | None = None,
                real: RealData | None = None, session_strength: float | None = None) -> dict | None:
    """Trained models on every real test file in ``lbipe_dir``, beside the released models
    on the same sets. None when the folder is absent. ``real``: the folder already loaded;
    ``session_strength``: overrides the folder's (:func:`evaluate_models`)."""
    if real is None and not Path(lbipe_dir).is_dir():
        return None
    real = real or load_real(lbipe_dir, seed=seed, n_sets=n_sets, l_max=l_max)
    ours = evaluate_models(models, real.objects, real.sets, l_max=real.l_max,
                           arm=LBIPE_ARM, session_strength=session_strength)
    names = [o.name for o in real.objects]
    ours["sha256"] = {o.name: f.meta.get("sha256") for o, f in zip(real.objects, real.files)}
    out = {"ours": {k: ours[k] for k in ("objects", "torque", "session_ratio", "session_strength",
                                         "sha256", "com_models", "com_session") if k in ours},
           "files": {n: str(p) for n, p in real.layout.test_files.items()},
           "sets": dict(zip(names, real.sources))}
    released = released_benchmark(lbipe_dir, real=real)["objects"]
    out["released"] = {k: {m: v[m] for m in ("T", "T-A")} for k, v in released.items()}
    out["note"] = ("Real files: " + ", ".join(f"{k} ({v} sets)" for k, v in out["sets"].items())
                   + ". The released models were trained on the authors' real training set.")
    return out
