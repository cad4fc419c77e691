"""The folds' trainings from scratch rehearsed on placeholder samples while the simulators
calibrate (jaxinertia.app.fold_rehearsal): the real trainings find their programs compiled,
and train what they train without it."""

from __future__ import annotations

import jax
import numpy as np
from support.asserts import assert_tree_equal
from support.compiles import compile_counter
from support.synthetic import synthetic_samples

from jaxinertia.app import fold_rehearsal, pipeline
from jaxinertia.app.fold_rehearsal import placeholder_samples
from jaxinertia.app.programs import side_by_side
from jaxinertia.sim.run import ScenarioRequest, request_counts
from jaxinertia.training import TrainConfig
from jaxinertia.training_group import TrainingGroup, rehearse_as
from jaxinertia.training_setup import feature_config_from, split_validation

#: Epoch programs of the torque models ("update", one epoch a call) and the attention's.
EPOCHS = ("update", "run")
CFG = TrainConfig(n_models=2, torque_epochs=3, attention_epochs=2, attention_sets=8,
                  attention_val_sets=4, val_fraction=0.2)


def _data(n: int, seed: int):
    """A training's samples, four objects (``n`` no other test trains on: its programs are
    compiled here)."""
    return synthetic_samples(np.random.default_rng(seed), n=n, n_obj=4)


def _group_trains(jobs: dict, group: TrainingGroup | None = None) -> dict:
    """Each member's training from scratch (``pipeline._fit``, as ``train`` runs it) in a
    thread of its own, as members of ``group`` (default: a new one): name -> (torque,
    attention)."""
    group = group or TrainingGroup(jobs)

    def member(name):
        cfg, data = jobs[name]
        tr, va = split_validation(data, cfg.val_fraction, cfg.seed)
        with group.member(name):
            _, _, torque, attention, _ = pipeline._fit(cfg, feature_config_from(tr), tr, va,
                                                       None, False)
        return torque, attention

    return dict(zip(jobs, side_by_side([lambda n=n: member(n) for n in jobs], workers=2)))


def test_a_rehearsal_on_placeholders_compiles_what_the_groups_trainings_run():
    """Two members' trainings from scratch rehearsed on placeholder samples of their data's
    per-object counts (other values): the group's trainings on the real data then compile
    no epoch program, torque's or attention's, and train the same models as the same
    group again. A group whose data has other shapes compiles its own (the check can
    fail)."""
    jobs = {name: (CFG.replace(seed=seed), _data(181, seed))
            for name, seed in (("cube/paper", 3), ("white/paper", 4))}
    group = TrainingGroup(jobs)
    assert not any(group.rehearsal.began(n) for n in jobs)
    threads = []
    for name, (cfg, data) in jobs.items():
        counts = np.bincount(data.object_id).tolist()
        holder = placeholder_samples(counts, seed=7)
        assert holder.n_samples == data.n_samples and holder.n_objects == data.n_objects
        threads.append(rehearse_as(group, name,
                                   lambda c=cfg, h=holder: fold_rehearsal._training(c, h)))
    for t in threads:
        t.join()
    assert all(group.rehearsal.began(n) for n in jobs)
    # The real trainings in that group: every epoch program found compiled.
    with compile_counter(*EPOCHS) as seen:
        got = _group_trains(jobs, group)
    assert sum(seen.compiles.values()) == 0, seen.compiles
    # Nothing of the rehearsal in what was trained: the same group again (programs
    # compiled by now) trains the same models, bit for bit.
    again = _group_trains(jobs)
    for name in jobs:
        for g, w, part in zip(got[name], again[name], ("torque", "attention")):
            assert_tree_equal(g.variables, w.variables, what=f"{name} {part}")
            np.testing.assert_array_equal(g.history, w.history, err_msg=f"{name} {part}")
            assert g.history.shape[0] == getattr(CFG, f"{part}_epochs")
    # The control: data of other shapes (one sample more), not rehearsed, compiles its own.
    other = {name: (cfg, _data(182, cfg.seed)) for name, (cfg, _) in jobs.items()}
    with compile_counter(*EPOCHS) as seen:
        _group_trains(other)
    assert seen.compiles["update"] >= 2, seen.compiles  # the torque's and the attention's


def test_the_planned_counts_are_the_simulated_scenarios(stream_programs):
    """``request_counts`` says per object how many samples a scenario makes before it is
    simulated: what the simulation then returns (every sample at rest)."""
    from jaxinertia.sim.params import datasheet_sim_params
    from jaxinertia.sim.run import simulate_scenarios

    requests = [ScenarioRequest("random", 3, None, 5), ScenarioRequest("test", 2, ["cube"], 1)]
    got = simulate_scenarios(datasheet_sim_params(), requests, programs=stream_programs,
                             progress=False)
    for r, res in zip(requests, got):
        made = [len(fields["q"]) for _, fields in res.values()]
        assert made == request_counts(r) == [r.n] * len(res), (r, made)
        assert all(np.all(fields["at_rest"]) for _, fields in res.values())
    grid = request_counts(ScenarioRequest("planning", None, None, 0))
    assert len(grid) == 4 and len(set(grid)) == 1 and grid[0] > 1000
    assert request_counts(ScenarioRequest("planning", 7, None, 0)) == [7] * 4


def test_placeholders_have_the_fields_a_training_reads():
    """Placeholder samples: the simulated files' fields and dtypes, one object per count,
    and a feature configuration that can be made of them (finite, positive scales)."""
    holder = placeholder_samples([5, 6, 7], seed=1)
    real = _data(18, 0)
    for field in ("q_d", "q", "direction", "current_tau", "tau_g", "A", "tau", "x"):
        a, b = getattr(holder, field), getattr(real, field)
        assert a.dtype == b.dtype and a.shape[1:] == b.shape[1:], field
    assert np.bincount(holder.object_id).tolist() == [5, 6, 7]
    fc = feature_config_from(holder, current_input=True)
    assert np.all(np.isfinite(fc.qe_scale)) and np.all(fc.current_scale > 0)
    assert len(set(holder.names)) == 3
    assert jax.tree_util.tree_structure(holder) == jax.tree_util.tree_structure(
        holder.take(np.arange(3)))
