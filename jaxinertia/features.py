"""Network input featurisation: one documented, configurable function.

Per sample and joint j the networks see four numbers (paper Sec. IV, "Implementation"):

    [ (q_j - q_min_j) / (q_max_j - q_min_j),   min-max normalised present position
      (q_d_j - q_j) / qe_scale_j,              scaled encoder discrepancy
      s_j == +1,  s_j == -1 ]                  approach direction, one-hot

and the torque model's output is multiplied by ``tau_scale`` to give N m. The defaults are
the constants of the authors' released OpenMANIPULATOR-X models (shared/lbipe/README.md).

A configuration with a ``current_scale`` adds a fifth number per joint, the servo's own
current torque ``k_t I / current_scale`` (issue 30): the motor torque the position loop
asked for, which a change of supply voltage or winding resistance does not decouple from
the joint torque, where it does the discrepancy's.
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
    #: (N,) scale of the current torque input [N m]; None: the paper's four inputs.
    current_scale: jnp.ndarray | None = None

    @property
    def n_inputs(self) -> int:
        """Inputs per joint: 4 (the paper's), 5 with the current torque."""
        return 4 if self.current_scale is None else 5

    @property
    def n_joints(self) -> int:
        return int(np.shape(self.q_min)[0])

    @classmethod
    def create(cls, q_min, q_max, qe_scale, tau_scale, current_scale=None) -> FeatureConfig:
        given = [a for a in (q_min, q_max, qe_scale, tau_scale, current_scale) if a is not None]
        arrs = [np.asarray(a, dtype=np.float64) for a in given]
        n = arrs[0].shape
        if any(a.shape != n or a.ndim != 1 for a in arrs):
            raise ValueError(f"FeatureConfig: all arrays must have shape (N,), got "
                             f"{[a.shape for a in arrs]}")
        if np.any(arrs[1] <= arrs[0]) or any(np.any(a <= 0) for a in arrs[2:]):
            raise ValueError("FeatureConfig: need q_max > q_min and positive scales")
        return cls(*arrs)

    def to_dict(self) -> dict:
        keys = ("q_min", "q_max", "qe_scale", "tau_scale") + (
            () if self.current_scale is None else ("current_scale",))
        return {k: np.asarray(getattr(self, k)).tolist() for k in keys}

    @classmethod
    def from_dict(cls, d: dict) -> FeatureConfig:
        return cls.create(d["q_min"], d["q_max"], d["qe_scale"], d["tau_scale"],
                          d.get("current_scale"))


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
    config: FeatureConfig, q: jnp.ndarray, q_d: jnp.ndarray, direction: jnp.ndarray,
    current_tau: jnp.ndarray | None = None,
) -> jnp.ndarray:
    """Network inputs (..., N, 4) from present position q, goal q_d and direction (..., N);
    (..., N, 5) with the current torque ``current_tau`` [N m] where ``config`` takes it.

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
    cols = [q_norm, qe, pos, neg]
    if config.current_scale is not None:
        if current_tau is None:
            raise ValueError("these models take the servo's current as an input: the "
                             "samples need their current torque")
        cols.append(jnp.asarray(current_tau, dtype) / c(config.current_scale))
    return jnp.stack(cols, axis=-1)
