"""A model folder that answers with the mean of several (``jaxinertia.app.ensemble``):
estimate and evaluate of a folder that names members give the mean of what each member
gives on its own, per model pair and set; the baselines stay the folder's own."""

from __future__ import annotations

import json

import numpy as np
import pytest
from support.synthetic import feature_config, synthetic_samples, tiny_pair

from jaxinertia.app.cli import main
from jaxinertia.app.ensemble import ENSEMBLE_MEMBERS, attach_members
from jaxinertia.app.estimate import estimate
from jaxinertia.app.pipeline import copy_models, evaluate_models
from jaxinertia.baselines import fit_baselines
from jaxinertia.errors import ModelFolderError, UsageError
from jaxinertia.evaluation import choose_sets, evaluate
from jaxinertia.metrics import inertial_metrics
from jaxinertia.samples import save_native
from jaxinertia.statics import torque_scale_sensitivity

ROBOT = "open_manipulator_x"
MEMBERS = ["members/1", "members/2"]


def _x(answer: dict) -> np.ndarray:
    """``x = [m, m p]`` of one method's answer as ``estimate`` gives it."""
    return np.r_[answer["mass_kg"], answer["mass_kg"] * np.asarray(answer["com_tag_m"])]


@pytest.fixture(scope="module")
def folders(tmp_path_factory):
    """A sample file and three folders of untrained pairs: one, and two more inside it
    (seeds whose pairs all give a physically possible answer on that file)."""
    tmp = tmp_path_factory.mktemp("ensemble")
    d = synthetic_samples(np.random.default_rng(11), n=96, n_obj=1)
    path = save_native(tmp / "s.npz", d, {"robot": ROBOT})
    b = fit_baselines(d.q_d, d.q, d.direction, d.current_tau, d.q_d)
    from jaxinertia.checkpoints import save_models  # noqa: PLC0415 - orbax at first use

    save_models(tmp / "m", tiny_pair(seed=0), b, feature_config(), robot=ROBOT)
    for seed, name in zip((1, 3), MEMBERS):
        save_models(tmp / "m" / name, tiny_pair(seed=seed), b, feature_config(), robot=ROBOT)
    return d, path, tmp / "m"


def test_the_answer_is_the_members_mean_and_the_baselines_the_folders(folders, capsys):
    d, path, models = folders
    kw = dict(set_size=32, n_sets=8, max_mass=1e3, max_com=1e3)
    alone = [estimate(models / sub, path, **kw) for sub in (".", *MEMBERS)]
    attach_members(models, MEMBERS)
    assert json.loads((models / "config.json").read_text())[ENSEMBLE_MEMBERS] == MEMBERS
    both = estimate(models, path, **kw)
    assert both["ensemble_members"] == [str(models / n) for n in MEMBERS]
    (name,) = both["objects"]
    m = both["objects"][name]["methods"]
    a = [r["objects"][name]["methods"] for r in alone]
    for method in ("Sensor", "PE"):  # the baselines: the folder's own, whole
        assert m[method] == a[0][method]
    # What 1 % of a joint's torque moves T's answer (every row alike): the statics' own
    # sensitivity at the members' mean (jaxinertia.statics, checked against new solves).
    assert m["T"]["ok"], m["T"]
    np.testing.assert_allclose(m["T"]["servo_state_sensitivity"]["mass_kg"],
                               torque_scale_sensitivity(d.A, d.tau_g, _x(m["T"]),
                                                        rel=0.01)[:, 0], rtol=1e-9)
    answered = 0
    for method in ("T", "T-A"):
        if not (m[method]["ok"] and all(r[method]["ok"] for r in a)):
            continue
        answered += 1
        # Each member's answer is the mean over its K pairs: the mean of the three is the
        # mean of x over every member and pair.
        x = np.array([_x(r[method]) for r in a])
        want = x.mean(axis=0)
        assert m[method]["mass_kg"] == pytest.approx(want[0], rel=1e-9)
        np.testing.assert_allclose(m[method]["com_tag_m"], want[1:] / want[0], rtol=1e-9)
        # Covariance: the members' residual parts averaged, plus the spread of every
        # member's pairs (at least the spread of the members' means, which it contains).
        noise = np.mean([r[method]["covariance_terms"]["noise"] for r in a], axis=0)
        np.testing.assert_allclose(m[method]["covariance_terms"]["noise"], noise, rtol=1e-9)
        spread = np.asarray(m[method]["covariance_terms"]["ensemble"])
        assert spread[0, 0] >= np.var(x[:, 0], ddof=1) * (len(x) - 1) / (3 * 2 - 1) - 1e-18
        np.testing.assert_allclose(m[method]["covariance_x"], noise + spread, rtol=1e-9)
    assert answered > 0, "no network method answered in every folder: nothing was checked"
    assert main(["estimate", "--models", str(models), "--samples", str(path), "--set-size",
                 "32", "--max-mass", "1000", "--max-com", "1000"]) == 0
    assert "the mean of these models and 2 more inside them" in capsys.readouterr().out
    # Table I of such a folder: the metrics of the mean of the members' estimates, per
    # model pair and set; the baselines' the folder's own.
    # No fine-tuning starts from the mean of several folders.
    capsys.readouterr()
    assert main(["train", "--init", str(models), "--data", str(path), "--out",
                 str(models.parent / "ft")]) == 2
    assert "no one set of models to start from" in capsys.readouterr().err
    assert not (models.parent / "ft").exists()
    # (A copy of the folder is its own models alone: it names no members it lacks.)
    copy = copy_models(models, models.parent / "copy")
    assert ENSEMBLE_MEMBERS not in json.loads((copy / "config.json").read_text())
    sets, _ = choose_sets(d.by_object(), n_sets=8, set_size=32, seed=0)
    res = evaluate_models(models, d.by_object(), sets, l_max=[0.1])
    plain = [evaluate_models(f, d.by_object(), sets, l_max=[0.1])
             for f in (copy, *(models / n for n in MEMBERS))]
    for method in ("T", "T-A"):
        x = np.mean([p["estimates"][method] for p in plain], axis=0).reshape(-1, 4)
        x = x[np.all(np.isfinite(x), axis=-1)]
        want = inertial_metrics(x, d.by_object()[0].x[0], 0.1)
        got = res["objects"][name][method]
        assert got == pytest.approx(want, rel=1e-9)
    assert res["objects"][name]["PE"] == plain[0]["objects"][name]["PE"]
    assert res["ensemble_members"] == [str(models / n) for n in MEMBERS]


