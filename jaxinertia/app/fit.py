"""Fitting K model pairs (torque, then attention), and fine-tunings that start from a fit
still running.

A fine-tuning of the servo part alone (``--trainable servo``, the held-out folds') changes
the start's torque models and keeps its attention as it is: it needs the start's torque
models first and its attention only when it writes its folder. :class:`EarlyStart` is
such a start: :func:`jaxinertia.app.pipeline.train` publishes into it what the start's
folder will hold as soon as its torque models are trained (their parameters, the feature
scaling, the record), and the finished folder once written; a fine-tuning given it as
``init`` trains its torque models while the start's attention trains, and waits for that
attention only at its end. The fine-tuned models are those a fine-tuning of the written
folder gives (the same numbers: tests/test_folds.py). On an accelerator the held-out
folds' fine-tunings then run beside the attention's epochs instead of after them
(docs/benchmarks.md, "Session 33").
"""

from __future__ import annotations

import time
from collections.abc import Callable
from concurrent.futures import Future
from contextlib import contextmanager
from pathlib import Path

import jax
import numpy as np

from jaxinertia.baselines import fit_baselines
from jaxinertia.estimation import ModelPair
from jaxinertia.samples import Samples
from jaxinertia.training import (
    TrainConfig,
    rehearse_attention,
    train_attention_models,
    train_torque_models,
)

__all__ = ["EarlyStart", "fit_pairs"]


def fit_pairs(cfg: TrainConfig, fc, train_set: Samples, val_set: Samples,
              start: ModelPair | None, progress: bool,
              on_torque: Callable[[ModelPair], None] | None = None):
    """The K torque and attention model pairs (from ``start``'s parameters when given) and
    the baselines; returns them, the two trainings' results and when the torque's ended.
    ``on_torque``: called with the pair once the torque models are trained (its
    attention the untrained start's, never to be used)."""
    k_t, k_a = jax.random.split(jax.random.key(cfg.seed))
    # In a group (GPU folds) the attention compiles while the torque models train; done when
    # they are (every member then started its rehearsal or left): benchmarks.md, Session 30.
    rehearsal = rehearse_attention(cfg, fc, train_set, val_set, k_a) if start is None else None
    torque = train_torque_models(cfg, fc, train_set, val_set, k_t, progress=progress,
                                 init=None if start is None else start.torque_vars,
                                 model=None if start is None else start.torque_model)
    if rehearsal is not None:
        rehearsal.join()
    t1 = time.perf_counter()
    if on_torque is not None:
        on_torque(torque)
    attention = train_attention_models(
        cfg, fc, torque, train_set, val_set, k_a, progress=progress,
        init=None if start is None else start.attention_vars,
        model=None if start is None else start.attention_model)
    baselines = fit_baselines(train_set.q_d, train_set.q, train_set.direction,
                              train_set.current_tau, train_set.tau)
    pair = ModelPair(torque_vars=torque.variables, attention_vars=attention.variables,
                     tau_scale=np.asarray(fc.tau_scale, np.float32),
                     torque_model=torque.model, attention_model=attention.model)
    return pair, baselines, torque, attention, t1


class _PendingPair:
    """A :class:`~jaxinertia.estimation.ModelPair` whose attention is still training: the
    torque models now, ``attention_vars`` once the start's folder is written."""

    def __init__(self, torque, tau_scale, n_models: int, final: Future):
        self.torque_vars, self.torque_model = torque.variables, torque.model
        self.tau_scale, self.n_models, self._final = tau_scale, n_models, final

    @property
    def attention_model(self):
        return self._final.result().attention_model

    @property
    def attention_vars(self):
        return self._final.result().attention_vars


class _Start:
    """What ``train(init=...)`` reads of a start: its pair, feature scaling and record."""

    def __init__(self, pair, features, config: dict):
        self.pair, self.features, self.config = pair, features, config


class EarlyStart:
    """The model folder ``path`` being trained, as a fine-tuning's start (``init`` of
    :func:`jaxinertia.app.pipeline.train`) before it is written: :meth:`start` waits for
    its torque models; the attention waits for the folder (:meth:`written`). A failed
    start fails the fine-tunings that wait for it (:meth:`failed`)."""

    def __init__(self, path):
        self.path = Path(path)
        self._torque: Future = Future()
        self._final: Future = Future()

    def torque_trained(self, torque, features, config: dict) -> None:
        """The start's torque models, feature scaling and record (``config.json`` as it will
        be written, but for the training's results)."""
        pair = _PendingPair(torque, np.asarray(features.tau_scale, np.float32),
                            int(jax.tree_util.tree_leaves(torque.variables)[0].shape[0]),
                            self._final)
        self._torque.set_result(_Start(pair, features, config))

    def written(self, pair: ModelPair) -> None:
        """The start's model pairs, as its folder now holds them."""
        self._final.set_result(pair)

    def failed(self, error: BaseException) -> None:
        """The start failed with ``error``: every fine-tuning waiting for it (or that will)
        raises it; what was already published stays."""
        for f in (self._torque, self._final):
            if not f.done():
                f.set_exception(error)

    @contextmanager
    def resolving(self):
        """Around the whole of the start's making: whatever it raises, where :func:`train`
        does not see it too (setting the training up), fails the fine-tunings waiting for
        it, and a block that ends without the folder written fails them as well, so that
        none waits for ever."""
        try:
            yield self
        except BaseException as e:
            self.failed(e)
            raise
        if not self._final.done():
            self.failed(RuntimeError(f"{self.path}: its training ended without writing it"))

    def start(self) -> _Start:
        """The start as a fine-tuning reads it (waits for the torque models)."""
        return self._torque.result()
