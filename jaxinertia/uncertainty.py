"""How sure an estimate is: covariance of ``x = [m, m p]``, standard errors, intervals,
coverage, and what the poses alone can determine.

Per set and per model pair the WLS estimate is ``x_k = G^-1 A^T W y_k`` with
``G = A^T W A``; its error is ``G^-1 A^T W e_k`` for the torque model's error ``e_k``.
The covariance of the answer (the mean over the K pairs) adds two terms:

* **noise** (per pair, then averaged over the pairs): the sandwich
  ``G^-1 (sum_j sigma_j^2 A_j^T W_j^2 A_j) G^-1`` with a per-joint torque error level
  ``sigma_j``. ``sigma_j^2`` is the set's residual scatter on joint j,
  ``RSS_j / (M - h_j)`` (``h_j``: the joint's share of the hat matrix's trace, so that the
  divisors sum to ``M N - 4``), but never below ``floor_j^2``, the torque model's own error
  level measured on validation data (:func:`validation_torque_error`). The floor covers
  what residuals cannot show: the part of the model's error that the fit absorbs (it lies
  in the span of A) and sets whose residuals are small by chance.
* **ensemble**: the sample covariance of ``x_k`` over the K pairs (ddof 1; zero for one
  pair), the models' disagreement as a proxy for their shared, systematic error.

The mass and COM ``p = (m p) / m`` get their covariance by the delta method
(:func:`mass_com_covariance`); intervals are normal, ``value +- z se``.

Everything per set is written as sums of per-sample statistics, like
:mod:`jaxinertia.identification`: the residual sums of squares are
``y^T y - 2 x^T A^T y + x^T A^T A x`` per joint, so the sets are never gathered and one
jitted call (:func:`set_uncertainty`) covers objects x model pairs x sets. In float64 (the
library's choice for identification) the cancellation in that expansion costs nothing
measurable: the residuals are ~1-10 % of the torques, i.e. ~1e-13 relative.

:func:`identifiability` is the pose-only part: the condition number, rank and predicted
standard errors ``(sum_s A_s^T diag(1/sigma^2) A_s)^-1`` of a set before any torque is
measured (``jaxinertia estimate`` refuses sets that cannot determine the COM).

One module: the set covariance, the intervals and coverage read from it, and the pose-only
prediction share the per-set statistics and the delta method; apart, each would import
the others.
"""

from __future__ import annotations

from collections.abc import Sequence
from statistics import NormalDist
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxinertia.baselines import Baselines
from jaxinertia.errors import UsageError
from jaxinertia.estimation import (
    ModelPair,
    estimate_sets,
    predict_torques_stacked,
    run_once_jit,
)
from jaxinertia.evaluation import baseline_methods, baseline_torques, stack
from jaxinertia.features import FeatureConfig, featurize
from jaxinertia.identification import (
    DEFAULT_MAX_CONDITION,
    identity_solves,
    set_statistics,
    solve_normal,
    sum_over_sets,
)
from jaxinertia.linalg import cholesky_solve
from jaxinertia.samples import Samples
from jaxinertia.sharding import shard

__all__ = [
    "DEFAULT_TORQUE_NOISE_NM",
    "LEVELS",
    "Identifiability",
    "SetUncertainty",
    "coverage",
    "fit_inflation",
    "identifiability",
    "interval_coverage",
    "intervals",
    "mass_com_covariance",
    "set_uncertainty",
    "standard_errors",
    "training_validation_error",
    "uncertainty_of",
    "validation_torque_error",
    "z_of",
    "z_scores",
]

#: Per-joint torque error level [N m] assumed for pose-only predictions when no measured
#: level is known (the simulator-trained torque models reach ~10-20 N mm RMS per joint).
DEFAULT_TORQUE_NOISE_NM = 0.02

#: The interval levels reported (two-sided).
LEVELS = (0.68, 0.95)


def _chi2_3_ppf(level: float) -> float:
    """Quantile of the chi-square distribution with 3 degrees of freedom (scipy.stats, half
    a second to import, only when coverage is measured)."""
    import scipy.stats  # here, not at start: see the docstring

    return float(scipy.stats.chi2.ppf(level, 3))


def z_of(level: float) -> float:
    """Two-sided normal quantile: the half-width of a ``level`` interval in standard errors."""
    return NormalDist().inv_cdf(0.5 + level / 2)


# ---- per-set covariance -----------------------------------------------------------------