def test_members_must_be_there_and_agree_in_model_count(folders, tmp_path):
    d, path, models = folders
    with pytest.raises(FileNotFoundError, match="no model folder to average"):
        attach_members(models, ["members/none"])
    from jaxinertia.checkpoints import save_models  # noqa: PLC0415 - orbax at first use

    b = fit_baselines(d.q_d, d.q, d.direction, d.current_tau, d.q_d)
    save_models(tmp_path / "m", tiny_pair(seed=0), b, feature_config(), robot=ROBOT)
    save_models(tmp_path / "m" / "three", tiny_pair(K=3, seed=1), b, feature_config(),
                robot=ROBOT)
    attach_members(tmp_path / "m", ["three"])
    sets, _ = choose_sets(d.by_object(), n_sets=4, set_size=32, seed=0)
    with pytest.raises(UsageError, match="as many model pairs each"):
        evaluate_models(tmp_path / "m", d.by_object(), sets, l_max=[0.1])
    # A member is a plain folder inside, named once: not the folder itself (evaluate would
    # recurse), not one that answers with members of its own (estimate reads a member's
    # own models only, evaluate would read its members too).
    for names, match in ((["three", "three"], "named twice"), (["."], "inside"),
                         (["../m/three"], None), (["three/.."], "inside")):
        if match is None:  # (a roundabout name of a folder inside is that folder)
            attach_members(tmp_path / "m", names)
            continue
        with pytest.raises(UsageError, match=match):
            attach_members(tmp_path / "m", names)
    save_models(tmp_path / "m" / "outer", tiny_pair(seed=2), b, feature_config(), robot=ROBOT)
    save_models(tmp_path / "m" / "outer" / "inner", tiny_pair(seed=4), b, feature_config(),
                robot=ROBOT)
    attach_members(tmp_path / "m" / "outer", ["inner"])
    with pytest.raises(UsageError, match="its own models only, not with ensemble_members"):
        attach_members(tmp_path / "m", ["outer"])
    # Shares edited by hand to another count than the members': one line naming the folder.
    attach_members(tmp_path / "m", ["outer/inner"], [1.0, 1.0])
    config = json.loads((tmp_path / "m" / "config.json").read_text())
    config["ensemble_weights"] = [0.5, 0.25, 0.25]
    (tmp_path / "m" / "config.json").write_text(json.dumps(config))
    with pytest.raises(ModelFolderError, match=r"m \[ensemble_weights\]: 2 shares >= 0"):
        evaluate_models(tmp_path / "m", d.by_object(), sets, l_max=[0.1])
    with pytest.raises(ModelFolderError, match=r"ensemble_weights\]: 2 shares"):
        estimate(tmp_path / "m", path, set_size=32, n_sets=4, max_mass=1e3, max_com=1e3)


