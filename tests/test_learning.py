"""Learning pipeline: baselines, training through the WLS, tables, checkpoints, end to end."""

from __future__ import annotations

import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from support.asserts import assert_tree_equal
from support.compiles import compile_counter
from support.synthetic import feature_config as _fc
from support.synthetic import synthetic_samples as _synthetic
from support.synthetic import tiny_pair as _tiny_pair

from jaxinertia.app.estimate import estimate
from jaxinertia.app.reproduce import Scale, reproduce
from jaxinertia.baselines import fit_baselines
from jaxinertia.checkpoints import load_models, save_models
from jaxinertia.errors import FileFormatError, ModelFolderError, RobotMismatchError, UsageError
from jaxinertia.estimation import estimate_sets
from jaxinertia.evaluation import evaluate, mean_filter, sliding_windows
from jaxinertia.metrics import inertial_metrics
from jaxinertia.samples import Samples, load_samples, save_native
from jaxinertia.training import (
    TrainConfig,
    attention_loss,
    draw_sets,
    feature_config_from,
    split_validation,
    torque_predictions,
    train_torque_models,
)

# Tolerances, one per reference:
# The constants of the exact synthetic law (_synthetic) recovered by the baselines' fits:
# float64 least squares on noiseless data.
EXACT_LAW_RTOL = 1e-9  # the PE gains (~10-18 N m/rad)
EXACT_LAW_ATOL = 1e-10  # frictions and offsets [N m], and the PE torques
# Central finite differences (eps 1e-6, float64) of the attention loss.
FD_TOL = {"rtol": 1e-5, "atol": 1e-12}
# The attention loss of exact torques: zero up to float64 rounding of squared errors.
EXACT_LOSS_MAX = 1e-20
# Validation MSE recomputed here (float32 networks) against the one recorded while training.
HISTORY_RTOL = 1e-4
# numpy lstsq set by set (the Sensor estimates) and metrics computed by hand in numpy.
LSTSQ_TOL = {"rtol": 1e-8, "atol": 1e-12}
METRICS_RTOL = 1e-9


def test_baselines_recover_the_constants_of_an_exact_law():
    d = _synthetic(np.random.default_rng(0))
    b = fit_baselines(d.q_d, d.q, d.direction, d.current_tau, d.tau)
    np.testing.assert_allclose(b.pe_gain, [16.0, 18.0, 17.0, 10.0], rtol=EXACT_LAW_RTOL)
    np.testing.assert_allclose(b.pe_friction, [0.02, 0.05, 0.03, 0.01], atol=EXACT_LAW_ATOL)
    np.testing.assert_allclose(b.pe_offset, 0.01, atol=EXACT_LAW_ATOL)
    np.testing.assert_allclose(b.sensor_friction, -0.03, atol=EXACT_LAW_ATOL)
    np.testing.assert_allclose(b.sensor_offset, -0.004, atol=EXACT_LAW_ATOL)
    np.testing.assert_allclose(b.pe(d.q_d, d.q, d.direction), d.tau, atol=EXACT_LAW_ATOL)


def test_attention_loss_gradient_through_batched_wls_equals_finite_differences():
    rng = np.random.default_rng(1)
    B, M, N = 3, 16, 4
    A = jnp.asarray(rng.normal(size=(B, M, N, 4)))
    x_true = jnp.asarray(np.column_stack([[0.05, 0.0, 0.12],
                                          rng.normal(size=(3, 3)) * 1e-3]))
    y = jnp.einsum("bmnp,bp->bmn", A, x_true) + 0.05 * rng.normal(size=(B, M, N))
    w0 = jnp.asarray(rng.uniform(0.1, 1.0, (B, M, N)))

    # Compiled once (run eagerly, the loss and its gradient dispatch op by op: ~15 s on the
    # 2-core CI machine); the truth x is an argument so that both uses share the program.
    @jax.jit
    def loss(w, x):
        return attention_loss(w, A, y, x, w_mass=1.0, w_com=0.3)[0]

    g = jax.jit(jax.grad(loss))(w0, x_true)
    eps = 1e-6
    for idx in [(0, 0, 0), (1, 5, 2), (2, 15, 3), (0, 7, 1)]:
        e = jnp.zeros_like(w0).at[idx].set(eps)
        fd = (loss(w0 + e, x_true) - loss(w0 - e, x_true)) / (2 * eps)
        np.testing.assert_allclose(g[idx], fd, **FD_TOL)
    # The empty-gripper set (m = 0) carries no COM loss: its COM column cannot matter.
    x2 = x_true.at[1, 1:].set(0.5)
    assert loss(w0, x_true) == loss(w0, x2)


