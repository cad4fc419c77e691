"""Reliability II (issue 32): the second probe's cases, each a one-line refusal with exit code
2 before any work (or a correct result), nothing lost or overwritten: objects are their ids
(duplicate names refused), nothing shipped is written, outputs are locked, journal records
and model folders are checked, memory is estimated before it is allocated.

Every case here fails before any JAX work (or uses files of a few kilobytes): the file
costs seconds, most of it the one tiny model folder."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys

import numpy as np
import pytest
from support.synthetic import feature_config, synthetic_samples, tiny_pair

from jaxinertia.app import cli
from jaxinertia.app.cli import main
from jaxinertia.baselines import fit_baselines
from jaxinertia.checkpoints import load_models, save_models
from jaxinertia.errors import FileFormatError, ModelFolderError
from jaxinertia.fileio import check_output, release_locks, replacing_dir, write_text
from jaxinertia.robot import data_path
from jaxinertia.samples import Samples, save_lbipe, save_native

ROBOT = {"robot": "open_manipulator_x"}


def _one_line(capsys, *words) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    lines = [ln for ln in err.strip().splitlines() if not ln.startswith("note: ")]
    assert len(lines) == 1, lines
    for w in words:
        assert w in lines[0], (w, lines[0])
    return lines[0]


def _samples(n=40, n_obj=1, seed=0) -> Samples:
    return synthetic_samples(np.random.default_rng(seed), n=n * n_obj, n_obj=n_obj)


def _raw_native(path, samples: Samples, names) -> str:
    """A native file written around save_native's checks (as an edited file would be)."""
    meta = {"format": "jaxinertia-samples", "format_version": 1, **ROBOT, "objects": names}
    np.savez(path, metadata=np.asarray(json.dumps(meta)), **samples.fields())
    return str(path)


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    d = synthetic_samples(np.random.default_rng(1))  # test_reliability's: programs cached
    b = fit_baselines(d.q_d, d.q, d.direction, d.current_tau, d.tau)
    return save_models(tmp_path_factory.mktemp("models") / "m", tiny_pair(), b,
                       feature_config(), robot="open_manipulator_x")


# ---- 1. an object is its id: duplicate names refused when read or written ---------------


@pytest.mark.parametrize("command", ["estimate", "evaluate"])
def test_duplicate_object_names_are_refused_when_read(command, tmp_path, capsys):
    f = _raw_native(tmp_path / "dup.npz", _samples(n_obj=2), ["unknown", "unknown"])
    before = (tmp_path / "dup.npz").read_bytes()
    assert main([command, "--models", str(tmp_path / "none"), "--samples", f]) == 2
    _one_line(capsys, "dup.npz", "'unknown'", "[0, 1]")
    assert (tmp_path / "dup.npz").read_bytes() == before


def test_the_evaluator_refuses_objects_of_one_name():
    from jaxinertia.errors import UsageError
    from jaxinertia.evaluation import evaluate

    a = _samples(seed=2).replace(names=("unknown",))
    with pytest.raises(UsageError, match="repeat a name"):
        evaluate([a, a], [np.zeros((1, 4), int)] * 2, l_max=[0.1, 0.1])


def test_duplicate_object_names_are_refused_when_written(tmp_path):
    a = _samples(seed=2).replace(names=("unknown",))
    b = _samples(seed=3).replace(names=("unknown",))
    out = tmp_path / "joined.npz"
    out.write_bytes(b"precious")
    with pytest.raises(FileFormatError, match="'unknown' names objects"):
        save_native(out, Samples.concatenate([a, b]), ROBOT)
    with pytest.raises(FileFormatError, match="'unknown' names objects"):
        save_lbipe(tmp_path, "test", Samples.concatenate([a, b]))
    assert out.read_bytes() == b"precious"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["joined.npz"]


# ---- 2. nothing shipped is written by a command -----------------------------------------


