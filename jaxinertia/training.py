"""Training the torque and attention models (paper Sec. III-B, III-D; Sec. IV details).

Both trainings are jit-compiled per epoch (a ``lax.scan`` over the minibatches) and run K
model pairs with different seeds in parallel under ``vmap``: K small MLPs make one wider
program instead of K sequential runs. Keys are explicit; the same seed gives the same models.
One epoch skeleton (:func:`make_epoch`, state in :class:`TrainState`) serves both; each
trainer gives its loss, its minibatches and its validation loss.

Torque model: MSE between the predicted and the true normalised joint torques (tau divided
by ``tau_scale``, the training set's max |tau| per joint), Adam, batch 256, 300 epochs,
lr 3e-4.

Attention model: trained *through* the weighted least squares. A training item is a set of
64 samples of one object; the frozen torque model gives ``tau_hat``, the attention model the
weights, the WLS ``x = [m, m p]``; the loss is ``w_m (m_hat - m)^2 + w_com |p_hat - p|^2``
(SI units: kg, m) with ``p_hat = x[1:] / m`` from the *true* mass (the paper's training
trick); sets of the empty gripper carry no COM loss. Adam, batch 32, 30 epochs, lr 1e-4.

Both keep the epoch with the lowest validation loss, per model (held-out samples; the
attention model's validation sets are drawn from them). Fine-tuning (``init``: a trained
folder's parameters, e.g. simulator-trained models adapted on real samples of known
objects) starts from given parameters, which compete as epoch -1, so it never returns
models worse on validation than the ones it started from.

The two trainers and the fine-tuning options are one module on purpose: they share the
epoch skeleton and the optimiser (what ``trainable`` leaves fixed). What a run is given
(its configuration, the split, the sets) is :mod:`jaxinertia.training_setup`; its names
are re-exported here.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from jaxinertia.compile_options import run_once_jit
from jaxinertia.errors import UsageError
from jaxinertia.estimation import predict_torques_stacked
from jaxinertia.features import FeatureConfig, featurize
from jaxinertia.identification import solve_normal
from jaxinertia.linalg import gram_statistics
from jaxinertia.networks import (
    TORQUE_MODELS,
    AttentionModel,
    PhysicalTorqueModel,
    TorqueModel,
    parameter_shapes,
)
from jaxinertia.samples import Samples
from jaxinertia.training_group import rehearse, run_epochs, shared_cache
from jaxinertia.training_setup import (
    FINETUNE_DEFAULTS,
    TrainConfig,
    draw_sets,
    feature_config_from,
    per_object_subset,
    split_validation,
    subset_per_object,
)

__all__ = [
    "FINETUNE_DEFAULTS",
    "Epoch",
    "TrainConfig",
    "TrainState",
    "accelerated_epochs",
    "attention_loss",
    "draw_sets",
    "feature_config_from",
    "make_epoch",
    "optimizer",
    "per_object_subset",
    "rehearse_attention",
    "split_validation",
    "subset_per_object",
    "train_attention_models",
    "train_torque_models",
]


def _features(fc: FeatureConfig, d: Samples) -> jnp.ndarray:
    return featurize(fc, jnp.asarray(d.q), jnp.asarray(d.q_d), jnp.asarray(d.direction),
                     jnp.asarray(d.current_tau)).astype(jnp.float32)


def _init_stacked_fn(model, keys, example):
    return jax.vmap(lambda k: model.init(k, example))(keys)


# One program per architecture and shape (eager, every layer's initialiser compiled op by
# op: dozens of small programs per training); run once per training, so on a GPU compiled
# without the autotuner (``compile_options.run_once_jit``).
_init_stacked = run_once_jit(_init_stacked_fn, static_argnums=0)


def _start(model, key, K: int, example, init):
    """K stacked parameter sets: ``init`` (fine-tuning: checked against the model's shapes)
    or fresh ones from ``key``."""
    fresh = parameter_shapes(model, example.shape[-2], K, example.dtype, example.shape[-1])
    if init is None:
        return _init_stacked(model, jax.random.split(key, K), example)
    if (jax.tree_util.tree_structure(init) != jax.tree_util.tree_structure(fresh) or any(
            np.shape(a) != b.shape for a, b in zip(jax.tree_util.tree_leaves(init),
                                                   jax.tree_util.tree_leaves(fresh)))):
        raise UsageError(f"the initial parameters do not fit {type(model).__name__} with "
                         f"{K} models (another architecture or model count)")
    return jax.tree_util.tree_map(lambda a, b: jnp.asarray(a, b.dtype), init, fresh)


#: The parameter names of the physical torque model's servo part.
SERVO_PARAMS = ("stiffness", "offset", "friction", "load_friction")


def _is_trainable(path, trainable: str) -> bool:
    if trainable == "none":
        return False
    keys = [str(getattr(k, "key", "")) for k in path]
    if trainable == "head":
        return not any(k.startswith("joint") for k in keys)
    servo = keys[-1] in SERVO_PARAMS and "residual" not in keys
    if trainable == "servo":
        return servo
    if trainable == "servo+input":  # and the residual's per-joint input layers
        return servo or ("residual" in keys and keys[-2:-1] == ["hidden"]
                         and any(k.startswith("joint") for k in keys))
    return True


def _part_trainable(trainable: str, part: str) -> str:
    """What ``trainable`` (:class:`TrainConfig`) leaves trainable in the torque model
    (``part="torque"``) or the attention model (``"attention"``), as one of "all",
    "head", "servo", "servo+input", "none"."""
    if trainable == "servo+attention":
        return "servo" if part == "torque" else "all"
    if trainable == "servo+input":
        return trainable if part == "torque" else "none"
    if trainable == "attention":
        return "none" if part == "torque" else "all"
    return trainable


def _any_trainable(params, trainable: str) -> bool:
    return any(_is_trainable(path, trainable)
               for path, _ in jax.tree_util.tree_flatten_with_path(params)[0])


def optimizer(lr: float, *, trainable: str = "all", flat: bool = False
              ) -> optax.GradientTransformation:
    """Adam on the parameters ``trainable`` names (:class:`TrainConfig`); the others get
    no updates. ``flat`` (with ``trainable="all"``): Adam on the parameters raveled into one
    vector (``optax.flatten``): the same arithmetic element by element, in a few kernels
    instead of a few per parameter."""
    if trainable == "all":
        return optax.flatten(optax.adam(lr)) if flat else optax.adam(lr)
    adam = optax.adam(lr)

    def labels(params):
        return jax.tree_util.tree_map_with_path(
            lambda path, _: "train" if _is_trainable(path, trainable) else "frozen", params)

    return optax.multi_transform({"train": adam, "frozen": optax.set_to_zero()}, labels)


@struct.dataclass
class TrainState:
    """K models trained together: every field but ``epoch`` is stacked (K, ...)."""

    params: Any  # the current parameters
    opt_state: Any  # the optimiser's state
    best_params: Any  # the parameters of the best validation epoch so far
    best_loss: jax.Array  # (K,) their validation loss (inf before the first epoch)
    best_epoch: jax.Array  # (K,) int32, the epoch they come from
    epoch: jax.Array  # () int32, the epochs run


class Epoch(NamedTuple):
    """A training epoch of K models in the optax style: ``state = init(params, loss_dtype)``,
    ``state, train_loss, val_loss = update(state, key, data, val_data)`` (jitted; losses (K,)).
    ``update_fn`` is ``update`` before ``jax.jit`` and ``compiler_options`` what its
    programs are compiled with, as ``((name, value), ...)`` (hashable: epochs are cache
    keys): a group of trainings (:mod:`jaxinertia.training_group`) compiles its own
    program of ``update_fn`` with them (JAX takes compiler options at the outermost jit
    only)."""

    init: Callable[..., TrainState]
    update: Callable[..., tuple[TrainState, jax.Array, jax.Array]]
    update_fn: Callable[..., tuple[TrainState, jax.Array, jax.Array]]
    compiler_options: tuple = ()


#: A training of fewer minibatch steps than this (epochs x minibatches per epoch: a
#: fine-tuning's 200 epochs of up to 70 minibatches, 14,000 steps in the folds) compiles
#: its epoch without XLA's GPU autotuner (:func:`epoch_compiler_options`); a training from
#: scratch at the paper's scale (300 epochs of 289) with it. Session 45: at 2,000 the
#: folds' fine-tunings of 250 and 1,000 real samples (3,500 and 14,000 steps) autotuned;
#: once the attentions ran beside them on the GPU (no longer held up drawing their sets)
#: those compiles took 44-47 s; without the autotuner 3-5 s (docs/benchmarks.md,
#: "Session 45").
AUTOTUNE_MIN_STEPS = 20_000


def epoch_compiler_options(steps: int, backend: str | None = None) -> tuple:
    """The compiler options of the epoch programs of a training of ``steps`` minibatch
    steps on ``backend`` (default: JAX's), ``((name, value), ...)``: on a GPU, without XLA's
    autotuner below :data:`AUTOTUNE_MIN_STEPS`.

    The autotuner compiles and times candidate kernels for the matrix products on the
    device: seconds of compile per program, more while other programs run on the GPU. A
    fine-tuning runs for about a second of device time: in ``reproduce --full`` on one H100
    the folds' grouped fine-tunings compiled for 12 s each autotuned, 1.3 s without. A long
    training pays it back: without the autotuner the torque models from scratch ran 1.8 x
    slower there (300 epochs in 20 s against 11 s) and the attention's 30 epochs took 12 s
    against 7 s, although random inputs of the same shapes ran at the same speed either way
    (``experiments/epoch_compile.py``; docs/benchmarks.md, "Where a GPU fold's time goes").
    Session 28: alone, the epochs as a GPU now builds them (:func:`accelerated_epochs`) ran
    as fast without it (``epoch_compile.py --as-trained``), but in ``reproduce --full``, every
    epoch compiled without it, the grouped torque trainings ran 10-20 % slower and the folds
    ended 6-17 s later (two runs each way): the threshold stays. The attention's training
    asks for a short one's options whatever its length (:func:`train_attention_models`,
    session 30). A CPU has no autotuner: nothing to set."""
    if steps >= AUTOTUNE_MIN_STEPS or (backend or jax.default_backend()) != "gpu":
        return ()
    return (("xla_gpu_autotune_level", 0),)


def accelerated_epochs(backend: str | None = None) -> dict:
    """How the epochs on ``backend`` (default: JAX's) are built, as keywords of the epoch
    builders: on a GPU the joints' embedding layers as batched products (``stacked``: the
    networks' ``stacked_joints``) and Adam on the raveled parameters (``flat``:
    :func:`optimizer`'s); elsewhere neither. One minibatch step of the small
    MLPs is a chain of small kernels whose count, not their size, sets its time on a GPU:
    these cut it from 64 fusions and 33 matrix products to 41 and 14 per step of the
    physical torque model, and an epoch of the folds' shapes to 0.68-0.73 x (attention
    0.85 x) on an H100 (``experiments/epoch_step.py``; docs/benchmarks.md). The same
    models and parameters, the products summed in another order: equal up to float
    rounding, which training carries. On a CPU they gain nothing measurable, and a CPU
    run's numbers stay those of the per-joint products."""
    gpu = (backend or jax.default_backend()) == "gpu"
    return {"stacked": gpu, "flat": gpu}


def make_epoch(tx: optax.GradientTransformation, loss_fn, batches_fn, val_fn,
               compiler_options: tuple = ()) -> Epoch:
    """One epoch: per model (``vmap``), a ``lax.scan`` of ``tx`` steps over its minibatches,
    then the validation loss and keep-best.

    ``data`` and ``val_data`` are pairs ``(shared, own)``: ``shared`` is the same for every
    model, ``own`` is stacked (K, ...) (``None`` when the models share all data).
    ``batches_fn(key, shared)`` gives one model's (steps, ...) minibatches of the epoch (the
    leading axis is scanned), ``loss_fn(params, shared, own, batch)`` one model's minibatch
    loss and ``val_fn(params, shared, own)`` its validation loss. Everything that varies
    between trainings is in ``data``: one ``Epoch`` serves every training of its shapes,
    traced once (:func:`_torque_epoch`, :func:`_attention_epoch` keep them).
    ``compiler_options``: for every program of the epoch (:func:`epoch_compiler_options`).
    """
    jit = functools.partial(jax.jit, compiler_options=dict(compiler_options) or None)

    @jit
    def val_losses(params, val_data):
        v_shared, v_own = val_data
        return jax.vmap(lambda p, o: val_fn(p, v_shared, o))(params, v_own)

    def init(params, loss_dtype, val_data=None) -> TrainState:
        """With ``val_data`` the starting parameters compete for the best validation loss
        (as epoch -1: fine-tuning never returns worse models than it started from)."""
        K = jax.tree_util.tree_leaves(params)[0].shape[0]
        best = jnp.full(K, jnp.inf, loss_dtype)
        if val_data is not None:
            best = val_losses(params, val_data).astype(loss_dtype)
        return TrainState(params, jax.vmap(tx.init)(params), params, best,
                          jnp.full(K, -1 if val_data is not None else 0, jnp.int32),
                          jnp.int32(0))

    def update(state: TrainState, key, data, val_data):
        (shared, own), (v_shared, v_own) = data, val_data

        def one_model(p, o, own_k, k):
            def step(carry, batch):
                p, o = carry
                loss, g = jax.value_and_grad(loss_fn)(p, shared, own_k, batch)
                upd, o = tx.update(g, o, p)
                return (optax.apply_updates(p, upd), o), loss

            (p, o), losses = jax.lax.scan(step, (p, o), batches_fn(k, shared))
            return p, o, jnp.mean(losses)

        K = state.best_loss.shape[0]
        params, opt_state, train_loss = jax.vmap(one_model)(state.params, state.opt_state, own,
                                                            jax.random.split(key, K))
        val_loss = jax.vmap(lambda p, o: val_fn(p, v_shared, o))(params, v_own)
        improved = val_loss < state.best_loss
        state = TrainState(
            params, opt_state, _keep_best(state.best_params, params, improved),
            jnp.where(improved, val_loss, state.best_loss),
            jnp.where(improved, state.epoch, state.best_epoch), state.epoch + 1)
        return state, train_loss, val_loss

    return Epoch(init, jit(update), update, compiler_options)


def _keep_best(best, new, improved):
    return jax.tree_util.tree_map(
        lambda b, n: jnp.where(improved.reshape((-1,) + (1,) * (n.ndim - 1)), n, b), best, new)


class TrainedTorque(NamedTuple):
    model: TorqueModel
    variables: dict  # stacked (K, ...) best-validation parameters
    history: np.ndarray  # (epochs, 2, K) train / validation MSE
    best_epoch: np.ndarray  # (K,)


def train_torque_models(
    cfg: TrainConfig,
    fc: FeatureConfig,
    train: Samples,
    val: Samples,
    key: jax.Array,
    *,
    model: TorqueModel | None = None,
    init: dict | None = None,
    progress: bool = True,
    on_epoch: Callable[[int, tuple], None] | None = None,
) -> TrainedTorque:
    """K torque models (``cfg.n_models``) trained in parallel, best epoch by validation;
    ``init``: stacked (K, ...) parameters to start from (fine-tuning) instead of fresh ones;
    ``on_epoch(e, (train_loss, val_loss))`` after each epoch if given."""
    model = model or TORQUE_MODELS[cfg.torque_model](n_joints=train.q.shape[1])
    trainable = _part_trainable(cfg.trainable, "torque")
    if trainable.startswith("servo") and not isinstance(model, PhysicalTorqueModel):
        raise UsageError(f"trainable {cfg.trainable!r} needs the physical torque model (the "
                         "paper's network has no servo parameters)")
    if trainable == "none" and init is None:
        raise UsageError(f"trainable {cfg.trainable!r} keeps the torque models it starts "
                         "from: give them (init)")
    if init is not None and not _any_trainable(init, trainable):
        # ``trainable="attention"``: the start's torque models as they are, no epoch run.
        return TrainedTorque(model, init, np.zeros((0, 2, cfg.n_models), np.float32),
                             np.full(cfg.n_models, -1, np.int32))
    X, Xv = _features(fc, train), _features(fc, val)
    scale = jnp.asarray(fc.tau_scale, jnp.float32)
    Y = jnp.asarray(train.tau, jnp.float32) / scale
    Yv = jnp.asarray(val.tau, jnp.float32) / scale
    k_init, k_epochs = jax.random.split(key)
    batch = min(cfg.torque_batch, len(X))
    steps = len(X) // batch
    epoch = _torque_epoch(model, cfg.torque_lr, trainable, batch,
                          epoch_compiler_options(cfg.torque_epochs * steps),
                          **accelerated_epochs())
    state = epoch.init(_start(model, k_init, cfg.n_models, X[:1], init), jnp.float32,
                       None if init is None else ((Xv, Yv), None))
    state, hist = run_epochs(epoch, state, ((X, Y), None), ((Xv, Yv), None), cfg.torque_epochs,
                              k_epochs, "torque model", progress, on_epoch,
                              steps_per_epoch=steps)
    return TrainedTorque(model, state.best_params, hist, np.asarray(state.best_epoch))


def rehearse_attention(cfg: TrainConfig, fc: FeatureConfig, train: Samples, val: Samples,
                       key: jax.Array):
    """The attention's training of these inputs (``key`` as :func:`train_attention_models`
    would get it), compiled ahead in a group member's thread beside its torque training:
    :func:`jaxinertia.training_group.rehearse` with an untrained torque model of the
    trained one's shapes. The thread, or None outside a group."""
    def attention():
        model = TORQUE_MODELS[cfg.torque_model](n_joints=train.q.shape[1])
        params = _start(model, jax.random.key(0), cfg.n_models, _features(fc, train)[:1], None)
        torque = TrainedTorque(model, params, np.zeros((0, 2, cfg.n_models), np.float32),
                               np.zeros(cfg.n_models, np.int32))
        train_attention_models(cfg, fc, torque, train, val, key, progress=False)

    return rehearse(attention)


# The epochs are kept per architecture and setting (models are hashable Flax modules): a
# later training of the same kind and shapes (the second fold, another fine-tuning) runs
# the jitted epoch it already traced, instead of tracing and lowering it again.
@shared_cache
def _torque_epoch(model, lr: float, trainable: str, batch: int,
                  compiler_options: tuple = (), stacked: bool = False,
                  flat: bool = False) -> Epoch:
    """Minibatches of ``batch`` samples of the features and scaled torques ``(X, Y)``;
    ``stacked`` and ``flat``: :func:`accelerated_epochs`."""
    model = model.clone(stacked_joints=stacked)

    def mse(p, x, y):
        return jnp.mean((model.apply(p, x) - y) ** 2)

    def batches(k, XY):
        S = XY[0].shape[0]
        return jax.random.permutation(k, S)[: S // batch * batch].reshape(-1, batch)

    return make_epoch(optimizer(lr, trainable=trainable, flat=flat),
                      loss_fn=lambda p, XY, _, idx: mse(p, XY[0][idx], XY[1][idx]),
                      batches_fn=batches, val_fn=lambda p, XYv, _: mse(p, *XYv),
                      compiler_options=compiler_options)


@shared_cache
def _attention_epoch(model, lr: float, trainable: str, batch: int, w_mass: float,
                     w_com: float, compiler_options: tuple = (), stacked: bool = False,
                     flat: bool = False, torque_spread: float = 0.0) -> Epoch:
    """Minibatches of ``batch`` of the sets; ``shared`` is (features, A, x per sample,
    sets), each model's own data its torque model's ``tau_hat - tau_g``; ``stacked`` and
    ``flat``: :func:`accelerated_epochs`. ``torque_spread`` > 0
    (``TrainConfig.attention_torque_spread``): ``shared`` also holds ``tau_g`` per sample
    and the validation sets' fixed factors (V, N); each training set's ``tau_hat`` is
    scaled per joint by ``1 + torque_spread * z``, ``z`` drawn with the minibatch."""
    model = model.clone(stacked_joints=stacked)

    def loss(p, shared, y, batch_):
        feats, A, x_obj = shared[:3]
        idx, factors = batch_ if torque_spread > 0 else (batch_, None)
        y_b = y[idx]
        if factors is not None:  # (B, N): tau_hat * f - tau_g = y + (f - 1) tau_hat
            y_b = y_b + (factors[:, None, :] - 1) * (y_b + shared[4][idx])
        w = model.apply(p, feats[idx])
        value, _ = attention_loss(w, A[idx], y_b, x_obj[idx[:, 0]], w_mass=w_mass,
                                  w_com=w_com)
        return value

    def batches(k, shared):
        sets = shared[3]
        perm = jax.random.permutation(k, sets.shape[0])[: sets.shape[0] // batch * batch]
        idx = sets[perm].reshape(-1, batch, sets.shape[1])
        if torque_spread == 0:
            return idx
        n = shared[0].shape[1]  # the same minibatches as without the spread, and factors
        z = jax.random.normal(jax.random.fold_in(k, 1), idx.shape[:2] + (n,), shared[1].dtype)
        return idx, 1 + torque_spread * z

    def val_fn(p, shared, y):
        return loss(p, shared, y, (shared[3], shared[5]) if torque_spread > 0 else shared[3])

    return make_epoch(optimizer(lr, trainable=trainable, flat=flat), loss, batches,
                      val_fn=val_fn, compiler_options=compiler_options)


def attention_loss(weights, A, y, x_true, *, w_mass: float, w_com: float):
    """The paper's attention loss for B sets of M samples.

    Args:
      weights: (B, M, N) attention weights; A: (B, M, N, 4); y: (B, M, N) ``tau_hat - tau_g``;
      x_true: (B, 4) true ``[m, m p]``.
    Returns the scalar loss and the (B,) per-set mass and COM errors (NaN for singular sets).
    """
    dtype = A.dtype
    w = weights.astype(dtype)
    res = solve_normal(*gram_statistics(A, y, w, rows=2))
    m = x_true[:, 0]
    loaded = m > 0
    m_safe = jnp.where(loaded, m, 1.0)
    ok = ~res.rank_deficient
    x = jnp.where(ok[:, None], res.x, 0.0)
    e_m = x[:, 0] - m
    e_p = jnp.linalg.norm((x[:, 1:] - x_true[:, 1:]) / m_safe[:, None], axis=-1)
    n_ok = jnp.maximum(jnp.sum(ok), 1)
    n_com = jnp.maximum(jnp.sum(ok & loaded), 1)
    L_m = jnp.sum(jnp.where(ok, e_m**2, 0.0)) / n_ok
    L_com = jnp.sum(jnp.where(ok & loaded, e_p**2, 0.0)) / n_com
    return w_mass * L_m + w_com * L_com, (jnp.where(ok, e_m, jnp.nan),
                                          jnp.where(ok & loaded, e_p, jnp.nan))


class TrainedAttention(NamedTuple):
    model: AttentionModel
    variables: dict  # stacked (K, ...)
    history: np.ndarray  # (epochs, 2, K)
    best_epoch: np.ndarray  # (K,)


def torque_predictions(model, variables, fc: FeatureConfig, data: Samples) -> jnp.ndarray:
    """(K, S, N) torques [N m] of K stacked torque models."""
    return predict_torques_stacked(model, variables, _features(fc, data),
                                   jnp.asarray(fc.tau_scale, jnp.float32))


def train_attention_models(
    cfg: TrainConfig,
    fc: FeatureConfig,
    torque: TrainedTorque,
    train: Samples,
    val: Samples,
    key: jax.Array,
    *,
    model: AttentionModel | None = None,
    init: dict | None = None,
    progress: bool = True,
    on_epoch: Callable[[int, tuple], None] | None = None,
) -> TrainedAttention:
    """K attention models, model k trained through the WLS on torque model k's outputs;
    ``init`` and ``on_epoch`` as in :func:`train_torque_models`."""
    model = model or AttentionModel(n_joints=train.q.shape[1])
    K = cfg.n_models
    dtype = jnp.result_type(float)
    k_init, k_epochs = jax.random.split(key)
    trainable = _part_trainable(cfg.trainable, "attention")
    if init is not None and not _any_trainable(init, trainable):
        # Nothing to train (``trainable="servo"``: the attention fixed): its epochs would
        # change no parameter and keep the start (epoch -1), so none are run or compiled.
        features = jax.eval_shape(lambda: _features(fc, train))  # (S, N, F): no compile
        start = _start(model, k_init, K, np.zeros((1,) + features.shape[1:], np.float32),
                       init)
        return TrainedAttention(model, start, np.zeros((0, 2, K), np.float32),
                                np.full(K, -1, np.int32))
    sets = jnp.asarray(draw_sets(train.object_id, cfg.attention_sets, cfg.set_size, cfg.seed))
    vsets = jnp.asarray(draw_sets(val.object_id, cfg.attention_val_sets, cfg.set_size,
                                  cfg.seed + 1))

    def arrays(d: Samples):
        y = torque_predictions(torque.model, torque.variables, fc, d).astype(dtype)
        y = y - jnp.asarray(d.tau_g, dtype)
        return (_features(fc, d), jnp.asarray(d.A, dtype), y,
                jnp.asarray(d.x, dtype)[jnp.asarray(d.object_id)])

    (feats, A, y, x_obj), (vf, vA, vy, vx) = arrays(train), arrays(val)
    spread = float(cfg.attention_torque_spread)
    batch = min(cfg.attention_batch, sets.shape[0])
    steps = sets.shape[0] // batch
    # Without the GPU's autotuner, however long (as a short training's): in the folds it
    # compiles beside the torque models' training (rehearse_attention), where autotuning
    # timed kernels on a busy GPU and slowed both. Its 30 epochs then take about 16 s
    # instead of 8 on an H100, but its 14 s compile leaves the critical path: the
    # attention's stage 21 s instead of 33 (docs/benchmarks.md, "Session 30").
    epoch = _attention_epoch(model, cfg.attention_lr, trainable, batch, cfg.w_mass,
                             cfg.w_com, epoch_compiler_options(0), **accelerated_epochs(),
                             **({"torque_spread": spread} if spread > 0 else {}))
    data, val_data = ((feats, A, x_obj, sets), y), ((vf, vA, vx, vsets), vy)
    if spread > 0:  # the validation sets' sessions drawn once: one loss to select by
        v_factors = 1 + spread * jax.random.normal(jax.random.key(cfg.seed + 2),
                                                   (vsets.shape[0], vf.shape[1]), dtype)
        data = ((feats, A, x_obj, sets, jnp.asarray(train.tau_g, dtype)), y)
        val_data = ((vf, vA, vx, vsets, jnp.asarray(val.tau_g, dtype), v_factors), vy)
    state = epoch.init(_start(model, k_init, K, feats[:1], init), dtype,
                       None if init is None else val_data)
    state, hist = run_epochs(epoch, state, data, val_data, cfg.attention_epochs, k_epochs,
                             "attention model", progress, on_epoch, steps_per_epoch=steps)
    return TrainedAttention(model, state.best_params, hist, np.asarray(state.best_epoch))