def test_attention_loss_is_zero_for_exact_torques_and_flags_singular_sets():
    rng = np.random.default_rng(2)
    A = rng.normal(size=(2, 8, 4, 4))
    x = np.array([[0.1, 1e-3, 2e-3, -3e-3], [0.06, 0, 1e-3, -1e-3]])
    y = np.einsum("bmnp,bp->bmn", A, x)
    A[1, :, :, 2] = 0.0  # set 1 cannot see the y coordinate of the COM
    loss, (e_m, e_p) = attention_loss(jnp.ones((2, 8, 4)), jnp.asarray(A), jnp.asarray(y),
                                      jnp.asarray(x), w_mass=1.0, w_com=0.3)
    assert float(loss) < EXACT_LOSS_MAX
    assert np.isfinite(e_m[0]) and np.isnan(e_m[1]) and np.isnan(e_p[1])


def test_the_attentions_torque_spread_scales_the_predicted_torques_not_the_objects():
    """``TrainConfig.attention_torque_spread``: a set's validation loss is the attention
    loss of the predicted torques scaled per joint, ``tau_hat * f - tau_g``, written here
    from its definition (the epoch adds ``(f - 1) tau_hat`` to ``tau_hat - tau_g``)."""
    from jaxinertia.networks import AttentionModel
    from jaxinertia.training import _attention_epoch

    rng = np.random.default_rng(7)
    S, N, V, M = 40, 4, 3, 16
    feats = jnp.asarray(rng.normal(size=(S, N, 3)))
    A = jnp.asarray(rng.normal(size=(S, N, 4)))
    x_obj = jnp.asarray(np.tile([0.08, 1e-3, -2e-3, 4e-3], (S, 1)))
    tau_g = jnp.asarray(rng.normal(size=(S, N)) * 0.5)  # the arm's own: large
    y = jnp.einsum("snp,sp->sn", A, x_obj) + 0.01 * rng.normal(size=(S, N))  # tau_hat - tau_g
    vsets = jnp.asarray(rng.choice(S, size=(V, M)))
    f = jnp.asarray(1 + 0.05 * rng.normal(size=(V, N)))
    model = AttentionModel(n_joints=N)
    params = jax.vmap(lambda k: model.init(k, feats[:1]))(jax.random.split(jax.random.key(0), 1))
    epoch = _attention_epoch(model, 1e-3, "all", 2, 1.0, 0.3, torque_spread=0.05)
    got = epoch.init(params, jnp.float64,
                     ((feats, A, x_obj, vsets, tau_g, f), y[None])).best_loss  # (K,)

    p0 = jax.tree.map(lambda a: a[0], params)
    tau_hat = y + tau_g
    want = attention_loss(model.apply(p0, feats[vsets]), A[vsets],
                          tau_hat[vsets] * f[:, None, :] - tau_g[vsets], x_obj[vsets[:, 0]],
                          w_mass=1.0, w_com=0.3)[0]
    plain = attention_loss(model.apply(p0, feats[vsets]), A[vsets], y[vsets],
                           x_obj[vsets[:, 0]], w_mass=1.0, w_com=0.3)[0]
    np.testing.assert_allclose(got[0], want, rtol=1e-9)
    assert abs(float(want) / float(plain) - 1) > 0.1  # the factors matter here


