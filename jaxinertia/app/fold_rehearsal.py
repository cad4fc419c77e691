"""The held-out folds' trainings from scratch, compiled while the folds' simulators calibrate.

On an accelerator (:mod:`jaxinertia.app.fold_groups`) a fold's critical path is its
calibration, the simulation of its training data, then the trainings from scratch (the
paper network and each physical branch, grouped into few programs), whose torque epochs
and attention compiled only once that data existed (6-11 s and the models' initialisers on
the path; docs/benchmarks.md, "Session 31"). The shapes of that data are known before it is
simulated: every sample of the simulated scenarios comes to rest, so each object's count is
the scenario's (:func:`jaxinertia.sim.run.request_counts`). Each member of the folds'
``scratch`` group therefore rehearses its training (:func:`jaxinertia.training_group.rehearse_as`)
on placeholder samples of those shapes while the calibration runs: the torque models'
training, then the attention's, compiled and not run. The real trainings then find their
programs compiled (JAX keeps them per function and shapes; the epochs are cached per model
and setting, :func:`jaxinertia.training_group.shared_cache`).

Nothing computed is kept: the programs are the trainings' own, so no number changes. Where
a planned shape is wrong (a simulated sample that timed out before rest), the rehearsal
compiled a program nobody runs, and the training compiles its own as before.
"""

from __future__ import annotations

import threading

import jax
import numpy as np

from jaxinertia.app.fold_groups import branch_tags
from jaxinertia.networks import TORQUE_MODELS, parameter_shapes
from jaxinertia.objects import TRAINING_LOADS_KG, load_name
from jaxinertia.sample_record import Samples
from jaxinertia.sim.run import ScenarioRequest, request_counts
from jaxinertia.training import train_attention_models, train_torque_models
from jaxinertia.training_group import rehearse_as
from jaxinertia.training_setup import feature_config_from, per_object_subset, split_validation

__all__ = ["placeholder_samples", "rehearse_folds", "scratch_counts"]


