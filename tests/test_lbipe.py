"""The released models on the real data: golden outputs, Table I/III, the CLI, bad input."""

from __future__ import annotations

import json
import shutil
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from support.asserts import assert_tree_close, assert_tree_equal
from support.reference import reference_loop

from jaxinertia.app.cli import main as cli_main
from jaxinertia.app.pipeline import load_real, released_benchmark
from jaxinertia.errors import FileFormatError, WeightsError
from jaxinertia.estimation import predict_torques, predict_weights
from jaxinertia.evaluation import stack
from jaxinertia.features import LBIPE_FEATURES, featurize
from jaxinertia.lbipe import find_layout, load_golden, load_released_models
from jaxinertia.metrics import error_metrics, inertial_metrics
from jaxinertia.networks import load_released_pair
from jaxinertia.samples import load_lbipe, load_samples, save_lbipe

OBJECTS = ["cube", "white"]

# Tolerances, one per reference (max |error| unless relative):
# golden/*.npz, the authors' code in PyTorch float32 on the same files and weights:
GOLDEN_FEATURES_TOL = 1e-6  # network inputs (O(1), float32)
GOLDEN_TORQUE_TOL = 1e-5  # [N m] torques of the ten torque models (float32, XLA vs PyTorch)
GOLDEN_WEIGHTS_TOL = 1e-6  # attention weights on the golden features
# Attention weights from our own features, which differ from the authors' by <= 5e-7 (the
# README's rounded qe_scale).
OWN_FEATURES_WEIGHTS_TOL = 2e-6
# Softmax weights sum to one (float32).
WEIGHTS_SUM_TOL = 1e-6
# golden/reference_metrics.json (Table I/III over the golden sets, float64 from the float32
# model outputs), relative; and its L_max, the README's diagonals to 6 digits, relative.
REFERENCE_METRICS_RTOL = 1e-3
L_MAX_RTOL = 1e-6
# The authors' per-set numpy loop (support/reference.py): the networks run in float32 on
# both sides (XLA vs numpy summation order: ~1e-7 relative in tau_hat), which moves m*p
# (~1e-4 kg m) by ~1e-8: 1e-7 kg m is 0.002 mm.
LOOP_TOL = {"rtol": 1e-5, "atol": 1e-7}
# Other random sets (the authors' layout draws its own), same models and data: the same
# Table I numbers to a few per cent.
OTHER_SETS_RTOL = 0.1


@pytest.fixture(scope="module")
def lbipe_run(lbipe_dir):
    return released_benchmark(lbipe_dir)


@pytest.fixture(scope="module")
def released(lbipe_dir):
    return load_released_models(find_layout(lbipe_dir).weights_dir)


def _data(lbipe_dir, name):
    ds = load_lbipe(lbipe_dir / "data" / f"data_test_{name}.npz")
    g = load_golden(lbipe_dir / "golden" / f"golden_{name}.npz", ds.n_samples)
    return ds, g


@pytest.mark.parametrize("name", OBJECTS)
def test_features_equal_golden(lbipe_dir, name):
    ds, g = _data(lbipe_dir, name)
    f = featurize(LBIPE_FEATURES, jnp.asarray(ds.q), ds.q_d, ds.direction)
    assert f.shape == (ds.n_samples, 4, 4)
    # golden features are joint-major flat (S, 4N)
    np.testing.assert_allclose(np.asarray(f).reshape(ds.n_samples, -1), g["features"],
                               atol=GOLDEN_FEATURES_TOL)


@pytest.mark.parametrize("name", OBJECTS)
def test_torque_predictions_equal_golden_for_all_ten_models(lbipe_dir, released, name):
    ds, g = _data(lbipe_dir, name)
    f = np.asarray(featurize(LBIPE_FEATURES, jnp.asarray(ds.q), ds.q_d, ds.direction),
                   np.float32)
    tau = jax.vmap(lambda v: predict_torques(released.torque_model, v, jnp.asarray(f),
                                             released.tau_scale))(released.torque_vars)
    assert tau.shape == g["tau_model"].shape == (10, ds.n_samples, 4)
    np.testing.assert_allclose(tau, g["tau_model"], atol=GOLDEN_TORQUE_TOL)


