"""``models_real``: the mass's and the COM's folders made as the recipe says, once each, the
COM's inside the mass's; side by side on an accelerator, their trainings in one group."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import pytest

from jaxinertia import training_group
from jaxinertia.app import models_real as M
from jaxinertia.app import recipe as R

#: What the folds' recipe chose in session 20's full run: the mass from the drawn-sessions
#: current-input model fine-tuned, the COM from that model from the simulator alone.
MASS = {"candidate": "physical with the current input, sessions drawn, servo part fine-tuned "
                     "on 250 real samples", "session_strength": 0.0, "finetune_samples": 250,
        "current_input": True, "sessions_drawn": True}
COM = {"candidate": "physical with the current input, sessions drawn, simulator only",
       "session_strength": 1.0, "finetune_samples": None, "current_input": True,
       "sessions_drawn": True}


def _fakes(monkeypatch, accelerator):
    """models_real with its simulation, trainings, copies and evaluation recorded, not run:
    (simulated, trained, copied)."""
    monkeypatch.setattr(M, "side_by_side_workers", lambda: 4 if accelerator else 1)
    simulated, trained, copied = [], [], []

    def fake_simulate(params, wanted, **kw):
        simulated.append([Path(w[0]).name for w in wanted])
        return [w[0] for w in wanted]

    def fake_train(files, out, cfg, *, init=None, samples_per_object=None, **kw):
        member = getattr(training_group._local, "member", None)
        trained.append((Path(out).name, None if init is None else Path(init).name,
                        [Path(getattr(f, "path", f)).name for f in files], cfg.session_strength,
                        cfg.current_input, None if member is None else member[1]))
        Path(out).mkdir(parents=True)
        return {"samples": {"train": samples_per_object}}

    def fake_copy(src, dst, *, session_strength, uniform):
        copied.append((Path(src).name, str(Path(dst).relative_to(dst_root)), session_strength)
                      + (("uniform",) if uniform else ()))
        Path(dst).mkdir(parents=True)
        (Path(dst) / "config.json").write_text(json.dumps({"from": Path(src).name}))

    dst_root = None

    def set_root(path):
        nonlocal dst_root
        dst_root = path

    monkeypatch.setattr(M, "simulate_files", fake_simulate)
    monkeypatch.setattr(M, "arm_sim_params", lambda: SimpleNamespace(
        robot=SimpleNamespace(n_joints=4)))
    monkeypatch.setattr(M, "train", fake_train)
    monkeypatch.setattr(M, "copy_models", fake_copy)
    monkeypatch.setattr(M, "evaluate_models", lambda dst, *a, **k: {
        "objects": {}, "session_ratio": {}, "folder": Path(dst).name})
    return simulated, trained, copied, set_root


REAL = SimpleNamespace(files=[SimpleNamespace(path=Path("data_test_cube.npz"))],
                       objects=[], sets=[], l_max=[])
SCALE = SimpleNamespace(train=M.TrainConfig(n_models=2), random_per_load=8,
                        fold_session_draws=4, real_finetune_samples=1000)
TRAIN_FILES = ["train_random.npz", "train_planning.npz"]
DRAWN = ["train_random_sessions.npz", "train_planning.npz"]


@pytest.mark.parametrize("accelerator", [False, True], ids=["cpu", "accelerator"])
@pytest.mark.parametrize("com_drawn", [True, False], ids=["shared-start", "own-start"])
def test_the_folders_are_made_as_the_folds_made_them_and_the_com_lands_inside(
        tmp_path, monkeypatch, accelerator, com_drawn):
    """Trained and fine-tuned at the folds' training strength (1), each folder then written
    with its recipe's strength; a simulator-trained model the two parts share is trained
    once; two different ones side by side on an accelerator, as one group."""
    simulated, trained, copied, set_root = _fakes(monkeypatch, accelerator)
    set_root(tmp_path)
    com = COM if com_drawn else {**COM, "candidate": "physical with the current input, "
                                 "simulator only", "sessions_drawn": False}
    res = M.models_real(tmp_path, [tmp_path / f for f in TRAIN_FILES], REAL, SCALE,
                        {**MASS, "com": com}, 0, False, None)
    # The drawn sessions simulated once.
    assert simulated == [["train_random_sessions.npz"]]
    group = accelerator and not com_drawn  # two trainings at once: a group
    starts = [("models_physical_current_sessions", None, DRAWN, 1.0, True,
               "models_physical_current_sessions" if group else None)]
    if not com_drawn:
        starts.append(("models_physical_current", None, TRAIN_FILES, 1.0, True,
                       "models_physical_current" if group else None))
    # (A fine-tuning keeps its start's inputs whatever its config says: pipeline.train.)
    ft = [("models_real_finetuned_current_sessions_250", "models_physical_current_sessions",
           ["data_test_cube.npz"], 1.0, False, None)]
    assert sorted(trained[:len(starts)]) == sorted(starts) and trained[len(starts):] == ft
    assert copied == [("models_real_finetuned_current_sessions_250", "models_real", 0.0),
                      (starts[-1][0], "models_real_com", 1.0)]
    assert json.loads((tmp_path / "models_real" / "com" / "config.json").read_text()) == {
        "from": copied[1][0]}
    assert not (tmp_path / "models_real_com").exists()
    config = json.loads((tmp_path / "models_real" / "config.json").read_text())
    assert config["from"] == copied[0][0] and config["com_models"] == "com"
    assert "ensemble_members" not in config
    assert res["samples"] == {"train": 250} and res["models"] == str(tmp_path / "models_real")


@pytest.mark.parametrize("accelerator", [False, True], ids=["cpu", "accelerator"])
def test_an_average_of_every_candidate_makes_each_member_once(tmp_path, monkeypatch,
                                                              accelerator):
    """The recipe's mass from the folds' average of every candidate (app.ensemble): every
    member made as the folds made it, each start and fine-tuning once, shared with the COM
    part; the members inside models_real, named in its config, at the recipe's strength."""
    simulated, trained, copied, set_root = _fakes(monkeypatch, accelerator)
    set_root(tmp_path)
    names = ["paper network, simulator only", "physical, simulator only",
             "physical, servo part fine-tuned on 64 real samples",
             "physical with the current input, servo part fine-tuned on 1000 real samples",
             "physical with the current input, sessions drawn, simulator only",
             "physical with the current input, sessions drawn, servo part fine-tuned on 64 "
             "real samples"]
    members = [R._recipe(n, 0.0, attention=False) for n in names]
    recipe = {**R._recipe(R.ENSEMBLE, 0.0, names, attention=False), "com": COM}
    assert recipe["members"] == members
    res = M.models_real(tmp_path, [tmp_path / f for f in TRAIN_FILES], REAL, SCALE,
                        recipe, 0, False, None)
    assert simulated == [["train_random_sessions.npz"]]
    group = accelerator  # several trainings at once
    starts = [(f"models_physical{tag}", None, files, 1.0, current, name if group else None)
              for tag, files, current in (("", TRAIN_FILES, False),
                                          ("_current", TRAIN_FILES, True),
                                          ("_current_sessions", DRAWN, True))
              for name in [f"models_physical{tag}"]]
    fts = [(f"models_real_finetuned{tag}_{n}", f"models_physical{tag}",
            ["data_test_cube.npz"], 1.0, False, f"models_real_finetuned{tag}_{n}"
            if group else None)
           for tag, n in (("", 64), ("_current", 1000), ("_current_sessions", 64))]
    assert sorted(trained[:3]) == sorted(starts) and sorted(trained[3:]) == sorted(fts)
    # Every member of the mass without its attention, as the recipe says; the COM's with.
    assert copied == [
        ("models", "models_real", 0.0, "uniform"),
        ("models_physical", "models_real/members/1", 0.0, "uniform"),
        ("models_real_finetuned_64", "models_real/members/2", 0.0, "uniform"),
        ("models_real_finetuned_current_1000", "models_real/members/3", 0.0, "uniform"),
        ("models_physical_current_sessions", "models_real/members/4", 0.0, "uniform"),
        ("models_real_finetuned_current_sessions_64", "models_real/members/5", 0.0,
         "uniform"),
        ("models_physical_current_sessions", "models_real_com", 1.0)]
    config = json.loads((tmp_path / "models_real" / "config.json").read_text())
    assert config["ensemble_members"] == [f"members/{i}" for i in range(1, 6)]
    assert config["com_models"] == "com"
    assert res["samples"] is None  # the mass's first member is no fine-tuning


