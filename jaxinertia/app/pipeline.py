"""The paper's steps as the command line runs them: train, evaluate, estimate, the released
models' benchmark and sim-to-real.

``train`` turns sample files of known objects into a model folder (orbax checkpoint and
JSON config, see :mod:`jaxinertia.checkpoints`); every evaluation goes through the one
evaluator :func:`jaxinertia.evaluation.evaluate` with sets from
:func:`jaxinertia.evaluation.choose_sets`; ``estimate`` gives the mass and COM of an unknown
object from a sample file.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import jax
import numpy as np

from jaxinertia.baselines import fit_baselines
from jaxinertia.checkpoints import file_sha256, load_models, save_models
from jaxinertia.errors import FileFormatError, UsageError
from jaxinertia.estimation import ModelPair
from jaxinertia.evaluation import choose_sets, evaluate, l_max_of
from jaxinertia.features import LBIPE_FEATURES
from jaxinertia.lbipe import (
    LbipeLayout,
    find_layout,
    golden_path,
    load_golden,
    load_released_models,
    test_files,
)
from jaxinertia.samples import Samples, load_samples
from jaxinertia.training import (
    TrainConfig,
    feature_config_from,
    split_validation,
    train_attention_models,
    train_torque_models,
)

__all__ = ["RealData", "estimate", "evaluate_models", "evaluate_samples", "load_real",
           "released_benchmark", "sim_to_real", "train", "write_json"]


def train(sample_files: Sequence[str | os.PathLike], out: str | os.PathLike, cfg: TrainConfig,
          *, progress: bool = True) -> dict:
    """Trains K model pairs and fits the baselines; writes the model folder ``out``."""
    parts, metas = [], []
    for f in sample_files:
        d, meta = load_samples(f)
        parts.append(d)
        metas.append(meta)
    robots = {m.get("robot") for m in metas}
    if len(robots) != 1:
        raise FileFormatError(sample_files[0], "metadata", f"files of different robots {robots}")
    data = Samples.concatenate(parts)
    t0 = time.perf_counter()
    train_set, val_set = split_validation(data, cfg.val_fraction, cfg.seed)
    fc = feature_config_from(train_set)
    key = jax.random.key(cfg.seed)
    k_t, k_a = jax.random.split(key)
    torque = train_torque_models(cfg, fc, train_set, val_set, k_t, progress=progress)
    t1 = time.perf_counter()
    attention = train_attention_models(cfg, fc, torque, train_set, val_set, k_a,
                                       progress=progress)
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
                  "seed": m.get("seed"), "source": m.get("source")}
                 for f, m in zip(sample_files, metas)],
        "simulator": metas[0].get("simulator"),
        "samples": {"train": train_set.n_samples, "validation": val_set.n_samples},
        "best_epoch": {"torque": torque.best_epoch.tolist(),
                       "attention": attention.best_epoch.tolist()},
        "history": {"torque": torque.history.tolist(), "attention": attention.history.tolist()},
        "wall_time_s": {"torque": t1 - t0, "attention": t2 - t1},
    }
    save_models(out, pair, baselines, fc, robot=robots.pop(), extra=info)
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


def evaluate_models(models: str | os.PathLike, objects: Sequence[Samples],
                    sets: Sequence[np.ndarray], *, l_max: Sequence[float] | None = None,
                    robot: str | None = None) -> dict:
    """A model folder (its pairs and baselines) on known objects over the given sets."""
    pair, baselines, fc, config = load_models(models, robot=robot)
    t = time.perf_counter()
    res = evaluate(objects, sets, pair=pair, baselines=baselines, fc=fc, l_max=l_max)
    res["wall_time_s"] = time.perf_counter() - t
    res["config"] = config
    return res


def evaluate_samples(models: str | os.PathLike, sample_file: str | os.PathLike, *,
                     n_sets: int = 1000, set_size: int = 64, seed: int = 0) -> dict:
    """A model folder on every object of a sample file (random sets, seed + i)."""
    data, meta = load_samples(sample_file)
    objects = data.by_object()
    sets, _ = choose_sets(objects, n_sets=n_sets, set_size=set_size, seed=seed)
    return evaluate_models(models, objects, sets, l_max=l_max_of(objects, path=sample_file),
                           robot=meta.get("robot"))


def sim_to_real(models: str | os.PathLike, lbipe_dir: str | os.PathLike, *, seed: int = 0,
                n_sets: int = 1000, l_max: dict[str, float] | None = None) -> dict | None:
    """Trained models on every real test file in ``lbipe_dir``, beside the released models
    on the same sets. None when the folder is absent."""
    if not Path(lbipe_dir).is_dir():
        return None
    real = load_real(lbipe_dir, seed=seed, n_sets=n_sets, l_max=l_max)
    ours = evaluate_models(models, real.objects, real.sets, l_max=real.l_max)
    names = [o.name for o in real.objects]
    out = {"ours": {"objects": ours["objects"], "torque": ours["torque"]},
           "files": {n: str(p) for n, p in real.layout.test_files.items()},
           "sets": dict(zip(names, real.sources))}
    released = released_benchmark(lbipe_dir, real=real)["objects"]
    out["released"] = {k: {m: v[m] for m in ("T", "T-A")} for k, v in released.items()}
    out["note"] = ("Real files: " + ", ".join(f"{k} ({v} sets)" for k, v in out["sets"].items())
                   + ". The released models were trained on the authors' real training set.")
    return out


def estimate(models: str | os.PathLike, sample_file: str | os.PathLike, *, set_size: int = 64,
             n_sets: int = 200, seed: int = 0) -> dict:
    """Mass and COM of an unknown object from a sample file, by every method.

    Uses all samples in one WLS (the estimate) and, when there are more than ``set_size``,
    ``n_sets`` random sets of ``set_size`` samples for a spread. A singular set of samples
    (e.g. too few distinct configurations) is an error, not a NaN.
    """
    data, meta = load_samples(sample_file, need_truth=False)
    pair, baselines, fc, _ = load_models(models, robot=meta.get("robot"))
    if data.n_samples < 2:
        raise UsageError(f"{sample_file}: {data.n_samples} sample(s); need at least 2 "
                         "configurations")
    obj = data.without_truth().replace(object_id=np.zeros(data.n_samples, np.int64),
                                       names=("unknown",))
    res = evaluate([obj], [np.arange(data.n_samples)[None]], pair=pair, baselines=baselines,
                   fc=fc, l_max=[np.nan])
    out: dict = {"n_samples": data.n_samples, "methods": {}}
    for m, x in res["estimates"].items():
        x = np.asarray(x).reshape(-1, 4)
        if not np.all(np.isfinite(x)):
            raise UsageError(f"{sample_file}: the samples do not determine mass and COM "
                             f"(singular least squares for {m}): add configurations that "
                             "vary all joints")
        mass = x[:, 0]
        com = x[:, 1:] / x[:, :1]
        out["methods"][m] = {"mass_kg": float(np.mean(mass)), "com_tag_m": np.mean(com, 0).tolist(),
                             "mass_std_across_models_kg": float(np.std(mass))}
    if data.n_samples > set_size:
        sets, _ = choose_sets([obj], n_sets=n_sets, set_size=set_size, seed=seed)
        spread = evaluate([obj], sets, pair=pair, baselines=baselines, fc=fc, l_max=[np.nan])
        for m, x in spread["estimates"].items():
            x = np.asarray(x).reshape(-1, 4)
            x = x[np.all(np.isfinite(x), axis=-1)]
            out["methods"][m][f"mass_std_over_{set_size}_sample_sets_kg"] = float(np.std(x[:, 0]))
            out["methods"][m][f"com_std_over_{set_size}_sample_sets_m"] = np.std(
                x[:, 1:] / x[:, :1], axis=0).tolist()
    return out


def write_json(path: str | os.PathLike, obj) -> Path:
    """``obj`` as indented JSON (numpy arrays as lists), written atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(obj, indent=2, default=_json_default) + "\n")
    os.replace(tmp, path)
    return path


def _json_default(o):
    if isinstance(o, np.ndarray | np.generic):
        return o.tolist()
    raise TypeError(type(o).__name__)
