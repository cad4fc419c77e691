"""The paper's two baselines (Sec. IV, "Baselines"), fitted by least squares per joint.

Sensor (current-based):  tau_hat = tau_raw - s * tau_f1 + b1
PE (position error):     tau_hat = P * (q_d - q) - s * tau_f2 + b2

``tau_raw`` is the torque the servo's Present Current implies (datasheet torque constant);
its gain is 1 as in the paper, only the friction and the offset are fitted. Both baselines
estimate x by least squares with identity weights.

A joint whose servo senses no current (XL430-W250: Present Load only) has NaN for
``tau_raw``: its Sensor constants are NaN, and the Sensor baseline is unavailable on samples
of such an arm (:func:`jaxinertia.evaluation.baseline_methods` says so).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxinertia.fileio import nan_to_null, null_to_nan

__all__ = ["Baselines", "fit_baselines", "fit_pe_law", "pe_rows"]


@struct.dataclass
class Baselines:
    """Per-joint (N,) constants [N m/rad, N m]."""

    pe_gain: jnp.ndarray
    pe_friction: jnp.ndarray
    pe_offset: jnp.ndarray
    sensor_friction: jnp.ndarray
    sensor_offset: jnp.ndarray

    def pe(self, q_d, q, direction) -> jnp.ndarray:
        """PE torque estimate [N m] (..., N)."""
        return self.pe_gain * (q_d - q) - direction * self.pe_friction + self.pe_offset

    def sensor(self, current_tau, direction) -> jnp.ndarray:
        """Current-based torque estimate [N m] (..., N)."""
        return current_tau - direction * self.sensor_friction + self.sensor_offset

    def to_dict(self) -> dict[str, list[float | None]]:
        """Plain data (a joint without a current sensor: null Sensor constants)."""
        return {k: nan_to_null(v) for k, v in self.__dict__.items()}

    @classmethod
    def from_dict(cls, d: dict) -> Baselines:
        return cls(**{k: jnp.asarray(null_to_nan(d[k]), jnp.float64 if _x64() else jnp.float32)
                      for k in cls.__dataclass_fields__})


def _x64() -> bool:
    return bool(jax.config.jax_enable_x64)


def pe_rows(q_err, direction) -> np.ndarray:
    """(S, 3) regressor rows ``[q_d - q, -s, 1]`` of the position-error law of one joint,
    ``tau = k (q_d - q) - s f + c``, for errors and directions (S,)."""
    return np.column_stack([q_err, -direction, np.ones(len(q_err))])


def fit_pe_law(q_err, direction, tau) -> np.ndarray:
    """``[k, f, c]`` (3,) of the position-error law ``tau = k (q_d - q) - s f + c`` of one
    joint, fitted by least squares to errors ``q_err`` [rad], directions and torques
    ``tau`` [N m] (S,): the PE baseline's gain, friction and offset."""
    coef, *_ = np.linalg.lstsq(pe_rows(q_err, direction), tau, rcond=None)
    return coef


def fit_baselines(q_d, q, direction, current_tau, tau) -> Baselines:
    """Least-squares fit of both baselines on training samples (S, N) [rad, N m]."""
    q_d, q, s, cur, tau = (np.asarray(a, np.float64) for a in (q_d, q, direction, current_tau,
                                                               tau))
    if q.ndim != 2 or len(q) < 3:
        raise ValueError(f"need (S, N) arrays with S >= 3 to fit the baselines, got {q.shape}")
    one = np.ones(len(q))
    out: dict[str, list[float]] = {k: [] for k in Baselines.__dataclass_fields__}
    for j in range(q.shape[1]):
        P, f, b = fit_pe_law(q_d[:, j] - q[:, j], s[:, j], tau[:, j])
        out["pe_gain"].append(P)
        out["pe_friction"].append(f)
        out["pe_offset"].append(b)
        X = np.column_stack([-s[:, j], one])
        read = np.isfinite(cur[:, j])  # a servo without a current sensor reads none
        (f, b), *_ = (np.linalg.lstsq(X[read], (tau[:, j] - cur[:, j])[read], rcond=None)
                      if read.sum() >= 3 else ((np.nan, np.nan),))
        out["sensor_friction"].append(f)
        out["sensor_offset"].append(b)
    return Baselines.from_dict(out)
