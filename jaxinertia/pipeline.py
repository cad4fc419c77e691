"""The paper end to end: train on known objects, evaluate (Tables I-III), sim-to-real.

``train`` turns a sample file of known objects into a model folder (orbax checkpoint and
JSON config, see :mod:`jaxinertia.checkpoints`); ``evaluate_*`` turns a model folder and
test objects (simulated or the real lbipe files) into tables; ``estimate`` gives the mass and
COM of an unknown object from a sample file.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import jax
import numpy as np

from jaxinertia.baselines import fit_baselines
from jaxinertia.checkpoints import file_sha256, load_models, save_models
from jaxinertia.datasets import load_samples
from jaxinertia.estimation import ModelPair
from jaxinertia.evaluation import ObjectBatch, evaluate, stack_objects
from jaxinertia.lbipe import BOUNDING_BOX_DIAGONALS, LbipeDataset, LbipeFormatError
from jaxinertia.training import (
    SampleSet,
    TrainConfig,
    feature_config_from,
    split_validation,
    train_attention_models,
    train_torque_models,
)

__all__ = ["estimate", "evaluate_samples", "objects_from_samples", "sets_for", "train"]


def train(sample_files: list[str | os.PathLike], out: str | os.PathLike, cfg: TrainConfig, *,
          progress: bool = True) -> dict:
    """Trains K model pairs and fits the baselines; writes the model folder ``out``."""
    parts, metas = [], []
    offset = 0
    for f in sample_files:
        d, meta = load_samples(f)
        parts.append(d._replace(object_id=d.object_id + offset))
        offset += len(d.x)
        metas.append(meta)
    robots = {m.get("robot") for m in metas}
    if len(robots) != 1:
        raise LbipeFormatError(sample_files[0], "metadata", f"files of different robots {robots}")
    data = SampleSet(*(np.concatenate([getattr(p, k) for p in parts])
                       for k in SampleSet._fields))
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


def objects_from_samples(data: SampleSet, names: list[str],
                         l_max: dict[str, float] | None = None) -> list[LbipeDataset]:
    """Splits a sample set by object into the evaluation's per-object datasets."""
    diag = {**BOUNDING_BOX_DIAGONALS, **(l_max or {})}
    out = []
    for o, name in enumerate(names):
        idx = np.flatnonzero(data.object_id == o)
        if len(idx) == 0:
            continue
        if name not in diag:
            raise ValueError(f"no bounding-box diagonal for object {name!r}")
        d = data.take(idx)
        out.append(LbipeDataset(name=name, q_d=d.q_d, q=d.q, current_tau=d.current_tau,
                                direction=d.direction, tau=d.tau, tau_g=d.tau_g, A=d.A,
                                x=data.x[o]))
    return out


def sets_for(datasets: list[LbipeDataset], *, n_sets: int, set_size: int, seed: int):
    """Independent random sets per object (each drawn without replacement)."""
    from jaxinertia.lbipe_benchmark import random_sets

    return [random_sets(d.n_samples, n_sets=n_sets, set_size=set_size, seed=seed + i)
            for i, d in enumerate(datasets)]


def evaluate_datasets(models: str | os.PathLike, datasets: list[LbipeDataset], *,
                      n_sets: int = 1000, set_size: int = 64, seed: int = 0,
                      sets: list[np.ndarray] | None = None, robot: str | None = None) -> dict:
    pair, baselines, fc, config = load_models(models, robot=robot)
    l_max = [BOUNDING_BOX_DIAGONALS.get(d.name, np.nan) for d in datasets]
    sets = sets or sets_for(datasets, n_sets=n_sets, set_size=set_size, seed=seed)
    batch: ObjectBatch = stack_objects(datasets, l_max, sets, fc)
    t = time.perf_counter()
    res = evaluate(batch, pair, baselines)
    res["wall_time_s"] = time.perf_counter() - t
    res["config"] = config
    return res


def evaluate_samples(models, sample_file, **kw) -> dict:
    """Evaluates a model folder on every object of a native sample file."""
    data, meta = load_samples(sample_file)
    names = meta.get("objects") or [f"object{i}" for i in range(len(data.x))]
    return evaluate_datasets(models, objects_from_samples(data, names), robot=meta.get("robot"),
                             **kw)


def estimate(models: str | os.PathLike, sample_file: str | os.PathLike, *, set_size: int = 64,
             n_sets: int = 200, seed: int = 0) -> dict:
    """Mass and COM of an unknown object from a sample file, by every method.

    Uses all samples in one WLS (the estimate) and, when there are more than ``set_size``,
    ``n_sets`` random sets of ``set_size`` samples for a spread. A singular set of samples
    (e.g. too few distinct configurations) is an error, not a NaN.
    """
    data, meta = load_samples(sample_file, need_tau=False)
    pair, baselines, fc, config = load_models(models, robot=meta.get("robot"))
    if data.n_samples < 2:
        raise ValueError(f"{sample_file}: {data.n_samples} sample(s); need at least 2 "
                         "configurations")
    d = LbipeDataset(name="unknown", q_d=data.q_d, q=data.q, current_tau=data.current_tau,
                     direction=data.direction, tau=np.zeros_like(data.q), tau_g=data.tau_g,
                     A=data.A, x=np.full(4, np.nan))
    all_set = np.arange(data.n_samples)[None]
    batch = stack_objects([d], [np.nan], [all_set], fc)
    res = evaluate(batch, pair, baselines)
    out: dict = {"n_samples": data.n_samples, "methods": {}}
    for m, x in res["estimates"].items():
        x = np.asarray(x).reshape(-1, 4)
        if not np.all(np.isfinite(x)):
            raise ValueError(f"{sample_file}: the samples do not determine mass and COM "
                             f"(singular least squares for {m}): add configurations that "
                             "vary all joints")
        mass = x[:, 0]
        com = x[:, 1:] / x[:, :1]
        out["methods"][m] = {"mass_kg": float(np.mean(mass)), "com_tag_m": np.mean(com, 0).tolist(),
                             "mass_std_across_models_kg": float(np.std(mass))}
    if data.n_samples > set_size:
        sets = sets_for([d], n_sets=n_sets, set_size=set_size, seed=seed)
        spread = evaluate(stack_objects([d], [np.nan], sets, fc), pair, baselines)
        for m, x in spread["estimates"].items():
            x = np.asarray(x).reshape(-1, 4)
            x = x[np.all(np.isfinite(x), axis=-1)]
            out["methods"][m][f"mass_std_over_{set_size}_sample_sets_kg"] = float(np.std(x[:, 0]))
            out["methods"][m][f"com_std_over_{set_size}_sample_sets_m"] = np.std(
                x[:, 1:] / x[:, :1], axis=0).tolist()
    return out


def write_json(path: str | os.PathLike, obj) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(obj, indent=2, default=_json_default) + "\n")
    return path


def _json_default(o):
    if isinstance(o, np.ndarray | np.generic):
        return o.tolist()
    raise TypeError(type(o).__name__)