@pytest.mark.parametrize("name", OBJECTS)
def test_attention_weights_equal_golden_for_all_ten_models(lbipe_dir, released, name):
    """On the golden features the weights agree to 1e-6; from our own features (which differ
    from the authors' by <= 5e-7, the README's rounded qe_scale) to 2e-6."""
    ds, g = _data(lbipe_dir, name)
    gf = jnp.asarray(g["features"].reshape(ds.n_samples, 4, 4))
    w = jax.vmap(lambda v: predict_weights(released.attention_model, v, gf))(
        released.attention_vars)
    np.testing.assert_allclose(w, g["weights"], atol=GOLDEN_WEIGHTS_TOL)
    np.testing.assert_allclose(np.sum(np.asarray(w), axis=-1), 1.0, atol=WEIGHTS_SUM_TOL)
    f = featurize(LBIPE_FEATURES, jnp.asarray(ds.q), ds.q_d, ds.direction).astype(jnp.float32)
    w_ours = jax.vmap(lambda v: predict_weights(released.attention_model, v, f))(
        released.attention_vars)
    np.testing.assert_allclose(w_ours, g["weights"], atol=OWN_FEATURES_WEIGHTS_TOL)


@pytest.mark.parametrize("name", OBJECTS)
def test_authors_layout_round_trips_field_by_field(lbipe_dir, tmp_path, name):
    """The Samples record of a file survives save_lbipe -> load_lbipe and reads the same
    through load_samples (which recognises the layout)."""
    ds = load_lbipe(lbipe_dir / "data" / f"data_test_{name}.npz")
    assert ds.names == (name,) and ds.known
    (path,) = save_lbipe(tmp_path, "test", ds)
    assert path.name == f"data_test_{name}.npz"
    assert_tree_equal(load_lbipe(path), ds, what=f"{name}: after save_lbipe/load_lbipe")
    assert_tree_equal(load_samples(path)[0], ds, what=f"{name}: load_samples vs load_lbipe")


def test_the_empty_gripper_file_of_the_authors_training_set_loads(lbipe_dir, tmp_path):
    """Their training reads data_train_0g.npz (x = 0): it loads as a known object of mass 0;
    a negative mass, or a COM without mass, is refused with the file and field named."""
    path = lbipe_dir / "data" / "data_test_cube.npz"
    d = dict(np.load(path))
    for x, ok in (([0.0, 0, 0, 0], True), ([-0.01, 0, 0, 0], False),
                  ([0.0, 0.001, 0, 0], False)):
        out = tmp_path / "data_train_0g.npz"
        np.savez(out, **(d | {"x": np.asarray(x)}))
        if ok:
            s = load_lbipe(out)
            assert s.names == ("0g",) and s.mass == 0.0 and s.n_samples == len(d["joint_data"])
        else:
            with pytest.raises(FileFormatError, match=r"data_train_0g.npz \[x\]"):
                load_lbipe(out)


def test_pt_and_npz_give_identical_parameters(lbipe_dir):
    wdir = find_layout(lbipe_dir).weights_dir
    for k in range(1, 11):
        a = load_released_pair(wdir, k, prefer="npz")
        b = load_released_pair(wdir, k, prefer="pt")
        assert a[0] == b[0] and a[2] == b[2]
        for va, vb in ((a[1], b[1]), (a[3], b[3])):
            la, lb = jax.tree_util.tree_leaves(va), jax.tree_util.tree_leaves(vb)
            assert len(la) == len(lb) > 0
        # Same dtypes and bits, leaf by leaf; a failure names the parameter (for example
        # ['attention']['params']['joint0']['hidden']['kernel']).
        assert_tree_equal({"torque": a[1], "attention": a[3]},
                          {"torque": b[1], "attention": b[3]}, equal_nan=False,
                          what=f"pair {k}: npz vs pt")