class SetUncertainty(NamedTuple):
    """Leading axes (O, B): objects x sets; the K model pairs are reduced.

    x: (O, B, 4) the answer, the mean of the pairs' estimates.
    cov: (O, B, 4, 4) its covariance, ``cov_noise + cov_ensemble``.
    cov_noise: the residual / validation-floor sandwich, averaged over the pairs.
    cov_ensemble: the covariance of the pairs' estimates (zero for one pair).
    noise_std: (O, B, N) per-joint torque error level used [N m] (RMS over the pairs).
    floor_used: (O, B, N) fraction of the pairs whose level is the validation floor.
    """

    x: jnp.ndarray
    cov: jnp.ndarray
    cov_noise: jnp.ndarray
    cov_ensemble: jnp.ndarray
    noise_std: jnp.ndarray
    floor_used: jnp.ndarray


def _inv_spd(G: jnp.ndarray) -> jnp.ndarray:
    """Inverse of small SPD matrices (..., P, P), column-scaled first (kg against kg m)."""
    P = G.shape[-1]
    d2 = jnp.diagonal(G, axis1=-2, axis2=-1)
    d = jnp.sqrt(jnp.where(d2 > 0, d2, jnp.nan))
    Gs = G / (d[..., :, None] * d[..., None, :])
    eye = jnp.eye(P, dtype=G.dtype)
    inv_s = cholesky_solve(Gs[..., None, :, :], jnp.broadcast_to(eye, Gs.shape))
    return inv_s / (d[..., :, None] * d[..., None, :])


def _per_set_moments(A, y, w, sets):
    """Per set and joint: ``sum y^2`` (B, N), ``sum y a`` (B, N, P), ``sum a a^T``,
    ``sum w a a^T``, ``sum w^2 a a^T`` (B, N, P, P); one selection product for all."""
    S, N, P = A.shape
    aa = A[..., :, None] * A[..., None, :]
    parts = [y * y, (y[..., None] * A).reshape(S, -1), aa.reshape(S, -1),
             (w[..., None, None] * aa).reshape(S, -1),
             ((w * w)[..., None, None] * aa).reshape(S, -1)]
    (summed,) = sum_over_sets(sets, jnp.concatenate(parts, axis=-1))
    B = sets.shape[0]
    cuts = np.cumsum([N, N * P, N * P * P, N * P * P])
    yy, ya, aa_, waa, w2aa = jnp.split(summed, cuts, axis=-1)
    return (yy, ya.reshape(B, N, P), aa_.reshape(B, N, P, P), waa.reshape(B, N, P, P),
            w2aa.reshape(B, N, P, P))


def _noise_covariance(A, y, w, sets, x, floor):
    """One object and model: (B, P, P) sandwich covariance, (B, N) level, (B, N) floor used."""
    yy, ya, aa, waa, w2aa = _per_set_moments(A, y, w, sets)
    M = sets.shape[1]
    rss = yy - 2 * jnp.einsum("bnp,bp->bn", ya, x) + jnp.einsum("bp,bnpq,bq->bn", x, aa, x)
    Gi = _inv_spd(jnp.sum(waa, axis=1))
    lever = jnp.einsum("bpq,bnqp->bn", Gi, waa)  # sums to P over the joints
    resid_var = jnp.maximum(rss, 0.0) / jnp.maximum(M - lever, 1.0)
    var = jnp.maximum(resid_var, floor**2)
    meat = jnp.einsum("bn,bnpq->bpq", var, w2aa)
    return Gi @ meat @ Gi, var, (floor**2 > resid_var).astype(A.dtype)


def set_uncertainty(A: jnp.ndarray, tau_g: jnp.ndarray, tau_hat: jnp.ndarray,
                    weights: jnp.ndarray | None, sets: jnp.ndarray, x: jnp.ndarray,
                    floor: jnp.ndarray) -> SetUncertainty:
    """The covariance of every set's answer, for O objects x K model pairs x B sets at once.

    Args:
      A: (O, S, N, 4) load regressors; tau_g: (O, S, N) free-motion torques [N m].
      tau_hat: (O, K, S, N) the pairs' torques [N m] (K = 1 for a single model).
      weights: (O, K, S, N) the WLS weights (attention), or None for identity weights.
      sets: (O, B, M) sample indices; x: (O, K, B, 4) the pairs' estimates of each set.
      floor: (N,) the torque model's validation error level per joint [N m] (zeros: none).
    """
    dtype = A.dtype
    y = tau_hat.astype(dtype) - tau_g[:, None].astype(dtype)
    w = jnp.ones_like(y) if weights is None else jnp.maximum(weights.astype(dtype), 0.0)
    x = x.astype(dtype)
    floor = jnp.asarray(floor, dtype)
    per_model = jax.vmap(_noise_covariance, in_axes=(None, 0, 0, None, 0, None))
    per_object = jax.vmap(per_model, in_axes=(0, 0, 0, 0, 0, None))
    cov_k, var_k, floor_k = per_object(A, y, w, sets, x, floor)  # (O, K, B, ...)
    K = x.shape[1]
    mean = jnp.mean(x, axis=1)
    dev = x - mean[:, None]
    ens = jnp.einsum("okbp,okbq->obpq", dev, dev) / max(K - 1, 1)
    noise = jnp.mean(cov_k, axis=1)
    return SetUncertainty(mean, noise + ens, noise, ens, jnp.sqrt(jnp.mean(var_k, axis=1)),
                          jnp.mean(floor_k, axis=1))