def test_calibrate_needs_out_and_leaves_the_shipped_file_alone(tmp_path, capsys,
                                                                monkeypatch):
    monkeypatch.chdir(tmp_path)
    shipped = data_path("open_manipulator_x_sim.json")
    digest = hashlib.sha256(shipped.read_bytes()).hexdigest()
    assert main(["calibrate", "--iterations", "1"]) == 2
    _one_line(capsys, "--out", "required")
    assert hashlib.sha256(shipped.read_bytes()).hexdigest() == digest
    assert not any(tmp_path.iterdir())


# ---- 3. outputs locked from the check to the rename, with the user's permissions --------


WRITERS = {"simulate": ["simulate", "--scenario", "test", "--n", "4"],
           "collect": ["collect", "--port", "/dev/null", "--plan", "random", "--n", "3",
                       "--object", "cube"]}


@pytest.mark.parametrize("command", WRITERS)
def test_a_second_writer_is_refused_at_once(command, tmp_path, capsys):
    out = tmp_path / "x.npz"
    check_output(out)  # this process is the first writer
    try:
        assert main([*WRITERS[command], "--out", str(out)]) == 2
        _one_line(capsys, "being written", str(out))
        other = subprocess.run(  # another process: the same answer
            [sys.executable, "-c", "import sys; from jaxinertia.fileio import check_output; "
             "check_output(sys.argv[1])", str(out)], capture_output=True, text=True)
        assert other.returncode == 1 and "being written" in other.stderr
        assert not out.exists()
    finally:
        release_locks()
    write_text(out, "mine")  # released: a writer goes ahead, and leaves no lock behind
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.npz"]


def test_a_full_disk_is_one_line_and_keeps_the_old_output(tmp_path):
    import errno

    from jaxinertia.fileio import OutputError, replacing

    out = tmp_path / "x.json"
    out.write_text("old")
    with pytest.raises(OutputError) as e, replacing(out) as tmp:
        tmp.write_text("half")
        raise OSError(errno.ENOSPC, "No space left on device")
    assert e.value.exit_code == 2 and "No space left" in str(e.value)
    assert out.read_text() == "old" and sorted(p.name for p in tmp_path.iterdir()) == ["x.json"]


def test_the_lock_is_held_until_the_rename(tmp_path):
    out = tmp_path / "r.txt"
    check_output(out)
    write_text(out, "one")  # the rename releases the lock ...
    check_output(out, overwrite=True)  # ... so the next check takes it again
    release_locks()
    assert out.read_text() == "one" and not (tmp_path / ".r.txt.lock").exists()


def test_outputs_honour_the_umask(tmp_path):
    old = os.umask(0o027)
    try:
        write_text(tmp_path / "f.txt", "x")
        with replacing_dir(tmp_path / "d") as tmp:
            (tmp / "inner").write_text("y")
    finally:
        os.umask(old)
    assert oct((tmp_path / "f.txt").stat().st_mode & 0o777) == oct(0o640)
    assert oct((tmp_path / "d").stat().st_mode & 0o777) == oct(0o750)


@pytest.mark.parametrize("argv, words", [
    (["simulate", "--scenario", "test", "--n", "4", "--overwrite", "--out", "DIR"],
     ["is a folder"]),
    (["train", "--data", "a.npz", "--overwrite", "--out", "FILE"], ["is a file"]),
    (["lbipe-benchmark", "--plot", "fig.xyz"], ["--plot", "unknown figure format"]),
], ids=["folder for a file", "file for a folder", "plot extension"])
def test_outputs_are_checked_before_the_work(argv, words, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "DIR").mkdir()
    (tmp_path / "FILE").write_text("precious")
    assert main(argv) == 2
    _one_line(capsys, *words)
    assert (tmp_path / "FILE").read_text() == "precious" and not any((tmp_path / "DIR").iterdir())
    assert sorted(p.name for p in tmp_path.iterdir()) == ["DIR", "FILE"]