def test_attention_sets_are_uniform_ordered_choices_of_one_objects_samples():
    """Every ordered choice of k distinct samples equally likely, on both of draw_sets'
    paths (redrawn repeats where k is small against n, random keys where it is not):
    a chi-square over all ordered k-tuples within 6 standard deviations of its mean."""
    for n, k in ((12, 3), (5, 4)):  # 6 <= 2 n: redrawn repeats; 12 > 2 n: random keys
        object_id = np.repeat([7, 2], [n, n + 3])  # two objects, not sorted by id
        per_tuple = 100
        n_tuples = int(np.prod(np.arange(n - k + 1, n + 1)))
        sets = draw_sets(object_id, per_tuple * n_tuples, k, seed=0)
        assert sets.shape == (2 * per_tuple * n_tuples, k)
        first, second = sets[: per_tuple * n_tuples], sets[per_tuple * n_tuples:]
        assert (object_id[first] == 2).all() and (object_id[second] == 7).all()
        for part in (first, second):
            assert (np.sort(part, axis=1)[:, 1:] != np.sort(part, axis=1)[:, :-1]).all()
        pos = np.searchsorted(np.flatnonzero(object_id == 7), second)  # 0..n-1
        counts = np.unique(np.ravel_multi_index(pos.T, (n,) * k), return_counts=True)[1]
        assert len(counts) == n_tuples
        expected = per_tuple
        chi2 = ((counts - expected) ** 2 / expected).sum()
        dof = n_tuples - 1
        assert abs(chi2 - dof) < 6 * np.sqrt(2 * dof), (n, k, chi2, dof)
    large = draw_sets(np.zeros(3000, int), 2000, 100, seed=2)  # random keys, in pieces
    assert large.shape == (2000, 100) and large.max() < 3000
    assert (np.sort(large, axis=1)[:, 1:] != np.sort(large, axis=1)[:, :-1]).all()
    few = draw_sets(np.zeros(3, int), 50, 4, seed=1)  # 3 samples, sets of 4: replaced
    assert few.shape == (50, 4) and set(np.unique(few)) == {0, 1, 2}
    np.testing.assert_array_equal(draw_sets(object_id, 5, 3, seed=3),
                                  draw_sets(object_id, 5, 3, seed=3))


def test_attention_alone_needs_torque_models_to_keep():
    d = _synthetic(np.random.default_rng(3), n=40)
    with pytest.raises(UsageError, match="keeps the torque models"):
        train_torque_models(TrainConfig(n_models=1, trainable="attention"),
                            feature_config_from(d), d, d, jax.random.key(0), progress=False)


def test_torque_training_learns_and_keeps_the_best_validation_epoch():
    d = _synthetic(np.random.default_rng(3), n=1200)
    train, val = split_validation(d, 0.2, 0)
    assert train.n_samples + val.n_samples == d.n_samples
    assert not set(map(tuple, train.q)) & set(map(tuple, val.q))
    fc = feature_config_from(train)
    cfg = TrainConfig(n_models=2, torque_epochs=60, torque_lr=3e-3)
    seen = []
    res = train_torque_models(cfg, fc, train, val, jax.random.key(0), progress=False,
                              on_epoch=lambda e, losses: seen.append((e, losses)))
    hist = res.history  # (epochs, 2, K)
    assert hist.shape == (60, 2, 2)
    # on_epoch sees every epoch's (train, validation) losses, in order.
    assert [e for e, _ in seen] == list(range(60))
    np.testing.assert_array_equal(np.asarray([losses for _, losses in seen]), hist)
    assert np.all(hist[-1, 1] < 0.05 * hist[0, 1])  # validation MSE falls 20-fold
    best = np.argmin(hist[:, 1], axis=0)
    np.testing.assert_array_equal(res.best_epoch, best)
    # The kept parameters are the best epoch's: their validation MSE is the minimum.
    pred = np.asarray(torque_predictions(res.model, res.variables, fc, val))
    mse = np.mean(((pred - val.tau) / np.asarray(fc.tau_scale)) ** 2, axis=(1, 2))
    np.testing.assert_allclose(mse, hist[best, 1, [0, 1]], rtol=HISTORY_RTOL)
    # Two seeds, two different models.
    leaf = jax.tree_util.tree_leaves(res.variables)[0]
    assert not np.allclose(leaf[0], leaf[1])


def test_checkpoints_round_trip_and_refuse_another_robot(tmp_path):
    d = _synthetic(np.random.default_rng(4))
    b = fit_baselines(d.q_d, d.q, d.direction, d.current_tau, d.tau)
    pair = _tiny_pair()
    save_models(tmp_path / "m", pair, b, _fc(), robot="open_manipulator_x", extra={"a": 1})
    folder = load_models(tmp_path / "m", robot="open_manipulator_x")
    pair2, b2, fc2, cfg = folder.pair, folder.baselines, folder.features, folder.config
    assert folder.directory == (tmp_path / "m").absolute()
    # Bit for bit, field by field (a failure names the parameter, e.g.
    # .torque_vars['params']['joint0']['hidden']['kernel']): the variables, tau_scale and
    # both module definitions; all the baselines' and the feature configuration's fields.
    assert_tree_equal(pair2, pair, what="ModelPair after a round trip")
    assert pair2.torque_model == pair.torque_model and cfg["a"] == 1
    assert_tree_equal(b2, b, what="Baselines after a round trip")
    assert_tree_equal(fc2, _fc(), what="FeatureConfig after a round trip")
    with pytest.raises(RobotMismatchError, match="trained for robot 'open_manipulator_x'"):
        load_models(tmp_path / "m", robot="another_arm")
    with pytest.raises(ModelFolderError, match="not a jaxinertia model folder"):
        load_models(tmp_path / "nothing")


