"""No silent garbage, nothing lost: bad options, bad files and impossible answers end in one
line and exit code 2 (or a correct result), outputs are checked before the work and written
atomically, model folders prove themselves (issue 18)."""

from __future__ import annotations

import json
import pathlib
import zipfile
from pathlib import Path

import jax
import numpy as np
import pytest
from support.synthetic import feature_config, synthetic_samples, tiny_pair

from jaxinertia import checkpoints, samples
from jaxinertia.app.cli import main
from jaxinertia.app.estimate import estimate
from jaxinertia.baselines import fit_baselines
from jaxinertia.checkpoints import load_models, save_models
from jaxinertia.errors import FileFormatError, JaxinertiaError, ModelFolderError, UsageError
from jaxinertia.robot import data_path
from jaxinertia.samples import Samples, lbipe_arrays, load_samples, save_native
from jaxinertia.training import TrainConfig


def _one_line_error(capsys, *words) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    for w in words:
        assert w in err[0], (w, err[0])
    return err[0]


# ---- options: checked when parsed, one line, exit 2 ------------------------------------

BAD_OPTIONS = [
    (["simulate", "--scenario", "test", "--n", "0", "--out", "x.npz"], "--n"),
    (["simulate", "--scenario", "test", "--n", "-2", "--out", "x.npz"], "--n"),
    (["simulate", "--scenario", "continuous", "--switch-every", "0", "--out", "x.npz"],
     "--switch-every"),
    (["train", "--data", "a.npz", "--out", "m", "--torque-epochs", "0"], "--torque-epochs"),
    (["train", "--data", "a.npz", "--out", "m", "--torque-lr", "nan"], "--torque-lr"),
    (["train", "--data", "a.npz", "--out", "m", "--n-models", "-1"], "--n-models"),
    (["train", "--data", "a.npz", "--out", "m", "--set-size", "0"], "--set-size"),
    (["train", "--data", "a.npz", "--out", "m", "--torque-batch", "0"], "--torque-batch"),
    (["train", "--data", "a.npz", "--out", "m", "--val-fraction", "1.5"], "--val-fraction"),
    (["train", "--data", "a.npz", "--out", "m", "--attention-lr", "inf"], "--attention-lr"),
    (["evaluate", "--models", "m", "--sets", "0"], "--sets"),
    (["estimate", "--models", "m", "--samples", "s.npz", "--set-size", "-1"], "--set-size"),
    (["estimate", "--models", "m", "--samples", "s.npz", "--max-mass", "0"], "--max-mass"),
    (["calibrate", "--iterations", "0"], "--iterations"),
    (["calibrate", "--kinetic-ratio", "2"], "--kinetic-ratio"),
    (["tag-pose", "--image", "a", "--intrinsics", "b", "--tag-size", "0"], "--tag-size"),
    (["lbipe-benchmark", "--l-max", "mystery=-1", "--lbipe-dir", "nowhere"], "--l-max"),
]