def test_a_model_folder_may_be_overwritten(tmp_path, capsys):
    (tmp_path / "m").mkdir()  # passes both checks (the command's, train's): to the data
    assert main(["train", "--data", str(tmp_path / "none.npz"), "--overwrite", "--out",
                 str(tmp_path / "m")]) == 2
    _one_line(capsys, "none.npz", "no such file")


# ---- 4. journal records and model folders checked ---------------------------------------


def _journal(tmp_path, **change):
    from jaxinertia.hardware.collect import RECORD_FIELDS, Journal, plan_digest

    q_d, direction = np.full((2, 4), 0.1), np.ones((2, 4))
    header = {"kind": "header", "n_samples": 2, "object": "cube", "servo_ids": [11, 12, 13, 14],
              "plan_digest": plan_digest(q_d, direction)}
    rec = {"index": 0, "q_d": [0.1] * 4, "q": [0.09] * 4, "current": [1.0] * 4,
           "current_tau": [0.1] * 4, "direction": [1.0] * 4, "R_base_tag": np.eye(3).tolist(),
           "p_base_tag": [0.2, 0.0, 0.1], "at_rest": True, "settle_time": 0.3,
           "timestamp": 1.0, "temperature": [30.0] * 4, "voltage": [12.0] * 4, **change}
    assert set(RECORD_FIELDS) <= set(rec)
    path = tmp_path / "x.npz.journal.jsonl"
    path.write_text(json.dumps(header) + "\n" + json.dumps(rec) + "\n")
    return Journal, path, header, (q_d, direction)


def test_a_valid_journal_record_resumes(tmp_path):
    Journal, path, header, plan = _journal(tmp_path)
    assert list(Journal.open(path, header, resume=True, plan=plan).records) == [0]


def test_a_record_of_joints_without_a_current_sensor_resumes(tmp_path):
    # null: no reading (the Koch's XL430s: Present Load only); the sample file gets NaN.
    from jaxinertia.hardware.collect import samples_from_records
    from jaxinertia.robot import open_manipulator_x

    Journal, path, header, plan = _journal(tmp_path, current_tau=[None, None, 0.1, 0.1])
    records = Journal.open(path, header, resume=True, plan=plan).records
    s = samples_from_records(records, open_manipulator_x(), None, "cube")
    np.testing.assert_array_equal(np.isnan(s.current_tau), [[True, True, False, False]])
    assert not s.has_current


def test_the_sensor_baseline_says_it_is_unavailable_without_current_sensors(tmp_path):
    from jaxinertia.evaluation import evaluate
    from jaxinertia.uncertainty import uncertainty_of

    d = _samples(seed=3)
    cur = np.asarray(d.current_tau).copy()
    cur[:, :2] = np.nan  # joints 0 and 1 read no current
    d = d.replace(current_tau=cur)
    b = fit_baselines(d.q_d, d.q, d.direction, d.current_tau, d.tau)
    assert np.isnan(b.sensor_friction[:2]).all() and np.isfinite(b.sensor_friction[2:]).all()
    sets = [np.arange(d.n_samples)[None]]
    res = evaluate([d], sets, baselines=b, l_max=[0.1])
    assert "Sensor" not in res["objects"]["o0"] and "PE" in res["objects"]["o0"]
    assert "Sensor" not in res["estimates"] and "Sensor" not in res["torque"]
    why = res["unavailable"]["Sensor"]
    assert "joints [0, 1]" in why and "no current sensor" in why, why
    assert set(uncertainty_of([d], sets, baselines=b)) == {"PE"}
    # A model folder keeps them (null in config.json: strict JSON) and reads them back.
    folder = save_models(tmp_path / "m", tiny_pair(), b, feature_config(), robot="koch_v1_1")
    assert json.loads((folder / "config.json").read_text())["baselines"][
        "sensor_friction"][:2] == [None, None]
    back = load_models(folder).baselines
    for k in ("sensor_friction", "sensor_offset", "pe_gain"):
        np.testing.assert_array_equal(np.asarray(getattr(back, k)), np.asarray(getattr(b, k)),
                                      err_msg=k)


