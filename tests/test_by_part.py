"""Mass from one model folder, COM from another (``jaxinertia.app.by_part``): estimate and
evaluate of a folder that names COM models give exactly the mass folder's mass and the COM
folder's COM, each with its own spread and intervals, and no joint covariance."""

from __future__ import annotations

import json

import numpy as np
import pytest
from support.synthetic import feature_config, synthetic_samples, tiny_pair

from jaxinertia.app.by_part import COM_MODELS, attach_com_models, merge_answers
from jaxinertia.app.cli import main
from jaxinertia.app.estimate import estimate
from jaxinertia.app.pipeline import copy_models, evaluate_models
from jaxinertia.baselines import fit_baselines
from jaxinertia.evaluation import choose_sets
from jaxinertia.samples import save_native

ROBOT = "open_manipulator_x"


@pytest.fixture(scope="module")
def folders(tmp_path_factory):
    """A sample file and a model folder whose ``com/`` holds other models (a network
    method that the untrained pairs answer, or not, either way is checked)."""
    tmp = tmp_path_factory.mktemp("by_part")
    d = synthetic_samples(np.random.default_rng(11), n=96, n_obj=1)
    path = save_native(tmp / "s.npz", d, {"robot": ROBOT})
    b = fit_baselines(d.q_d, d.q, d.direction, d.current_tau, d.q_d)
    from jaxinertia.checkpoints import save_models  # noqa: PLC0415 - orbax at first use

    save_models(tmp / "m", tiny_pair(seed=0), b, feature_config(), robot=ROBOT)
    save_models(tmp / "m" / "com", tiny_pair(seed=1), b, feature_config(), robot=ROBOT)
    return d, path, tmp / "m"


def test_the_mass_is_the_mass_folders_and_the_com_the_com_folders(folders, capsys):
    d, path, models = folders
    kw = dict(set_size=32, n_sets=8, max_mass=1e3, max_com=1e3)
    mass, com = estimate(models, path, **kw), estimate(models / "com", path, **kw)
    attach_com_models(models)
    assert json.loads((models / "config.json").read_text())[COM_MODELS] == "com"
    both = estimate(models, path, **kw)
    assert both["com_models"] == str(models / "com")
    assert both["com_session_strength"] == com["session_strength"]
    (name,) = both["objects"]
    a, c, m = (r["objects"][name]["methods"] for r in (mass, com, both))
    for method in ("Sensor", "PE"):  # the baselines: the mass folder's, whole
        assert m[method] == a[method]
    answered = 0
    for method in ("T", "T-A"):
        if not (a[method]["ok"] and c[method]["ok"]):
            assert not m[method]["ok"]
            continue
        answered += 1
        assert m[method]["mass_kg"] == a[method]["mass_kg"]
        assert m[method]["mass_se_kg"] == a[method]["mass_se_kg"]
        assert m[method]["com_tag_m"] == c[method]["com_tag_m"]
        assert m[method]["com_se_m"] == c[method]["com_se_m"]
        assert m[method]["interval_95"] == {"mass_kg": a[method]["interval_95"]["mass_kg"],
                                            "com_tag_m": c[method]["interval_95"]["com_tag_m"]}
        assert "covariance_x" not in m[method] and "covariance_note" in m[method]
        assert m[method]["mass_kg"] != c[method]["mass_kg"]  # two different folders
        # What 1 % of a joint's torque moves: the mass's from the mass folder's answer, the
        # COM's from the COM folder's.
        sens = m[method]["servo_state_sensitivity"]
        assert sens["mass_kg"] == a[method]["servo_state_sensitivity"]["mass_kg"]
        assert sens["com_m"] == c[method]["servo_state_sensitivity"]["com_m"]
    assert answered > 0, "no network method answered on both folders: nothing was checked"
    # The command line says where each part comes from.
    assert main(["estimate", "--models", str(models), "--samples", str(path), "--set-size",
                 "32", "--max-mass", "1000", "--max-com", "1000"]) == 0
    said = capsys.readouterr().out
    assert f"the COM of T and T-A from {models / 'com'}" in said, said
    assert "servo state (a bias the intervals do not hold): 1 % of one joint's torque" in said
    # Table I of such a folder: mass metrics the mass folder's, COM metrics the COM's.
    sets, _ = choose_sets(d.by_object(), n_sets=8, set_size=32, seed=0)
    res = evaluate_models(models, d.by_object(), sets, l_max=[0.1])
    plain = [evaluate_models(models / sub, d.by_object(), sets, l_max=[0.1])
             for sub in (".", "com")]
    for method in ("T", "T-A"):
        got = res["objects"][name][method]
        for k, v in got.items():
            src = plain[1] if k.startswith("com_") else plain[0]
            assert v == src["objects"][name][method][k], (method, k)
    assert res["objects"][name]["PE"] == plain[0]["objects"][name]["PE"]
    # A copy of the folder is the mass folder alone: it names no COM models it lacks.
    copy = copy_models(models, models.parent / "copy")
    assert COM_MODELS not in json.loads((copy / "config.json").read_text())


def test_a_method_that_fails_in_either_folder_is_no_answer():
    ok = {"ok": True, "mass_kg": 0.1, "com_tag_m": [0.0, 0.0, 0.01]}
    bad = {"ok": False, "reason": "non-physical mass -3.0 g"}

    def answer(t):
        return {"objects": {"o": {"methods": {"T": t, "T-A": ok}, "session_ratio": [1.0]}}}

    merged = merge_answers(answer(ok), answer(bad))["objects"]["o"]["methods"]
    assert merged["T"] == {"ok": False, "reason": "COM models: non-physical mass -3.0 g"}
    assert merged["T-A"]["ok"] and merged["T-A"]["mass_kg"] == 0.1
    merged = merge_answers(answer(bad), answer(ok))["objects"]["o"]["methods"]
    assert merged["T"]["reason"] == "mass models: non-physical mass -3.0 g"
