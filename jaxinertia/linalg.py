"""Small dense linear algebra shared by identification, design, uncertainty, training and
the simulator: the unrolled Cholesky factorisation (factor, solve, log-det) and the Gram
statistics of weighted least squares.

The systems are tiny (P = 4 unknowns of the load, N = 4 joints of the arm) and come in
batches of thousands, so the factorisation and both substitutions are unrolled into
elementwise operations on the matrix entries: one fused kernel over any batch, with no
LAPACK call per matrix, differentiable like any jnp code. The entries are taken by an
accessor, so the same code serves batch-first arrays ``(..., P, P)`` (identification,
design) and the batch-last nested lists ``M[i][j]`` of shape (B,) that
:mod:`jaxinertia.sim.batched` steps without ``vmap``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp

__all__ = [
    "cholesky_factor",
    "cholesky_solve",
    "cholesky_substitute",
    "gram",
    "gram_statistics",
    "logdet_spd",
    "spd_inverse_rows",
]

#: Above this size the Cholesky solve goes to LAPACK/cuSOLVER instead of being unrolled.
MAX_UNROLLED = 8

Entry = Callable[[int, int], jnp.ndarray]


def cholesky_factor(entry: Entry, P: int, *, guard: bool = False):
    """The lower Cholesky factor ``L`` of a symmetric matrix, entry by entry.

    ``entry(i, j)`` returns the (i, j) entry (any batch shape); only ``i >= j`` is read.
    Returns ``L`` as a dict ``{(i, j): array}`` for ``i >= j``. With ``guard``, pivots that
    are not positive are replaced by 1 (so that no NaN is made) and the factor comes with
    ``ok`` (the matrix is positive definite) and the pivots' log sum ``sum_j log L_jj``
    accumulated column by column: ``(L, ok, log_diag)``.
    """
    L: dict[tuple[int, int], jnp.ndarray] = {}
    ok = total = None
    for j in range(P):
        d = entry(j, j) - sum((L[j, k] ** 2 for k in range(j)), start=0.0)
        if guard:
            if j == 0:
                shape, dtype = jnp.shape(d), jnp.result_type(d)
                total, ok = jnp.zeros(shape, dtype), jnp.ones(shape, bool)
            ok = ok & (d > 0)
            L[j, j] = jnp.sqrt(jnp.where(d > 0, d, 1.0))
            total = total + jnp.log(L[j, j])
        else:
            L[j, j] = jnp.sqrt(d)
        for i in range(j + 1, P):
            off = entry(i, j) - sum((L[i, k] * L[j, k] for k in range(j)), start=0.0)
            L[i, j] = off / L[j, j]
    return (L, ok, total) if guard else L


def cholesky_substitute(L: dict, b: Sequence[jnp.ndarray]) -> list[jnp.ndarray]:
    """``z`` with ``L L^T z = b`` for the factor of :func:`cholesky_factor`; ``b`` and ``z``
    as lists of the P entries (any batch shape)."""
    P = len(b)
    u = []  # L u = b
    for i in range(P):
        u.append((b[i] - sum((L[i, k] * u[k] for k in range(i)), start=0.0)) / L[i, i])
    z = [None] * P  # L^T z = u
    for i in reversed(range(P)):
        acc = u[i] - sum((L[k, i] * z[k] for k in range(i + 1, P)), start=0.0)
        z[i] = acc / L[i, i]
    return z


def cholesky_solve(S: jnp.ndarray, b: jnp.ndarray) -> jnp.ndarray:
    """Solves ``S z = b`` for symmetric positive-definite S (..., P, P), b (..., P).

    For P <= 8 the factorisation and both substitutions are unrolled into elementwise
    operations (one fused kernel over any batch, differentiable like any jnp code);
    larger systems go to LAPACK/cuSOLVER.
    """
    P = S.shape[-1]
    if P > MAX_UNROLLED:
        L = jnp.linalg.cholesky(S)
        return jax.scipy.linalg.cho_solve((L, True), b[..., None])[..., 0]
    L = cholesky_factor(lambda i, j: S[..., i, j], P)
    return jnp.stack(cholesky_substitute(L, [b[..., i] for i in range(P)]), axis=-1)


def logdet_spd(G: jnp.ndarray) -> jnp.ndarray:
    """``log det`` of small symmetric matrices (..., P, P) by an unrolled Cholesky
    factorisation (one fused kernel over any batch); ``-inf`` where not positive definite."""
    _, ok, log_diag = cholesky_factor(lambda i, j: G[..., i, j], G.shape[-1], guard=True)
    return jnp.where(ok, 2.0 * log_diag, -jnp.inf)


def spd_inverse_rows(M: Sequence[Sequence[jnp.ndarray]], dtype) -> list[list[jnp.ndarray]]:
    """``M^-1`` of a symmetric positive-definite matrix given as nested lists ``M[i][j]`` of
    equal-shape arrays (e.g. (B,), batch last): row c is ``solve(M, e_c)`` (by symmetry also
    column c), as nested lists of the same shape."""
    P = len(M)
    L = cholesky_factor(lambda i, j: M[i][j], P)
    return [cholesky_substitute(L, [jnp.asarray(1.0 if i == col else 0.0, dtype)
                                    for i in range(P)])
            for col in range(P)]


def gram(A: jnp.ndarray, w: jnp.ndarray | None = None) -> jnp.ndarray:
    """Per-sample weighted Gram matrices ``A_s^T W_s A_s`` (S, P, P) of regressors A
    (S, N, P), ``W_s = diag(w_s)``; ``w`` (S, N) or (N,) non-negative weights, None for
    identity weights."""
    if w is None:
        return jnp.einsum("...np,...nq->...pq", A, A)
    return jnp.einsum("...np,...n,...nq->...pq", A, w, A)


def gram_statistics(A: jnp.ndarray, y: jnp.ndarray, w: jnp.ndarray | None = None, *,
                    rows: int = 1):
    """The statistics of weighted least squares ``min (A x - y)^T W (A x - y)`` summed over
    the last ``rows`` axes before P: ``(A^T W A (..., P, P), A^T W y (..., P), y^T W y (...,))``.

    Args:
      A: (..., R_1, ..., R_rows, P) regressor rows, e.g. (S, N, P) for per-sample
        statistics, (R, P) for one set of rows, (B, M, N, P) with ``rows=2`` per set.
      y: A's shape without P; w: the same shape, non-negative weights, or None (identity).
    """
    r = "klmn"[4 - rows:]
    if w is None:
        G = jnp.einsum(f"...{r}p,...{r}q->...pq", A, A)
        b = jnp.einsum(f"...{r}p,...{r}->...p", A, y)
        return G, b, jnp.sum(y * y, axis=tuple(range(-rows, 0)))
    # Weights multiply the right-hand factor (w A_q, w y): one association everywhere.
    G = jnp.einsum(f"...{r}p,...{r},...{r}q->...pq", A, w, A)
    b = jnp.einsum(f"...{r}p,...{r},...{r}->...p", A, w, y)
    c = jnp.einsum(f"...{r},...{r},...{r}->...", y, w, y)
    return G, b, c
