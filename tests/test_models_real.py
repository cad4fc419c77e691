"""``models_real``: the mass's and the COM's folders made as the recipe says, once each, the
COM's inside the mass's; side by side on an accelerator, their trainings in one group."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import pytest

from jaxinertia import training_group
from jaxinertia.app import models_real as M

#: What the folds' recipe chose in session 20's full run: the mass from the drawn-sessions
#: current-input model fine-tuned, the COM from that model from the simulator alone.
MASS = {"candidate": "physical with the current input, sessions drawn, servo part fine-tuned "
                     "on 250 real samples", "session_strength": 0.0, "finetune_samples": 250,
        "current_input": True, "sessions_drawn": True}
COM = {"candidate": "physical with the current input, sessions drawn, simulator only",
       "session_strength": 1.0, "finetune_samples": None, "current_input": True,
       "sessions_drawn": True}


@pytest.mark.parametrize("accelerator", [False, True], ids=["cpu", "accelerator"])
def test_the_mass_and_com_folders_each_train_once_and_the_com_lands_inside(
        tmp_path, monkeypatch, accelerator):
    monkeypatch.setattr(M, "side_by_side_workers", lambda: 4 if accelerator else 1)
    simulated, trained = [], []

    def fake_simulate(params, wanted, **kw):
        simulated.append([Path(w[0]).name for w in wanted])
        return [w[0] for w in wanted]

    def fake_train(files, out, cfg, *, init=None, **kw):
        member = getattr(training_group._local, "member", None)
        trained.append((Path(out).name, None if init is None else Path(init).name,
                        [Path(getattr(f, "path", f)).name for f in files], cfg.session_strength,
                        None if member is None else member[1]))
        Path(out).mkdir(parents=True)
        (Path(out) / "config.json").write_text(json.dumps({"out": Path(out).name}))
        return {"samples": {"train": 1}}

    monkeypatch.setattr(M, "simulate_files", fake_simulate)
    monkeypatch.setattr(M, "arm_sim_params", lambda: SimpleNamespace(
        robot=SimpleNamespace(n_joints=4)))
    monkeypatch.setattr(M, "train", fake_train)
    monkeypatch.setattr(M, "evaluate_models", lambda dst, *a, **k: {
        "objects": {}, "session_ratio": {}, "folder": Path(dst).name})
    real = SimpleNamespace(files=[SimpleNamespace(path=Path("data_test_cube.npz"))],
                           objects=[], sets=[], l_max=[])
    scale = SimpleNamespace(train=M.TrainConfig(n_models=2), random_per_load=8,
                            fold_session_draws=4, real_finetune_samples=1000)
    res = M.models_real(tmp_path, [tmp_path / "train_random.npz",
                                   tmp_path / "train_planning.npz"], real, scale,
                        {**MASS, "com": COM}, 0, False, None)
    # The drawn sessions simulated once, for both folders.
    assert simulated == [["train_random_sessions.npz"]]
    drawn = ["train_random_sessions.npz", "train_planning.npz"]
    mass = [("models_physical", None, drawn, 0.0, "mass"),
            ("models_real", "models_physical", ["data_test_cube.npz"], 0.0, "mass")]
    com = [("models_real_com", None, drawn, 1.0, "com")]
    if accelerator:  # side by side, each part a member of the group
        assert sorted(trained) == sorted(mass + com)
    else:  # in order, no group
        assert trained == [t[:-1] + (None,) for t in mass + com]
    assert json.loads((tmp_path / "models_real" / "com" / "config.json").read_text()) == {
        "out": "models_real_com"}
    assert not (tmp_path / "models_real_com").exists()
    config = json.loads((tmp_path / "models_real" / "config.json").read_text())
    assert config["out"] == "models_real" and config["com_models"] == "com"
    assert res["samples"] == {"train": 1} and res["models"] == str(tmp_path / "models_real")