def test_tables_equal_a_direct_numpy_computation():
    rng = np.random.default_rng(5)
    d = _synthetic(rng, n=200, n_obj=2)
    b = fit_baselines(d.q_d, d.q, d.direction, d.current_tau, d.tau)
    objs = [o.replace(current_tau=o.current_tau + rng.normal(size=o.q.shape) * 0.02)
            for o in d.by_object()]
    assert [o.name for o in objs] == ["o0", "o1"]
    sets = [np.stack([rng.choice(o.n_samples, 20, replace=False) for _ in range(7)])
            for o in objs]
    pair = _tiny_pair()
    res = evaluate(objs, sets, pair=pair, baselines=b, fc=_fc(), l_max=[0.07, 0.08])
    for o, ds in enumerate(objs):
        # Sensor by hand: numpy lstsq with identity weights, set by set.
        tau_hat = ds.current_tau - ds.direction * np.asarray(b.sensor_friction) + np.asarray(
            b.sensor_offset)
        xs = np.stack([np.linalg.lstsq(ds.A[i].reshape(-1, 4),
                                       (tau_hat - ds.tau_g)[i].reshape(-1), rcond=None)[0]
                       for i in sets[o]])
        np.testing.assert_allclose(res["estimates"]["Sensor"][o], xs, **LSTSQ_TOL)
        m, p = ds.mass, ds.com
        e_m = xs[:, 0] - m
        e_p = np.linalg.norm(xs[:, 1:] / xs[:, :1] - p, axis=1)
        got = res["objects"][ds.name]["Sensor"]
        assert got["mass_MAE_g"] == pytest.approx(np.mean(np.abs(e_m)) * 1e3, rel=METRICS_RTOL)
        assert got["com_NMAE_pct"] == pytest.approx(
            100 * np.mean(e_p) / [0.07, 0.08][o], rel=METRICS_RTOL)
        assert got["com_NRMSE_pct"] == pytest.approx(
            100 * np.sqrt(np.mean(e_p**2)) / [0.07, 0.08][o], rel=METRICS_RTOL)
        # T-A through the networks equals inertial_metrics of its own estimates.
        x_ta = res["estimates"]["T-A"][o].reshape(-1, 4)
        assert res["objects"][ds.name]["T-A"] == inertial_metrics(x_ta, ds.x[0],
                                                                   [0.07, 0.08][o])
    # Table II (PE) by hand, over all samples of both objects.
    tau = np.concatenate([o.tau for o in objs])
    pe = np.concatenate([np.asarray(b.pe(o.q_d, o.q, o.direction)) for o in objs])
    mae = np.mean(np.abs(pe - tau), axis=0) * 1e3
    np.testing.assert_allclose(res["torque"]["PE"]["MAE_Nmm"], mae, rtol=METRICS_RTOL)


def _estimate_inputs(rng, S, O=2, B=3, M=7):
    """features (O, S, N, 4) float32, A (O, S, N, 4), tau_g (O, S, N), sets (O, B, M)."""
    sets = [np.stack([rng.choice(S, M, replace=False) for _ in range(B)]) for _ in range(O)]
    return (jnp.asarray(rng.normal(size=(O, S, 4, 4)), jnp.float32),
            jnp.asarray(rng.normal(size=(O, S, 4, 4)) * [1.0, 0.1, 0.1, 0.1]),
            jnp.asarray(rng.normal(size=(O, S, 4)) * 0.2), jnp.asarray(np.stack(sets)))


