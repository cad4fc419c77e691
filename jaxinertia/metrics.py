"""The paper's error metrics (Sec. IV): MAE, NMAE and NRMSE.

    MAE   = mean |e_k|
    NMAE  = MAE / y_scale * 100 %
    NRMSE = sqrt(mean |e_k|^2) / y_scale * 100 %

Mass: e = m_hat - m, scale = true mass. COM: |e| = distance between estimated and true COM,
scale = the diagonal of the object's bounding box. Torque: scale = max |tau| of the joint in
the evaluated set.
"""

from __future__ import annotations

import numpy as np

__all__ = ["error_metrics", "inertial_metrics", "torque_metrics"]


def error_metrics(abs_err: np.ndarray, scale: float, *, unit: float = 1.0) -> dict[str, float]:
    """MAE (times ``unit``), NMAE and NRMSE (%) of absolute errors ``abs_err``; the
    normalised ones are NaN when ``scale`` is zero (e.g. the mass error of the empty
    gripper) or when there are no errors."""
    e = np.abs(np.asarray(abs_err, dtype=np.float64))
    if e.size == 0:
        return {"MAE": np.nan, "NMAE_pct": np.nan, "NRMSE_pct": np.nan}
    mae = float(np.mean(e))
    rmse = float(np.sqrt(np.mean(e**2)))
    ok = bool(scale > 0)
    return {
        "MAE": mae * unit,
        "NMAE_pct": 100.0 * mae / scale if ok else np.nan,
        "NRMSE_pct": 100.0 * rmse / scale if ok else np.nan,
    }


def inertial_metrics(
    x_hat: np.ndarray, x_true: np.ndarray, bbox_diagonal: float
) -> dict[str, float]:
    """Table I metrics for estimates ``x_hat`` (..., 4) of ``x_true`` (4,), in g, mm and %.

    The COM is recovered with the *estimated* mass, as at test time in the paper.
    """
    x_hat = np.asarray(x_hat, dtype=np.float64).reshape(-1, 4)
    x_true = np.asarray(x_true, dtype=np.float64)
    m, m_hat = x_true[0], x_hat[:, 0]
    mass = error_metrics(m_hat - m, m, unit=1e3)
    if m > 0:  # an empty gripper has no COM
        with np.errstate(divide="ignore", invalid="ignore"):  # a zero estimate: inf error
            p_hat = x_hat[:, 1:] / x_hat[:, :1]
        com = error_metrics(np.linalg.norm(p_hat - x_true[1:] / m, axis=-1), bbox_diagonal,
                            unit=1e3)
    else:
        com = error_metrics(np.empty(0), bbox_diagonal)
    return {
        "mass_MAE_g": mass["MAE"],
        "mass_NMAE_pct": mass["NMAE_pct"],
        "mass_NRMSE_pct": mass["NRMSE_pct"],
        "com_MAE_mm": com["MAE"],
        "com_NMAE_pct": com["NMAE_pct"],
        "com_NRMSE_pct": com["NRMSE_pct"],
    }


def torque_metrics(tau_hat: np.ndarray, tau: np.ndarray) -> dict[str, list[float]]:
    """Table II metrics per joint: tau_hat, tau (S, N) -> MAE [N mm], NMAE and NRMSE [%]."""
    tau_hat = np.asarray(tau_hat, dtype=np.float64)
    tau = np.asarray(tau, dtype=np.float64)
    scale = np.max(np.abs(tau), axis=0)
    per = [error_metrics(tau_hat[:, j] - tau[:, j], scale[j], unit=1e3)
           for j in range(tau.shape[1])]
    return {
        "MAE_Nmm": [p["MAE"] for p in per],
        "NMAE_pct": [p["NMAE_pct"] for p in per],
        "NRMSE_pct": [p["NRMSE_pct"] for p in per],
    }
