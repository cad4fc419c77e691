"""What a training run is given: its configuration (:class:`TrainConfig`, the paper's
hyperparameters by default; :data:`FINETUNE_DEFAULTS`), the feature scaling taken from the
training data, the validation split, the per-object subset and the attention model's
training sets. Pure NumPy on :class:`~jaxinertia.samples.Samples`; the trainers are
:mod:`jaxinertia.training`."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from jaxinertia.errors import UsageError
from jaxinertia.features import FeatureConfig
from jaxinertia.networks import TORQUE_MODELS
from jaxinertia.samples import Samples

__all__ = ["FINETUNE_DEFAULTS", "TRAINABLE", "TrainConfig", "draw_sets", "feature_config_from",
           "per_object_subset", "split_validation", "subset_per_object"]


#: What fine-tuning may change (``TrainConfig.trainable``).
TRAINABLE = ("all", "head", "servo", "servo+input", "servo+attention", "attention")


@dataclass(frozen=True)
class TrainConfig:
    """Hyperparameters; the defaults are the paper's (the number of attention training
    sets is not given there: we draw ``attention_sets`` per training object, as many as the
    test protocol's repeats)."""

    n_models: int = 10
    seed: int = 0
    torque_epochs: int = 300
    torque_batch: int = 256
    torque_lr: float = 3e-4
    attention_epochs: int = 30
    attention_batch: int = 32
    attention_lr: float = 1e-4
    set_size: int = 64
    attention_sets: int = 1000
    attention_val_sets: int = 200
    w_mass: float = 1.0
    w_com: float = 0.3
    val_fraction: float = 0.1
    #: What training may change (fine-tuning): "all"; "head" (the per-joint encoders
    #: fixed); "servo" (only the physical model's servo parameters; the attention fixed);
    #: "servo+input" (those and the first layer of the residual's per-joint encoders: how
    #: the residual reads its inputs, the current torque among them; the attention fixed);
    #: "servo+attention" (the servo parameters and every attention parameter); "attention"
    #: (every attention parameter; the torque models fixed).
    trainable: str = "all"
    torque_model: str = "paper"  # or "physical" (networks.TORQUE_MODELS)
    #: Each training file is a recording session: its discrepancy is rescaled towards the
    #: session of the training data as a whole by ``(g_file / g_ref) ** session_strength``
    #: (:mod:`jaxinertia.session`; 0: off), and the folder records the reference and the
    #: strength, so that a new file is adapted the same way when it is evaluated.
    session_strength: float = 1.0
    #: The servo's current torque as a fifth input per joint (features.FeatureConfig).
    current_input: bool = False
    #: Fine-tuning on several files: each file its own servo term, a factor per joint on
    #: its discrepancy fitted from its known torques and centred over the files
    #: (:mod:`jaxinertia.session_terms`); the shared servo learns what the files share.
    session_terms: bool = False
    #: The attention's training sets with a recording session the torque models do not
    #: know: each set's predicted torques of joint j scaled by ``1 + spread * z`` (``z`` a
    #: standard normal, drawn per set and joint at every step; fixed for the validation
    #: sets), so that the attention learns weights whose answer a few per cent of one
    #: joint's torque does not move (docs/results.md). 0: the paper's training.
    attention_torque_spread: float = 0.0

    def __post_init__(self):
        positive = ("n_models", "torque_epochs", "torque_batch", "attention_epochs",
                    "attention_batch", "set_size", "attention_sets", "attention_val_sets")
        for name in positive:
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | np.integer) or v < 1:
                raise UsageError(f"{name} must be a positive integer, got {v!r}")
        for name in ("torque_lr", "attention_lr"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise UsageError(f"{name} must be a positive finite number, got {v!r}")
        for name in ("w_mass", "w_com"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise UsageError(f"{name} must be a finite number >= 0, got {v!r}")
        if not (np.isfinite(self.session_strength) and 0 <= self.session_strength <= 1):
            raise UsageError(f"session_strength must be in [0, 1], got {self.session_strength!r}")
        if not (np.isfinite(self.attention_torque_spread) and self.attention_torque_spread >= 0):
            raise UsageError("attention_torque_spread must be a finite number >= 0, got "
                             f"{self.attention_torque_spread!r}")
        if self.w_mass + self.w_com <= 0:
            raise UsageError("w_mass and w_com are both zero: the attention loss would be zero")
        if not 0.0 < self.val_fraction < 1.0:
            raise UsageError(f"val_fraction must be in (0, 1), got {self.val_fraction!r}")
        if self.torque_model not in TORQUE_MODELS:
            raise UsageError(f"torque_model must be one of {sorted(TORQUE_MODELS)}, got "
                             f"{self.torque_model!r}")
        if self.trainable not in TRAINABLE:
            raise UsageError(f"trainable must be one of {list(TRAINABLE)}, got "
                             f"{self.trainable!r}")

    def replace(self, **kw) -> TrainConfig:
        return dataclasses.replace(self, **kw)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


# Fine-tuning's defaults (``train --init``): a few real samples of known objects adapt
# simulator-trained models; small steps, few epochs, early stopping on the validation split.
FINETUNE_DEFAULTS = {"torque_epochs": 200, "torque_batch": 64, "torque_lr": 1e-4,
                     "attention_epochs": 20, "attention_lr": 1e-4, "attention_sets": 250,
                     "attention_val_sets": 100}


def feature_config_from(data: Samples, *, current_input: bool = False) -> FeatureConfig:
    """Min-max bounds of q and the scales of q_d - q and tau (max |.|) from training data;
    ``current_input``: the current torque as a fifth input, scaled like the torque."""
    qe = np.abs(data.q_d - data.q)
    q_min, q_max = data.q.min(axis=0), data.q.max(axis=0)
    pad = np.maximum(1e-3, 1e-6 * (q_max - q_min))
    tau_scale = np.maximum(np.abs(data.tau).max(axis=0), 1e-4)
    unsensed = np.flatnonzero(~np.all(np.isfinite(data.current_tau), axis=0))
    if current_input and unsensed.size:
        raise UsageError(f"the current input needs a current on every joint; joints "
                         f"{(unsensed + 1).tolist()} have none (a servo without a current "
                         "sensor)")
    return FeatureConfig.create(q_min - pad, q_max + pad, np.maximum(qe.max(axis=0), 1e-4),
                                tau_scale, tau_scale if current_input else None)


def split_validation(data: Samples, fraction: float, seed: int) -> tuple[Samples, Samples]:
    """Random held-out split, stratified by object."""
    rng = np.random.default_rng(seed)
    val = []
    for o in np.unique(data.object_id):
        idx = np.flatnonzero(data.object_id == o)
        val.append(rng.choice(idx, int(round(fraction * len(idx))), replace=False))
    val = np.sort(np.concatenate(val))
    train = np.setdiff1d(np.arange(data.n_samples), val)
    return data.take(train), data.take(val)


def per_object_subset(data: Samples, n: int, seed: int) -> Samples:
    """At most ``n`` samples of each object (a seeded random choice, in file order)."""
    rng = np.random.default_rng(seed)
    keep = []
    for o in np.unique(data.object_id):
        idx = np.flatnonzero(data.object_id == o)
        keep.append(np.sort(rng.choice(idx, n, replace=False)) if len(idx) > n else idx)
    return data.take(np.concatenate(keep))


def subset_per_object(parts: Sequence[Samples], n: int | Sequence[int] | None,
                      seed: int) -> Samples:
    """The parts concatenated, with at most ``n`` samples of each object
    (:func:`per_object_subset`; None: all); a sequence: ``n[i]`` of each object of
    ``parts[i]`` (the objects of different parts are different objects)."""
    if n is None or np.ndim(n) == 0:
        data = Samples.concatenate(parts)
        return data if n is None else per_object_subset(data, int(n), seed)
    if len(n) != len(parts):
        raise UsageError(f"samples per object: {len(n)} counts for {len(parts)} files")
    return Samples.concatenate([per_object_subset(p, int(k), seed) for p, k in zip(parts, n)])


def draw_sets(object_id: np.ndarray, per_object: int, set_size: int, seed: int) -> np.ndarray:
    """(per_object * O, set_size) index sets, each of one object's samples (without
    replacement within a set; with replacement only if the object has too few samples).

    Each set is a uniformly random ordered choice, drawn for all of an object's sets at
    once (:func:`_choices`). Drawn a set at a time (``Generator.choice`` per set) each draw
    gave the GIL up and waited to get it back from the busy threads beside it: in the GPU
    folds the 24 attention trainings drew their sets for 15 s before their first epoch
    (docs/benchmarks.md, "Session 45")."""
    rng = np.random.default_rng(seed)
    out = []
    for o in np.unique(object_id):
        idx = np.flatnonzero(object_id == o)
        out.append(idx[_choices(rng, len(idx), per_object, set_size)])
    return np.concatenate(out)


def _choices(rng: np.random.Generator, n: int, count: int, k: int) -> np.ndarray:
    """(count, k) positions in ``range(n)``, each row a uniformly random ordered choice of
    k distinct positions (k of n with replacement where n < k)."""
    if n < k:
        return rng.integers(n, size=(count, k))
    if k * (k - 1) > 2 * n:  # dense: a row of k draws repeats a position more often than not
        # Random keys, the k smallest; at most 2**22 keys (32 MB) at a time.
        step = max(1, (1 << 22) // n)
        return np.concatenate([np.argsort(rng.random((min(step, count - i), n)), axis=1)[:, :k]
                               for i in range(0, count, step)])
    # Sparse: draw with replacement and redraw every row that repeats a position. Kept
    # rows are uniform among the rows without repeats: exactly the ordered choices; about
    # e - 1 redraws per row are expected at most (k (k - 1) <= 2 n).
    rows = rng.integers(n, size=(count, k))
    pending = np.arange(count)
    while pending.size:
        ordered = np.sort(rows[pending], axis=1)
        pending = pending[(ordered[:, 1:] == ordered[:, :-1]).any(axis=1)]
        rows[pending] = rng.integers(n, size=(pending.size, k))
    return rows