@pytest.mark.parametrize("change, words", [
    ({"R_base_tag": np.zeros((3, 3)).tolist()}, ["R_base_tag", "not a rotation"]),
    ({"q": [100.0, 0.0, 0.0, 0.0]}, ["line 2 q", "beyond one turn"]),
    ({"current_tau": [0.1, float("nan"), 0.1, 0.1]}, ["current_tau", "non-finite"]),
    ({"direction": [1.0, 0.0, 1.0, 1.0]}, ["direction", "+1 or -1"]),
    ({"q": [0.1, 0.1]}, ["line 2 q", "shape"]),
    ({"q_d": [0.2] * 4}, ["q_d", "not the plan's"]),
    ({"at_rest": "yes"}, ["at_rest", "true or false"]),
    ({"p_base_tag": "abc"}, ["p_base_tag", "not numbers"]),
], ids=["zero rotation", "q = 100 rad", "NaN current", "direction 0", "short q",
        "not the plan's goal", "at_rest text", "p text"])
def test_damaged_journal_records_are_refused_before_the_arm_moves(change, words, tmp_path):
    from jaxinertia.hardware.collect import JournalError

    Journal, path, header, plan = _journal(tmp_path, **change)
    before = path.read_bytes()
    with pytest.raises(JournalError) as e:
        Journal.open(path, header, resume=True, plan=plan)
    assert e.value.exit_code == 2 and "\n" not in str(e.value)
    for w in words:
        assert w in str(e.value), (w, str(e.value))
    assert path.read_bytes() == before  # nothing lost


def _copy(folder, dst):
    import shutil

    shutil.copytree(folder, dst)
    return dst


