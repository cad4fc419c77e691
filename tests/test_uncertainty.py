"""Covariance, standard errors, intervals and the identifiability gate, against Monte-Carlo
and numpy references on synthetic linear data with known noise."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from support.compiles import compile_counter
from support.synthetic import feature_config, synthetic_samples, tiny_pair

from jaxinertia.app.cli import main
from jaxinertia.app.estimate import estimate
from jaxinertia.app.report import coverage_table
from jaxinertia.app.reproduce import plot_interval_width
from jaxinertia.baselines import fit_baselines
from jaxinertia.checkpoints import save_models
from jaxinertia.design import regressors
from jaxinertia.errors import UsageError
from jaxinertia.open_manipulator_x import ARM as OMX
from jaxinertia.samples import Samples, save_native
from jaxinertia.uncertainty import (
    SetUncertainty,
    coverage,
    fit_inflation,
    identifiability,
    interval_coverage,
    mass_com_covariance,
    set_uncertainty,
    standard_errors,
    validation_torque_error,
    z_of,
)

# Monte-Carlo references: the acceptance, 5 % on standard errors. With R replicates
# the MC standard deviation itself is uncertain by ~1/sqrt(2R) (1.1 % at R = 4000).
MC_RTOL = 0.05
# Closed forms against numpy's formulas on the same numbers (float64 rounding only).
EXACT_RTOL = 1e-9
# Coverage of exact Gaussian intervals over 20000 draws: binomial sd 0.15-0.33 %.
COVERAGE_ATOL = 0.012


def _problem(rng, M=24, N=4):
    """A realistic set: the OMX regressors at M random poses, a 60 g object, per-joint
    noise levels and attention-like weights (fixed, unequal across joints)."""
    q = rng.uniform([-0.5, -0.85, 0.2, -0.35], [0.5, -0.2, 0.85, 0.35], (M, N))
    A = regressors(q, robot=OMX.robot(), tag=OMX.tag_in_ee)
    x = np.array([0.060, 0.060 * 0.004, 0.060 * -0.002, 0.060 * 0.020])
    sigma = np.array([0.010, 0.025, 0.015, 0.008])
    w = rng.uniform(0.2, 1.0, (M, N)) * np.array([0.15, 0.05, 0.05, 0.75])
    return A, x, sigma, w


def _monte_carlo(rng, A, x, sigma, w, R):
    """R noisy replicates y = A x + e; their WLS estimates solved independently in numpy
    (normal equations with np.linalg.solve), and the replicates laid out as R sets."""
    M, N, _ = A.shape
    e = rng.normal(size=(R, M, N)) * sigma
    y = np.einsum("mnp,p->mn", A, x)[None] + e
    G = np.einsum("mnp,mn,mnq->pq", A, w, A)
    b = np.einsum("mnp,mn,rmn->rp", A, w, y)
    x_hat = np.linalg.solve(G[None], b[..., None])[..., 0]
    return y, x_hat


def test_covariance_matches_monte_carlo_on_linear_data_with_known_noise():
    """Replicates of one set (same poses, fresh noise) as the K 'model pairs' of one object:
    the mean of the residual-based covariance estimates must match the Monte-Carlo
    covariance of the estimates (standard errors within 5 %), and so must the delta-method
    errors of mass and COM."""
    rng = np.random.default_rng(0)
    A, x, sigma, w = _problem(rng)
    R = 4000
    y, x_hat = _monte_carlo(rng, A, x, sigma, w, R)
    M, N, _ = A.shape
    u = set_uncertainty(jnp.asarray(A)[None], jnp.zeros((1, M, N)), jnp.asarray(y)[None],
                        jnp.broadcast_to(jnp.asarray(w), (1, R, M, N)),
                        jnp.arange(M)[None, None], jnp.asarray(x_hat)[None, :, None],
                        jnp.zeros(N))
    predicted = np.asarray(u.cov_noise[0, 0])  # the mean over the replicates' estimates
    mc = np.cov(x_hat.T)
    np.testing.assert_allclose(np.sqrt(np.diag(predicted)), np.sqrt(np.diag(mc)), rtol=MC_RTOL)
    corr = predicted / np.sqrt(np.outer(np.diag(predicted), np.diag(predicted)))
    corr_mc = mc / np.sqrt(np.outer(np.diag(mc), np.diag(mc)))
    np.testing.assert_allclose(corr, corr_mc, atol=MC_RTOL)
    # Mass and COM (nonlinear in x) by the delta method against their MC spread.
    se = np.asarray(standard_errors(x, predicted))
    mc_mc = np.column_stack([x_hat[:, 0], x_hat[:, 1:] / x_hat[:, :1]])
    np.testing.assert_allclose(se, mc_mc.std(axis=0, ddof=1), rtol=MC_RTOL)
    # The ensemble term of the same call is the replicates' sample covariance.
    np.testing.assert_allclose(np.asarray(u.cov_ensemble[0, 0]), mc, rtol=EXACT_RTOL)
    # Per-joint levels recovered (RMS over replicates of the residual estimates).
    np.testing.assert_allclose(np.asarray(u.noise_std[0, 0]), sigma, rtol=MC_RTOL)


def test_one_set_covariance_against_numpy_formulas():
    """One set: the sandwich with the residual levels (or the floor where it is larger),
    the ensemble covariance with ddof 1, and their sum, from numpy on the same numbers."""
    rng = np.random.default_rng(1)
    A, x, sigma, w = _problem(rng, M=30)
    M, N, _ = A.shape
    K = 3
    y, _ = _monte_carlo(rng, A, x, sigma, w, K)
    x_k = np.stack([np.linalg.lstsq(np.sqrt(w).reshape(-1, 1) * A.reshape(-1, 4),
                                    (np.sqrt(w) * y[k]).reshape(-1), rcond=None)[0]
                    for k in range(K)])
    floor = np.array([0.0, 0.0, 0.05, 0.0])  # above joint 3's residual level
    u = set_uncertainty(jnp.asarray(A)[None], jnp.zeros((1, M, N)), jnp.asarray(y)[None],
                        jnp.broadcast_to(jnp.asarray(w), (1, K, M, N)),
                        jnp.arange(M)[None, None], jnp.asarray(x_k)[None, :, None],
                        jnp.asarray(floor))
    G = np.einsum("mnp,mn,mnq->pq", A, w, A)
    Gi = np.linalg.inv(G)
    covs = []
    for k in range(K):
        r = y[k] - np.einsum("mnp,p->mn", A, x_k[k])
        H = np.einsum("mnp,pq,mnq,mn->mn", A, Gi, A, w)  # hat matrix diagonal
        var = np.maximum((r**2).sum(0) / (M - H.sum(0)), floor**2)
        covs.append(Gi @ np.einsum("mnp,mn,n,mnq->pq", A, w**2, var, A) @ Gi)
    ens = np.cov(x_k.T, ddof=1)
    np.testing.assert_allclose(np.asarray(u.cov_noise[0, 0]), np.mean(covs, axis=0),
                               rtol=EXACT_RTOL)
    np.testing.assert_allclose(np.asarray(u.cov_ensemble[0, 0]), ens, rtol=EXACT_RTOL)
    np.testing.assert_allclose(np.asarray(u.cov[0, 0]), np.mean(covs, axis=0) + ens,
                               rtol=EXACT_RTOL)
    np.testing.assert_allclose(np.asarray(u.x[0, 0]), x_k.mean(axis=0), rtol=EXACT_RTOL)
    assert np.asarray(u.floor_used[0, 0]).tolist() == [0.0, 0.0, 1.0, 0.0]
    # One model: no ensemble term.
    u1 = set_uncertainty(jnp.asarray(A)[None], jnp.zeros((1, M, N)), jnp.asarray(y[:1])[None],
                         None, jnp.arange(M)[None, None], jnp.asarray(x_k[:1])[None, :, None],
                         jnp.zeros(N))
    assert np.all(np.asarray(u1.cov_ensemble) == 0)


def test_delta_method_against_numpy_jacobian():
    rng = np.random.default_rng(2)
    x = np.array([0.08, 0.08 * 0.01, 0.08 * -0.02, 0.08 * 0.03])
    L = rng.normal(size=(4, 4)) * 1e-3
    cov = L @ L.T
    v, c = (np.asarray(a) for a in mass_com_covariance(x, cov))
    m = x[0]
    J = np.zeros((4, 4))
    J[0, 0] = 1
    J[1:, 0] = -x[1:] / m**2
    J[1:, 1:] = np.eye(3) / m
    np.testing.assert_allclose(v, [m, *(x[1:] / m)], rtol=EXACT_RTOL)
    np.testing.assert_allclose(c, J @ cov @ J.T, rtol=EXACT_RTOL)


def test_coverage_and_inflation_on_gaussian_errors():
    """Estimates drawn from N(truth, cov) cover at the nominal rates; drawn with twice the
    stated spread, the fitted inflation factor is 2 and restores the rate."""
    rng = np.random.default_rng(3)
    B = 20000
    truth = np.array([0.1, 0.1 * 0.01, 0.1 * -0.01, 0.1 * 0.02])
    L = np.diag([2e-3, 1e-4, 2e-4, 1.5e-4])
    cov = np.broadcast_to(L @ L.T, (B, 4, 4))
    x = truth + rng.normal(size=(B, 4)) @ L.T
    c = coverage(x, cov, truth)
    for level in (0.68, 0.95):
        assert c[level]["mass"] == pytest.approx(level, abs=COVERAGE_ATOL)
        assert c[level]["com"] == pytest.approx(level, abs=COVERAGE_ATOL)
        assert c[level]["com_region"] == pytest.approx(level, abs=COVERAGE_ATOL)
    wide = truth + 2 * rng.normal(size=(B, 4)) @ L.T
    assert coverage(wide, cov, truth)[0.95]["mass"] < 0.7
    kappa = fit_inflation(wide, cov, truth)
    np.testing.assert_allclose(kappa, 2.0, rtol=0.05)
    inflated = coverage(wide, cov, truth, inflate=kappa)[0.95]
    assert inflated["mass"] == pytest.approx(0.95, abs=COVERAGE_ATOL)
    assert inflated["com"] == pytest.approx(0.95, abs=COVERAGE_ATOL)
    # Only the mass too wide: the COM's factor stays 1.
    mixed = np.column_stack([wide[:, :1], x[:, 1:]])
    k = fit_inflation(mixed, cov, truth)
    assert k[0] == pytest.approx(2.0, rel=0.05) and k[1] == pytest.approx(1.0, rel=0.05)
    assert z_of(0.95) == pytest.approx(1.959964, rel=1e-6)


def test_identifiability_one_pose_is_singular_and_predictions_match_numpy():
    rng = np.random.default_rng(4)
    A, x, sigma, _ = _problem(rng, M=40)
    one_pose = np.repeat(A[:1], 40, axis=0)
    r = identifiability(jnp.asarray(one_pose), jnp.arange(40)[None], jnp.asarray(sigma),
                        jnp.asarray(x))
    assert bool(r.rank_deficient[0]) and np.isinf(r.condition[0])
    assert np.all(np.isnan(np.asarray(r.se)))
    r = identifiability(jnp.asarray(A), jnp.arange(40)[None], jnp.asarray(sigma), jnp.asarray(x))
    assert not bool(r.rank_deficient[0])
    G = np.einsum("mnp,n,mnq->pq", A, 1 / sigma**2, A)
    np.testing.assert_allclose(np.asarray(r.cov[0]), np.linalg.inv(G), rtol=1e-8)
    np.testing.assert_allclose(np.asarray(r.se[0]),
                               np.asarray(standard_errors(x, np.linalg.inv(G))), rtol=1e-8)
    Aw = (A / sigma[None, :, None]).reshape(-1, 4)
    np.testing.assert_allclose(r.condition[0], np.linalg.cond(Aw / np.linalg.norm(Aw, axis=0)),
                               rtol=1e-6)


def test_set_uncertainty_compiles_once():
    rng = np.random.default_rng(5)
    A, x, sigma, w = _problem(rng, M=20)
    M, N, _ = A.shape

    def call(seed):
        y, x_hat = _monte_carlo(np.random.default_rng(seed), A, x, sigma, w, 3)
        return set_uncertainty(jnp.asarray(A)[None], jnp.zeros((1, M, N)), jnp.asarray(y)[None],
                               jnp.broadcast_to(jnp.asarray(w), (1, 3, M, N)),
                               jnp.arange(M)[None, None], jnp.asarray(x_hat)[None, :, None],
                               jnp.zeros(N))

    with compile_counter("set_uncertainty") as seen:
        a, b = call(6), call(7)
    assert seen.compiles["set_uncertainty"] == 1, seen
    assert not np.allclose(a.cov, b.cov)


def test_the_answers_post_processing_is_one_program_and_nests_on_a_gpu(monkeypatch):
    """Standard errors, intervals and z-scores run as one program each per shape (called
    eagerly, each of their operations compiled a program of its own), and inside another
    program being traced (``identifiability`` calls ``standard_errors``) they become part
    of it: on a GPU their own programs carry compiler options, which JAX refuses on a
    nested jit (session 32's first GPU run stopped there)."""
    from jaxinertia.uncertainty import intervals, z_scores  # noqa: PLC0415

    rng = np.random.default_rng(9)
    x = np.array([0.05, 0.05 * 0.01, 0.05 * 0.002, -0.05 * 0.02])
    L = rng.normal(size=(6, 4, 4)) * 1e-3
    cov = L @ np.swapaxes(L, -1, -2) + 1e-8 * np.eye(4)
    with compile_counter("standard_errors", "_intervals", "z_scores", "matmul",
                         "concatenate") as seen:
        se = np.asarray(standard_errors(x, cov))
        _, lo, hi = (np.asarray(a) for a in intervals(x, cov, 0.95))
        z, _ = z_scores(x, cov, x)
    assert seen.compiles["standard_errors"] == 1 and seen.compiles["_intervals"] == 1
    assert seen.compiles["matmul"] == seen.compiles["concatenate"] == 0, seen
    np.testing.assert_allclose(hi - lo, 2 * 1.959963984540054 * se, rtol=1e-5)
    np.testing.assert_array_equal(np.asarray(z), 0.0)
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")  # the GPU's options
    nested = jax.jit(lambda c: standard_errors(x, c))(cov)
    np.testing.assert_allclose(np.asarray(nested), se, rtol=1e-6)


def test_validation_error_is_one_program_per_shape_and_equals_the_models_predictions():
    """After every training and fine-tuning: one jitted program for the K models' torques
    (op by op, an eager vmap compiled every product and sum anew for each new sample count:
    a full GPU run's fine-tunings waited on them, docs/benchmarks.md "Session 27")."""
    pair, fc = tiny_pair(K=3), feature_config()
    val = synthetic_samples(np.random.default_rng(8), n=37, n_obj=2)
    with compile_counter("_predict_stacked", "dot_general") as seen:
        err = validation_torque_error(pair, fc, val)
    assert seen.compiles == {"_predict_stacked": 1}, seen
    # The same numbers as each model's own prediction, pooled as the docstring says.
    from jaxinertia.estimation import predict_torques  # noqa: PLC0415
    from jaxinertia.features import featurize  # noqa: PLC0415
    feats = jnp.asarray(featurize(fc, jnp.asarray(val.q), val.q_d, val.direction,
                                  val.current_tau), jnp.float32)
    tau_hat = np.stack([np.asarray(predict_torques(
        pair.torque_model, jax.tree_util.tree_map(lambda a, i=i: a[i], pair.torque_vars),
        feats, pair.tau_scale), np.float64) for i in range(3)])
    want = np.sqrt(np.mean((tau_hat - val.tau[None]) ** 2, axis=(0, 1)))
    np.testing.assert_allclose(err, want, rtol=1e-5)


# ---- estimate: intervals, covariance, and the identifiability gate ----------------------


@pytest.fixture
def model_folder(tmp_path):
    d = synthetic_samples(np.random.default_rng(1))
    b = fit_baselines(d.q_d, d.q, d.direction, d.current_tau, d.tau)
    return save_models(tmp_path / "m", tiny_pair(), b, feature_config(),
                       robot="open_manipulator_x")


def _omx_samples(q: np.ndarray) -> Samples:
    """Samples at goals q (S, 4) whose A is the arm's regressor there (a 60 g object)."""
    rng = np.random.default_rng(6)
    S = len(q)
    A = regressors(q, robot=OMX.robot(), tag=OMX.tag_in_ee)
    x = np.array([[0.060, 0.060 * 0.004, 0.060 * -0.002, 0.060 * 0.020]])
    tau_g = rng.normal(size=(S, 4)) * 0.2
    tau = tau_g + np.einsum("snp,p->sn", A, x[0]) + rng.normal(size=(S, 4)) * 0.005
    s = rng.choice([-1.0, 1.0], (S, 4))
    return Samples(q_d=q + tau / 17.0, q=q, direction=s, current_tau=tau, tau=tau, tau_g=tau_g,
                   A=A, object_id=np.zeros(S, np.int64), x=x, names=("thing",))


def _write(path, samples: Samples) -> str:
    save_native(path, samples.without_truth(), {"robot": "open_manipulator_x"})
    return str(path)


def test_estimate_refuses_all_samples_at_one_pose(model_folder, tmp_path, capsys):
    q = np.repeat(np.array([[0.1, -0.5, 0.5, 0.1]]), 80, axis=0)
    path = _write(tmp_path / "one.npz", _omx_samples(q))
    with pytest.raises(UsageError, match="poses do not determine mass and COM"):
        estimate(model_folder, path)
    assert main(["estimate", "--models", str(model_folder), "--samples", path]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "1 distinct pose(s) in 80 samples" in err[0], err


def test_estimate_reports_standard_errors_intervals_and_covariance(model_folder, tmp_path,
                                                                   capsys):
    rng = np.random.default_rng(7)
    q = rng.uniform([-0.5, -0.85, 0.2, -0.35], [0.5, -0.2, 0.85, 0.35], (120, 4))
    path = _write(tmp_path / "s.npz", _omx_samples(q))
    out_json = tmp_path / "e.json"
    assert main(["estimate", "--models", str(model_folder), "--samples", path,
                 "--json", str(out_json)]) == 0
    printed = capsys.readouterr().out
    assert "+-" in printed and "95 %" in printed and "predicted standard error" in printed
    res = json.loads(out_json.read_text())
    obj = res["objects"]["thing"]
    assert res["torque_error_floor"]["Nm"] is None  # saved without training data
    for m, r in obj["methods"].items():
        if not r["ok"]:
            continue
        cov = np.asarray(r["covariance_x"])
        assert cov.shape == (4, 4) and np.allclose(cov, cov.T)
        assert np.all(np.linalg.eigvalsh(cov) > 0), m
        se = np.asarray(standard_errors(np.r_[r["mass_kg"], r["mass_kg"] * np.asarray(
            r["com_tag_m"])], cov))
        np.testing.assert_allclose([r["mass_se_kg"], *r["com_se_m"]], se, rtol=1e-9)
        lo, hi = r["interval_95"]["mass_kg"]
        assert lo == pytest.approx(r["mass_kg"] - z_of(0.95) * se[0], rel=1e-9)
        assert hi == pytest.approx(r["mass_kg"] + z_of(0.95) * se[0], rel=1e-9)
        assert (r["interval_68"]["mass_kg"][1] - r["interval_68"]["mass_kg"][0]) < (hi - lo)
    ident = obj["identifiability"]
    assert ident["predicted_com_se_m"][2] > 0 and np.isfinite(ident["condition"])
    # A COM threshold below the predicted error refuses; above it, answers.
    limit = min(ident["predicted_com_se_m"]) / 2
    assert main(["estimate", "--models", str(model_folder), "--samples", path,
                 "--max-com-se", f"{limit:.6f}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--max-com-se" in err[0], err
    assert main(["estimate", "--models", str(model_folder), "--samples", path,
                 "--max-com-se", "1.0"]) == 0


def test_coverage_table_and_plot_from_interval_coverage(tmp_path):
    """The report's table shows interval_coverage()'s numbers; the plot is written."""
    rng = np.random.default_rng(8)
    B = 400
    truths = np.array([[0.05, 0.05 * 0.01, 0.0, 0.05 * 0.02], [0.09, 0.0, 0.09 * 0.01, 0.0]])
    L = np.diag([2e-3, 1e-4, 2e-4, 1.5e-4])
    x = truths[:, None] + rng.normal(size=(2, B, 4)) @ L.T
    cov = np.broadcast_to(L @ L.T, (2, B, 4, 4))
    z4 = np.zeros((2, B, 4))
    u = SetUncertainty(jnp.asarray(x), jnp.asarray(cov), jnp.asarray(cov), jnp.zeros_like(cov),
                       jnp.asarray(z4), jnp.asarray(z4))
    objects = [Samples(q_d=np.zeros((1, 4)), q=np.zeros((1, 4)), direction=np.ones((1, 4)),
                       current_tau=np.zeros((1, 4)), tau_g=np.zeros((1, 4)),
                       A=np.zeros((1, 4, 4)), object_id=np.zeros(1, np.int64), x=t[None],
                       tau=np.zeros((1, 4)), names=(name,))
               for t, name in zip(truths, ("a", "b"))]
    cal = interval_coverage(objects, {"T-A": u})
    for o, name in enumerate(("a", "b")):
        c = cal["objects"][name]["T-A"]
        assert c == coverage(x[o], cov[o], truths[o]) | {"median_se": c["median_se"],
                                                          "rms_error": c["rms_error"]}
    table = coverage_table(cal["objects"], "t", methods=("T-A",))
    c = cal["objects"]["a"]["T-A"]
    assert f"| a | T-A | {100 * c[0.68]['mass']:.1f} | {100 * c[0.95]['mass']:.1f} |" in table
    assert "| average | T-A |" in table
    png = plot_interval_width(cal, tmp_path / "c.png", "t")
    assert png.stat().st_size > 10_000
