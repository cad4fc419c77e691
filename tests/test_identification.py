"""Weighted least squares against numpy's SVD-based lstsq; flags; batching; precision."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads
from support.asserts import assert_tree_close

import jaxinertia.identification as ident
from jaxinertia.identification import (
    mass_and_com,
    set_statistics,
    solve_sets,
    symmetric_eigvals,
    wls,
    wls_batched,
)
from jaxinertia.linalg import cholesky_solve
from jaxinertia.samples import load_lbipe

# Tolerances, one per reference:
# numpy's SVD-based lstsq on synthetic well-conditioned problems (columns scaled as the real
# A): x from float64 normal equations agrees to float64 rounding times kappa^2.
LSTSQ_RTOL = 1e-10
LSTSQ_ATOL = 1e-12  # x entries near zero (m p ~ 1e-3 kg m)
# numpy's residual norm and np.linalg.cond: ours come from the Gram statistics (residual
# from y'Wy - x'A'Wy, condition from Jacobi eigenvalues), which lose digits to cancellation.
DERIVED_RTOL = 1e-8
# numpy lstsq on the real files' sets (64 samples; identification.py: kappa ~10-60).
LSTSQ_REAL_TOL = {"rtol": 1e-9, "atol": 1e-12}
# The files' own x recovered from their ground-truth torques (tau - tau_g = A x).
TRUTH_TOL = {"rtol": 1e-3, "atol": 1e-6}
# Our two batched paths against each other: wls_batched on gathered rows vs solve_sets on
# per-sample statistics (other summation order) ...
PATHS_RTOL = 1e-10
# ... and the gather vs the 0/1 selection-matrix sums of set_statistics (same sums).
GATHER_RTOL = 1e-12
# Central finite differences of jax.test_util.check_grads.
FD_TOL = 1e-6
# numpy's LAPACK eigvalsh (relative to the largest eigenvalue) and np.linalg.solve.
EIGVALS_RTOL = 1e-13
CHOLESKY_TOL = {"rtol": 1e-8, "atol": 1e-10}
# mass_and_com's COM against the hand-divided one.
COM_RTOL = 1e-14
# float32 against float64 on the real sets: far below the method's own error (grams, mm).
FLOAT32_MASS_RTOL = 1e-4
FLOAT32_COM_MM = 1e-2

# Compiled once per module and shape (run eagerly, the Jacobi sweeps of the condition number
# dispatch op by op: 50 single-set solves took ~20 s on the 2-core CI machine). Jitted and
# eager runs are the same float64 arithmetic; the tolerances above cover either.
_wls = jax.jit(wls)
_wls_batched = jax.jit(wls_batched)
_solve_sets = jax.jit(solve_sets)


def _problem(rng, rows=256, scales=(1.0, 0.02, 0.03, 0.05), collinear=None):
    A = rng.standard_normal((rows, 4)) * np.asarray(scales)
    if collinear is not None:  # column 3 = column 2 + tiny perturbation
        A[:, 3] = A[:, 2] * 1.7 + collinear * rng.standard_normal(rows) * scales[2]
    y = rng.standard_normal(rows)
    w = rng.uniform(0.0, 1.0, rows)
    return A, y, w


def _lstsq(A, y, w):
    sw = np.sqrt(w)
    return np.linalg.lstsq(A * sw[:, None], y * sw, rcond=None)[0]


def test_wls_equals_numpy_lstsq_on_random_weighted_problems():
    rng = np.random.default_rng(0)
    for _ in range(50):
        A, y, w = _problem(rng)
        res = _wls(jnp.asarray(A), jnp.asarray(y), jnp.asarray(w))
        ref = _lstsq(A, y, w)
        np.testing.assert_allclose(res.x, ref, rtol=LSTSQ_RTOL, atol=LSTSQ_ATOL)
        sw = np.sqrt(w)
        np.testing.assert_allclose(res.residual, np.linalg.norm(sw * (A @ ref - y)),
                                   rtol=DERIVED_RTOL)
        As = A * sw[:, None]
        np.testing.assert_allclose(res.condition, np.linalg.cond(As / np.linalg.norm(As, axis=0)),
                                   rtol=DERIVED_RTOL)
        assert not bool(res.rank_deficient) and not bool(res.ill_conditioned)


def test_identity_weights_equal_unweighted_lstsq():
    rng = np.random.default_rng(1)
    A, y, _ = _problem(rng)
    res = _wls(jnp.asarray(A), jnp.asarray(y))
    np.testing.assert_allclose(res.x, np.linalg.lstsq(A, y, rcond=None)[0], rtol=LSTSQ_RTOL)


def test_rank_deficient_sets_are_flagged_and_nan():
    rng = np.random.default_rng(2)
    A, y, w = _problem(rng)
    cases = {
        "zero column": A * np.array([1.0, 0.0, 1.0, 1.0]),
        "collinear columns": np.column_stack([A[:, 0], A[:, 1], A[:, 2], 2.0 * A[:, 2]]),
        "weights select too few rows": A,
    }
    for name, Ac in cases.items():
        wc = w.copy()
        if name == "weights select too few rows":
            wc[3:] = 0.0  # three non-zero rows for four unknowns
        res = _wls(jnp.asarray(Ac), jnp.asarray(y), jnp.asarray(wc))
        assert bool(res.rank_deficient), name
        assert np.all(np.isnan(np.asarray(res.x))), name
        assert np.isinf(float(res.condition)), name


def test_ill_conditioned_sets_are_flagged_but_solved():
    rng = np.random.default_rng(3)
    A, y, w = _problem(rng, collinear=1e-6)
    res = _wls(jnp.asarray(A), jnp.asarray(y), jnp.asarray(w))
    assert bool(res.ill_conditioned) and not bool(res.rank_deficient)
    assert float(res.condition) > 1e4
    assert np.all(np.isfinite(np.asarray(res.x)))
    assert not bool(res.ok)


def test_non_finite_inputs_are_flagged():
    rng = np.random.default_rng(4)
    A, y, w = _problem(rng)
    y[7] = np.nan
    assert bool(_wls(jnp.asarray(A), jnp.asarray(y), jnp.asarray(w)).rank_deficient)
    A2 = A.copy()
    A2[3, 1] = np.inf
    assert bool(_wls(jnp.asarray(A2), jnp.asarray(np.ones(256)), jnp.asarray(w)).rank_deficient)


def test_batched_sets_equal_one_by_one_and_gather_path():
    rng = np.random.default_rng(5)
    S, N, B, M = 300, 4, 40, 64
    A = rng.standard_normal((S, N, 4)) * np.array([1.0, 0.02, 0.03, 0.05])
    y = rng.standard_normal((S, N))
    w = rng.uniform(size=(S, N))
    sets = np.stack([rng.choice(S, M, replace=False) for _ in range(B)])
    res = _solve_sets(jnp.asarray(A), jnp.asarray(y), jnp.asarray(w), jnp.asarray(sets))
    for b in range(B):
        idx = sets[b]
        ref = _lstsq(A[idx].reshape(-1, 4), y[idx].reshape(-1), w[idx].reshape(-1))
        np.testing.assert_allclose(res.x[b], ref, rtol=LSTSQ_RTOL, atol=LSTSQ_ATOL)
    batched = _wls_batched(
        jnp.asarray(A[sets].reshape(B, -1, 4)),
        jnp.asarray(y[sets].reshape(B, -1)),
        jnp.asarray(w[sets].reshape(B, -1)),
    )
    # Every field of the WLSResult (x, condition, flags, residual), not x alone.
    assert_tree_close(batched, res, rtol=PATHS_RTOL, what="wls_batched vs solve_sets")
    # The gather path (used for very large sets x samples) gives the same statistics.
    mm = set_statistics(jnp.asarray(A), jnp.asarray(y), jnp.asarray(w), jnp.asarray(sets))
    old = ident.MAX_SELECTION_ENTRIES
    ident.MAX_SELECTION_ENTRIES = 0
    try:
        ga = set_statistics(jnp.asarray(A), jnp.asarray(y), jnp.asarray(w), jnp.asarray(sets))
    finally:
        ident.MAX_SELECTION_ENTRIES = old
    names = ("AtWA", "AtWy", "ytWy")
    assert len(mm) == len(ga) == len(names)
    assert_tree_close(dict(zip(names, mm)), dict(zip(names, ga)), rtol=GATHER_RTOL,
                      what="gather vs selection-matrix set statistics")


def test_gradient_through_batched_wls_equals_finite_differences():
    rng = np.random.default_rng(6)
    S, N = 120, 4
    A = jnp.asarray(rng.standard_normal((S, N, 4)) * np.array([1.0, 0.02, 0.03, 0.05]))
    y = jnp.asarray(rng.standard_normal((S, N)))
    sets = jnp.asarray(np.stack([rng.choice(S, 64, replace=False) for _ in range(5)]))

    def loss(logits):
        w = jax.nn.softmax(logits, axis=-1)
        return jnp.sum(solve_sets(A, y, w, sets).x ** 2)

    check_grads(jax.jit(loss), (jnp.asarray(rng.standard_normal((S, N))),), order=1,
                modes=["rev"], atol=FD_TOL, rtol=FD_TOL)


def test_symmetric_eigvals_and_cholesky_solve_match_numpy():
    rng = np.random.default_rng(7)
    M = rng.standard_normal((500, 4, 4))
    S = M @ np.swapaxes(M, 1, 2) + 1e-3 * np.eye(4)
    ev = np.sort(np.asarray(symmetric_eigvals(jnp.asarray(S))), axis=-1)
    ref = np.linalg.eigvalsh(S)
    assert np.max(np.abs(ev - ref) / ref.max(axis=-1, keepdims=True)) < EIGVALS_RTOL
    b = rng.standard_normal((500, 4))
    np.testing.assert_allclose(cholesky_solve(jnp.asarray(S), jnp.asarray(b)),
                               np.linalg.solve(S, b[..., None])[..., 0], **CHOLESKY_TOL)


def test_mass_and_com():
    x = jnp.array([[0.2, 0.2 * 0.01, -0.2 * 0.02, 0.2 * 0.03]])
    m, p = mass_and_com(x)
    np.testing.assert_allclose(m, [0.2])
    np.testing.assert_allclose(p, [[0.01, -0.02, 0.03]], rtol=COM_RTOL)


@pytest.mark.parametrize("name", ["cube", "white"])
def test_float32_against_float64_on_real_regressors(lbipe_dir, name):
    """The precision decision, measured: float64 is exact to ~1e-12 on the real sets;
    float32 (normal equations square kappa) loses ~kappa^2 * 6e-8 relative."""
    ds = load_lbipe(lbipe_dir / "data" / f"data_test_{name}.npz")
    rng = np.random.default_rng(8)
    sets = np.stack([rng.choice(ds.n_samples, 64, replace=False) for _ in range(200)])
    y = ds.tau - ds.tau_g
    r64 = _solve_sets(jnp.asarray(ds.A), jnp.asarray(y), None, jnp.asarray(sets))
    r32 = _solve_sets(jnp.asarray(ds.A, jnp.float32), jnp.asarray(y, jnp.float32), None,
                     jnp.asarray(sets))
    assert r32.x.dtype == jnp.float32 and r64.x.dtype == jnp.float64
    for b in range(0, 200, 20):
        idx = sets[b]
        ref = np.linalg.lstsq(ds.A[idx].reshape(-1, 4), y[idx].reshape(-1), rcond=None)[0]
        np.testing.assert_allclose(r64.x[b], ref, **LSTSQ_REAL_TOL)
    # The true x is recovered from the ground-truth torques (tau - tau_g = A x holds).
    np.testing.assert_allclose(r64.x, np.broadcast_to(ds.x[0], r64.x.shape), **TRUTH_TOL)
    m64, p64 = mass_and_com(r64.x)
    m32, p32 = mass_and_com(jnp.asarray(r32.x, jnp.float64))
    mass_rel = float(np.max(np.abs(m32 - m64) / m64))
    com_mm = float(np.max(np.linalg.norm(p32 - p64, axis=-1))) * 1e3
    kappa = float(np.max(np.asarray(r64.condition)))
    print(f"{name}: kappa <= {kappa:.1f}; float32 vs float64: mass {mass_rel:.2e} relative, "
          f"COM {com_mm:.2e} mm")
    assert kappa < 100
    # float32 is good to far below the method's own error (grams, millimetres) ...
    assert mass_rel < FLOAT32_MASS_RTOL and com_mm < FLOAT32_COM_MM
    # ... but float64 is the default: identification of near-singular sets needs it.
