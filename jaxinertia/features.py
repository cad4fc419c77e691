"""Network input featurisation: one documented, configurable function.

Per sample and joint j the networks see four numbers (paper Sec. IV, "Implementation"):

    [ (q_j - q_min_j) / (q_max_j - q_min_j),   min-max normalised present position
      (q_d_j - q_j) / qe_scale_j,              scaled encoder discrepancy
      s_j == +1,  s_j == -1 ]                  approach direction, one-hot

and the torque model's output is multiplied by ``tau_scale`` to give N m. The defaults are
the constants of the authors' released OpenMANIPULATOR-X models (shared/lbipe/README.md).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from flax import struct

__all__ = ["FeatureConfig", "featurize", "LBIPE_FEATURES"]


@struct.dataclass
class FeatureConfig:
    """Normalisation constants, per joint (N,). Angles in rad, torques in N m."""

    q_min: jnp.ndarray
    q_max: jnp.ndarray
    qe_scale: jnp.ndarray
    tau_scale: jnp.ndarray

    @property
    def n_joints(self) -> int:
        return int(np.shape(self.q_min)[0])

    @classmethod
    def create(cls, q_min, q_max, qe_scale, tau_scale) -> FeatureConfig:
        arrs = [np.asarray(a, dtype=np.float64) for a in (q_min, q_max, qe_scale, tau_scale)]
        n = arrs[0].shape
        if any(a.shape != n or a.ndim != 1 for a in arrs):
            raise ValueError(f"FeatureConfig: all four arrays must have shape (N,), got "
                             f"{[a.shape for a in arrs]}")
        if np.any(arrs[1] <= arrs[0]) or np.any(arrs[2] <= 0) or np.any(arrs[3] <= 0):
            raise ValueError("FeatureConfig: need q_max > q_min and positive scales")
        return cls(*arrs)

    def to_dict(self) -> dict:
        return {k: np.asarray(getattr(self, k)).tolist()
                for k in ("q_min", "q_max", "qe_scale", "tau_scale")}

    @classmethod
    def from_dict(cls, d: dict) -> FeatureConfig:
        return cls.create(d["q_min"], d["q_max"], d["qe_scale"], d["tau_scale"])


_DEG = np.pi / 180.0
#: The released lbipe models' constants: the authors' workspace bounds q1 in [-30, 30],
#: q2 in [-50, -10], q3 in [10, 50], q4 in [-20, 20] deg, and their scales.
LBIPE_FEATURES = FeatureConfig.create(
    q_min=np.array([-30.0, -50.0, 10.0, -20.0]) * _DEG,
    q_max=np.array([30.0, -10.0, 50.0, 20.0]) * _DEG,
    qe_scale=[0.0376165, 0.0776274, 0.0568421, 0.0392332],
    tau_scale=[0.449317, 1.221304, 0.635542, 0.294940],
)


def featurize(
    config: FeatureConfig, q: jnp.ndarray, q_d: jnp.ndarray, direction: jnp.ndarray
) -> jnp.ndarray:
    """Network inputs (..., N, 4) from present position q, goal q_d and direction (..., N).

    ``direction`` is +1 or -1 (the sign of the joint velocity while approaching rest).
    Reshape to (..., 4N) for the authors' flat layout (joint-major).
    """
    q = jnp.asarray(q)
    dtype = q.dtype
    c = lambda a: jnp.asarray(a, dtype=dtype)  # noqa: E731
    q_norm = (q - c(config.q_min)) / (c(config.q_max) - c(config.q_min))
    qe = (jnp.asarray(q_d, dtype) - q) / c(config.qe_scale)
    d = jnp.asarray(direction)
    pos = (d > 0).astype(dtype)
    neg = (d < 0).astype(dtype)
    return jnp.stack([q_norm, qe, pos, neg], axis=-1)
