"""Weighted least squares for x = [m, m*p]: one set, or many sets in one jit + vmap call.

    x_hat = argmin_x (A x - y)^T W (A x - y),   W = diag(w),  y = tau_hat - tau_g

The unknown has only P = 4 entries, so every set reduces to its weighted Gram matrix
``G = A^T W A`` (4 x 4) and ``b = A^T W y``. Per-sample statistics are formed once and
summed over each set's indices; a set then costs a 4 x 4 Cholesky solve, which makes the
paper's 1000 repeats x objects x model pairs one cheap batched call. There is no explicit
inverse: the columns are scaled to unit norm (so the diagnostic does not depend on kg
versus kg*m) and the scaled Gram matrix is factored.

Precision: forming G squares the condition number kappa of ``sqrt(W) A``. The real data's
64-sample sets have kappa ~ 10-60, so in float64 (the library's choice for identification,
``jax_enable_x64``, set by the CLI) the relative error is ~kappa^2 * 1e-16 < 1e-12;
``tests/test_identification.py`` checks it against numpy's SVD-based ``lstsq`` and measures
float32 against float64 on the real regressors. Sets are flagged, never silently solved:
``rank_deficient`` where the scaled Gram matrix is numerically singular in the working
dtype (x is NaN), ``ill_conditioned`` where kappa exceeds ``max_condition``.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxinertia.linalg import cholesky_solve, gram_statistics

__all__ = [
    "DEFAULT_MAX_CONDITION",
    "WLSResult",
    "identity_solves",
    "mass_and_com",
    "solve_normal",
    "set_statistics",
    "solve_sets",
    "sum_over_sets",
    "symmetric_eigvals",
    "wls",
    "wls_batched",
]

#: Sets whose column-scaled ``sqrt(W) A`` has a larger 2-norm condition number are
#: flagged ill-conditioned. The real data's 64-sample sets sit around 10-60.
DEFAULT_MAX_CONDITION = 1e4


class WLSResult(NamedTuple):
    """Result of weighted least-squares solves (any leading batch axes).

    x: (..., P) the estimate; NaN where the set is rank deficient (never silent garbage).
    condition: 2-norm condition number of the column-scaled ``sqrt(W) A``.
    rank_deficient: the regressor is numerically singular (x is NaN).
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


def symmetric_eigvals(S: jnp.ndarray, sweeps: int = 5) -> jnp.ndarray:
    """Eigenvalues (unsorted) of small symmetric matrices (..., P, P) by cyclic Jacobi.

    The P(P+1)/2 entries are kept as separate arrays and every rotation is elementwise, so
    XLA fuses the whole iteration into one kernel over the batch: thousands of 4 x 4
    matrices cost about a millisecond, where ``jnp.linalg.eigvalsh`` makes one LAPACK call
    each (~10x slower on CPU). Jacobi converges quadratically; five sweeps reach machine
    precision for P <= 6 (tests/test_identification.py compares with numpy).
    """
    P = S.shape[-1]
    a = {(i, j): S[..., i, j] for i in range(P) for j in range(i, P)}

    def get(i, j):
        return a[(i, j) if i <= j else (j, i)]

    def put(i, j, v):
        a[(i, j) if i <= j else (j, i)] = v

    tiny = jnp.finfo(S.dtype).tiny
    keys = list(a)

    def sweep(_, entries):
        a.update(zip(keys, entries))
        for p in range(P - 1):
            for q in range(p + 1, P):
                app, aqq, apq = get(p, p), get(q, q), get(p, q)
                small = jnp.abs(apq) <= tiny
                theta = (aqq - app) / (2.0 * jnp.where(small, 1.0, apq))
                t = jnp.sign(theta) / (jnp.abs(theta) + jnp.sqrt(theta * theta + 1.0))
                t = jnp.where(small, 0.0, jnp.where(theta == 0, 1.0, t))
                c = 1.0 / jnp.sqrt(t * t + 1.0)
                s = t * c
                for k in range(P):
                    if k in (p, q):
                        continue
                    akp, akq = get(k, p), get(k, q)
                    put(k, p, c * akp - s * akq)
                    put(k, q, s * akp + c * akq)
                put(p, p, app - t * apq)
                put(q, q, aqq + t * apq)
                put(p, q, jnp.zeros_like(apq))
        return tuple(a[k] for k in keys)

    # A rolled loop over sweeps keeps the compiled program (and compile time) small.
    a.update(zip(keys, jax.lax.fori_loop(0, sweeps, sweep, tuple(a[k] for k in keys))))
    return jnp.stack([a[(i, i)] for i in range(P)], axis=-1)


