"""The held-out folds' fine-tunings, compiled while the models they start from train.

On an accelerator (:mod:`jaxinertia.app.fold_groups`) each fold's physical branches train
from scratch (the torque models, then the attention, grouped into few programs), then
fine-tune their servo part on 64, 250 and 1000 of the fold's real samples (again grouped).
The fine-tunings' programs compiled only when their start folders existed: 5-6 s of a
GPU fold's critical path, its host otherwise idle during the attention's epochs before
(docs/benchmarks.md, "Session 31"). Their shapes are known long before: the models' (the
branch's architecture and model count) and the real samples' (the fold's own file). So once
every member of the ``scratch`` group has trained its torque models, each fine-tuning is
rehearsed (:func:`jaxinertia.training_group.rehearse_as`) as the member of the
``finetune`` group's twin: its training on the fold's real samples from parameters of the
start's shapes, compiled and not run. The real fine-tunings then find their programs
compiled (JAX keeps them per function and shapes; the epochs are cached per model and
setting, :func:`jaxinertia.training_group.shared_cache`).

Nothing computed is kept: the programs are the trainings' own, so no number changes.

Tried and not kept (the same session): rehearsing the trainings from scratch too, on
placeholder samples of the simulated data's shapes, during the calibration or the
simulation. Their programs were found compiled (the torque stage 42 -> 23 s), but the
tracing beside those stages' host loops slowed them as much (calibration 31.8 -> 49.2 s,
or simulation 21 -> 30 s): the host, not the GPU, is what a fold waits for there.
"""

from __future__ import annotations

import threading

import jax
import numpy as np

from jaxinertia.app.fold_groups import branch_tags
from jaxinertia.networks import TORQUE_MODELS, parameter_shapes
from jaxinertia.training import train_torque_models
from jaxinertia.training_group import rehearse_as
from jaxinertia.training_setup import feature_config_from, per_object_subset, split_validation

__all__ = ["rehearse_finetunes"]


def rehearse_finetunes(folds, groups) -> threading.Thread:
    """A thread (a daemon, started here) that waits until every member of
    ``groups.scratch`` has trained its torque models, then rehearses each fold's
    fine-tunings as the members of ``groups.finetune``'s twin (module docstring); ``folds``:
    :func:`jaxinertia.app.folds.run_folds`' folds. Nobody needs to wait for it: a
    fine-tuning that starts first compiles its programs itself."""
    def run() -> None:
        groups.scratch.wait_reached(0)  # the torque models' epochs: short GPU programs
        for fold in folds:
            for tag in branch_tags(fold.scale):
                for n in fold.scale.finetune_samples:
                    rehearse_as(groups.finetune, f"{fold.fit_on}/physical{tag}/{n}",
                                lambda f=fold, t=tag, n=n: finetuning(f, t, n))

    thread = threading.Thread(target=run, name="rehearse-fine-tunings", daemon=True)
    thread.start()
    return thread


def finetuning(fold, tag: str, n: int, start=None) -> None:
    """What :func:`jaxinertia.app.pipeline.train` runs of the fine-tuning of a fold's
    physical branch ``tag`` on ``n`` of its real samples (:func:`jaxinertia.app.folds.
    _finetuned`): the servo part of its torque models from ``start`` (default: zeros of
    the start's shapes, the start still training), on the fold's real samples (as read,
    not as the start's session reads them: the shapes are what counts). The attention is
    not trained (``trainable="servo"``): nothing of it to compile."""
    cfg = fold.scale.finetune.replace(seed=fold.seed, n_models=fold.scale.train.n_models,
                                      torque_model="physical", current_input=bool(tag))
    data = per_object_subset(fold.record(fold.fit_on), n, cfg.seed)
    train_set, val_set = split_validation(data, cfg.val_fraction, cfg.seed)
    fc = feature_config_from(train_set, current_input=cfg.current_input)
    model = TORQUE_MODELS["physical"](n_joints=train_set.n_joints)
    if start is None:
        start = jax.tree_util.tree_map(lambda s: np.zeros(s.shape, s.dtype), parameter_shapes(
            model, train_set.n_joints, cfg.n_models, np.float32, fc.n_inputs))
    k_t, _ = jax.random.split(jax.random.key(cfg.seed))
    train_torque_models(cfg, fc, train_set, val_set, k_t, init=start, model=model,
                        progress=False)
