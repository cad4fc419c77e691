"""Fine-tuning a model folder on new samples (``train --init``), the physics-structured
torque model (``train --torque-model physical``) and domain randomization of the
simulator (issue "Sim-to-real II")."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from support.asserts import assert_tree_equal
from support.synthetic import feature_config, synthetic_samples

from jaxinertia.app.cli import main
from jaxinertia.app.ensemble import attach_members
from jaxinertia.app.estimate import estimate
from jaxinertia.app.pipeline import (
    adapt_objects,
    copy_models,
    evaluate_samples,
    session_reference,
)
from jaxinertia.app.provenance import FITTED_ON, fitted_on, seen_by
from jaxinertia.baselines import fit_baselines
from jaxinertia.checkpoints import load_models, save_models
from jaxinertia.errors import JaxinertiaError, ModelFolderError, UsageError
from jaxinertia.estimation import ModelPair
from jaxinertia.networks import AttentionModel, PhysicalTorqueModel, TorqueModel
from jaxinertia.reference import reference_correction
from jaxinertia.samples import Samples, load_samples, save_native
from jaxinertia.session import servo_session
from jaxinertia.session_terms import with_session_terms
from jaxinertia.sim.params import default_sim_params
from jaxinertia.sim.randomize import (
    SESSION_PRIOR_REL,
    DomainSpread,
    SessionSpread,
    drawn,
    perturbed,
    session_prior,
    spread_from_samples,
)
from jaxinertia.training import (
    TrainConfig,
    _start,
    feature_config_from,
    per_object_subset,
    split_validation,
    torque_predictions,
    train_torque_models,
)
from jaxinertia.uncertainty import training_validation_error, validation_torque_error

# float32 networks evaluated twice the same way: equal up to float32 rounding.
F32 = {"rtol": 1e-5, "atol": 1e-6}
TINY = ["--n-models", "2", "--torque-epochs", "8", "--attention-epochs", "2",
        "--attention-sets", "6", "--attention-val-sets", "3", "--set-size", "16",
        "--torque-batch", "64", "--attention-batch", "4"]


def _file(path, rng, n, extra=None, **law):
    d = synthetic_samples(rng, n=n, **law)
    d = d.replace(extra={**d.extra, **(extra or {})})
    save_native(path, d, {"robot": "open_manipulator_x", "objects": list(d.names),
                          "source": "test"})
    return path


def _recorded_state(n, seed=12):
    """What ``collect`` records beside each sample: each servo's supply [V] (0.1 V steps)
    and temperature [deg C]."""
    rng = np.random.default_rng(seed)
    return {"voltage": 11.8 + 0.1 * rng.integers(-1, 2, (n, 4)),
            "temperature": 36.0 + rng.integers(0, 4, (n, 4)).astype(float)}


@pytest.fixture(scope="module")
def folders(tmp_path_factory):
    """A folder trained on one synthetic servo law and a file of another (stiffer, more
    friction): what fine-tuning adapts to."""
    tmp = tmp_path_factory.mktemp("finetune")
    rng = np.random.default_rng(11)
    sim = _file(tmp / "sim.npz", rng, 600)
    real = _file(tmp / "real.npz", rng, 300, k=(19.0, 22.0, 18.0, 11.0),
                 f=(0.04, 0.09, 0.05, 0.02), extra=_recorded_state(300))
    assert main(["train", "--data", str(sim), "--out", str(tmp / "m0"), *TINY]) == 0
    return tmp, sim, real


def test_physical_torque_model_is_its_servo_law_plus_the_residual():
    model = PhysicalTorqueModel()
    feats = jax.random.uniform(jax.random.key(0), (7, 4, 4), jnp.float32, -1.0, 1.0)
    feats = feats.at[..., 2].set(feats[..., 2] > 0).at[..., 3].set(feats[..., 2] <= 0)
    v = model.init(jax.random.key(1), feats)
    rng = np.random.default_rng(2)
    p = {**v["params"], **{k: jnp.asarray(rng.normal(size=4), jnp.float32)
                           for k in ("stiffness", "offset", "friction", "load_friction")}}
    out = np.asarray(model.apply({"params": p}, feats))
    e, s = np.asarray(feats[..., 1]), np.asarray(feats[..., 2] - feats[..., 3])
    k, c, f, g = (np.asarray(p[n]) for n in ("stiffness", "offset", "friction",
                                             "load_friction"))
    residual = np.asarray(TorqueModel().apply({"params": p["residual"]}, feats))
    np.testing.assert_allclose(out, k * e + c + s * (f + g * np.abs(k * e)) + residual, **F32)


def test_physical_model_round_trips_and_older_folders_read_as_the_paper_network(tmp_path):
    feats = jnp.zeros((1, 4, 4), jnp.float32)
    tm, am = PhysicalTorqueModel(), AttentionModel()
    keys = jax.random.split(jax.random.key(3), 2)
    pair = ModelPair(jax.vmap(lambda k: tm.init(k, feats))(keys),
                     jax.vmap(lambda k: am.init(k, feats))(keys),
                     jnp.asarray([0.4, 1.2, 0.6, 0.3], jnp.float32), tm, am)
    d = synthetic_samples(np.random.default_rng(4))
    fc = feature_config()
    b = fit_baselines(d.q_d, d.q, d.direction, d.current_tau, d.tau)
    save_models(tmp_path / "m", pair, b, fc, robot="open_manipulator_x")
    folder = load_models(tmp_path / "m")
    pair2, config = folder.pair, folder.config
    assert type(pair2.torque_model) is PhysicalTorqueModel
    assert config["torque_model"]["kind"] == "physical"
    assert_tree_equal(pair2, pair, what="a physical ModelPair after a round trip")
    cfg_path = tmp_path / "m" / "config.json"
    doc = json.loads(cfg_path.read_text())
    doc["torque_model"]["kind"] = "quantum"
    cfg_path.write_text(json.dumps(doc))
    with pytest.raises(ModelFolderError, match="unknown torque model kind 'quantum'"):
        load_models(tmp_path / "m")
    # A folder of the paper's network written before the option (no "kind") still loads.
    save_models(tmp_path / "p", pair.replace(torque_vars=jax.vmap(
        lambda k: TorqueModel().init(k, feats))(keys), torque_model=TorqueModel()), b, fc,
        robot="open_manipulator_x")
    doc = json.loads((tmp_path / "p" / "config.json").read_text())
    assert doc["torque_model"].pop("kind") == "paper"
    (tmp_path / "p" / "config.json").write_text(json.dumps(doc))
    assert type(load_models(tmp_path / "p").pair.torque_model) is TorqueModel


def test_the_physical_model_extrapolates_a_servo_law_in_load():
    """Trained on the lighter half of the loads (small discrepancies), judged on the
    heavier half: the servo part carries the law beyond the training range, the paper's
    network (ReLU pieces fitted to the range it saw) does worse."""
    d = synthetic_samples(np.random.default_rng(5), n=1600)
    light = np.abs(d.q_d - d.q).max(axis=1) < np.median(np.abs(d.q_d - d.q).max(axis=1))
    train, val = split_validation(d.take(np.flatnonzero(light)), 0.2, 0)
    heavy = d.take(np.flatnonzero(~light))
    fc = feature_config_from(d)
    err = {}
    for kind in ("paper", "physical"):
        cfg = TrainConfig(n_models=2, torque_epochs=80, torque_lr=3e-3, torque_model=kind)
        res = train_torque_models(cfg, fc, train, val, jax.random.key(0), progress=False)
        pred = np.asarray(torque_predictions(res.model, res.variables, fc, heavy))
        err[kind] = float(np.sqrt(np.mean((pred - heavy.tau) ** 2)))
    assert err["physical"] < 0.5 * err["paper"], err


def test_finetuning_starts_from_the_folder_keeps_its_scaling_and_improves(folders, capsys):
    tmp, _, real = folders
    folder = load_models(tmp / "m0")
    pair0, fc0 = folder.pair, folder.features
    out = tmp / "ft"
    assert main(["train", "--init", str(tmp / "m0"), "--data", str(real), "--out", str(out),
                 "--samples-per-object", "60", "--torque-epochs", "30", "--torque-lr", "3e-3",
                 "--attention-epochs", "2", "--attention-sets", "6",
                 "--attention-val-sets", "3", "--set-size", "16"]) == 0
    assert "fine-tuned 2 model pairs" in capsys.readouterr().out
    folder = load_models(out)
    pair, fc, config = folder.pair, folder.features, folder.config
    assert_tree_equal(fc, fc0, what="the fine-tuned folder's feature scaling")
    assert config["fine_tuned_from"]["folder"] == str((tmp / "m0").resolve())
    assert config["samples_per_object"] == 60
    assert config["samples"]["train"] + config["samples"]["validation"] == 3 * 60
    assert config["training"]["torque_batch"] == 64  # a fine-tuning default
    # On the new law's validation split: better than the folder it started from.
    _, val = split_validation(_take(real, 60), 0.1, 0)
    before = np.abs(np.asarray(torque_predictions(pair0.torque_model, pair0.torque_vars, fc0,
                                                  val)) - val.tau).mean()
    after = np.abs(np.asarray(torque_predictions(pair.torque_model, pair.torque_vars, fc,
                                                 val)) - val.tau).mean()
    assert after < 0.7 * before, (before, after)
    # The uncertainty floor: the error training measured on the validation samples it kept
    # (recorded in the folder, not recomputed from the files).
    floor, why = training_validation_error(config)
    assert floor is not None and f"({config['samples']['validation']} samples)" in why
    ratio = np.asarray(config["data"][0]["session_ratio"])  # the file as training read it
    val_read = val.replace(q_d=val.q + (val.q_d - val.q) * ratio)
    np.testing.assert_allclose(floor, validation_torque_error(pair, fc, val_read), rtol=1e-5)


def test_samples_per_object_of_each_file_keep_the_files_objects_apart(folders):
    """A count per file (the held-out folds' trainings from scratch): each file's objects
    keep that many samples, chosen as for the file alone, even where two files hold the
    same object; a count missing for a file is refused."""
    from jaxinertia.training import subset_per_object

    _, _, real = folders
    part = load_samples(real)[0]
    got = subset_per_object([part, part], (5, 7), 3)
    assert np.bincount(got.object_id).tolist() == [5] * part.n_objects + [7] * part.n_objects
    want = Samples.concatenate([per_object_subset(part, 5, 3), per_object_subset(part, 7, 3)])
    np.testing.assert_array_equal(got.q, want.q)
    one = subset_per_object([part, part], 5, 3)  # one count: every object of every file
    assert np.bincount(one.object_id).tolist() == [5] * (2 * part.n_objects)
    with pytest.raises(UsageError, match="2 counts for 3 files"):
        subset_per_object([part, part, part], (5, 7), 3)


def sha256_of(path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _take(path, n):
    return per_object_subset(load_samples(path)[0], n, 0)


def test_finetuning_never_returns_worse_than_it_started_and_can_freeze_encoders(folders,
                                                                                 capsys):
    """Fine-tuned on the data it was trained on with a step far too large, every epoch is
    worse than the start: the start (epoch -1) is kept, bit for bit. With the encoders
    frozen they stay bit for bit while the head moves."""
    tmp, sim, real = folders
    folder = load_models(tmp / "m0")
    pair0, cfg0 = folder.pair, folder.config
    out = tmp / "ft_big_step"
    assert main(["train", "--init", str(tmp / "m0"), "--data", str(sim), "--out", str(out),
                 "--torque-epochs", "3", "--torque-lr", "0.3", "--attention-epochs", "1",
                 "--attention-lr", "0.3", "--attention-sets", "6", "--attention-val-sets", "3",
                 "--set-size", "16", "--val-fraction", str(cfg0["training"]["val_fraction"])
                 ]) == 0
    folder = load_models(out)
    pair, config = folder.pair, folder.config
    assert config["best_epoch"] == {"torque": [-1, -1], "attention": [-1, -1]}
    assert_tree_equal(pair.torque_vars, pair0.torque_vars, what="torque start kept")
    out = tmp / "ft_frozen"
    assert main(["train", "--init", str(tmp / "m0"), "--data", str(real), "--out", str(out),
                 "--trainable", "head", "--torque-epochs", "5", "--torque-lr", "3e-3",
                 "--attention-epochs", "1", "--attention-sets", "6",
                 "--attention-val-sets", "3", "--set-size", "16", "--session-of", str(real),
                 "--session-strength", "0.5"]) == 0
    folder = load_models(out)
    pair, config = folder.pair, folder.config
    assert config["training"]["trainable"] == "head"
    # --session-of: the real file's own session is the models' reference (its ratio 1),
    # recorded with the strength for evaluate and estimate.
    want = servo_session(load_samples(real)[0]).current_gain
    np.testing.assert_allclose(config["session"]["current_gain"], want, rtol=1e-12)
    assert config["session"]["strength"] == 0.5 and config["training"]["session_strength"] == 0.5
    # ... and the supply and temperature that its samples recorded (their medians).
    for k, field in (("supply_voltage", "voltage"), ("temperature", "temperature")):
        np.testing.assert_allclose(config["session"][k],
                                   np.median(_recorded_state(300)[field], axis=0), err_msg=k)
    assert config["data"][0]["session_ratio"] == [1.0] * 4
    # evaluate reads another session's file in that session at that strength, says so with
    # the factors, and --session-strength 0 turns it off (other numbers).
    capsys.readouterr()
    said, answers = [], []
    for extra in ([], ["--session-strength", "0"]):
        js = tmp / f"evaluate{len(extra)}.json"
        assert main(["evaluate", "--models", str(out), "--samples", str(sim), "--sets", "4",
                     *(f"--l-max=o{i}=0.1" for i in range(3)), "--json", str(js), *extra]) == 0
        said.append(capsys.readouterr().out)
        answers.append(json.loads(js.read_text()))
    _, ratios = adapt_objects(load_samples(sim)[0].by_object(), session_reference(config))
    factors = ", ".join(f"{r:.3f}" for r in ratios[0])  # object o0's, at strength 0.5
    assert f"o0: session: discrepancy read in the models' session, x ({factors})" in said[0]
    assert "strength 0.5" in said[0] and "o0: session adaptation off" in said[1]
    assert [a["o0"]["T-A"] for a in answers][0] != answers[1]["o0"]["T-A"]
    # --json: beside each object's tables (lbipe-benchmark schema), its file, the session
    # it was read in and whether the models were fitted on it.
    for a, strength in zip(answers, (0.5, 0.0)):
        o0 = a["o0"]
        assert {"T", "T-A", "mean_attention_weight"} <= set(o0)
        assert o0["sha256"] == sha256_of(sim) and o0["session"]["strength"] == strength
        assert o0["fitted_on_this_file"] == {"mass": {"folders": 1, "of": 1}}
    np.testing.assert_allclose(answers[0]["o0"]["session"]["ratio"], ratios[0], rtol=1e-12)
    # Both files are ones the folder was fitted on (sim: its start was trained on it; real:
    # it was fine-tuned on it): said, never passed off as held out.
    for o in ("o0", "o1", "o2"):
        assert (f"{o}: NOT HELD OUT: 1 of 1 folder(s) answering the mass were calibrated, "
                "trained or fine-tuned on this file") in said[0]
    assert seen_by(out, "0" * 64) == {} and seen_by(tmp / "m0", sha256_of(real)) == {}
    assert seen_by(tmp / "m0", sha256_of(sim)) == {"mass": (1, 1)}
    # A fine-tuning carries its start's record forward (a chain of them loses nothing).
    assert config[FITTED_ON] == [{"sha256": sha256_of(sim)}]
    answer = estimate(out, real, n_sets=4, max_mass=1e3, max_com=1e3)
    assert answer["fitted_on_this_file"] == {"mass": {"folders": 1, "of": 1}}

    assert min(config["best_epoch"]["torque"]) >= 0
    for j in range(4):
        assert_tree_equal(pair.torque_vars["params"][f"joint{j}"],
                          pair0.torque_vars["params"][f"joint{j}"], what=f"joint{j} frozen")
    assert not np.allclose(pair.torque_vars["params"]["out"]["kernel"],
                           pair0.torque_vars["params"]["out"]["kernel"])


def test_what_a_folder_was_fitted_on_is_read_from_its_record_whatever_it_holds():
    config = {FITTED_ON: [{"file": "a.npz", "sha256": "a"}, "junk", {"sha256": 3}],
              "data": [{"sha256": "b", "source": "simulator"}, {"file": "c.npz"}, "x.npz"],
              "fine_tuned_from": {"data": [{"sha256": "d"}], "folder": "m0"}}
    assert fitted_on(config) == {"a", "b", "d"}
    for junk in ({"data": "x.npz"}, {"fine_tuned_from": "m0"}, {FITTED_ON: {"sha256": "a"}}):
        assert fitted_on(junk) == set()


def test_a_reference_of_known_torques_corrects_the_networks_and_not_the_baselines(folders,
                                                                                 capsys):
    """``estimate --reference``: a "session" in which the true joint torques are 1.1 x the
    models' own (the K pairs' mean) plus an offset per joint. Two known objects recorded in
    it (the reference) give that gain and offset back; on the third (the unknown), the
    networks' torques read through them make ``tau - tau_g = A x`` hold exactly, so T's
    answer (the least squares per pair, then the pairs' mean: linear in the torques) is
    the truth; the baselines' answer is the one without the reference, to the bit."""
    tmp, sim, _ = folders
    data, meta = load_samples(sim)
    folder = load_models(tmp / "m0")
    tau_hat = np.asarray(torque_predictions(folder.pair.torque_model, folder.pair.torque_vars,
                                            folder.features, data), np.float64).mean(0)
    gain, offset = 1.1, np.array([0.005, -0.01, 0.002, 0.001])
    tau = gain * tau_hat + offset
    data = data.replace(tau=tau, tau_g=tau - np.einsum("snp,sp->sn", data.A,
                                                       data.x[data.object_id]))
    objects = data.by_object()
    ref, unknown = tmp / "ref.npz", tmp / "unknown.npz"
    for path, objs in ((ref, objects[:2]), (unknown, objects[2:])):
        both = Samples.concatenate(objs)
        save_native(path, both, {"robot": meta["robot"], "source": "test",
                                 "objects": list(both.names)})
    answers = []
    for extra in ([], ["--reference", str(ref)]):
        js = tmp / f"estimate_ref{len(extra)}.json"
        capsys.readouterr()
        assert main(["estimate", "--models", str(tmp / "m0"), "--samples", str(unknown),
                     "--session-strength", "0", "--max-mass", "1000", "--max-com", "1000",
                     "--json", str(js), *extra]) == 0
        answers.append((json.loads(js.read_text()), capsys.readouterr().out))
    (plain, _), (got, said) = answers
    corr = got["reference"]["correction"]
    n_ref = objects[0].n_samples + objects[1].n_samples
    assert got["reference"]["objects"] == ["o0", "o1"] and got["reference"]["n_samples"] == n_ref
    assert said.startswith(f"reference {ref} (o0, o1, {n_ref} samples of known torque): "
                           "the networks' torques read x 1.100 +- 0.000")
    # The reference and the file: one servo law, so one session as far as the current says.
    assert "o2: this file against the reference: current gain x " in said
    assert got["objects"]["o2"]["reference_session"]["same_session"] is True
    np.testing.assert_allclose(corr["gain"], gain, rtol=1e-5)
    np.testing.assert_allclose(corr["offset_Nm"], offset, rtol=1e-4, atol=1e-7)
    obj = objects[2]
    answer, before = got["objects"]["o2"]["methods"], plain["objects"]["o2"]["methods"]
    assert answer["T"]["mass_kg"] == pytest.approx(obj.x[0, 0], rel=1e-5)
    np.testing.assert_allclose(answer["T"]["com_tag_m"], obj.x[0, 1:] / obj.x[0, 0], rtol=1e-4)
    miss = [abs(a["T"]["mass_kg"] / obj.x[0, 0] - 1) for a in (before, answer)]
    assert miss[0] > 0.01 and miss[0] > 100 * miss[1], miss  # without the reference: off
    for m in ("PE", "Sensor"):
        assert answer[m] == before[m], m
    # An ensemble's members each fit their own (here a copy of the same models: the same
    # correction, and the mean of two truths the truth).
    ens = copy_models(tmp / "m0", tmp / "ens")
    copy_models(tmp / "m0", ens / "members" / "1")
    attach_members(ens, ["members/1"])
    both = estimate(ens, unknown, session_strength=0.0, max_mass=1e3, max_com=1e3,
                    reference=ref)
    assert both["reference"]["members"] == [both["reference"]["correction"]]
    np.testing.assert_allclose(both["reference"]["correction"]["gain"], corr["gain"],
                               rtol=1e-12)
    assert both["objects"]["o2"]["methods"]["T"]["mass_kg"] == pytest.approx(obj.x[0, 0],
                                                                              rel=1e-5)
    # evaluate --reference: the same correction; the K pairs' mean answer on every set is
    # the truth (each pair's own is not: the pairs differ from their mean).
    res = evaluate_samples(ens, unknown, n_sets=4, session_strength=0.0, l_max={"o2": 0.1},
                           known=objects[:2])
    np.testing.assert_allclose(res["reference_correction"]["gain"], corr["gain"], rtol=1e-12)
    x_sets = np.asarray(res["estimates"]["T"])[0].mean(axis=0)  # (B, 4): the pairs' mean
    np.testing.assert_allclose(x_sets, np.broadcast_to(obj.x[0], x_sets.shape), rtol=1e-4)
    plain_res = evaluate_samples(ens, unknown, n_sets=4, session_strength=0.0,
                                 l_max={"o2": 0.1})
    assert res["objects"]["o2"]["PE"] == plain_res["objects"]["o2"]["PE"]
    capsys.readouterr()
    assert main(["evaluate", "--models", str(tmp / "m0"), "--samples", str(unknown),
                 "--reference", str(ref), "--sets", "4", "--l-max", "o2=0.1",
                 "--session-strength", "0"]) == 0
    assert "samples of known torque): the networks' torques read x 1.100 / 1.100" in \
        capsys.readouterr().out
    assert main(["evaluate", "--models", str(tmp / "m0"), "--reference", str(ref)]) == 2
    assert "--reference needs --samples" in capsys.readouterr().err
    # Too few samples to tell a gain and an offset, or a gain no servo's day explains (the
    # reference names another load than it carried, or another arm): refused, saying so.
    known = Samples.concatenate(objects[:2])
    with pytest.raises(UsageError, match="at least 8"):
        reference_correction(folder.pair, folder.features, known.take(np.arange(5)))
    with pytest.raises(UsageError, match=r"gain of joint\(s\) \[1, 2, 3, 4\] is \[2\.2"):
        reference_correction(folder.pair, folder.features,
                             known.replace(tau=2 * (known.tau - offset)))
    # A reference must carry its truth: an unknown object's file is refused, in one line.
    bare = tmp / "bare.npz"
    save_native(bare, known.without_truth(), {"robot": meta["robot"], "source": "test",
                                               "objects": list(known.names)})
    capsys.readouterr()
    assert main(["estimate", "--models", str(tmp / "m0"), "--samples", str(unknown),
                 "--reference", str(bare)]) == 2
    assert f"--reference {bare}: a reference is a known load" in capsys.readouterr().err
    # The empty gripper alone is no reference (docs/results.md): refused, saying what to
    # record instead.
    empty = tmp / "empty.npz"
    save_native(empty, known.replace(x=np.zeros_like(known.x), tau=known.tau_g),
                {"robot": meta["robot"], "source": "test", "objects": list(known.names)})
    assert main(["estimate", "--models", str(tmp / "m0"), "--samples", str(unknown),
                 "--reference", str(empty)]) == 2
    assert "the empty gripper alone is no reference" in capsys.readouterr().err


def test_finetuning_refuses_what_cannot_fit(folders, capsys):
    tmp, _, real = folders
    assert main(["train", "--init", str(tmp / "nothing"), "--data", str(real),
                 "--out", str(tmp / "x")]) == 2
    assert "not a jaxinertia model folder" in capsys.readouterr().err
    with pytest.raises(UsageError, match="do not fit"):
        _start(TorqueModel(hidden=5), jax.random.key(0), 2, jnp.zeros((1, 4, 4)),
               load_models(tmp / "m0").pair.torque_vars)
    assert not (tmp / "x").exists()


def test_the_domain_spread_is_the_load_dependence_of_the_samples():
    """Samples whose position-error gain is 20 % lower on the heavier half (and whose
    intercept shifts by 30 mN m there) give that spread back; a load-independent law
    gives none."""
    rng = np.random.default_rng(9)
    n = 4000
    tau = rng.uniform(-1.0, 1.0, (n, 4))
    s = rng.choice([-1.0, 1.0], (n, 4))
    heavy = np.abs(tau) > np.median(np.abs(tau), axis=0)
    k = np.where(heavy, 16.0, 20.0)
    c = np.where(heavy, -0.05, -0.02)
    q = rng.uniform(-0.5, 0.5, (n, 4))
    q_d = q + (tau + s * 0.03 - c) / k
    spread = spread_from_samples(q_d, q, s, tau)
    np.testing.assert_allclose(spread.gain_rel, 4.0 / 18.0, rtol=1e-9)
    np.testing.assert_allclose(spread.offset, 0.03, rtol=1e-9)
    flat = spread_from_samples(q + (tau + s * 0.03 + 0.02) / 18.0, q, s, tau)
    np.testing.assert_allclose(flat.gain_rel, 0.0, atol=1e-9)
    np.testing.assert_allclose(flat.offset, 0.0, atol=1e-9)


def test_perturbed_arms_scatter_around_the_identified_one_by_the_spread():
    params = default_sim_params()
    spread = DomainSpread(np.array([0.05, 0.1, 0.0, 0.02]), np.array([0.01, 0.0, 0.02, 0.005]))
    arms = [perturbed(params, jax.random.key(i), spread) for i in range(400)]
    k0 = np.asarray(params.servo.torque_constant)
    c0 = np.zeros(4) if params.torque_offset is None else np.asarray(params.torque_offset)
    gains = np.stack([np.asarray(a.servo.torque_constant) / k0 - 1 for a in arms])
    offsets = np.stack([np.asarray(a.torque_offset) - c0 for a in arms])
    # 400 normal draws: sample std within ~4 standard errors (7 %) of the spread
    np.testing.assert_allclose(gains.std(axis=0), spread.gain_rel, rtol=0.15, atol=1e-12)
    np.testing.assert_allclose(offsets.std(axis=0), spread.offset, rtol=0.15, atol=1e-12)
    assert np.all(np.abs(gains.mean(axis=0)) < 4 * spread.gain_rel / 20 + 1e-12)
    # everything else is the identified arm
    assert_tree_equal(arms[0].friction, params.friction, what="friction")
    assert_tree_equal(arms[0].robot, params.robot, what="robot")


def test_drawn_sessions_scale_the_supply_by_the_prior_and_nothing_else():
    """``drawn`` with a session spread draws recording sessions (``session_drawn``), with
    a domain spread other arms (``perturbed``); the session prior is 5 % electrical (the
    measured spread where wider), no torque-only part."""
    params = default_sim_params()
    measured = SessionSpread(np.array([0.01, 0.08, 0.0, 0.02]), np.full(4, 0.05))
    prior = session_prior(4, measured)
    np.testing.assert_allclose(prior.electrical_rel, [0.05, 0.08, 0.05, 0.05])
    np.testing.assert_allclose(prior.torque_rel, 0.0)
    np.testing.assert_allclose(session_prior(4).electrical_rel, SESSION_PRIOR_REL)
    sessions = [drawn(params, jax.random.key(i), prior) for i in range(400)]
    v0 = np.asarray(params.servo.supply_voltage)
    logs = np.stack([np.log(np.asarray(a.servo.supply_voltage) / v0) for a in sessions])
    # 400 normal draws: sample std within ~4 standard errors (14 %) of the spread
    np.testing.assert_allclose(logs.std(axis=0), prior.electrical_rel, rtol=0.15)
    for a in sessions[:3]:
        assert_tree_equal(a.servo.torque_constant, params.servo.torque_constant,
                          what="torque constant")
        assert_tree_equal(a.friction, params.friction, what="friction")
    arm = drawn(params, jax.random.key(0), DomainSpread(np.full(4, 0.1), np.zeros(4)))
    assert_tree_equal(arm, perturbed(params, jax.random.key(0),
                                     DomainSpread(np.full(4, 0.1), np.zeros(4))), what="arm")



def _servo_law_folder(path, k, f, K=2, residual=False):
    """A physical model folder whose servo part is the synthetic law (stiffness ``k``,
    friction ``f``, offset 0.01 N m; support.synthetic) and whose residual is zero (its
    output layer; ``residual``: the random one, through which gradients reach its
    encoders)."""
    feats = jnp.zeros((1, 4, 4), jnp.float32)
    tm, am = PhysicalTorqueModel(), AttentionModel()
    keys = jax.random.split(jax.random.key(3), K)
    tv, av = (jax.vmap(lambda key, m=m: m.init(key, feats))(keys) for m in (tm, am))
    fc = feature_config()
    tau_scale = np.asarray(fc.tau_scale)
    p = dict(tv["params"])
    servo = {"stiffness": np.asarray(k) * np.asarray(fc.qe_scale) / tau_scale,
             "offset": 0.01 / tau_scale, "friction": -np.asarray(f) / tau_scale,
             "load_friction": np.zeros(4)}
    p.update({n: jnp.asarray(np.tile(v, (K, 1)), jnp.float32) for n, v in servo.items()})
    if not residual:
        p["residual"] = {**p["residual"],
                         "out": jax.tree.map(jnp.zeros_like, p["residual"]["out"])}
    d = synthetic_samples(np.random.default_rng(4))
    b = fit_baselines(d.q_d, d.q, d.direction, d.current_tau, d.tau)
    save_models(path, ModelPair({"params": p}, av, jnp.asarray(tau_scale, jnp.float32), tm, am),
                b, fc, robot="open_manipulator_x")


def test_finetuning_gives_each_file_its_session_term_and_records_it(folders, capsys):
    """``--session-terms`` (jaxinertia.session_terms): two files of one servo law, the
    second's servo 15 % stiffer on joint 1 and 10 % softer on joint 4."""
    tmp, _, _ = folders
    rng = np.random.default_rng(5)
    k, f = np.array([16.0, 18.0, 17.0, 10.0]), np.array([0.02, 0.05, 0.03, 0.01])
    a = _file(tmp / "a.npz", rng, 300, k=k, f=f)
    b = _file(tmp / "b.npz", rng, 300, k=k * [1.15, 1.0, 1.0, 0.9], f=f)
    _servo_law_folder(tmp / "law", k * 1.05, f)  # a start 5 % stiffer than both
    ft = ["--init", str(tmp / "law"), "--trainable", "servo", "--torque-epochs", "3",
          "--attention-epochs", "1", "--attention-sets", "6", "--attention-val-sets", "3",
          "--set-size", "16", "--session-strength", "0"]
    assert main(["train", "--data", str(a), str(b), "--out", str(tmp / "terms"),
                 "--session-terms", *ft]) == 0
    rec = json.loads((tmp / "terms" / "config.json").read_text())["session_terms"]
    f, raw = np.asarray(rec["factor"]), np.asarray(rec["raw"])
    np.testing.assert_allclose(np.exp(np.log(f).mean(axis=0)), 1.0, atol=1e-12)
    # The start's servo is 5 % stiffer than a's: a's discrepancy, read by it, is 1.05
    # times too large (raw term 1 / 1.05), b's by 1.05 / (1.15, 1, 1, 0.9). Centred, b's
    # discrepancy grows by 1.15 on joint 1 against a's and shrinks by 0.9 on joint 4.
    np.testing.assert_allclose(raw, [[1 / 1.05] * 4, np.array([1.15, 1, 1, 0.9]) / 1.05],
                               rtol=1e-5)
    np.testing.assert_allclose(f[1] / f[0], [1.15, 1.0, 1.0, 0.9], rtol=1e-5)
    # One file: no term, the pooled fine-tuning's samples as they are.
    one = [load_samples(a)[0]]
    split = split_validation(one[0], 0.1, 0)
    *same, rec = with_session_terms(load_models(tmp / "law"), one, *split)
    assert same[0] is split[0] and same[1] is split[1]
    assert rec == {"raw": None, "factor": [[1.0] * 4]}
    # Models whose torque does not follow the files (the tiny paper network): refused.
    capsys.readouterr()
    assert main(["train", "--data", str(a), str(b), "--out", str(tmp / "x"),
                 "--session-terms", *ft[:1], str(tmp / "m0"), *ft[2:]]) == 2
    assert "factor reaches the 0.7-1.4 limit" in capsys.readouterr().err
    # A training from scratch has no models to fit the terms under.
    capsys.readouterr()
    assert main(["train", "--data", str(a), str(b), "--out", str(tmp / "x"),
                 "--session-terms", *TINY]) == 2
    assert "fine-tuning" in capsys.readouterr().err and not (tmp / "x").exists()


def test_servo_and_attention_finetuning_moves_both_and_nothing_else(folders):
    """``--trainable servo+attention``: the physical model's servo parameters and the whole
    attention model train; the torque residual stays the start's, bit for bit. With
    ``servo`` alone no attention epoch runs."""
    tmp, _, real = folders
    k, f = np.array([16.0, 18.0, 17.0, 10.0]), np.array([0.02, 0.05, 0.03, 0.01])
    _servo_law_folder(tmp / "law_att", k * 1.1, f)
    start = load_models(tmp / "law_att").pair
    ft = ["--init", str(tmp / "law_att"), "--torque-epochs", "3", "--torque-lr", "1e-3",
          "--attention-epochs", "3", "--attention-lr", "3e-3", "--attention-sets", "6",
          "--attention-val-sets", "3", "--set-size", "16", "--session-strength", "0"]
    for mode in ("servo", "servo+attention", "attention"):
        out = tmp / f"ft_{mode.replace('+', '_')}"
        assert main(["train", "--data", str(real), "--out", str(out), "--trainable", mode,
                     *ft]) == 0
        folder = load_models(out)
        pair, config = folder.pair, folder.config
        assert config["training"]["trainable"] == mode
        assert_tree_equal(pair.torque_vars["params"]["residual"],
                          start.torque_vars["params"]["residual"], what="residual frozen")
        if mode == "attention":  # no torque epoch runs: the start's torque models, whole
            assert config["history"]["torque"] == []
            assert_tree_equal(pair.torque_vars, start.torque_vars, what="torque kept")
        else:
            assert min(config["best_epoch"]["torque"]) >= 0  # the stiffer start moved
            assert not np.allclose(pair.torque_vars["params"]["stiffness"],
                                   start.torque_vars["params"]["stiffness"])
        if mode == "servo":
            assert config["history"]["attention"] == []
            assert_tree_equal(pair.attention_vars, start.attention_vars, what="kept")
        else:
            assert len(config["history"]["attention"]) == 3
            best = np.asarray(config["best_epoch"]["attention"])
            # The random start's attention improved (with the stiffer start's torques kept,
            # "attention", in at least one of the two pairs).
            assert np.all(best >= 0) if mode == "servo+attention" else best.max() >= 0, best
            differ = np.all if mode == "servo+attention" else np.any  # every pair / one
            moved = [bool(differ(np.asarray(a) != np.asarray(b))) for a, b in
                     zip(jax.tree.leaves(pair.attention_vars),
                         jax.tree.leaves(start.attention_vars))]
            assert any(moved)
    # The attention trained with a session the torque models do not know
    # (--attention-torque-spread): the same minibatches, their torques scaled per set and
    # joint. A vanishing spread is the plain training within float32 rounding (its train
    # and validation losses, epoch by epoch); 0.3 another one.
    plain = np.asarray(load_models(tmp / "ft_attention").config["history"]["attention"])
    for spread, same in (("1e-9", True), ("0.3", False)):
        out = tmp / f"ft_attention_spread_{spread}"
        assert main(["train", "--data", str(real), "--out", str(out), "--trainable",
                     "attention", "--attention-torque-spread", spread, *ft]) == 0
        config = load_models(out).config
        assert config["training"]["attention_torque_spread"] == float(spread)
        history = np.asarray(config["history"]["attention"])
        assert history.shape == plain.shape == (3, 2, 2)
        gap = np.abs(history / plain - 1).max()
        assert gap < 1e-6 if same else gap > 1e-3, (spread, gap)


def test_servo_and_input_finetuning_moves_the_residuals_input_layers_and_nothing_else(
        folders):
    """``--trainable servo+input``: the servo parameters and the first layer of each of the
    residual's per-joint encoders train; the encoders' second layers, the residual's head
    and the whole attention stay the start's, bit for bit, and no attention epoch runs."""
    tmp, _, real = folders
    k, f = np.array([16.0, 18.0, 17.0, 10.0]), np.array([0.02, 0.05, 0.03, 0.01])
    _servo_law_folder(tmp / "law_in", k * 1.1, f, residual=True)
    start = load_models(tmp / "law_in").pair
    out = tmp / "ft_servo_input"
    assert main(["train", "--data", str(real), "--out", str(out), "--trainable", "servo+input",
                 "--init", str(tmp / "law_in"), "--torque-epochs", "3", "--torque-lr", "1e-3",
                 "--attention-epochs", "3", "--attention-sets", "6", "--attention-val-sets",
                 "3", "--set-size", "16", "--session-strength", "0"]) == 0
    folder = load_models(out)
    assert folder.config["training"]["trainable"] == "servo+input"
    assert min(folder.config["best_epoch"]["torque"]) >= 0  # the stiffer start moved
    assert folder.config["history"]["attention"] == []
    assert_tree_equal(folder.pair.attention_vars, start.attention_vars, what="attention kept")
    new, old = folder.pair.torque_vars["params"], start.torque_vars["params"]
    assert not np.allclose(new["stiffness"], old["stiffness"])
    for name, tree in new["residual"].items():
        if name.startswith("joint"):  # the input layer moved, the embedding's layer not
            assert not np.allclose(tree["hidden"]["kernel"],
                                   old["residual"][name]["hidden"]["kernel"]), name
            assert_tree_equal(tree["embed"], old["residual"][name]["embed"], what=name)
        else:
            assert_tree_equal(tree, old["residual"][name], what=name)


def test_a_finetuning_from_a_start_still_training_is_the_one_from_its_folder(folders,
                                                                              monkeypatch):
    """``app.fit.EarlyStart`` (the held-out folds on an accelerator): a fine-tuning of the
    servo part given a start whose torque models are trained and whose attention is still
    training runs meanwhile (here the start's attention waits until it has begun), and
    writes the models, record and all, that the same fine-tuning of the written folder
    writes. A start that fails fails the fine-tunings waiting for it."""
    import threading  # noqa: PLC0415
    from concurrent.futures import ThreadPoolExecutor  # noqa: PLC0415

    from jaxinertia.app import fit  # noqa: PLC0415
    from jaxinertia.app.pipeline import train  # noqa: PLC0415
    from jaxinertia.training import FINETUNE_DEFAULTS  # noqa: PLC0415

    tmp, sim, real = folders
    start_cfg = TrainConfig(n_models=2, torque_epochs=6, attention_epochs=2, attention_sets=6,
                            attention_val_sets=3, set_size=16, torque_batch=64,
                            attention_batch=4, torque_model="physical")
    ft_cfg = TrainConfig(**{**FINETUNE_DEFAULTS, "torque_epochs": 5}, trainable="servo",
                         set_size=16)
    begun = threading.Event()

    class Watched(fit.EarlyStart):
        def start(self):
            s = super().start()
            begun.set()  # the fine-tuning has its start: the start's attention may train
            return s

    attention = fit.train_attention_models

    def after_the_finetuning_began(*args, **kw):
        assert begun.wait(120), "the fine-tuning did not begin before the start's attention"
        return attention(*args, **kw)

    monkeypatch.setattr(fit, "train_attention_models", after_the_finetuning_began)
    early = Watched(tmp / "early_start")
    kw = dict(overwrite=True, progress=False, samples_per_object=60)
    with ThreadPoolExecutor(1) as pool:
        tuned = pool.submit(train, [real], tmp / "tuned_early", ft_cfg, init=early, **kw)
        train([sim], tmp / "early_start", start_cfg, overwrite=True, progress=False,
              early=early)
        tuned.result(timeout=600)
    monkeypatch.setattr(fit, "train_attention_models", attention)
    train([real], tmp / "tuned_late", ft_cfg, init=tmp / "early_start", **kw)
    a, b = load_models(tmp / "tuned_early"), load_models(tmp / "tuned_late")
    assert_tree_equal(a.pair.torque_vars, b.pair.torque_vars, what="torque")
    assert_tree_equal(a.pair.attention_vars, b.pair.attention_vars, what="attention")
    assert_tree_equal(a.pair.attention_vars, load_models(tmp / "early_start").pair
                      .attention_vars, what="the start's attention, kept")
    mine = {k: v for k, v in a.config.items() if k not in ("wall_time_s", "checksums")}
    assert mine == {k: v for k, v in b.config.items() if k not in ("wall_time_s", "checksums")}
    # A start that fails, even before it trains (here: its folder exists and it may not
    # replace it), fails the fine-tuning waiting for it instead of leaving it waiting.
    failing = fit.EarlyStart(tmp / "early_start")
    with ThreadPoolExecutor(1) as pool:
        waiting = pool.submit(train, [real], tmp / "tuned_never", ft_cfg, init=failing, **kw)
        try:
            with pytest.raises(JaxinertiaError) as refused:
                train([sim], tmp / "early_start", start_cfg, progress=False, early=failing)
            with pytest.raises(type(refused.value), match="early_start"):
                waiting.result(timeout=120)
        finally:
            failing.failed(RuntimeError("released by the test"))  # never left waiting
    assert not (tmp / "tuned_never").exists()


def test_a_start_made_in_resolving_never_leaves_its_waiters_waiting(tmp_path):
    """``EarlyStart.resolving`` around a start's whole making (the folds' ``judged_start``):
    an error raised where ``train`` does not see it fails the waiting fine-tunings with that
    error, and a block that ends without the folder written fails them too; a written
    start is left as it is."""
    from jaxinertia.app import fit  # noqa: PLC0415

    raised = fit.EarlyStart(tmp_path / "raised")
    with pytest.raises(ValueError, match="setting up"), raised.resolving():
        raise ValueError("setting up")
    with pytest.raises(ValueError, match="setting up"):
        raised.start()
    unwritten = fit.EarlyStart(tmp_path / "unwritten")
    with unwritten.resolving():
        pass
    with pytest.raises(RuntimeError, match="unwritten: its training ended without writing"):
        unwritten.start()
    written = fit.EarlyStart(tmp_path / "written")
    with written.resolving():  # stand-ins for a start's torque models, record and pairs
        written.torque_trained(SimpleNamespace(variables={"w": np.zeros((2, 1))}, model=None),
                               SimpleNamespace(tau_scale=np.ones(4)), {"config": 1})
        written.written(None)
    assert written.start().config == {"config": 1}