def _benchmarked(lbipe_dir: Path, ref: dict) -> set[str]:
    """The objects the benchmark must answer for: every real file of the folder, among them
    every one the reference metrics name (a folder may hold further real files, which
    only the seeded sets judge)."""
    names = set(find_layout(lbipe_dir).test_files)
    assert set(ref) <= names, (sorted(ref), sorted(names))
    return names


def test_table_one_and_three_equal_reference_metrics(lbipe_dir, lbipe_run):
    ref = json.loads((lbipe_dir / "golden" / "reference_metrics.json").read_text())
    got = lbipe_run["objects"]
    assert set(got) == _benchmarked(lbipe_dir, ref)
    for name, r in ref.items():
        assert set(got[name]) == set(r)
        for method in ("T", "T-A"):
            assert set(got[name][method]) == set(r[method])
        # Every metric of T and T-A and the mean attention weights, field by field: a
        # failure lists each ['T-A']['mass_NMAE_pct'] that differs, with its difference.
        table = ("T", "T-A", "mean_attention_weight")
        assert_tree_close({k: got[name][k] for k in table}, {k: r[k] for k in table},
                          rtol=REFERENCE_METRICS_RTOL, what=f"{name} vs reference_metrics.json")
        assert got[name]["L_max_m"] == pytest.approx(r["L_max_m"], rel=L_MAX_RTOL)
    for name, d in lbipe_run["diagnostics"].items():
        for method in ("T", "T-A"):
            assert d[method]["rank_deficient"] == 0, (name, method)
            assert d[method]["n_solves"] == 10 * 1000


def test_batched_evaluation_equals_the_authors_per_set_loop(lbipe_dir, lbipe_run, released):
    real = load_real(lbipe_dir)
    est = lbipe_run["estimates"]
    for o, obj in enumerate(real.objects):
        sets = real.sets[o][:15]  # the loop is slow; 15 sets x 10 models
        inputs = stack([obj], [sets], LBIPE_FEATURES)
        xt, xta = reference_loop(released, inputs.features[0], inputs.A[0], inputs.tau_g[0],
                                 sets)
        assert_tree_close({"T": est["T"][o][:, :15], "T-A": est["T-A"][o][:, :15]},
                          {"T": xt, "T-A": xta}, **LOOP_TOL,
                          what=f"{obj.name}: batched vs the per-set loop")


def test_evaluating_without_float64_says_so(lbipe_dir):
    """A program of one's own that evaluates without ``jax_enable_x64`` is told that its
    statics and least squares run in float32 (the attention-weighted answers move: the
    warning's numbers, docs/results.md); with it (the tests' and the CLI's), nothing."""
    obj = load_lbipe(lbipe_dir / "data" / "data_test_cube.npz")
    sets = np.arange(128).reshape(2, 64)
    with jax.enable_x64(False), pytest.warns(RuntimeWarning, match="jax_enable_x64 is off"):
        assert stack([obj], [sets], LBIPE_FEATURES).A.dtype == jnp.float32
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert stack([obj], [sets], LBIPE_FEATURES).A.dtype == jnp.float64


