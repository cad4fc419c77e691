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
@pytest.mark.parametrize("com_drawn", [True, False], ids=["shared-start", "own-start"])
def test_the_folders_are_made_as_the_folds_made_them_and_the_com_lands_inside(
        tmp_path, monkeypatch, accelerator, com_drawn):
    """Trained and fine-tuned at the folds' training strength (1), each folder then written
    with its recipe's strength; a simulator-trained model the two parts share is trained
    once; two different ones side by side on an accelerator, as one group."""
    monkeypatch.setattr(M, "side_by_side_workers", lambda: 4 if accelerator else 1)
    simulated, trained, copied = [], [], []

    def fake_simulate(params, wanted, **kw):
        simulated.append([Path(w[0]).name for w in wanted])
        return [w[0] for w in wanted]

    def fake_train(files, out, cfg, *, init=None, **kw):
        member = getattr(training_group._local, "member", None)
        trained.append((Path(out).name, None if init is None else Path(init).name,
                        [Path(getattr(f, "path", f)).name for f in files], cfg.session_strength,
                        cfg.current_input, None if member is None else member[1]))
        Path(out).mkdir(parents=True)
        return {"samples": {"train": 1}}

    def fake_copy(src, dst, *, session_strength):
        copied.append((Path(src).name, Path(dst).name, session_strength))
        Path(dst).mkdir(parents=True)
        (Path(dst) / "config.json").write_text(json.dumps({"from": Path(src).name}))

    monkeypatch.setattr(M, "simulate_files", fake_simulate)
    monkeypatch.setattr(M, "arm_sim_params", lambda: SimpleNamespace(
        robot=SimpleNamespace(n_joints=4)))
    monkeypatch.setattr(M, "train", fake_train)
    monkeypatch.setattr(M, "copy_models", fake_copy)
    monkeypatch.setattr(M, "evaluate_models", lambda dst, *a, **k: {
        "objects": {}, "session_ratio": {}, "folder": Path(dst).name})
    real = SimpleNamespace(files=[SimpleNamespace(path=Path("data_test_cube.npz"))],
                           objects=[], sets=[], l_max=[])
    scale = SimpleNamespace(train=M.TrainConfig(n_models=2), random_per_load=8,
                            fold_session_draws=4, real_finetune_samples=1000)
    com = COM if com_drawn else {**COM, "candidate": "physical with the current input, "
                                 "simulator only", "sessions_drawn": False}
    res = M.models_real(tmp_path, [tmp_path / "train_random.npz",
                                   tmp_path / "train_planning.npz"], real, scale,
                        {**MASS, "com": com}, 0, False, None)
    # The drawn sessions simulated once.
    assert simulated == [["train_random_sessions.npz"]]
    drawn = ["train_random_sessions.npz", "train_planning.npz"]
    group = accelerator and not com_drawn  # two trainings at once: a group
    starts = [("models_physical", None, drawn, 1.0, True, "mass" if group else None)]
    if not com_drawn:
        starts.append(("models_physical_com", None, ["train_random.npz", "train_planning.npz"],
                       1.0, True, "com" if group else None))
    # (A fine-tuning keeps its start's inputs whatever its config says: pipeline.train.)
    ft = [("models_real_finetuned", "models_physical", ["data_test_cube.npz"], 1.0, False,
           None)]
    assert sorted(trained[:len(starts)]) == sorted(starts) and trained[len(starts):] == ft
    assert copied == [("models_real_finetuned", "models_real", 0.0),
                      ("models_physical" if com_drawn else "models_physical_com",
                       "models_real_com", 1.0)]
    assert json.loads((tmp_path / "models_real" / "com" / "config.json").read_text()) == {
        "from": copied[1][0]}
    assert not (tmp_path / "models_real_com").exists()
    config = json.loads((tmp_path / "models_real" / "config.json").read_text())
    assert config["from"] == "models_real_finetuned" and config["com_models"] == "com"
    assert res["samples"] == {"train": 1} and res["models"] == str(tmp_path / "models_real")