@pytest.mark.parametrize("damage, words", [
    ("flip", ["checksum mismatch"]),
    ("remove", ["missing"]),
    ("add", ["not recorded"]),
], ids=["a bit flipped", "a shard removed", "a file added"])
def test_model_folder_checksums_are_verified(models, tmp_path, capsys, damage, words):
    m = _copy(models, tmp_path / "m")
    shard = sorted(p for p in (m / "checkpoint").rglob("*") if p.is_file()
                   and "/d/" in p.as_posix())[0]
    if damage == "flip":
        raw = bytearray(shard.read_bytes())
        raw[len(raw) // 2] ^= 0x10
        shard.write_bytes(bytes(raw))
    elif damage == "remove":
        shard.unlink()
    else:
        (m / "checkpoint" / "extra").write_text("x")
    with pytest.raises(ModelFolderError, match=words[0]):
        load_models(m)
    f = save_native(tmp_path / "s.npz", _samples(n=80).without_truth(), ROBOT)
    assert main(["estimate", "--models", str(m), "--samples", str(f)]) == 2
    _one_line(capsys, *words)


def test_a_corrupt_folder_is_not_copied(models, tmp_path):
    """``copy_models`` (models_real from the folds' folders) copies the checkpoint's files as
    they are: it verifies them first, and a damaged source is load_models' error, with
    nothing written."""
    from jaxinertia.app.pipeline import copy_models  # noqa: PLC0415

    m = _copy(models, tmp_path / "m")
    shard = sorted(p for p in (m / "checkpoint").rglob("*") if p.is_file()
                   and "/d/" in p.as_posix())[0]
    raw = bytearray(shard.read_bytes())
    raw[len(raw) // 2] ^= 0x10
    shard.write_bytes(bytes(raw))
    with pytest.raises(ModelFolderError, match="checksum mismatch"):
        copy_models(m, tmp_path / "copy")
    assert not (tmp_path / "copy").exists()
    good = copy_models(models, tmp_path / "good", session_strength=0.5)
    assert load_models(good).config["copied_from"] == str(models.resolve())


def test_a_folder_without_checksums_loads_with_a_note(models, tmp_path, capsys):
    m = _copy(models, tmp_path / "old")
    c = json.loads((m / "config.json").read_text())
    del c["checksums"]
    (m / "config.json").write_text(json.dumps(c))
    assert load_models(m).config["n_models"] == 2
    assert "has no checksums" in capsys.readouterr().err


@pytest.mark.parametrize("config, words", [
    (b"[1, 2]", ["config.json", "got list"]),
    (b'{"format": "\xff\xfe"}', ["config.json", "unreadable", "utf-8"]),
    ("hidden", ["have shape", "needs"]),
], ids=["a list", "not UTF-8", "shapes disagree"])
def test_bad_model_configs_are_one_line(models, tmp_path, capsys, config, words):
    m = _copy(models, tmp_path / "m")
    if config == "hidden":  # the architecture no longer matches the checkpoint's shapes
        c = json.loads((m / "config.json").read_text())
        c["attention_model"]["hidden"] += 4
        (m / "config.json").write_text(json.dumps(c))
    else:
        (m / "config.json").write_bytes(config)
    f = save_native(tmp_path / "s.npz", _samples(n=80).without_truth(), ROBOT)
    assert main(["estimate", "--models", str(m), "--samples", str(f)]) == 2
    _one_line(capsys, *words)


# ---- 5. every other refusal: one line, exit 2, before the work --------------------------


def _file(tmp_path, kind) -> str:
    """The bad sample file of each case."""
    d = _samples(n=80, n_obj=1, seed=4)
    if kind == "empty":
        return str(save_native(tmp_path / "s.npz", d.take(np.arange(0)), ROBOT))
    if kind == "none at rest":
        return str(save_native(tmp_path / "s.npz", d.replace(at_rest=np.zeros(80, bool)),
                               ROBOT))
    if kind == "unknown objects":  # collect --object unknown
        return str(save_native(tmp_path / "s.npz", d.without_truth(), ROBOT))
    if kind == "one object timed out":
        d = _samples(n=80, n_obj=2, seed=4)
        return str(save_native(tmp_path / "s.npz", d.replace(at_rest=d.object_id == 0), ROBOT))
    x = d.x.copy()
    x[0] = {"negative mass": [-0.1, 0, 0, 0], "zero mass with a COM": [0.0, 0.01, 0, 0],
            "empty gripper": [0.0, 0, 0, 0]}[kind]
    return _raw_native(tmp_path / "s.npz", d.replace(x=x, tau=d.tau_g + d.A @ x[0]), ["o0"])


@pytest.mark.parametrize("command, kind, words", [
    ("estimate", "empty", ["the file holds none"]),
    ("estimate", "none at rest", ["all 80 timed out"]),
    ("estimate", "one object timed out", ["[o1]", "all 80 samples of this object"]),
    ("evaluate", "one object timed out", ["[o1]", "all 80 samples of this object"]),
    ("evaluate", "negative mass", ["[x]", "'o0'", "must be positive"]),
    ("estimate", "zero mass with a COM", ["[x]", "must be positive"]),
    ("evaluate", "empty gripper", ["mass 0"]),
    ("evaluate", "unknown objects", ["[tau]", "unknown here", "`jaxinertia estimate` answers"]),
])
def test_sample_files_without_an_answer_are_refused(command, kind, words, tmp_path, capsys):
    f = _file(tmp_path, kind)
    assert main([command, "--models", str(tmp_path / "no-models"), "--samples", f]) == 2
    _one_line(capsys, *words)


def test_training_on_unknown_objects_points_to_estimate(tmp_path, capsys):
    f = _file(tmp_path, "unknown objects")
    assert main(["train", "--data", f, "--out", str(tmp_path / "m")]) == 2
    _one_line(capsys, "[tau]", "unknown here", "`jaxinertia estimate` answers")
    assert not (tmp_path / "m").exists()


def test_evaluate_names_only_its_own_options(tmp_path, capsys):
    f = save_native(tmp_path / "s.npz", _samples(n=80), ROBOT)  # object "o0": no size known
    assert main(["evaluate", "--models", str(tmp_path / "none"), "--samples", str(f)]) == 2
    _one_line(capsys, "--l-max o0=METRES")
    assert main(["evaluate", "--models", str(tmp_path / "none"), "--samples", str(f),
                 "--l-max", "o0=0.1"]) == 2  # the option exists: now the models are missing
    _one_line(capsys, "no config.json")


@pytest.mark.parametrize("argv, words", [
    (["train", "--data", "D", "D", "--out", "m"], ["--data", "same file"]),
    (["train", "--data", "D", "COPY", "--out", "m"], ["--data", "same file"]),
    (["train", "--data", "D", "--init", "PAPER", "--torque-model", "physical", "--out", "m"],
     ["--torque-model physical", "'paper'"]),
    (["train", "--data", "D", "--trainable", "attention", "--out", "m"],
     ["--trainable attention", "--init"]),
    (["plan-poses", "--n", "1", "--out", "p.json"], ["--n", "at least 2"]),
    (["simulate", "--scenario", "test", "--n", "200000000", "--out", "x.npz"],
     ["--n 200000000", "JAXINERTIA_MAX_MEMORY_GB"]),
    (["plan-poses", "--step-deg", "0.05", "--out", "p.json"],
     ["--step-deg 0.05", "JAXINERTIA_MAX_MEMORY_GB"]),
    (["collect", "--port", "/dev/null", "--plan", "random", "--n", "1000000000", "--object",
      "cube", "--out", "x.npz"], ["--n 1000000000", "JAXINERTIA_MAX_MEMORY_GB"]),
    (["simulate", "--scenario", "test", "--calibration", "FIVE", "--out", "x.npz"],
     ["FIVE", "got int"]),
    (["simulate", "--scenario", "test", "--calibration", "LATIN1", "--out", "x.npz"],
     ["LATIN1", "not a readable calibration"]),
    (["simulate", "--scenario", "test", "--plan", "LATIN1", "--out", "x.npz"],
     ["LATIN1", "not JSON"]),
    # A non-UTF-8 path is read by Python, never handed to OpenCV (which crashed on it):
    # a missing file is one line like any other (tests/test_vision.py: such files work).
    (["tag-pose", "--image", "caf\udce9.png", "--intrinsics", "i.json"],
     ["i.json", "no such intrinsics file"]),
], ids=["--data f f", "--data f copy", "--init paper --torque-model physical",
        "--trainable attention without --init", "plan-poses --n 1", "simulate --n 2e8",
        "plan-poses --step-deg 0.05", "collect --n 1e9",
        "calibration 5", "calibration latin-1", "plan latin-1", "non-UTF-8 path"])
def test_requests_refused_before_the_work(argv, words, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    save_native(tmp_path / "D", _samples(seed=5), ROBOT)
    (tmp_path / "COPY").write_bytes((tmp_path / "D").read_bytes())
    (tmp_path / "PAPER").mkdir()
    (tmp_path / "PAPER" / "config.json").write_text('{"torque_model": {"kind": "paper"}}')
    (tmp_path / "FIVE").write_text("5")
    (tmp_path / "LATIN1").write_bytes(b'{"caf\xe9": 1}')
    before = sorted(p.name for p in tmp_path.iterdir())
    assert main(argv) == 2
    _one_line(capsys, *words)
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # nothing written


def test_the_memory_limit_is_the_users(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("JAXINERTIA_MAX_MEMORY_GB", "0.001")
    assert main(["simulate", "--scenario", "test", "--n", "1000", "--out",
                 str(tmp_path / "x.npz")]) == 2
    _one_line(capsys, "above the limit 0.001 GB")
    monkeypatch.setenv("JAXINERTIA_MAX_MEMORY_GB", "lots")
    assert main(["simulate", "--scenario", "test", "--n", "1000", "--out",
                 str(tmp_path / "x.npz")]) == 2
    _one_line(capsys, "JAXINERTIA_MAX_MEMORY_GB='lots'")


SEEDED = [["train", "--data", "a.npz", "--out", "m"],
          ["simulate", "--scenario", "test", "--out", "x.npz"],
          ["collect", "--port", "/dev/null", "--plan", "random", "--object", "cube", "--out",
           "x.npz"],
          ["virtual-robot"], ["plan-poses", "--out", "p.json"], ["lbipe-benchmark"],
          ["evaluate", "--models", "m"], ["calibrate", "--out", "c.json"], ["reproduce"]]


@pytest.mark.parametrize("value", ["-1", "1e23", "4294967296"])
@pytest.mark.parametrize("base", SEEDED, ids=[a[0] for a in SEEDED])
def test_bad_seeds_are_refused_when_parsed(base, value, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main([*base, "--seed", value]) == 2
    _one_line(capsys, "--seed", "an integer in 0..4294967295")
    assert not any(tmp_path.iterdir())


def test_reproduce_refuses_no_training_draw_and_its_help_gives_each_scales(
        tmp_path, capsys, monkeypatch):
    from jaxinertia.app.reproduce import FULL, QUICK

    monkeypatch.chdir(tmp_path)
    assert main(["reproduce", "--draws", "0"]) == 2
    _one_line(capsys, "--draws")
    assert not any(tmp_path.iterdir())
    assert main(["reproduce", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    assert f"(quick {QUICK.fold_draws}, full {FULL.fold_draws})" in text


def test_ctrl_c_in_train_ends_in_one_line(tmp_path, capsys, monkeypatch):
    from jaxinertia.app import pipeline

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(pipeline, "train", interrupted)
    assert main(["train", "--data", str(tmp_path / "a.npz"), "--out",
                 str(tmp_path / "m")]) == 130
    _one_line(capsys, "interrupted")
    assert not any(tmp_path.iterdir())


def test_truncated_released_weights_are_one_line(lbipe_dir, tmp_path, capsys):
    (tmp_path / "data").symlink_to(lbipe_dir / "data")
    (tmp_path / "weights").mkdir()
    for w in (lbipe_dir / "weights").iterdir():
        (tmp_path / "weights" / w.name).symlink_to(w)
    torn = tmp_path / "weights" / "dict_attn_3.npz"
    raw = torn.read_bytes()
    torn.unlink()
    torn.write_bytes(raw[: len(raw) // 2])
    assert main(["lbipe-benchmark", "--lbipe-dir", str(tmp_path)]) == 2
    _one_line(capsys, "model pair 3", "torn or corrupt")


def test_orbax_closed_loop_noise_is_dropped_and_nothing_else(monkeypatch):
    seen = []
    monkeypatch.setattr(sys, "__unraisablehook__", seen.append)

    class Unraisable:
        def __init__(self, exc):
            self.exc_value = exc

    cli._quiet_closed_loops(Unraisable(RuntimeError("Event loop is closed")))
    other = Unraisable(RuntimeError("something else"))
    cli._quiet_closed_loops(other)
    assert seen == [other]


def test_library_messages_name_arguments_and_the_cli_names_flags(tmp_path):
    """A library error names the caller's argument (`` `overwrite` ``), never a flag; the
    command line words the same message with the command's flags."""
    from jaxinertia.app.options import flag_wording
    from jaxinertia.errors import UsageError

    (tmp_path / "x.npz").write_bytes(b"")
    with pytest.raises(UsageError) as e:
        check_output(tmp_path / "x.npz")
    said = str(e.value)
    assert "--" not in said and "`out`" in said and "`overwrite`" in said
    assert flag_wording(said) == (f"--out {tmp_path / 'x.npz'} exists; pass --overwrite to "
                                  "replace it")
    assert flag_wording("`objects` ['x']: no", "calibrate") == "--real-objects ['x']: no"
    assert (flag_wording("`step_deg` and `l_max` mystery=METRES")
            == "--step-deg and --l-max mystery=METRES")