def scratch_counts(scale, seed: int, tag: str | None) -> list[int]:
    """Per object, in the order the training reads them, the simulated samples a fold's
    training from scratch gets (:func:`jaxinertia.app.folds._run_fold`): the random scenario
    (``tag`` ``"_current_sessions"``: over ``scale.session_draws`` drawn sessions, each
    ``ceil(n / draws)`` per object), then the planning grid when the scale has it.
    ``tag`` None: the paper network (the fold's own data, as the physical branch)."""
    n = scale.random_per_load
    if tag == "_current_sessions":
        draws = scale.session_draws
        counts = [draws * -(-n // draws)] * len(TRAINING_LOADS_KG)
    else:
        counts = request_counts(ScenarioRequest("random", n, None, seed))
    if scale.planning:
        counts += request_counts(ScenarioRequest("planning", None, None, seed))
    return counts


def placeholder_samples(counts: list[int], n_joints: int = 4, seed: int = 0) -> Samples:
    """Samples of the simulated training files' fields, dtypes and per-object counts
    (objects named like the training loads, one per count), with values of plausible
    scale: what a rehearsal compiles the training's programs on."""
    rng = np.random.default_rng(seed)
    S, N, O = int(sum(counts)), n_joints, len(counts)
    q = rng.uniform(-1.5, 1.5, (S, N))
    x = np.column_stack([rng.uniform(0.01, 0.15, O), rng.normal(0.0, 1e-3, (O, 3))])
    loads = [load_name(TRAINING_LOADS_KG[i % len(TRAINING_LOADS_KG)]) for i in range(O)]
    return Samples(
        q_d=q + rng.normal(0.0, 0.01, (S, N)), q=q, direction=rng.choice([-1.0, 1.0], (S, N)),
        current_tau=rng.normal(0.0, 0.1, (S, N)), tau_g=rng.normal(0.0, 0.3, (S, N)),
        A=rng.normal(0.0, 0.1, (S, N, 4)), object_id=np.repeat(np.arange(O), counts),
        x=x, tau=rng.normal(0.0, 0.3, (S, N)),
        names=tuple(f"{name}#{i}" for i, name in enumerate(loads)))


def rehearse_folds(folds, groups) -> threading.Thread:
    """Every fold's trainings rehearsed (module docstring): those from scratch as members of
    ``groups.scratch``'s twin (a thread each, started here), then, once those are
    compiled, the fine-tunings as members of ``groups.finetune``'s (while the models they
    start from train). ``folds``: :func:`jaxinertia.app.folds.run_folds`' folds. Returns
    the thread that waits for the first and starts the second (a daemon; nobody needs to
    wait for it: a training that starts first compiles its programs itself)."""
    scratch = [rehearse_as(groups.scratch, f"{fold.fit_on}/{name}",
                           lambda cfg=cfg, data=data: _training(cfg, data))
               for fold in folds for name, cfg, data in _scratch_trainings(fold)]

    def then() -> None:
        for t in scratch:
            t.join()
        for fold in folds:
            for tag in branch_tags(fold.scale):
                for n in fold.scale.finetune_samples:
                    rehearse_as(groups.finetune, f"{fold.fit_on}/physical{tag}/{n}",
                                lambda f=fold, t=tag, n=n: _finetuning(f, t, n))

    thread = threading.Thread(target=then, name="rehearse-fine-tunings", daemon=True)
    thread.start()
    return thread


def _scratch_trainings(fold) -> list[tuple]:
    """``(member name, configuration, placeholder data)`` of a fold's trainings from
    scratch: the paper network, then each physical branch (:func:`branch_tags`)."""
    out = []
    for tag in [None, *branch_tags(fold.scale)]:
        cfg = fold.scale.train.replace(seed=fold.seed)
        if tag is not None:
            cfg = cfg.replace(torque_model="physical", current_input=bool(tag))
        out.append(("paper" if tag is None else f"physical{tag}", cfg,
                    placeholder_samples(scratch_counts(fold.scale, fold.seed, tag),
                                        seed=fold.seed)))
    return out


def _training(cfg, data: Samples) -> None:
    """What :func:`jaxinertia.app.pipeline.train` runs of a training from scratch, on
    ``data``: the split, the features, the torque models, then the attention."""
    train_set, val_set = split_validation(data, cfg.val_fraction, cfg.seed)
    fc = feature_config_from(train_set, current_input=cfg.current_input)
    k_t, k_a = jax.random.split(jax.random.key(cfg.seed))
    torque = train_torque_models(cfg, fc, train_set, val_set, k_t, progress=False)
    train_attention_models(cfg, fc, torque, train_set, val_set, k_a, progress=False)


def _finetuning(fold, tag: str, n: int) -> None:
    """What :func:`jaxinertia.app.pipeline.train` runs of the fine-tuning of the fold's
    physical branch ``tag`` on ``n`` of its real samples (:func:`jaxinertia.app.folds.
    _finetuned`): its torque models' servo part from parameters of the start's shapes (the
    start is still training), on the fold's real samples (their values as read, not as
    the start's session reads them: the shapes are what counts). The attention is not
    trained (``trainable="servo"``): nothing to compile."""
    cfg = fold.scale.finetune.replace(seed=fold.seed, n_models=fold.scale.train.n_models,
                                      torque_model="physical", current_input=bool(tag))
    data = per_object_subset(fold.record(fold.fit_on), n, cfg.seed)
    train_set, val_set = split_validation(data, cfg.val_fraction, cfg.seed)
    fc = feature_config_from(train_set, current_input=cfg.current_input)
    model = TORQUE_MODELS["physical"](n_joints=train_set.n_joints)
    start = jax.tree_util.tree_map(lambda s: np.zeros(s.shape, s.dtype), parameter_shapes(
        model, train_set.n_joints, cfg.n_models, np.float32, fc.n_inputs))
    k_t, _ = jax.random.split(jax.random.key(cfg.seed))
    train_torque_models(cfg, fc, train_set, val_set, k_t, init=start, model=model,
                        progress=False)