def test_metrics_equal_direct_numpy():
    rng = np.random.default_rng(0)
    x_true = np.array([0.1, 0.1 * 0.01, 0.1 * -0.02, 0.1 * 0.03])
    x_hat = x_true + rng.normal(scale=[0.005, 1e-4, 1e-4, 1e-4], size=(37, 4))
    got = inertial_metrics(x_hat, x_true, 0.07)
    m_err = x_hat[:, 0] - 0.1
    d = np.sqrt(np.sum((x_hat[:, 1:] / x_hat[:, :1] - x_true[1:] / 0.1) ** 2, axis=1))
    assert got["mass_MAE_g"] == pytest.approx(np.abs(m_err).mean() * 1000)
    assert got["mass_NMAE_pct"] == pytest.approx(np.abs(m_err).mean() / 0.1 * 100)
    assert got["mass_NRMSE_pct"] == pytest.approx(np.sqrt((m_err**2).mean()) / 0.1 * 100)
    assert got["com_MAE_mm"] == pytest.approx(d.mean() * 1000)
    assert got["com_NMAE_pct"] == pytest.approx(d.mean() / 0.07 * 100)
    assert got["com_NRMSE_pct"] == pytest.approx(np.sqrt((d**2).mean()) / 0.07 * 100)
    assert error_metrics(np.array([-1.0, 3.0]), 2.0)["NRMSE_pct"] == pytest.approx(
        np.sqrt(5.0) / 2.0 * 100)


# ---- the CLI and its two layouts ------------------------------------------------------