# One program per shape, run once where it is called (a command's answer, a coverage table):
# on a GPU without the autotuner, whose timing of kernels made one compile take 15 s beside
# the folds in ``reproduce --full`` (docs/benchmarks.md, "Session 32").
set_uncertainty = run_once_jit(set_uncertainty)


# ---- mass, COM, intervals ---------------------------------------------------------------


def mass_com_covariance(x, cov):
    """``x = [m, m p]`` (..., 4) and its covariance -> ``[m, p]`` (..., 4) and the
    covariance of ``[m, p]`` by the delta method (``p = (m p) / m``)."""
    x, cov = jnp.asarray(x), jnp.asarray(cov)
    m = x[..., :1]
    p = x[..., 1:] / m
    J_top = jnp.broadcast_to(jnp.eye(1, 4, dtype=x.dtype), x.shape[:-1] + (1, 4))
    J_p = jnp.concatenate([-(p / m)[..., None],
                           jnp.broadcast_to(jnp.eye(3, dtype=x.dtype), x.shape[:-1] + (3, 3))
                           / m[..., None]], axis=-1)
    J = jnp.concatenate([J_top, J_p], axis=-2)
    return jnp.concatenate([m, p], axis=-1), J @ cov @ jnp.swapaxes(J, -1, -2)


def standard_errors(x, cov):
    """(..., 4) standard errors of ``[m, p_x, p_y, p_z]`` [kg, m]."""
    _, c = mass_com_covariance(x, cov)
    return jnp.sqrt(jnp.maximum(jnp.diagonal(c, axis1=-2, axis2=-1), 0.0))


def _intervals(x, cov, z):
    v, _ = mass_com_covariance(x, cov)
    half = z * standard_errors(x, cov)
    return v, v - half, v + half


def intervals(x, cov, level: float = 0.95):
    """``([m, p], lo, hi)`` (..., 4): the normal ``level`` interval of mass and COM."""
    return _intervals_jit(x, cov, z_of(level))


def z_scores(x, cov, x_true):
    """(..., 4) ``|estimate - truth| / se`` of ``[m, p_x, p_y, p_z]``, and (...,) the COM's
    squared Mahalanobis distance (for the joint 3-D region)."""
    v, c = mass_com_covariance(x, cov)
    m_t = jnp.asarray(x_true)[..., :1]
    truth = jnp.concatenate([m_t, jnp.asarray(x_true)[..., 1:] / m_t], axis=-1)
    err = v - truth
    se = jnp.sqrt(jnp.maximum(jnp.diagonal(c, axis1=-2, axis2=-1), 0.0))
    d = err[..., 1:]
    maha = jnp.einsum("...p,...p->...", d, cholesky_solve(c[..., 1:, 1:], d))
    return jnp.abs(err) / se, maha


# The answers' post-processing as one program each (per shape), not op by op: called
# eagerly, each of their dozens of operations compiled a program of its own (``estimate``,
# the coverage tables), slowing whatever ran beside them.
mass_com_covariance = run_once_jit(mass_com_covariance)
standard_errors = run_once_jit(standard_errors)
z_scores = run_once_jit(z_scores)
_intervals_jit = run_once_jit(_intervals)