def test_estimate_sets_compiles_once_per_shape():
    """Other model pairs (built apart) and other data of the same shapes reuse the program;
    a new shape compiles again (so the counter counts). Shapes not used elsewhere here."""
    rng = np.random.default_rng(8)
    with compile_counter("estimate_sets") as seen:
        a = estimate_sets(_tiny_pair(seed=0), *_estimate_inputs(rng, 29))
        b = estimate_sets(_tiny_pair(seed=1), *_estimate_inputs(rng, 29))
    assert seen.traces["estimate_sets"] == 1 and seen.compiles["estimate_sets"] == 1, seen
    assert not np.allclose(a.tau_hat, b.tau_hat) and not np.allclose(a.TA.x, b.TA.x)
    with compile_counter("estimate_sets") as seen:
        estimate_sets(_tiny_pair(seed=0), *_estimate_inputs(rng, 31))
    assert seen.compiles["estimate_sets"] == 1, seen


def test_evaluate_compiles_once_for_new_objects_of_the_same_shapes():
    """The evaluator's two jitted programs, estimate_sets (T, T-A) and the identity-weight
    solve_sets of the baselines (identification.identity_solves, Sensor and PE), compile once
    for two evaluations of other objects with the same sample and set counts."""
    rng = np.random.default_rng(9)
    pair = _tiny_pair()
    with compile_counter("estimate_sets", "identity_solves") as seen:
        for seed in (10, 11):
            d = _synthetic(np.random.default_rng(seed), n=90, n_obj=2)
            b = fit_baselines(d.q_d, d.q, d.direction, d.current_tau, d.tau)
            objs = d.by_object()
            sets = [np.stack([rng.choice(o.n_samples, 11, replace=False) for _ in range(5)])
                    for o in objs]
            evaluate(objs, sets, pair=pair, baselines=b, fc=_fc(), l_max=[0.07, 0.08])
    assert seen.compiles == {"estimate_sets": 1, "identity_solves": 1}, seen


def test_sliding_windows_and_mean_filter():
    w = sliding_windows(10, 4)
    assert w.shape == (7, 4) and w[0].tolist() == [0, 1, 2, 3] and w[-1].tolist() == [6, 7, 8, 9]
    x = np.arange(10.0)
    f = mean_filter(x, 4)
    assert f[5] == pytest.approx(np.mean(x[3:7]))
    assert f[0] == pytest.approx(np.mean(x[0:2]))
    with pytest.raises(ValueError):
        sliding_windows(3, 4)


def _write(path, d: Samples, drop=()):
    """A native file of ``d``; ``drop`` leaves fields out (as a broken writer would)."""
    save_native(path, d, {"robot": "open_manipulator_x"})
    if drop:
        with np.load(path) as z:
            fields = {k: z[k] for k in z.files if k not in drop}
        np.savez_compressed(path, **fields)
    return path


def test_native_file_round_trips_field_by_field(tmp_path):
    d = _synthetic(np.random.default_rng(6), n=50)
    loaded, meta = load_samples(_write(tmp_path / "a.npz", d))
    assert meta["robot"] == "open_manipulator_x" and meta["objects"] == list(d.names)
    assert_tree_equal(loaded, d, what="Samples after save_native/load_samples")
    unknown, _ = load_samples(_write(tmp_path / "u.npz", d.without_truth()), need_truth=False)
    assert_tree_equal(unknown, d.without_truth(), what="unknown-object Samples")


def test_bad_sample_files_give_one_clear_error(tmp_path):
    d = _synthetic(np.random.default_rng(6), n=50)
    with pytest.raises(FileFormatError, match=r"\[A\]: missing"):
        load_samples(_write(tmp_path / "a.npz", d, drop=("A",)))
    bad = d.replace(direction=d.direction * 0.5)
    with pytest.raises(FileFormatError, match=r"\[direction\]: must be"):
        load_samples(_write(tmp_path / "b.npz", bad))
    # An unknown object has no tau: fine for estimation (truth None), refused for training.
    unknown = d.replace(tau=np.full_like(d.tau, np.nan))
    p = _write(tmp_path / "c.npz", unknown)
    est, _ = load_samples(p, need_truth=False)
    assert est.n_samples == 50 and est.tau is None and est.x is None and not est.known
    with pytest.raises(FileFormatError, match=r"\[tau\]: holds non-finite"):
        load_samples(p)
    # Without ground truth at all (as collected from an unknown object).
    p = _write(tmp_path / "d.npz", d.without_truth())
    assert load_samples(p, need_truth=False)[0].tau is None
    with pytest.raises(FileFormatError, match=r"\[tau\]: missing"):
        load_samples(p)