def test_cli_writes_json_in_the_reference_schema(lbipe_dir, tmp_path, capsys):
    out = tmp_path / "m.json"
    assert cli_main(["lbipe-benchmark", "--lbipe-dir", str(lbipe_dir), "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "Table I" in text and "Table III" in text
    got = json.loads(out.read_text())
    ref = json.loads((lbipe_dir / "golden" / "reference_metrics.json").read_text())
    assert set(got) == _benchmarked(lbipe_dir, ref)
    for name in ref:
        assert got[name].keys() == ref[name].keys()
        assert got[name]["T-A"]["com_MAE_mm"] == pytest.approx(ref[name]["T-A"]["com_MAE_mm"],
                                                               rel=REFERENCE_METRICS_RTOL)


def _authors_layout(lbipe_dir: Path, root: Path, names=("cube",)) -> Path:
    """A checkout-like layout: data/ and dicts/*.pt (no golden sets)."""
    (root / "data").mkdir(parents=True)
    (root / "dicts").mkdir()
    for n in names:
        (root / "data" / f"data_test_{n}.npz").symlink_to(lbipe_dir / "data" / f"data_test_{n}.npz")
    for p in (lbipe_dir / "weights").glob("*.pt"):
        (root / "dicts" / p.name).symlink_to(p)
    return root


def test_cli_on_the_authors_layout_draws_seeded_sets(lbipe_dir, tmp_path):
    root = _authors_layout(lbipe_dir, tmp_path / "lbipe")
    a, b, c = (tmp_path / f"{k}.json" for k in "abc")
    for out, seed in ((a, 3), (b, 3), (c, 4)):
        assert cli_main(["lbipe-benchmark", "--lbipe-dir", str(root), "--json", str(out),
                         "--seed", str(seed)]) == 0
    ja, jb, jc = (json.loads(p.read_text()) for p in (a, b, c))
    assert ja == jb and ja != jc
    ref = json.loads((lbipe_dir / "golden" / "reference_metrics.json").read_text())["cube"]
    # Other random sets, same models and data: the same numbers to a few per cent.
    assert ja["cube"]["T-A"]["mass_MAE_g"] == pytest.approx(ref["T-A"]["mass_MAE_g"],
                                                           rel=OTHER_SETS_RTOL)


def test_cli_unknown_object_needs_l_max(lbipe_dir, tmp_path, capsys):
    root = _authors_layout(lbipe_dir, tmp_path / "lbipe", names=())
    (root / "data" / "data_test_mystery.npz").symlink_to(lbipe_dir / "data" / "data_test_cube.npz")
    assert cli_main(["lbipe-benchmark", "--lbipe-dir", str(root)]) == 2
    err = capsys.readouterr().err
    assert "data_test_mystery.npz" in err and "--l-max mystery=" in err
    out = tmp_path / "m.json"
    assert cli_main(["lbipe-benchmark", "--lbipe-dir", str(root), "--l-max", "mystery=0.0692820",
                     "--json", str(out)]) == 0
    assert json.loads(out.read_text())["mystery"]["L_max_m"] == pytest.approx(0.069282)
    capsys.readouterr()
    assert cli_main(["lbipe-benchmark", "--lbipe-dir", str(root), "--l-max", "mystery=-1"]) == 2
    assert "--l-max expects NAME=METRES" in capsys.readouterr().err


# ---- malformed input: one clear error naming the file and the field ------------------


def _write_variant(lbipe_dir, tmp_path, edit) -> Path:
    root = _authors_layout(lbipe_dir, tmp_path / "lbipe", names=())
    with np.load(lbipe_dir / "data" / "data_test_cube.npz") as z:
        d = {k: z[k] for k in z.files}
    path = root / "data" / "data_test_cube.npz"
    edit(d, path)
    return path


def _drop_x(d, path):
    del d["x"]
    np.savez(path, **d)


def _bad_shape(d, path):
    d["A"] = d["A"][:-1]
    np.savez(path, **d)


def _nan(d, path):
    d["joint_data"] = d["joint_data"].copy()
    d["joint_data"][5, 1, 2] = np.nan
    np.savez(path, **d)


def _direction(d, path):
    d["joint_data"] = d["joint_data"].copy()
    d["joint_data"][2, 5, 0] = 0.5
    np.savez(path, **d)


def _garbage(d, path):
    path.write_bytes(b"this is not a zip file")


def _torn(d, path):
    np.savez(path, **d)
    path.write_bytes(path.read_bytes()[:2000])  # a zip archive cut short


@pytest.mark.parametrize(
    "edit, field, words",
    [(_drop_x, "x", "missing"), (_bad_shape, "A", "shape"), (_nan, "joint_data", "non-finite"),
     (_direction, "joint_data", "direction"),
     (_garbage, None, "not an .npz file (not a zip archive of arrays)"),
     (_torn, None, "not a readable .npz file")],
    ids=["missing key", "wrong shape", "NaN", "bad direction", "not a zip", "torn"],
)
def test_malformed_test_file_gives_one_clear_error(lbipe_dir, tmp_path, capsys, edit, field,
                                                   words):
    path = _write_variant(lbipe_dir, tmp_path, edit)
    with pytest.raises(FileFormatError) as e:
        load_lbipe(path)
    assert e.value.path == str(path) and e.value.field == field
    assert words in str(e.value) and str(path) in str(e.value)
    assert "allow_pickle" not in str(e.value)  # numpy's advice to load it unsafely
    assert cli_main(["lbipe-benchmark", "--lbipe-dir", str(path.parent.parent)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(path) in err[0] and (field is None or f"[{field}]" in err[0])


def test_corrupt_weights_give_one_clear_error(lbipe_dir, tmp_path, capsys):
    root = _authors_layout(lbipe_dir, tmp_path / "lbipe")
    bad = root / "dicts" / "dict_attn_7.pt"
    bad.unlink()
    bad.write_bytes(b"PK\x03\x04 truncated")
    with pytest.raises(WeightsError, match="dict_attn_7.pt"):
        load_released_pair(root / "dicts", 7, prefer="pt")
    assert cli_main(["lbipe-benchmark", "--lbipe-dir", str(root)]) == 2
    assert "dict_attn_7.pt" in capsys.readouterr().err


def test_missing_directory_says_how_to_get_the_data(tmp_path, capsys):
    assert cli_main(["lbipe-benchmark", "--lbipe-dir", str(tmp_path / "nowhere")]) == 2
    err = capsys.readouterr().err
    assert "nowhere" in err and "ChirikjianLab/lbipe" in err


def test_find_layout_rejects_folder_without_weights(lbipe_dir, tmp_path):
    (tmp_path / "data").mkdir()
    shutil.copy(lbipe_dir / "data" / "data_test_cube.npz", tmp_path / "data")
    with pytest.raises(FileFormatError, match="neither weights/ nor dicts/"):
        find_layout(tmp_path)