def coverage(x, cov, x_true, *, levels: Sequence[float] = LEVELS, inflate=1.0) -> dict:
    """How often the truth lies inside the intervals, over the sets (leading axes) of one
    object: ``{"n_sets", "n_failed", level: {"mass", "com_xyz" [3], "com", "com_region"}}``
    (fractions; ``com`` the mean over the coordinates, ``com_region`` the joint 3-D
    ellipsoid). Sets without a finite covariance count as failed and are left out.
    ``inflate``: a factor on the standard errors, one or per ``[m, p_x, p_y, p_z]`` (the
    COM region takes the COM coordinates' largest)."""
    z, maha = (np.asarray(a) for a in z_scores(x, cov, np.broadcast_to(x_true, np.shape(x))))
    k = np.broadcast_to(np.asarray(inflate, np.float64), (4,))
    z = z.reshape(-1, 4) / k
    maha = maha.reshape(-1) / np.max(k[1:]) ** 2
    ok = np.all(np.isfinite(z), axis=-1) & np.isfinite(maha)
    z, maha = z[ok], maha[ok]
    out: dict = {"n_sets": int(ok.sum()), "n_failed": int((~ok).sum())}
    for level in levels:
        inside = z <= z_of(level)
        if not ok.any():
            out[level] = {"mass": np.nan, "com_xyz": [np.nan] * 3, "com": np.nan,
                          "com_region": np.nan}
            continue
        out[level] = {"mass": float(inside[:, 0].mean()),
                      "com_xyz": inside[:, 1:].mean(axis=0).tolist(),
                      "com": float(inside[:, 1:].mean()),
                      "com_region": float((maha <= _chi2_3_ppf(level)).mean())}
    return out


def fit_inflation(x, cov, x_true, *, level: float = 0.95) -> np.ndarray:
    """(4,) factors on the standard errors of ``[m, p_x, p_y, p_z]`` that make ``level``
    intervals cover the truth in ``level`` of the sets given: one for the mass, one for the
    COM coordinates (pooled). Fitted on one object, to be checked on another."""
    z, _ = z_scores(x, cov, np.broadcast_to(x_true, np.shape(x)))
    z = np.asarray(z).reshape(-1, 4)
    z = z[np.all(np.isfinite(z), axis=-1)]
    if len(z) == 0:
        raise UsageError("no set with a finite covariance to fit an inflation factor on")
    k_mass = np.quantile(z[:, 0], level) / z_of(level)
    k_com = np.quantile(z[:, 1:], level) / z_of(level)
    return np.array([k_mass, k_com, k_com, k_com])


# ---- pose-only identifiability -----------------------------------------------------------


class Identifiability(NamedTuple):
    """What the poses of each set can determine, before any torque is measured.

    condition: the 2-norm condition number of the column-scaled ``diag(1/sigma) A``.
    rank_deficient: the poses cannot determine x (inf condition, NaN standard errors).
    cov: (..., 4, 4) predicted covariance of x for independent per-joint errors sigma.
    se: (..., 4) predicted standard errors of ``[m, p_x, p_y, p_z]`` at ``x_nominal``.
    """

    condition: jnp.ndarray
    rank_deficient: jnp.ndarray
    cov: jnp.ndarray
    se: jnp.ndarray


@jax.jit
def identifiability(A: jnp.ndarray, sets: jnp.ndarray, noise: jnp.ndarray,
                    x_nominal: jnp.ndarray,
                    max_condition: float = DEFAULT_MAX_CONDITION) -> Identifiability:
    """Pose-only diagnostics of sets (B, M) of samples with regressors A (S, N, 4).

    ``noise`` (N,) the torque error level per joint [N m]; ``x_nominal`` (4,) or (B, 4) the
    object at which the COM's standard error is predicted (its mass matters: the COM's
    error scales as 1/m)."""
    dtype = A.dtype
    w = jnp.broadcast_to(1.0 / jnp.asarray(noise, dtype) ** 2, A.shape[:2])
    G, _, _ = set_statistics(A, jnp.zeros(A.shape[:2], dtype), w, sets)
    res = solve_normal(G, jnp.zeros(G.shape[:-1], dtype), jnp.zeros(G.shape[:-2], dtype),
                       max_condition=max_condition)
    cov = jnp.where(res.rank_deficient[..., None, None], jnp.nan, _inv_spd(G))
    xn = jnp.broadcast_to(jnp.asarray(x_nominal, dtype), cov.shape[:-1])
    return Identifiability(res.condition, res.rank_deficient, cov, standard_errors(xn, cov))


# ---- the torque model's error level -----------------------------------------------------


def validation_torque_error(pair: ModelPair, fc: FeatureConfig, val: Samples) -> np.ndarray:
    """(N,) RMS error per joint [N m] of the K torque models on held-out samples of known
    torque (the training run's validation split), pooled over the pairs."""
    if val.tau is None or val.n_samples == 0:
        raise UsageError("the validation error needs held-out samples with known torques")
    f64 = jnp.float64 if jax.config.jax_enable_x64 else jnp.float32
    feats = jnp.asarray(featurize(fc, jnp.asarray(val.q, f64), val.q_d, val.direction,
                                  val.current_tau),
                        jnp.float32)
    tau_hat = predict_torques_stacked(pair.torque_model, pair.torque_vars, feats,
                                      pair.tau_scale)
    err = np.asarray(tau_hat, np.float64) - np.asarray(val.tau, np.float64)[None]
    return np.sqrt(np.mean(err**2, axis=(0, 1)))