def test_a_folder_without_its_attention_answers_t_a_as_t(folders, capsys):
    """``copy_models(..., uniform=True)`` (models_real where the folds judged a part better
    without the attention): every joint of every sample weighted alike, so T-A's weighted
    least squares solves T's, set by set; recorded, and said by ``estimate``."""
    d, path, models = folders
    flat = copy_models(models / "members/1", models.parent / "flat", uniform=True)
    assert json.loads((flat / "config.json").read_text())["uniform_attention"] is True
    # The weights' files are copied as they are (the record says to zero the attention's
    # last layer when loading): the checkpoint byte for byte the source's.
    files = sorted(p.relative_to(flat / "checkpoint") for p in
                   (flat / "checkpoint").rglob("*") if p.is_file())
    assert files and files == sorted(p.relative_to(models / "members/1/checkpoint") for p in
                                     (models / "members/1/checkpoint").rglob("*")
                                     if p.is_file())
    for f in files:
        assert (flat / "checkpoint" / f).read_bytes() == (
            models / "members/1/checkpoint" / f).read_bytes(), f
    sets, _ = choose_sets(d.by_object(), n_sets=8, set_size=32, seed=0)
    res = evaluate_models(flat, d.by_object(), sets, l_max=[0.1])
    np.testing.assert_allclose(res["estimates"]["T-A"], res["estimates"]["T"], rtol=1e-9,
                               atol=1e-12)
    (name,) = res["objects"]
    w = np.asarray(res["objects"][name]["mean_attention_weight"])
    np.testing.assert_allclose(w, 0.25, rtol=1e-6)
    before = evaluate_models(models / "members/1", d.by_object(), sets, l_max=[0.1])
    assert not np.allclose(before["estimates"]["T-A"], before["estimates"]["T"])
    assert main(["estimate", "--models", str(flat), "--samples", str(path), "--set-size",
                 "32", "--max-mass", "1000", "--max-com", "1000"]) == 0
    assert "T-A answers as T" in capsys.readouterr().out


def test_several_objects_are_evaluated_by_the_one_object_programs(folders):
    """``evaluate`` goes object by object (each padded to the largest sample count): the
    evaluation of two objects compiles nothing that the evaluations of one each did not
    (``models_real`` on every real file after the folds judged each folder on one), and
    gives their numbers."""
    from support.compiles import compile_counter  # noqa: PLC0415

    from jaxinertia.checkpoints import load_models  # noqa: PLC0415
    from jaxinertia.evaluation import evaluate  # noqa: PLC0415

    d, _, models = folders
    one = d.by_object()[0]
    two = [one, one.take(np.arange(80)).replace(names=("other",))]
    folder = load_models(models / "members/2")
    sets, _ = choose_sets(two, n_sets=6, set_size=32, seed=0)
    kw = dict(pair=folder.pair, baselines=folder.baselines, fc=folder.features)
    alone = [evaluate([o], [s], l_max=[0.1], **kw) for o, s in zip(two[:1], sets[:1])]
    with compile_counter("estimate_sets", "identity_solves") as seen:
        both = evaluate(two, sets, l_max=[0.1, 0.1], **kw)
    assert sum(seen.compiles.values()) == 0, seen.compiles
    for m in ("Sensor", "PE", "T", "T-A"):
        np.testing.assert_array_equal(both["estimates"][m][:1], alone[0]["estimates"][m])
        assert both["objects"][one.name][m] == alone[0]["objects"][one.name][m]
    other = evaluate(two[1:], sets[1:], l_max=[0.1], **kw)
    # The baselines solve in float64 on the samples as given: the same to rounding.
    for m in ("Sensor", "PE"):
        np.testing.assert_allclose(both["estimates"][m][1:], other["estimates"][m], rtol=1e-12)
    # The torque models run in float32 on the padded batch (80 samples padded to the first
    # object's count): XLA's CPU may pick another matmul kernel for another row count, so
    # the second object's torques can differ by float32 rounding (1.2e-6 relative in x on
    # session 47's AMD EPYC, bit-equal on session 46's). A set that picked the wrong rows
    # or a padded sample (an indexing error of the stacking) moves x by far more.
    np.testing.assert_allclose(both["estimates"]["T"][1:], other["estimates"]["T"],
                               rtol=1e-5)
    # Their results are stacked: objects with sets of another shape are refused, one line.
    with pytest.raises(UsageError, match="differ in shape across objects"):
        evaluate(two, [sets[0], sets[1][:3]], l_max=[0.1, 0.1], **kw)


