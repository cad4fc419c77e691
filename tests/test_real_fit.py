"""The shipped simulator parameters against the real OpenMANIPULATOR-X data.

The real files' goals, directions and objects are simulated with the package's default
(fitted to the real arm) parameters; the baseline fits on simulated and on real samples are compared
with the acceptance bands of issue 3.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxinertia.errors import UsageError
from jaxinertia.objects import TEST_OBJECTS
from jaxinertia.open_manipulator_x import load_sim_fit
from jaxinertia.sim.params import default_sim_params, session_params
from jaxinertia.sim.real_fit import (
    baseline_statistics,
    fit_servo_friction,
    fit_servo_friction_many,
    real_files,
    real_plan,
    simulate_real_plan,
    simulate_real_plans,
)
from jaxinertia.sim.run import simulate_scenario

FIELDS = ("q_d", "q", "direction", "tau", "current_tau")

#: The acceptance bands of issue 3: the simulated statistic within this fraction of the
#: real one (the reference: the real data).
BANDS = {"pe_mae": 0.25, "k": 0.10, "current_mae": 0.25, "mu": 0.30, "tau_max": 0.20}


@pytest.fixture(scope="module")
def stats(lbipe_dir, stream_programs):
    """The baseline statistics of the real files the shipped parameters were fitted on, and
    of their plans simulated. Only those: a further real file in the folder is another
    recording session (and object), which issue 3's bands do not speak for."""
    params = default_sim_params()
    fitted_on = load_sim_fit()["link_gravity"]["source"]
    plans = real_plan(params.robot, real_files(lbipe_dir, fitted_on))
    sim = simulate_real_plan(params, plans, jax.random.key(123),  # not the fit's key
                             programs=stream_programs)
    real = {k: np.concatenate([getattr(d, k) for _, _, d in plans]) for k in FIELDS}
    assert np.mean(sim["at_rest"]) == 1.0
    return (baseline_statistics(*(real[k] for k in FIELDS)),
            baseline_statistics(*(sim[k] for k in FIELDS)))


def _assert_within(sim: np.ndarray, real: np.ndarray, name: str, joints=slice(None)):
    """The statistic ``name`` of the simulated samples is within its band of the real one
    on ``joints``; the failure names the statistic and both values."""
    sim, real = np.asarray(sim)[joints], np.asarray(real)[joints]
    ok = np.abs(sim / real - 1.0) <= BANDS[name]
    assert np.all(ok), f"{name}: sim {sim} vs real {real} (band {BANDS[name]:.0%})"


def test_position_error_baseline_matches_real(stats):
    real, sim = stats
    _assert_within(sim["pe_mae"], real["pe_mae"], "pe_mae")
    _assert_within(sim["k"], real["k"], "k")


def test_current_baseline_matches_real(stats):
    real, sim = stats
    _assert_within(sim["current_mae"], real["current_mae"], "current_mae")


def test_load_friction_slope_matches_real(stats):
    """mu within +-30 % on joints 1-3. Joint 4's real slope is 0.041 with a standard error
    of 0.013 (2000 samples): +-30 % is smaller than one standard error, so there the test
    asks for agreement within two combined standard errors instead (issue 3's band is not
    checkable on joint 4 with this much data; see the closing note)."""
    real, sim = stats
    _assert_within(sim["mu"], real["mu"], "mu", joints=slice(0, 3))
    assert real["mu_se"][3] > 0.3 * abs(real["mu"][3])  # the premise of the exception
    se = np.hypot(real["mu_se"][3], sim["mu_se"][3])
    assert abs(sim["mu"][3] - real["mu"][3]) <= 2 * se, (sim["mu"][3], real["mu"][3], se)


def test_max_torque_over_the_four_test_objects(stream_programs):
    """The test scenario as the paper ran it (1000 samples per object): a maximum over
    fewer samples is biased low."""
    res = simulate_scenario(default_sim_params(), "test", n=1000, seed=0,
                            programs=stream_programs, progress=False)
    assert list(res) == list(TEST_OBJECTS)
    tau_max = np.max([np.max(np.abs(r["tau"][r["at_rest"]]), axis=0)
                      for _, r in res.values()], axis=0)
    real = np.array([0.417, 1.131, 0.534, 0.247])
    _assert_within(tau_max, real, "tau_max")