def training_validation_error(config: dict) -> tuple[np.ndarray | None, str]:
    """The torque models' validation error per joint (N,) [N m] that training recorded in
    a model folder's config (``torque_validation_error_Nm``: :func:`validation_torque_error`
    on the run's own validation split). Returns ``(None, why)`` when there is none."""
    err = config.get("torque_validation_error_Nm")
    if err is None:
        return None, ("the model folder records no validation error (released models, or "
                      "trained before it was recorded)")
    n = config.get("samples", {}).get("validation")
    return np.asarray(err, np.float64), f"validation split of the training data ({n} samples)"


# ---- everything for objects and sets ----------------------------------------------------


def uncertainty_of(objects: Sequence[Samples], sets: Sequence[np.ndarray], *,
                   pair: ModelPair | None = None, fc: FeatureConfig | None = None,
                   baselines: Baselines | None = None, floor: np.ndarray | None = None,
                   ) -> dict[str, SetUncertainty]:
    """Every method's answer and covariance for each set of each object: ``{"T", "T-A"}``
    from the K pairs (one batched call each, ``floor`` the torque models' validation error
    per joint), ``{"Sensor", "PE"}`` from the baselines (one model, residuals only)."""
    if pair is not None and fc is None:
        raise UsageError("the models' uncertainty needs their feature configuration")
    batch = stack(objects, sets, fc if pair is not None else None)
    # The sets split over the local devices as evaluate() splits them: the same programs
    # (estimate_sets, identity_solves) serve both, compiled once (``jaxinertia estimate``
    # calls both on the same sets).
    batch = batch._replace(sets=shard(batch.sets, axis=1))
    n_joints = batch.A.shape[2]
    none = jnp.zeros(n_joints, batch.A.dtype)
    out: dict[str, SetUncertainty] = {}
    if baselines is not None:
        per_obj = [baseline_torques(baselines, o) for o in objects]
        for m in baseline_methods(objects)[0]:
            tau = jnp.asarray(np.stack([  # padded like stack(): the last sample repeated
                np.pad(p[m], ((0, batch.A.shape[1] - len(p[m])), (0, 0)), mode="edge")
                for p in per_obj]))
            x = identity_solves(batch.A, tau, batch.tau_g, batch.sets).x
            out[m] = set_uncertainty(batch.A, batch.tau_g, tau[:, None], None, batch.sets,
                                     x[:, None], none)
    if pair is not None:
        est = estimate_sets(pair, batch.features, batch.A, batch.tau_g, batch.sets)
        fl = none if floor is None else jnp.asarray(floor, batch.A.dtype)
        out["T"] = set_uncertainty(batch.A, batch.tau_g, est.tau_hat, None, batch.sets,
                                   est.T.x, fl)
        out["T-A"] = set_uncertainty(batch.A, batch.tau_g, est.tau_hat, est.weights,
                                     batch.sets, est.TA.x, fl)
    return out


def interval_coverage(objects: Sequence[Samples], answers: dict[str, SetUncertainty], *,
                levels: Sequence[float] = LEVELS, inflate=1.0) -> dict:
    """Coverage of every method's intervals on known objects, over each object's sets
    (``answers`` from :func:`uncertainty_of` on the same objects):
    ``{"objects": {name: {method: coverage + "median_se" [4], "rms_error" [4]}},
    "per_set": {method: {"se": (O, B, 4), "error": (O, B, 4)}}}`` (``[m, p]``, kg and m)."""
    out: dict = {"objects": {}, "per_set": {}}
    for m, u in answers.items():
        se = np.asarray(standard_errors(u.x, u.cov)) * np.asarray(inflate)
        v = np.asarray(mass_com_covariance(u.x, u.cov)[0])
        ux, ucov = np.asarray(u.x), np.asarray(u.cov)  # indexed on the host, not op by op
        err = np.stack([v[o] - np.r_[obj.x[0, 0], obj.x[0, 1:] / obj.x[0, 0]]
                        for o, obj in enumerate(objects)])
        out["per_set"][m] = {"se": se, "error": err}
        for o, obj in enumerate(objects):
            c = coverage(ux[o], ucov[o], obj.x[0], levels=levels, inflate=inflate)
            c["median_se"] = np.nanmedian(se[o], axis=0).tolist()
            c["rms_error"] = np.sqrt(np.nanmean(err[o] ** 2, axis=0)).tolist()
            out["objects"].setdefault(obj.name, {})[m] = c
    return out