@pytest.mark.parametrize("argv, option", BAD_OPTIONS, ids=[" ".join(a) for a, _ in BAD_OPTIONS])
def test_bad_options_give_one_line_and_exit_2(argv, option, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    _one_line_error(capsys, option)
    assert not any(tmp_path.iterdir())  # nothing written


def test_an_unknown_option_points_to_its_commands_help(capsys):
    assert main(["evaluate", "--models", "m", "--no-such-option"]) == 2
    _one_line_error(capsys, "--no-such-option", "(see jaxinertia evaluate --help)")
    assert main(["no-such-command"]) == 2
    _one_line_error(capsys, "no-such-command", "(see jaxinertia --help)")


def test_train_config_refuses_what_cannot_train():
    for bad in ({"torque_epochs": 0}, {"torque_lr": float("nan")}, {"n_models": -1},
                {"val_fraction": 0.0}, {"w_mass": 0.0, "w_com": 0.0}, {"attention_batch": 1.5}):
        with pytest.raises(UsageError, match=next(iter(bad))):
            TrainConfig(**bad)


def test_simulate_refuses_repeated_objects_before_simulating(capsys, tmp_path):
    assert main(["simulate", "--scenario", "test", "--objects", "cube", "cube", "--n", "4",
                 "--out", str(tmp_path / "x.npz")]) == 2
    _one_line_error(capsys, "--objects", "cube")
    assert not (tmp_path / "x.npz").exists()


@pytest.mark.parametrize("content, words", [
    ("{", ["not a readable calibration file"]),
    ('{"servo_friction": {}}', []),
    (None, ["[servo_friction.servo.p_gain]", "finite"]),
], ids=["torn", "fields missing", "nan"])
def test_simulate_refuses_a_bad_calibration_file_before_simulating(capsys, tmp_path, content,
                                                                   words):
    calib = tmp_path / "calib.json"
    if content is None:  # the shipped calibration with one gain made NaN
        doc = json.loads(data_path("open_manipulator_x_sim.json").read_text())
        doc["servo_friction"]["servo"]["p_gain"][1] = float("nan")
        content = json.dumps(doc)
    calib.write_text(content)
    assert main(["simulate", "--scenario", "test", "--n", "4", "--calibration", str(calib),
                 "--out", str(tmp_path / "x.npz")]) == 2
    _one_line_error(capsys, str(calib), *words)
    assert not (tmp_path / "x.npz").exists()


def test_camera_calibrate_refuses_a_nan_joint_angle_in_the_manifest(capsys, tmp_path):
    (tmp_path / "m.csv").write_text("image,q1,q2,q3,q4\na.png,0.1,nan,0.2,0.3\n")
    (tmp_path / "intr.json").write_text(json.dumps(
        {"fx": 600.0, "fy": 600.0, "cx": 320.0, "cy": 240.0, "width": 640, "height": 480}))
    assert main(["camera-calibrate", "--manifest", str(tmp_path / "m.csv"), "--intrinsics",
                 str(tmp_path / "intr.json"), "--tag-size", "0.03",
                 "--out", str(tmp_path / "cam.json")]) == 2
    _one_line_error(capsys, "m.csv", "a.png", "not finite")
    assert not (tmp_path / "cam.json").exists()


# ---- outputs: checked before the work, kept unless --overwrite, written atomically -----


def test_existing_outputs_are_kept_unless_overwrite(capsys, tmp_path):
    out = tmp_path / "x.npz"
    out.write_bytes(b"precious")
    assert main(["simulate", "--scenario", "test", "--n", "4", "--out", str(out)]) == 2
    _one_line_error(capsys, "--out", "exists", "--overwrite")
    assert out.read_bytes() == b"precious"
    (tmp_path / "m").mkdir()
    assert main(["train", "--data", str(out), "--out", str(tmp_path / "m")]) == 2
    _one_line_error(capsys, "exists")


def test_an_unwritable_output_is_reported_before_the_work(capsys, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    assert main(["simulate", "--scenario", "test", "--n", "4",
                 "--out", str(blocker / "sub" / "x.npz")]) == 2
    _one_line_error(capsys, "--out", "cannot create")


def test_model_folders_are_replaced_whole_or_not_at_all(tmp_path, monkeypatch):
    d = synthetic_samples(np.random.default_rng(0))
    b = fit_baselines(d.q_d, d.q, d.direction, d.current_tau, d.tau)
    save_models(tmp_path / "m", tiny_pair(seed=0), b, feature_config(), robot="r")
    before = {p.relative_to(tmp_path): p.read_bytes() for p in (tmp_path / "m").rglob("*")
              if p.is_file()}

    write_text = pathlib.Path.write_text

    def crash(self, *a, **k):  # the new checkpoint is written, then the config fails
        if self.name == "config.json":
            raise OSError("disk full")
        return write_text(self, *a, **k)

    monkeypatch.setattr(pathlib.Path, "write_text", crash)
    with pytest.raises(OSError, match="disk full"):
        save_models(tmp_path / "m", tiny_pair(seed=1), b, feature_config(), robot="r")
    after = {p.relative_to(tmp_path): p.read_bytes() for p in (tmp_path / "m").rglob("*")
             if p.is_file()}
    assert after == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m"]  # no temporary left behind


# ---- model folders prove themselves ------------------------------------------------------


@pytest.fixture()
def model_folder(tmp_path):
    d = synthetic_samples(np.random.default_rng(1))
    b = fit_baselines(d.q_d, d.q, d.direction, d.current_tau, d.tau)
    return save_models(tmp_path / "m", tiny_pair(), b, feature_config(),
                       robot="open_manipulator_x")


def _edit_config(folder, **changes):
    c = json.loads((folder / "config.json").read_text())
    c.update(changes)
    (folder / "config.json").write_text(json.dumps(c))


@pytest.mark.parametrize("changes, words", [
    ({"format_version": 99}, "format_version 99"),
    ({"n_models": 3}, "n_models"),
    ({"n_models": 0}, "n_models"),
    ({"features": {"q_min": [0.0]}}, "malformed"),
])
def test_load_models_refuses_a_folder_that_does_not_match_itself(model_folder, changes, words):
    _edit_config(model_folder, **changes)
    with pytest.raises(ModelFolderError, match=words) as e:
        load_models(model_folder)
    assert str(model_folder) in str(e.value)


def test_load_models_refuses_non_finite_weights(model_folder, tmp_path, monkeypatch):
    pair, loaded = tiny_pair(), load_models(model_folder)
    bad = pair.replace(attention_vars=jax.tree_util.tree_map(lambda a: a.at[0].set(np.nan),
                                                             pair.attention_vars))
    with pytest.raises(ModelFolderError, match="non-finite"):  # never written ...
        save_models(tmp_path / "nan", bad, loaded.baselines, loaded.features, robot="r")
    monkeypatch.setattr(checkpoints, "_check_finite", lambda *a: None)
    save_models(tmp_path / "nan", bad, loaded.baselines, loaded.features, robot="r")
    monkeypatch.undo()
    with pytest.raises(ModelFolderError, match=r"nan.*attention parameters.*non-finite"):
        load_models(tmp_path / "nan")  # ... and never read


# ---- estimate: per object, gated, refusing what it cannot answer -------------------------

#: Samples per object in the estimate tests: one size for all of them (and
#: test_uncertainty's), so that the programs compiled for one object's size (the estimate,
#: its sets, its uncertainty) serve every test; the refusals and gates do not depend on it.
S_EST = 120


def _write(path, samples: Samples) -> str:
    save_native(path, samples, {"robot": "open_manipulator_x"})
    return str(path)


def test_estimate_refuses_too_few_samples_and_zero_discrepancy(model_folder, tmp_path, capsys):
    d = synthetic_samples(np.random.default_rng(2), n=200, n_obj=1).without_truth()
    few = _write(tmp_path / "few.npz", d.take(np.arange(3)))
    assert main(["estimate", "--models", str(model_folder), "--samples", few,
                 "--set-size", "64"]) == 2
    _one_line_error(capsys, "few.npz", "3 sample(s)", "--set-size 64", "leave --set-size out")
    one = _write(tmp_path / "one.npz", d.take(np.arange(1)))
    assert main(["estimate", "--models", str(model_folder), "--samples", one]) == 2
    _one_line_error(capsys, "one.npz", "1 sample(s)", "at least 2")
    flat = _write(tmp_path / "flat.npz", d.replace(q_d=d.q))
    assert main(["estimate", "--models", str(model_folder), "--samples", flat]) == 2
    _one_line_error(capsys, "flat.npz", "q_d - q is zero")


def test_estimate_reports_absurd_answers_as_failed_never_as_numbers(model_folder, tmp_path):
    d = synthetic_samples(np.random.default_rng(3), n=S_EST, n_obj=1)
    mass = float(d.x[0, 0])
    huge = d.current_tau.copy()
    huge[5, 1] = 1e30  # one broken current reading: the Sensor method's answer is absurd
    res = estimate(model_folder, _write(tmp_path / "s.npz", d.replace(current_tau=huge)))
    methods = res["objects"]["o0"]["methods"]
    assert methods["Sensor"]["ok"] is False and "mass" in methods["Sensor"]["reason"]
    assert "mass_kg" not in methods["Sensor"]
    # PE follows the exact law of these samples: a correct answer.
    assert methods["PE"]["ok"] and methods["PE"]["mass_kg"] == pytest.approx(mass, rel=1e-6)
    for r in methods.values():
        assert (r["ok"] and np.isfinite(r["mass_kg"]) and 0 < r["mass_kg"] <= 5.0) or (
            not r["ok"] and r["reason"])


def test_estimate_answers_each_object_of_a_multi_object_file(model_folder, tmp_path, capsys,
                                                             monkeypatch):
    d = synthetic_samples(np.random.default_rng(4), n=3 * S_EST, n_obj=3)
    path = _write(tmp_path / "multi.npz", d)
    reads, read_npz = [], samples.read_npz

    def counted(p, **kw):
        reads.append(p)
        return read_npz(p, **kw)

    monkeypatch.setattr(samples, "read_npz", counted)
    res = estimate(model_folder, path)
    assert [Path(p) for p in reads] == [Path(path)]  # the sample file is read once
    assert list(res["objects"]) == ["o0", "o1", "o2"]
    assert res["fitted_on_this_file"] == {}  # a file the models never saw
    for o, name in enumerate(d.names):
        pe = res["objects"][name]["methods"]["PE"]
        assert pe["mass_kg"] == pytest.approx(d.x[o, 0], rel=1e-6), name
        # Fewer than 128 samples: the spread over sets of half of them (sets of all of
        # them would be one set over and over, their spread zero).
        assert res["objects"][name]["set_size"] == S_EST // 2
        key = "mass_std_over_sample_sets_kg"  # one name whatever the size (in set_size)
        assert key in pe and res["objects"][name]["methods"]["Sensor"][key] > 0
    assert main(["estimate", "--models", str(model_folder), "--samples",
                 str(tmp_path / "multi.npz")]) == 0
    out = capsys.readouterr().out
    assert all(f"{n}: {S_EST} samples (the spread over {S_EST // 2}-sample sets)" in out
               for n in d.names)


def test_estimate_with_no_possible_answer_is_an_error(model_folder, tmp_path, capsys):
    d = synthetic_samples(np.random.default_rng(5), n=S_EST, n_obj=1)
    d = d.replace(A=np.repeat(d.A[:1], S_EST, axis=0) * [1, 1, 0, 1])  # no y information
    assert main(["estimate", "--models", str(model_folder), "--samples",
                 _write(tmp_path / "s.npz", d.without_truth())]) == 2
    _one_line_error(capsys, "no method gives a physically possible estimate", "singular")


# ---- fuzzing the loaders: a clear error or a correct, finite result -------------------


def _native_and_lbipe(tmp_path):
    d = synthetic_samples(np.random.default_rng(6), n=40, n_obj=2)
    native = tmp_path / "native.npz"
    save_native(native, d, {"robot": "open_manipulator_x"})
    lbipe = tmp_path / "data_test_o0.npz"
    np.savez(lbipe, **lbipe_arrays(d.object(0)))
    return native, lbipe


def _corrupt(rng, src, dst):
    """One seeded corruption of an .npz: bytes truncated or flipped, or one array replaced
    by NaN/inf, another dtype, another shape, or removed."""
    kind = rng.integers(6)
    if kind <= 1:
        raw = bytearray(src.read_bytes())
        if kind == 0:
            raw = raw[: int(rng.integers(1, len(raw)))]
        else:
            for i in rng.integers(0, len(raw), 1 + int(rng.integers(8))):
                raw[i] ^= 1 << int(rng.integers(8))
        dst.write_bytes(bytes(raw))
        return
    with np.load(src) as z:
        arrays = {k: z[k] for k in z.files}
    key = sorted(arrays)[int(rng.integers(len(arrays)))]
    a = arrays[key]
    if kind == 2 and a.dtype.kind == "f" and a.size:
        a = a.copy()
        a.flat[int(rng.integers(a.size))] = rng.choice([np.nan, np.inf, -np.inf])
    elif kind == 3:
        a = a.astype(str) if key != "metadata" else np.asarray("{not json")
    elif kind == 4:
        a = a.reshape(-1)[: max(0, a.size - 1)]
    else:
        del arrays[key]
        a = None
    if a is not None:
        arrays[key] = a
    np.savez(dst, **arrays)


def test_fuzzed_sample_files_end_in_a_clear_error_or_a_correct_result(tmp_path):
    rng = np.random.default_rng(2024)
    sources = _native_and_lbipe(tmp_path)
    outcomes = {"error": 0, "loaded": 0}
    for i in range(300):
        src = sources[i % 2]
        bad = tmp_path / f"fuzz{i}.npz"
        _corrupt(rng, src, bad)
        for need_truth in (True, False):
            try:
                s, meta = load_samples(bad, need_truth=need_truth)
            except JaxinertiaError as e:
                assert isinstance(e, FileFormatError) and e.exit_code == 2
                assert str(bad) in str(e) and "\n" not in str(e)
                outcomes["error"] += 1
                continue
            outcomes["loaded"] += 1
            for k in ("q_d", "q", "direction", "current_tau", "tau_g", "A"):
                assert np.all(np.isfinite(getattr(s, k))), (i, k)
            assert np.all(np.isin(s.direction, (-1, 1)))
            if s.known:
                assert np.all(np.isfinite(s.tau)) and np.all(np.isfinite(s.x))
            elif need_truth:
                pytest.fail(f"case {i}: unknown truth accepted for training")
    assert outcomes["error"] > 100 and outcomes["loaded"] > 10, outcomes


def test_fuzzed_options_end_in_one_line_and_exit_2(capsys, tmp_path, monkeypatch):
    """Random bad values for every numeric option of the cheap-to-check commands."""
    monkeypatch.chdir(tmp_path)
    rng = np.random.default_rng(7)
    values = ["0", "-1", "nan", "inf", "-inf", "abc", "", "1e400", "0x10", "2.5.1"]
    cases = [(["train", "--data", "a.npz", "--out", "m"],
              ["--n-models", "--torque-epochs", "--torque-batch", "--torque-lr",
               "--attention-epochs", "--attention-batch", "--attention-lr", "--set-size",
               "--attention-sets", "--attention-val-sets", "--val-fraction"]),
             (["simulate", "--scenario", "random", "--out", "x.npz"], ["--n", "--switch-every"]),
             (["estimate", "--models", "m", "--samples", "s.npz"],
              ["--set-size", "--max-mass", "--max-com"])]
    for _ in range(60):
        base, options = cases[int(rng.integers(len(cases)))]
        option = options[int(rng.integers(len(options)))]
        value = values[int(rng.integers(len(values)))]
        assert main([*base, option, value]) == 2, (option, value)
        _one_line_error(capsys, option)
    assert not any(tmp_path.iterdir())


def test_a_torn_npz_is_named_in_the_error(tmp_path):
    native, _ = _native_and_lbipe(tmp_path)
    with zipfile.ZipFile(native) as z:
        names = z.namelist()
    assert "q.npy" in names
    raw = native.read_bytes()
    (tmp_path / "torn.npz").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(FileFormatError, match="torn.npz"):
        load_samples(tmp_path / "torn.npz")