def solve_normal(
    G: jnp.ndarray,
    b: jnp.ndarray,
    yWy: jnp.ndarray,
    *,
    max_condition: float = DEFAULT_MAX_CONDITION,
) -> WLSResult:
    """Solves ``G x = b`` for Gram statistics ``G = A^T W A``, ``b = A^T W y``.

    ``yWy = y^T W y`` gives the residual norm without the rows
    (``r^2 = yWy - b^T x`` at the optimum). All arguments may carry leading batch axes.
    """
    dtype = jnp.result_type(G, b)
    G, b, yWy = G.astype(dtype), b.astype(dtype), jnp.asarray(yWy, dtype)
    P = G.shape[-1]
    d2 = jnp.diagonal(G, axis1=-2, axis2=-1)
    zero_column = jnp.any(d2 <= 0, axis=-1)
    d = jnp.sqrt(jnp.where(d2 > 0, d2, 1.0))
    Gs = G / (d[..., :, None] * d[..., None, :])
    bs = b / d
    ev = symmetric_eigvals(jax.lax.stop_gradient(Gs))
    lmin, lmax = jnp.min(ev, axis=-1), jnp.max(ev, axis=-1)
    finite = jnp.all(jnp.isfinite(ev), axis=-1) & jnp.all(jnp.isfinite(bs), axis=-1)
    eps = jnp.finfo(dtype).eps
    # Eigenvalues of Gs are only resolved to ~eps * lmax: below that the set is singular.
    rank_deficient = zero_column | ~finite | (lmin <= 16 * P * eps * lmax)
    condition = jnp.where(rank_deficient, jnp.inf, jnp.sqrt(lmax / jnp.where(lmin > 0, lmin, 1)))
    # Guard the factorisation so that singular sets do not poison values or gradients.
    eye = jnp.eye(P, dtype=dtype)
    Gs = jnp.where(rank_deficient[..., None, None], eye, Gs)
    z = cholesky_solve(Gs, bs)
    x = z / d
    r2 = yWy - jnp.sum(bs * z, axis=-1)
    residual = jnp.sqrt(jnp.maximum(r2, 0.0))
    x = jnp.where(rank_deficient[..., None], jnp.nan, x)
    return WLSResult(x, condition, rank_deficient, condition > max_condition, residual)


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
    A, y = A.astype(dtype), y.astype(dtype)
    w = None if w is None else jnp.maximum(w.astype(dtype), 0.0)
    return solve_normal(*gram_statistics(A, y, w), max_condition=max_condition)


#: ``wls`` over a leading batch axis of sets: A (B, R, P), y (B, R), w (B, R).
wls_batched = jax.vmap(wls, in_axes=(0, 0, 0))


def set_statistics(
    A: jnp.ndarray, y: jnp.ndarray, w: jnp.ndarray | None, sets: jnp.ndarray
) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    """Gram statistics ``(A^T W A, A^T W y, y^T W y)`` of every set, leading axis B.

    Args:
      A: (S, N, P) per-sample regressors; y: (S, N) ``tau_hat - tau_g``;
      w: (S, N) per-sample joint weights or None (identity).
      sets: (B, M) integer sample indices of B sets of M samples.
    Under ``vmap`` over model pairs with ``A`` and ``w=None`` shared, the Gram matrices are
    summed once, not once per model.
    """
    dtype = jnp.result_type(A, y)
    A, y = A.astype(dtype), y.astype(dtype)
    w = None if w is None else jnp.maximum(w.astype(dtype), 0.0)
    G, b, c = gram_statistics(A, y, w)
    # Sum only the unique entries of G, and keep G apart from (b, c) so that G stays
    # unbatched under vmap when it does not depend on the batched arguments.
    P = A.shape[-1]
    iu, ju = jnp.triu_indices(P)
    G_u, bc = sum_over_sets(sets, G[:, iu, ju], jnp.concatenate([b, c[:, None]], axis=-1))
    G = jnp.zeros(G_u.shape[:-1] + (P, P), G_u.dtype).at[..., iu, ju].set(G_u)
    G = G.at[..., ju, iu].set(G_u)
    return G, bc[..., :P], bc[..., P]


def solve_sets(
    A: jnp.ndarray,
    y: jnp.ndarray,
    w: jnp.ndarray | None,
    sets: jnp.ndarray,
    *,
    max_condition: float = DEFAULT_MAX_CONDITION,
) -> WLSResult:
    """Solves every sample set at once (arguments as :func:`set_statistics`).

    Returns a :class:`WLSResult` with leading axis B.
    """
    return solve_normal(*set_statistics(A, y, w, sets), max_condition=max_condition)


@jax.jit
def identity_solves(A: jnp.ndarray, tau_hat: jnp.ndarray, tau_g: jnp.ndarray,
                    sets: jnp.ndarray) -> WLSResult:
    """Identity-weight WLS of every object's sets (the Sensor and PE baselines): A
    (O, S, N, P), torque estimates tau_hat and free-motion torques tau_g (O, S, N) [N m],
    sets (O, B, M). Returns a :class:`WLSResult` with leading axes (O, B)."""
    return jax.vmap(lambda A_o, y_o, g_o, s_o: solve_sets(A_o, y_o - g_o, None, s_o))(
        A, tau_hat.astype(A.dtype), tau_g, sets)


#: Above this many (sets x samples) entries, sums over sets use a gather instead of the
#: 0/1 selection matrix (8 bytes per entry in float64).
MAX_SELECTION_ENTRIES = 2**24


def sum_over_sets(sets: jnp.ndarray, *stats: jnp.ndarray) -> list[jnp.ndarray]:
    """``stat[sets].sum(axis=1)`` for per-sample statistics (S, ...) and sets (B, M).

    Written as one matrix product with the (B, S) selection matrix when it is small: XLA's
    CPU gather moves ~4 ns per element, so summing 10 models x 1000 sets x 64 samples by
    gather takes ~40 ms, the matmul ~5 ms. The sums are exact in either form (the
    selection matrix holds integers; HIGHEST precision keeps GPUs off TF32).
    """
    n_samples = stats[0].shape[0]
    B = sets.shape[0]
    if B * n_samples > MAX_SELECTION_ENTRIES:
        return [s[sets].sum(axis=1) for s in stats]
    dtype = jnp.result_type(*stats)
    sel = jnp.zeros((B, n_samples), dtype).at[jnp.arange(B)[:, None], sets].add(1.0)
    return [
        jnp.tensordot(sel, s, axes=1, precision=jax.lax.Precision.HIGHEST) for s in stats
    ]


def mass_and_com(x: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """``x = [m, m*p]`` (..., 4) -> mass (...,) [kg] and COM p (..., 3) in the tag frame [m]."""
    return x[..., 0], x[..., 1:] / x[..., :1]