def test_shares_weigh_the_members_and_another_model_count_enters_by_its_pairs_mean(
        folders, tmp_path, capsys):
    """``attach_members(..., weights)`` (models_real_with_released: the released models'
    half): evaluate and estimate give the weighted mean of what each folder gives alone; a
    member of another model count then enters with its pairs' mean on each set."""
    d, path, _ = folders
    from jaxinertia.checkpoints import save_models  # noqa: PLC0415 - orbax at first use

    b = fit_baselines(d.q_d, d.q, d.direction, d.current_tau, d.q_d)
    models = tmp_path / "m"
    save_models(models, tiny_pair(seed=0), b, feature_config(), robot=ROBOT)
    save_models(models / "two", tiny_pair(seed=1), b, feature_config(), robot=ROBOT)
    save_models(models / "three", tiny_pair(K=3, seed=3), b, feature_config(), robot=ROBOT)
    for bad in ([1.0, 1.0], [1.0, -1.0, 1.0], [0.0, 0.0, 0.0], [1.0, np.nan, 1.0],
                "0.5,0.5,1", {"two": 1.0}, [1e308, 1e308, 1e308], ["a", "b", "c"],
                ["1", "2", "3"], [True, False, True], [1, 10**400, 1]):
        with pytest.raises(UsageError, match="shares >= 0"):
            attach_members(models, ["two", "three"], bad)
    attach_members(models, ["two", "three"], [1.0, 1.0, 2.0])
    assert json.loads((models / "config.json").read_text())["ensemble_weights"] == [
        0.25, 0.25, 0.5]
    sets, _ = choose_sets(d.by_object(), n_sets=8, set_size=32, seed=0)
    res = evaluate_models(models, d.by_object(), sets, l_max=[0.1])
    copy = copy_models(models, tmp_path / "copy")
    # (the copy is the folder's own models alone: neither members nor their shares)
    assert not {"ensemble_members", "ensemble_weights"} & set(
        json.loads((copy / "config.json").read_text()))
    plain = [evaluate_models(f, d.by_object(), sets, l_max=[0.1])["estimates"]
             for f in (copy, models / "two", models / "three")]
    (name,) = res["objects"]
    for method in ("T", "T-A"):
        a, b2, c = (np.asarray(p[method], np.float64) for p in plain)
        assert a.shape[1] == 2 and c.shape[1] == 3
        want = 0.25 * a + 0.25 * b2 + 0.5 * c.mean(axis=1, keepdims=True)
        np.testing.assert_allclose(res["estimates"][method], want, rtol=1e-9, atol=1e-15)
        x = want.reshape(-1, 4)
        x = x[np.all(np.isfinite(x), axis=-1)]
        assert res["objects"][name][method] == pytest.approx(
            inertial_metrics(x, d.by_object()[0].x[0], 0.1), rel=1e-9)
    assert res["ensemble_weights"] == [0.25, 0.25, 0.5]
    # estimate: the answer on all samples is the weighted mean of each folder's answer
    # (each folder's the mean over its own pairs), and says the shares.
    kw = dict(set_size=32, n_sets=8, max_mass=1e3, max_com=1e3)
    alone = [estimate(f, path, **kw)["objects"][name]["methods"]
             for f in (copy, models / "two", models / "three")]
    both = estimate(models, path, **kw)
    assert both["ensemble_weights"] == [0.25, 0.25, 0.5]
    m = both["objects"][name]["methods"]
    answered = 0
    for method in ("T", "T-A"):
        if not (m[method]["ok"] and all(r[method]["ok"] for r in alone)):
            continue
        answered += 1
        x = np.array([_x(r[method]) for r in alone])
        want = np.average(x, axis=0, weights=[0.25, 0.25, 0.5])
        assert m[method]["mass_kg"] == pytest.approx(want[0], rel=1e-9)
        np.testing.assert_allclose(m[method]["com_tag_m"], want[1:] / want[0], rtol=1e-9)
        noise = np.average([r[method]["covariance_terms"]["noise"] for r in alone], axis=0,
                           weights=[0.25, 0.25, 0.5])
        np.testing.assert_allclose(m[method]["covariance_terms"]["noise"], noise, rtol=1e-9)
        # The spread: every member's pairs, each weighing its member's share over the
        # member's pair count (np.cov's aweights, ddof 1), rebuilt here from each folder's
        # own spread (ddof 1 over its K pairs) and answer (its pairs' mean).
        w, k = np.array([0.25, 0.25, 0.5]), np.array([2, 2, 3])
        own = [np.asarray(r[method]["covariance_terms"]["ensemble"]) for r in alone]
        scatter = sum(wi / ki * ((ki - 1) * ci + ki * np.outer(xi - want, xi - want))
                      for wi, ki, ci, xi in zip(w, k, own, x))
        spread = scatter / (1 - np.sum(w ** 2 / k))
        np.testing.assert_allclose(m[method]["covariance_terms"]["ensemble"], spread,
                                   rtol=1e-7, atol=1e-7 * np.abs(spread).max())
        np.testing.assert_allclose(m[method]["covariance_x"], noise + spread, rtol=1e-7,
                                   atol=1e-7 * np.abs(noise + spread).max())
    assert answered > 0, "no network method answered in every folder: nothing was checked"
    capsys.readouterr()
    assert main(["estimate", "--models", str(models), "--samples", str(path), "--set-size",
                 "32", "--max-mass", "1000", "--max-com", "1000"]) == 0
    assert "shares: 0.25 each, but three 0.5" in capsys.readouterr().out
    # A folder without its attention whose member keeps its own (the released models in
    # models_real_with_released): T-A is no longer T, and estimate does not say it is.
    flat = copy_models(models, tmp_path / "flat", uniform=True)
    copy_models(models / "three", flat / "own")
    attach_members(flat, ["own"], [1.0, 3.0])
    mixed = estimate(flat, path, **kw)
    assert mixed["uniform_attention"] is False
    # What 1 % of a joint's torque moves T-A's answer: each folder's shift with its own
    # attention (the folder's uniform, the member's its own, each pair's), by its share.
    ta = mixed["objects"][name]["methods"]["T-A"]
    assert ta["ok"], ta
    from jaxinertia.checkpoints import load_models  # noqa: PLC0415

    own = load_models(flat / "own")
    obj = d.by_object()[0]
    w_own = np.asarray(evaluate([obj], [np.arange(obj.n_samples)[None]], pair=own.pair,
                                fc=own.features, l_max=[np.nan])["model_estimates"]
                       .weights[0])  # (K, S, N)
    assert not np.allclose(w_own, 0.25)  # the member's attention is not the folder's

    def moved(w):
        return torque_scale_sensitivity(d.A, d.tau_g, _x(ta), w, rel=0.01)[:, 0]

    want = 0.25 * moved(None) + 0.75 * np.mean([moved(w) for w in w_own], axis=0)
    np.testing.assert_allclose(ta["servo_state_sensitivity"]["mass_kg"], want, rtol=1e-6)
    assert not np.allclose(want, moved(None), rtol=1e-3)  # the member's weights count
    assert main(["estimate", "--models", str(flat), "--samples", str(path), "--set-size",
                 "32", "--max-mass", "1000", "--max-com", "1000"]) == 0
    assert "T-A answers as T" not in capsys.readouterr().out