def test_estimate_refuses_a_singular_sample_set(tmp_path):
    d = _synthetic(np.random.default_rng(7), n=64, n_obj=1)
    d = d.replace(A=np.repeat(d.A[:1], 64, axis=0) * [1, 1, 0, 1])  # no y information
    p = _write(tmp_path / "s.npz", d.without_truth())
    b = fit_baselines(d.q_d, d.q, d.direction, d.current_tau, d.q_d)
    save_models(tmp_path / "m", _tiny_pair(), b, _fc(), robot="open_manipulator_x")
    with pytest.raises(UsageError, match="do not determine mass and COM"):
        estimate(tmp_path / "m", p)


def test_tiny_end_to_end_report_numbers_come_from_the_run(tmp_path, small_lbipe_dir):
    """simulate -> train -> evaluate -> continuous -> sim-to-real -> report, tiny.

    The sizes are test_folds' (training samples and configuration, the real files cut to
    their first samples), so that the programs compiled there serve here: what is checked,
    that the report's numbers are the run's, does not depend on them."""
    scale = Scale(planning=False, random_per_load=40, test_per_object=70,
                  # one chunk of the continuous run (it steps 128 samples at a time)
                  continuous_samples=128, switch_every=32, n_sets=20,
                  fold_calibration_iterations=0,  # the folds: tests/test_folds.py
                  real_finetune_samples=30,
                  train=TrainConfig(n_models=2, torque_epochs=5, attention_epochs=2,
                                    attention_sets=8, attention_val_sets=4, set_size=64,
                                    val_fraction=0.2))
    res = reproduce(tmp_path / "run", scale=scale, lbipe_dir=small_lbipe_dir, progress=False)
    run = Path(tmp_path / "run")
    tables = json.loads((run / "tables.json").read_text())
    report = (run / "report.md").read_text()
    for name in ("cube", "red", "white", "black"):
        for m in ("Sensor", "PE", "T", "T-A"):
            v = tables["simulated"]["objects"][name][m]["com_NMAE_pct"]
            assert np.isfinite(v)
            assert f"| {name} | {m} | " in report and f"{v:.2f}" in report
    assert res["simulated"]["objects"] == tables["simulated"]["objects"]
    for png in ("training.png", "table1_sim.png", "continuous.png", "table1_real.png"):
        assert (run / png).stat().st_size > 10_000
    # Sim-to-real ran on the real files, beside the released models on the same sets.
    assert set(tables["real"]["ours"]["objects"]) == {"cube", "white"}
    assert set(tables["real"]["released"]) == {"cube", "white"}
    # The models for a new real object: fine-tuned on 30 samples of every real file and as
    # many of each of the four loads of the run's simulated random data (the anchor).
    ft = tables["real_finetuned"]
    assert set(ft["objects"]) == {"cube", "white"}
    assert ft["samples"]["train"] + ft["samples"]["validation"] == 2 * 30 + 4 * 30
    assert ft["real_samples"] == 30 and ft["anchor"] == ["train_random.npz"]
    config = json.loads((run / "models_real" / "config.json").read_text())
    assert config["torque_model"]["kind"] == "physical"
    assert config["training"]["trainable"] == "servo" and config["samples_per_object"] == 30
    # Fine-tuned beside it and written with the recipe's strength (the default recipe's: 1).
    assert Path(config["copied_from"]).name == "models_real_finetuned_30"
    assert config["session"]["strength"] == 1.0
    assert {Path(d["file"]).name for d in config["data"]} == {
        "data_test_cube.npz", "data_test_white.npz", "train_random.npz"}
    assert "## Models for a new real object" in report and "**not held out**" in report
    assert ("on 30 real samples of each of cube, white and as many of each load of the run's "
            f"simulated train_random.npz ({ft['samples']['train']} + "
            f"{ft['samples']['validation']} (validation) in all)") in report
    v = ft["objects"]["white"]["T-A"]["mass_NMAE_pct"]
    assert np.isfinite(v) and f"{v:.2f}" in report
    # The models load back and estimate an object from the run's own test file.
    _, meta = load_samples(run / "data" / "test.npz")
    assert meta["request"]["n"] == 70
    assert set(tables["continuous"]) == {"Sensor", "PE", "T", "T-A"}
