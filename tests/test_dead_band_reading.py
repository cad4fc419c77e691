"""The Present Current reading's dead band (``ServoParams.current_dead_band``).

The real XM430s of the OpenMANIPULATOR-X read no current within 1-3 ticks of position
error (docs/results.md, "The dead band"); the simulator's reading does the same where the
fit says so, while the torque the servo holds, and so where the arm rests, is untouched.
The simulator fit takes the band from the real files, on the joints where it can be seen.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxinertia.session import dead_band_fit, seen_dead_band
from jaxinertia.sim.params import apply_servo_friction, default_sim_params, params_to_dict
from jaxinertia.sim.real_fit import fit_servo_friction, real_files, real_plan, simulate_real_plan
from jaxinertia.sim.servo import RAD_PER_TICK, current_reading_share


def test_without_a_band_the_reading_is_the_current_and_beyond_one_it_grows_by_the_same_gain():
    e = np.arange(-6.0, 7.0)
    np.testing.assert_array_equal(np.asarray(current_reading_share(e, 0.0)), np.ones_like(e))
    d = 1.5
    share = np.asarray(current_reading_share(e, d))
    inside = np.abs(e) <= d
    assert inside.sum() == 3 and np.all(share[inside] == 0.0)
    # share * e is the current in ticks of error: e - d sign(e) beyond the band.
    np.testing.assert_allclose((share * e)[~inside], (e - d * np.sign(e))[~inside], rtol=1e-12)


def test_the_simulated_reading_has_the_band_and_the_arm_rests_where_it_did(small_lbipe_dir,
                                                                            stream_programs):
    data = real_files(small_lbipe_dir)
    plain = default_sim_params()
    band = np.array([1.0, 0.0, 1.0, 2.5])
    banded = plain.replace(servo=plain.servo.replace(current_dead_band=jnp.asarray(band)))
    plans = real_plan(plain.robot, data)
    key = jax.random.key(5)
    a = simulate_real_plan(plain, plans, key, programs=stream_programs)
    b = simulate_real_plan(banded, plans, key, programs=stream_programs)
    # The torque is untouched: the same rests, to the bit; joint 2 (no band) reads the same.
    for k in ("q", "at_rest", "settle_time", "tau"):
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    np.testing.assert_array_equal(a["current_tau"][:, 1], b["current_tau"][:, 1])
    # Within the band the reading is 0 (noise and all); the plain one mostly is not.
    e = np.round(np.asarray(b["q_d"]) / RAD_PER_TICK) - np.asarray(b["q"]) / RAD_PER_TICK
    inside = np.abs(e) <= band
    for j in (0, 2, 3):
        assert inside[:, j].sum() >= 10, (j, inside[:, j].sum())
        assert np.all(b["current_tau"][inside[:, j], j] == 0.0), j
        assert np.mean(a["current_tau"][inside[:, j], j] == 0.0) < 0.5, j
    # The fit that reads a real file's band (session.dead_band_fit) finds the band set here
    # and, beyond it, the plain reading's gain.
    ga, _, _ = dead_band_fit(e * RAD_PER_TICK, a["current_tau"])
    gb, _, db = dead_band_fit(e * RAD_PER_TICK, b["current_tau"])
    np.testing.assert_allclose((db / RAD_PER_TICK)[[0, 2, 3]], band[[0, 2, 3]], atol=0.5)
    np.testing.assert_allclose(gb[[0, 2, 3]], ga[[0, 2, 3]], rtol=0.1)


def test_the_band_is_read_from_the_real_files_where_it_can_be_seen(lbipe_dir):
    """Joints 1, 3 and 4 change sign and show a band of about 1, 1 and 2.3 ticks; joint 2
    (it carries the arm: its error keeps one sign) has none to see. (The paper's two files,
    whatever further real files the folder holds: each is its own session.)"""
    data = real_files(lbipe_dir, ["cube", "white"])
    pooled = seen_dead_band(data) / RAD_PER_TICK
    assert pooled[1] == 0.0
    for one in (seen_dead_band(data[:1]) / RAD_PER_TICK, seen_dead_band(data[1]) / RAD_PER_TICK,
                pooled):
        assert np.all((one[[0, 2, 3]] >= 0.5) & (one[[0, 2, 3]] <= 3.0)), one
        assert one[3] > one[0] and one[3] > one[2], one
    # The simulator fit sets it (the shipped default has none: its servo is the datasheet's
    # where a calibration file says nothing).
    fit = {"servo_friction": params_to_dict(default_sim_params().replace(
        servo=default_sim_params().servo.replace(current_dead_band=jnp.asarray(pooled))))}
    back = apply_servo_friction(default_sim_params(), fit)
    np.testing.assert_array_equal(np.asarray(back.servo.current_dead_band), pooled)
    del fit["servo_friction"]["servo"]["current_dead_band"]  # a calibration made before it
    old = apply_servo_friction(default_sim_params(), fit)
    np.testing.assert_array_equal(np.asarray(old.servo.current_dead_band), np.zeros(4))


def test_the_simulator_fit_sets_the_files_band_when_asked(small_lbipe_dir, stream_programs):
    """``fit_servo_friction(dead_band=True)`` (``calibrate --dead-band``) gives the simulator
    the band of the files it fits; by default (off: docs/results.md) it has none."""
    data = real_files(small_lbipe_dir)
    kw = dict(iterations=1, log=lambda m: None, programs=stream_programs)
    banded, _ = fit_servo_friction(default_sim_params(), data, dead_band=True, **kw)
    band = seen_dead_band(data) / RAD_PER_TICK
    np.testing.assert_allclose(np.asarray(banded.servo.current_dead_band), band, rtol=1e-12)
    assert np.all(band[[0, 2, 3]] > 0)  # (the check above can fail)
    plain, _ = fit_servo_friction(default_sim_params(), data, **kw)
    np.testing.assert_array_equal(np.asarray(plain.servo.current_dead_band), np.zeros(4))
