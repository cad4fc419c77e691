"""Weighted least squares for x = [m, m*p]: one set, or many sets in one jit + vmap call.

    x_hat = argmin_x (A x - y)^T W (A x - y),   W = diag(w),  y = tau_hat - tau_g

Solved by QR of ``sqrt(W) A`` after scaling A's columns to unit norm: no explicit inverse,
no squared condition number (the normal equations would square it), and the solution is
differentiable, so the attention model can be trained through it.

Precision: float64 is the library's choice for identification (``jax_enable_x64``, set by
the CLI); the result follows the input dtype. tests/test_identification.py measures
float32 against float64 on the real data's regressors.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

__all__ = [
    "WLSResult",
    "DEFAULT_MAX_CONDITION",
    "wls",
    "wls_batched",
    "solve_sets",
    "mass_and_com",
]

#: Sets whose column-scaled ``sqrt(W) A`` has a larger condition number are flagged
#: ill-conditioned. The real data's 64-sample sets sit around 10-30.
DEFAULT_MAX_CONDITION = 1e4


class WLSResult(NamedTuple):
    """Result of one weighted least-squares solve (leading batch axes allowed).

    x: (4,) the estimate; NaN where the set is rank deficient (never silent garbage).
    condition: 2-norm condition number of the column-scaled weighted regressor.
    rank_deficient: the regressor loses rank numerically (x is NaN).
    ill_conditioned: condition above the threshold (x is returned, but suspect).
    residual: weighted residual norm ``||sqrt(W) (A x - y)||``.
    """

    x: jnp.ndarray
    condition: jnp.ndarray
    rank_deficient: jnp.ndarray
    ill_conditioned: jnp.ndarray
    residual: jnp.ndarray

    @property
    def ok(self) -> jnp.ndarray:
        return ~(self.rank_deficient | self.ill_conditioned)


def wls(
    A: jnp.ndarray,
    y: jnp.ndarray,
    w: jnp.ndarray | None = None,
    *,
    max_condition: float = DEFAULT_MAX_CONDITION,
) -> WLSResult:
    """Weighted least squares for one set.

    Args:
      A: (R, P) regressor rows (for M samples of N joints, R = M*N, P = 4).
      y: (R,) right-hand side, ``tau_hat - tau_g`` [N m].
      w: (R,) non-negative weights; None for identity weights.
      max_condition: flag threshold on the condition number.
    """
    dtype = jnp.result_type(A, y)
    A = A.astype(dtype)
    y = y.astype(dtype)
    sw = jnp.ones_like(y) if w is None else jnp.sqrt(jnp.maximum(w.astype(dtype), 0.0))
    Aw = A * sw[:, None]
    yw = y * sw
    # Column scaling makes the condition number independent of units (kg versus kg*m).
    norms = jnp.linalg.norm(Aw, axis=0)
    safe = jnp.where(norms > 0, norms, 1.0)
    Q, R = jnp.linalg.qr(Aw / safe, mode="reduced")
    s = jnp.linalg.svd(R, compute_uv=False)
    eps = jnp.finfo(dtype).eps
    rank_deficient = (s[-1] <= s[0] * eps * max(A.shape)) | jnp.any(norms == 0)
    rank_deficient = rank_deficient | ~jnp.all(jnp.isfinite(R)) | ~jnp.all(jnp.isfinite(yw))
    condition = jnp.where(rank_deficient, jnp.inf, s[0] / jnp.where(s[-1] > 0, s[-1], 1.0))
    # Guard the triangular solve so that rank-deficient sets do not poison gradients.
    R_safe = jnp.where(rank_deficient, jnp.eye(R.shape[0], dtype=dtype), R)
    z = jax.scipy.linalg.solve_triangular(R_safe, Q.T @ yw, lower=False)
    x = z / safe
    residual = jnp.linalg.norm(Aw @ x - yw)
    x = jnp.where(rank_deficient, jnp.nan, x)
    return WLSResult(x, condition, rank_deficient, condition > max_condition, residual)


#: ``wls`` over a leading batch axis of sets: A (B, R, P), y (B, R), w (B, R) or None.
wls_batched = jax.vmap(wls, in_axes=(0, 0, 0))


def solve_sets(
    A: jnp.ndarray,
    y: jnp.ndarray,
    w: jnp.ndarray | None,
    sets: jnp.ndarray,
    *,
    max_condition: float = DEFAULT_MAX_CONDITION,
) -> WLSResult:
    """Solves every sample set at once.

    Args:
      A: (S, N, 4) per-sample regressors; y: (S, N) ``tau_hat - tau_g``;
      w: (S, N) per-sample joint weights or None (identity).
      sets: (B, M) integer sample indices of B sets of M samples.
    Returns a :class:`WLSResult` with leading axis B.
    """
    def one(idx):
        A_s = A[idx].reshape(-1, A.shape[-1])
        y_s = y[idx].reshape(-1)
        w_s = None if w is None else w[idx].reshape(-1)
        return wls(A_s, y_s, w_s, max_condition=max_condition)

    return jax.vmap(one)(sets)


def mass_and_com(x: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """``x = [m, m*p]`` (..., 4) -> mass (...,) [kg] and COM p (..., 3) in the tag frame [m]."""
    return x[..., 0], x[..., 1:] / x[..., :1]