def test_each_recording_session_gets_its_own_servo(small_lbipe_dir, stream_programs):
    """``fit_servo_friction(sessions=True)``: each real file is its own session, so each
    file's plan replayed with its session's servo gives that file's own PE gain and current
    gain, where one servo for both (the start, the shipped pooled fit: the fit's first
    iteration replays it on each file) misses a file by more. The physics (friction,
    offsets) is one: every session shares it."""
    data = real_files(small_lbipe_dir)
    start = default_sim_params()
    shared, info = fit_servo_friction(start, data, sessions=True, iterations=3,
                                      log=lambda m: None, programs=stream_programs)
    real = {r["name"]: r for r in info["real_sessions"]}
    assert set(real) == {"cube", "white"}

    def worst(it):  # the largest relative miss of k and the current gain, any file/joint
        sim = {s["name"]: s for s in info["history"][it]["sessions"]}
        return max(np.max(np.abs(np.asarray(sim[n][q]) / np.asarray(real[n][q]) - 1.0))
                   for n in real for q in ("k", "gain"))

    per_session, common = worst(-1), worst(0)
    # (three iterations: within 5 %; the fit's own six reach 0.5 % on the full files)
    assert per_session < 0.05 and common > 2 * per_session, (per_session, common)
    # Each session's terms are relative to the common servo (geometric mean 1), and the
    # spread over sessions is what they show.
    terms = info["sessions"]["per_session"]
    for part in ("electrical", "torque"):
        f = np.array([t[part] for t in terms])
        np.testing.assert_allclose(np.exp(np.mean(np.log(f), axis=0)), 1.0, atol=1e-12)
        np.testing.assert_allclose(info["sessions"]["spread"][f"{part}_rel"],
                                   np.std(np.log(f), axis=0, ddof=1), rtol=1e-12)
    # ... and session_params puts a session back: its P gain and torque constant.
    fit = {"sessions": info["sessions"]}
    cube = session_params(shared, fit, "cube")
    np.testing.assert_allclose(np.asarray(cube.servo.p_gain),
                               np.asarray(shared.servo.p_gain) * terms[0]["electrical"])
    with pytest.raises(UsageError, match="recording sessions"):
        session_params(shared, fit, "mug")


def test_several_simulators_replay_in_one_program(small_lbipe_dir, stream_programs):
    """``simulate_real_plans``: each request (simulators, real plans, a key) gets the
    samples it gets alone (ticks, rest and settle times exactly; the statics' torques up to
    the last bits), every simulation in one program (a simulator per file: a simulation
    per file)."""
    data = real_files(small_lbipe_dir)
    base = default_sim_params()
    other = base.replace(torque_offset=jnp.asarray([0.01, -0.02, 0.0, 0.005]))
    # Two simulations in all, as in the test below: its programs compile once.
    requests = [(base, real_plan(base.robot, data[:1]), jax.random.key(1)),
                ([other], real_plan(other.robot, data[1:]), jax.random.key(2))]
    together = simulate_real_plans(requests, programs=stream_programs)
    for (params, plans, key), got in zip(requests, together):
        alone = simulate_real_plan(params, plans, key, programs=stream_programs)
        assert set(got) == set(alone)
        for k in ("q", "at_rest", "settle_time", "current_tau", "q_d", "direction"):
            np.testing.assert_array_equal(got[k], alone[k], err_msg=k)
        for k in ("tau", "tau_g", "A"):
            np.testing.assert_allclose(got[k], alone[k], rtol=1e-12, atol=1e-14, err_msg=k)
    # The two simulators differ: so do their samples (the check above can fail).
    assert not np.array_equal(together[0]["q"], together[1]["q"])


def test_fits_in_lockstep_are_each_fit_alone(small_lbipe_dir, stream_programs):
    """``fit_servo_friction_many`` (the held-out folds' calibrations on an accelerator):
    each fit ends where it ends alone, its simulations made together with the others'."""
    data = real_files(small_lbipe_dir)
    start = default_sim_params()
    kw = dict(iterations=1, log=lambda m: None, programs=stream_programs)
    fits = [(start, data[:1]), (start, data[1:])]
    many = fit_servo_friction_many(fits, **kw)
    for (params, d), (got, info) in zip(fits, many):
        want, want_info = fit_servo_friction(params, d, **kw)
        assert len(info["history"]) == len(want_info["history"]) == 2
        for part in ("servo", "friction"):
            for a, b in zip(jax.tree.leaves(getattr(got, part)),
                            jax.tree.leaves(getattr(want, part))):
                np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-9)
    # The two fits are fitted to their own files: they end apart.
    assert not np.allclose(np.asarray(many[0][0].servo.p_gain),
                           np.asarray(many[1][0].servo.p_gain), rtol=1e-6)