def test_starts_trained_beforehand_are_not_trained_again(tmp_path, monkeypatch):
    """``starts`` (reproduce trains them beside the folds on an accelerator): the kinds it
    has are used as they are; only the others train."""
    simulated, trained, copied, set_root = _fakes(monkeypatch, False)
    set_root(tmp_path)
    early = {(True, True): tmp_path / "models_physical_current_sessions"}
    res = M.models_real(tmp_path, [tmp_path / f for f in TRAIN_FILES], REAL, SCALE,
                        {**MASS, "com": {**COM, "candidate": "physical with the current "
                                         "input, simulator only", "sessions_drawn": False}},
                        0, False, None, starts=early)
    assert simulated == []  # the drawn sessions came with the early start
    assert [t[0] for t in trained] == ["models_physical_current",
                                       "models_real_finetuned_current_sessions_250"]
    assert trained[1][1] == "models_physical_current_sessions"
    assert copied[1] == ("models_physical_current", "models_real_com", 1.0)
    assert res["models"] == str(tmp_path / "models_real")


def test_the_kinds_the_folds_start_from_are_trained_beside_the_simulated_stages(
        tmp_path, monkeypatch):
    """Every kind of physical model the folds' candidates start from (the full scale: three;
    the quick scale: one); ``reproduce`` hands them to the simulated stages, which train
    them beside their own once the simulated files are there."""
    from jaxinertia.app import reproduce as P  # noqa: PLC0415 - the command's module

    assert M.fold_kinds(P.FULL) == [(False, False), (True, False), (True, True)]
    assert M.fold_kinds(P.QUICK) == [(False, False)]
    assert M.fold_kinds(SimpleNamespace(fold_finetune_samples=())) == []
    calls = []
    monkeypatch.setattr(P, "simulate_files", lambda params, wanted, **kw: [
        Path(w[0]) for w in wanted])
    monkeypatch.setattr(P, "arm_sim_params", lambda arm: None)
    monkeypatch.setattr(P, "sim_fit_session", lambda real: "session")
    monkeypatch.setattr(P, "_stages_after_simulate", lambda *a: {"train_files": a[-2]})
    monkeypatch.setattr(P, "train_starts", lambda out, files, scale, kinds, *a: (
        calls.append(([f.name for f in files], kinds, a[-1])) or {k: out for k in kinds}))
    arm = SimpleNamespace(name="open_manipulator_x")
    for early in (None, [(True, True)]):
        res = P._simulated_stages(tmp_path, P.FULL, arm, None, tmp_path, None, 0, False,
                                  P._Stages(), early)
        assert res["train_files"] == [tmp_path / "data" / f for f in TRAIN_FILES]
        assert res["starts"] == (None if early is None else {(True, True): tmp_path})
    assert calls == [(TRAIN_FILES, [(True, True)], "session")]
