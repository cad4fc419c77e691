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


def test_files_simulated_together_are_the_files_simulated_one_by_one(monkeypatch, tmp_path,
                                                                      stream_programs):
    """``simulate_many`` (the held-out folds' training files on an accelerator): the
    streams of every call, a plain one and a domain-randomized one's simulated arms, run as
    one program when their plans have the same shapes, and each file holds the samples
    ``simulate_files`` writes alone (up to the last bits of the simulator's state); a
    re-run reuses every file and simulates nothing."""
    import jax.numpy as jnp
    import numpy as np

    from jaxinertia.app import simdata
    from jaxinertia.sim.params import datasheet_sim_params
    from jaxinertia.sim.randomize import session_prior
    from jaxinertia.sim.run import simulate_scenarios_many

    base = datasheet_sim_params()
    other = base.replace(torque_offset=jnp.asarray([0.01, -0.02, 0.0, 0.005]))

    def calls(root):
        # Three random samples per load and arm: the randomized call's two arms make plans
        # of the plain calls' shapes, so the four streams share one program.
        return [simdata.FilesRequest(base, [(root / "a.npz", "random", 3, 0)]),
                simdata.FilesRequest(other, [(root / "b.npz", "random", 3, 1)]),
                simdata.FilesRequest(base, [(root / "s.npz", "random", 6, 2)],
                                     spread=session_prior(4), draws=2)]

    programs = []

    def many(jobs, **kw):
        programs.append(len(jobs))
        return simulate_scenarios_many(jobs, **kw)

    monkeypatch.setattr(simdata, "simulate_scenarios_many", many)
    together = simdata.simulate_many(calls(tmp_path / "together"), progress=False)
    assert programs == [4]
    alone = [simdata.simulate_files(c.params, c.wanted, spread=c.spread, draws=c.draws,
                                    progress=False) for c in calls(tmp_path / "alone")]
    assert programs == [4]  # one by one: no program of several streams
    for got, want in zip(together, alone):
        (got,), (want,) = got, want
        assert got.meta["request"] == want.meta["request"]
        assert got.meta.get("domain_randomization") == want.meta.get("domain_randomization")
        a, b = got.samples, want.samples
        assert len(a.q) == len(b.q) == (24 if got.meta.get("domain_randomization") else 12)
        for k in ("q", "q_d", "direction", "object_id"):
            np.testing.assert_array_equal(getattr(a, k), getattr(b, k), err_msg=k)
        for k in ("tau", "tau_g", "current_tau", "p_base_tag"):
            np.testing.assert_allclose(getattr(a, k), getattr(b, k), rtol=1e-12, atol=1e-14,
                                       err_msg=k)
    # The simulators differ, and so do their samples (the checks above can fail).
    assert not np.allclose(together[0][0].samples.tau, together[1][0].samples.tau)

    def simulate(*a, **kw):
        raise AssertionError("nothing should be simulated")

    monkeypatch.setattr(simdata, "simulate_scenarios", simulate)
    monkeypatch.setattr(simdata, "simulate_scenarios_many", simulate)
    again = simdata.simulate_many(calls(tmp_path / "together"), progress=False)
    assert [f.meta["sha256"] for (f,) in again] == [f.meta["sha256"] for (f,) in together]