def test_members_side_by_side_give_the_loops_answers_in_its_order(folders, monkeypatch):
    """``map_members`` runs the members in threads: the results in the members' order (the
    first finishing last here), a failing member's error as the loop raises it (the first
    in order), and an ensemble's evaluation and estimate the loop's, bit for bit."""
    import time  # noqa: PLC0415

    from jaxinertia.app import ensemble  # noqa: PLC0415

    monkeypatch.setattr(ensemble.os, "cpu_count", lambda: 4)
    monkeypatch.setattr(ensemble, "MEMBER_THREADS", 4)
    assert ensemble.map_members(lambda m: time.sleep(0.05 * (4 - m)) or m * m,
                                range(4)) == [0, 1, 4, 9]

    def failing(m):
        if m in (1, 3):
            raise ValueError(f"member {m}")
        return m

    with pytest.raises(ValueError, match="member 1"):
        ensemble.map_members(failing, range(4))

    d, path, models = folders
    attach_members(models, MEMBERS)
    sets, _ = choose_sets(d.by_object(), n_sets=8, set_size=32, seed=0)
    kw = dict(set_size=32, n_sets=8, max_mass=1e3, max_com=1e3)
    answers = {}
    for threads in (4, 1):
        monkeypatch.setattr(ensemble, "MEMBER_THREADS", threads)
        answers[threads] = (evaluate_models(models, d.by_object(), sets, l_max=[0.1]),
                            estimate(models, path, **kw))
    (ev4, est4), (ev1, est1) = answers[4], answers[1]
    for m in ("T", "T-A"):
        np.testing.assert_array_equal(ev4["estimates"][m], ev1["estimates"][m])
    (name,) = est1["objects"]
    assert est4["objects"][name]["methods"] == est1["objects"][name]["methods"]
