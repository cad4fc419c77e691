"""Simulated sample files: made once, reused by a re-run of the same request."""

from __future__ import annotations


def test_simulate_files_returns_the_files_it_reuses_when_every_one_is_there(monkeypatch,
                                                                            tmp_path):
    """A re-run whose every file is there reuses them all and simulates nothing (it used
    to fail with an unbound name: found running experiments/current_input_folds.py)."""
    from jaxinertia.app import simdata
    from jaxinertia.sim.params import datasheet_sim_params

    made = {}

    def reused(path, request, **kw):
        made[path] = object()
        return made[path]

    def simulate(*a, **kw):
        raise AssertionError("nothing should be simulated")

    monkeypatch.setattr(simdata, "reused", reused)
    monkeypatch.setattr(simdata, "simulate_scenarios", simulate)
    wanted = [(tmp_path / "a.npz", "random", 10, 0), (tmp_path / "b.npz", "test", 5, 1)]
    out = simdata.simulate_files(datasheet_sim_params(), wanted, progress=False)
    assert out == [made[tmp_path / "a.npz"], made[tmp_path / "b.npz"]]
