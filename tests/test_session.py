"""Session terms read from a file itself (issue 30): the current-discrepancy gain, the
rescaling towards a model folder's reference session, and the recipe the held-out folds
choose."""

from __future__ import annotations

import numpy as np
import pytest
from support.synthetic import synthetic_samples

from jaxinertia.app.recipe import choose_recipe
from jaxinertia.app.with_reference import ReferenceFile, same_session
from jaxinertia.errors import UsageError
from jaxinertia.lbipe import find_layout
from jaxinertia.lbipe import load_test_files as real_files
from jaxinertia.session import (
    DEAD_BAND_GRID,
    MAX_RELATIVE_SE,
    RATIO_RANGE,
    ServoSession,
    SessionReference,
    adapt,
    servo_session,
    servo_state_change,
)


def _session(rng, gain, n=500, noise=0.004):
    """Samples whose current torque is ``gain * (q_d - q)`` + offset + noise per joint."""
    d = synthetic_samples(rng, n=n, n_obj=1)
    e = d.q_d - d.q
    return d.replace(current_tau=e * np.asarray(gain) + 0.01 + noise * rng.normal(size=e.shape))


def test_the_current_gain_is_read_from_the_samples_alone():
    rng = np.random.default_rng(0)
    gain = np.array([13.4, 18.3, 13.4, 5.5])
    s = servo_session(_session(rng, gain))
    # Within four standard errors, and the standard errors are what the noise implies.
    np.testing.assert_array_less(np.abs(s.current_gain - gain), 4 * s.current_gain_se)
    assert np.all(s.current_gain_se < 0.01 * gain) and s.n_samples == 500
    # Truth plays no part: the same without tau, x.
    s2 = servo_session(_session(np.random.default_rng(0), gain).without_truth())
    np.testing.assert_array_equal(s.current_gain, s2.current_gain)


def test_the_gain_beyond_the_dead_band_does_not_depend_on_the_load():
    """A servo that reads no current within a dead band of its error: a light load (errors
    near zero) and a heavy one (errors far from it) give the same gain and dead band,
    where a straight line through every sample would differ by tens of per cent."""
    tick = 2 * np.pi / 4096
    gain, dead = np.array([15.0, 18.0, 15.0, 11.0]), np.array([1.0, 3.0, 0.9, 2.5]) * tick

    def servo(rng, spread):
        d = synthetic_samples(rng, n=1000, n_obj=1)
        e = rng.normal(size=d.q.shape) * spread * tick
        cur = gain * np.sign(e) * np.maximum(np.abs(e) - dead, 0) + 0.002 * rng.normal(
            size=e.shape)
        return d.replace(q_d=d.q + e, current_tau=cur)

    light, heavy = servo(np.random.default_rng(2), 2.5), servo(np.random.default_rng(3), 8.0)
    s_light, s_heavy = servo_session(light), servo_session(heavy)
    for s in (s_light, s_heavy):
        np.testing.assert_allclose(s.current_gain, gain, rtol=0.03)
        np.testing.assert_allclose(s.dead_band, dead, atol=0.3 * tick)
    # The straight line through every sample: the light load's "gain" is far lower.
    line = [np.polyfit((d.q_d - d.q)[:, 3], d.current_tau[:, 3], 1)[0] for d in (light, heavy)]
    assert line[0] < 0.85 * line[1]
    assert DEAD_BAND_GRID[0] == 0.0 and DEAD_BAND_GRID[-1] == pytest.approx(5 * tick)


def test_adapt_rescales_the_discrepancy_towards_the_reference_session():
    rng = np.random.default_rng(1)
    ref_gain = np.array([13.4, 18.3, 13.4, 5.5])
    day = np.array([1.0, 0.95, 1.03, 1.2])  # another session: the servo's gain of the day
    d = _session(rng, ref_gain * day)
    ref = SessionReference(ref_gain)
    out, ratio = adapt(d, ref)
    np.testing.assert_allclose(ratio, day, rtol=5e-3)
    # Only the discrepancy changes: q, current, truth and the regressor are untouched.
    np.testing.assert_allclose(out.q_d - out.q, (d.q_d - d.q) * ratio, rtol=1e-12, atol=1e-15)
    for k in ("q", "current_tau", "tau", "tau_g", "A", "direction"):
        np.testing.assert_array_equal(getattr(out, k), getattr(d, k), err_msg=k)
    # Read in the reference session, the file's current gain is the reference's.
    np.testing.assert_allclose(servo_session(out).current_gain, ref_gain, rtol=5e-3)
    # Strength 0 (and no reference): unchanged; strength 1/2: the square root.
    assert adapt(d, ref.replace(strength=0.0))[0] is d and adapt(d, None)[0] is d
    np.testing.assert_allclose(adapt(d, ref.replace(strength=0.5))[1], np.sqrt(ratio))


def test_a_gain_that_cannot_be_told_or_is_not_a_servos_day_is_not_followed():
    ref = SessionReference(np.array([10.0, 10.0, 10.0, 10.0]))
    s = ServoSession(current_gain=np.array([11.0, 30.0, 4.0, 11.0]),
                     current_gain_se=np.array([0.1, 0.1, 0.1, MAX_RELATIVE_SE * 11.0 * 1.01]))
    r = ref.ratio(s)
    assert r[0] == pytest.approx(1.1)
    assert r[1] == RATIO_RANGE[1] and r[2] == RATIO_RANGE[0]  # clipped
    assert r[3] == 1.0  # too uncertain: left as it is
    # The ratio itself, before clipping: none for the joint that cannot be told.
    g = ref.gain_ratio(s)
    np.testing.assert_allclose(g[:3], [1.1, 3.0, 0.4])
    assert np.isnan(g[3])
    # A dead current reading (no slope) leaves the joint alone.
    assert ref.ratio(s.replace(current_gain=np.array([0.0, 10.0, 10.0, 10.0])))[0] == 1.0
    with pytest.raises(UsageError, match="3 joints"):
        ref.ratio(ServoSession(np.ones(3), np.zeros(3)))
    assert SessionReference.from_dict(ref.to_dict()).current_gain.tolist() == [10.0] * 4
    assert SessionReference.from_dict(None) is None


def test_the_recorded_supply_and_temperature_are_the_sessions_and_compared_not_used():
    """Files of ``collect`` record each servo's Present Input Voltage and Temperature with
    every sample: the session takes their per-joint medians, a model folder's reference
    keeps them (a folder of older files, or the authors', has none), and a new file's are
    compared with the reference's. They rescale nothing: the current gain carries the
    supply already."""
    rng = np.random.default_rng(4)
    gain = np.array([13.4, 18.3, 13.4, 5.5])
    d = _session(rng, gain, n=301)
    volts = 12.0 + 0.1 * rng.integers(-2, 3, size=d.q.shape)  # 0.1 V register steps
    warm = np.array([31.0, 35.0, 33.0, 30.0]) + rng.integers(0, 3, size=d.q.shape)
    rec = d.replace(extra={**d.extra, "voltage": volts, "temperature": warm})
    s = servo_session(rec)
    np.testing.assert_array_equal(s.supply_voltage, np.median(volts, axis=0))
    np.testing.assert_array_equal(s.temperature, np.median(warm, axis=0))
    # Pooled records: only where every one recorded them; a record without: none.
    both = servo_session([rec, rec])
    np.testing.assert_array_equal(both.supply_voltage, s.supply_voltage)
    assert servo_session([rec, d]).supply_voltage is None
    assert servo_session(d).supply_voltage is None and servo_session(d).temperature is None
    assert "supply_voltage" not in servo_session(d).to_dict()
    # The reference a folder records (strength and gain as before), written and read back;
    # a reference written before these fields reads as none recorded.
    ref = SessionReference.of(s, 0.5)
    back = SessionReference.from_dict(ref.to_dict())
    assert back.strength == 0.5
    for k in ("current_gain", "supply_voltage", "temperature"):
        np.testing.assert_array_equal(getattr(back, k), getattr(s, k), err_msg=k)
    old = SessionReference.from_dict({"current_gain": gain.tolist(), "strength": 1.0})
    assert old.supply_voltage is None and old.temperature is None
    # A new file on a sagging supply and warmer: the change against the reference.
    day = np.array([0.95, 0.95, 0.95, 0.95])
    sag = _session(rng, gain * day, n=301)
    sag = sag.replace(extra={**sag.extra, "voltage": 0.95 * volts, "temperature": warm + 8})
    change = servo_state_change(ref, servo_session(sag))
    np.testing.assert_allclose(change["supply_ratio"], 0.95, rtol=1e-12)
    np.testing.assert_allclose(change["temperature_change"], 8.0)
    np.testing.assert_allclose(change["reference_supply_voltage"], s.supply_voltage)
    # The current gain saw the same day (within its standard error), adaptation or not.
    np.testing.assert_allclose(change["current_gain_ratio"], day, rtol=0.01)
    np.testing.assert_array_equal(change["current_gain_ratio"],
                                  ref.gain_ratio(servo_session(sag)))
    # Nothing recorded on either side: nothing compared; the file's alone: its own only.
    bare = servo_state_change(old, servo_session(sag))
    assert bare["supply_ratio"] is None and bare["reference_temperature"] is None
    assert bare["supply_voltage"] == pytest.approx((0.95 * s.supply_voltage).tolist())
    none = servo_state_change(None, servo_session(d))
    assert all(v is None for v in none.values())
    # estimate --reference: a reference whose recorded supply is 3 % off the file's is
    # another session, whatever the current gains say (here the same samples: equal).
    ref_file = ReferenceFile("ref", None, [rec])
    assert same_session(ref_file, rec)["same_session"] is True
    other = rec.replace(extra={**rec.extra, "voltage": 0.97 * volts})
    st = same_session(ref_file, other)
    assert st["same_session"] is False and st["other_session_joints"] == [1, 2, 3, 4]
    np.testing.assert_allclose(st["current_gain_ratio"], 1.0)
    # Not used to rescale: the same factors whether the reference recorded them or not.
    np.testing.assert_array_equal(adapt(sag, ref)[1],
                                  adapt(sag, SessionReference(ref.current_gain, 0.5))[1])


def test_the_real_files_are_two_sessions(lbipe_dir):
    """The two real files' current gains (no ground truth used): joint 2's differs by
    4.4 %, as their torque gains do in part (issue 30)."""
    files = {o.name: o for o in real_files(find_layout(lbipe_dir))}
    cube, white = (servo_session(files[n]) for n in ("cube", "white"))
    assert cube.n_samples == white.n_samples == 1000
    ratio = white.current_gain / cube.current_gain
    assert ratio[1] == pytest.approx(0.956, abs=0.005)
    # Beyond the dead band (1-3 ticks here) every joint of white's session is 3-6 %
    # weaker than cube's: one supply for four servos. A line through every sample puts
    # joint 4 at +28 %, an artefact of white's heavier load (docs/results.md).
    np.testing.assert_allclose(ratio, 0.955, atol=0.025)
    tick = DEAD_BAND_GRID[10]
    assert np.all((cube.dead_band > 0.5 * tick) & (cube.dead_band < DEAD_BAND_GRID[-1]))
    assert 4 * max(cube.current_gain_se[1], white.current_gain_se[1]) < 0.044 * cube.current_gain[1]


def test_a_reference_from_another_session_is_told_from_one_of_the_same(lbipe_dir):
    """``estimate --reference`` checks, without any truth, that the reference looks recorded
    in the file's session: each joint's current gain must agree within six standard
    errors (or 2 %). The two real files are two sessions (every joint 2.6-5.8 % apart): told
    apart. One file cut at random into a reference of 250 samples and the rest is one
    session: in 20 cuts of each file, none is taken for another."""
    files = {o.name: o for o in real_files(find_layout(lbipe_dir))}
    for ref, other in (("cube", "white"), ("white", "cube")):
        st = same_session(ReferenceFile(ref, None, [files[ref]]), files[other])
        assert st["same_session"] is False and 2 in st["other_session_joints"], st
        assert abs(st["current_gain_ratio"][1] - (0.955 if ref == "cube" else 1 / 0.955)) < 0.01
    for o in files.values():
        for seed in range(20):
            idx = np.random.default_rng(seed).permutation(o.n_samples)
            st = same_session(ReferenceFile(o.name, None, [o.take(idx[:250])]),
                              o.take(idx[250:]))
            assert st["same_session"] is True, (o.name, seed, st)


def _objects(ta_mass, ta_com, t=None):
    """A held-out object's T-A metrics, and T's (``t``: (mass, com); default: twice T-A's,
    so that the attention on wins)."""
    t_mass, t_com = t or (2 * ta_mass, 2 * ta_com)
    return {"o": {"T-A": {"mass_NMAE_pct": ta_mass, "com_NMAE_pct": ta_com},
                  "T": {"mass_NMAE_pct": t_mass, "com_NMAE_pct": t_com}}}


def test_the_recipe_is_the_lowest_mean_over_every_fold():
    released = {"o": {"T-A": {"mass_NMAE_pct": 4.0, "com_NMAE_pct": 10.0},
                      "T": {"mass_NMAE_pct": 4.0, "com_NMAE_pct": 10.0}}}

    def fold(sim, ft, only_here=None):
        f = {"held_out": ["o"], "released": released,
             "by_strength": {"0.0": _objects(*sim[0]), "1.0": _objects(*sim[1])},
             "fine_tuned": {"250": {"by_strength": {"0.0": _objects(*ft[0]),
                                                    "1.0": _objects(*ft[1])}}}}
        if only_here:
            f["fine_tuned"]["64"] = {"by_strength": {"0.0": _objects(*only_here),
                                                     "1.0": _objects(*only_here)}}
        return f

    # Fine-tuned + adapted is best on average though not in the first fold; a candidate
    # that only one fold judged (64 samples, excellent there) does not compete.
    folds = {"a": fold(((8, 20), (6, 15)), ((6, 14), (5, 13)), only_here=(1, 1)),
             "b": fold(((8, 20), (7, 18)), ((9, 22), (5, 12)))}
    r = choose_recipe(folds)
    assert r["candidate"] == "physical, servo part fine-tuned on 250 real samples"
    assert r["session_strength"] == 1.0 and r["finetune_samples"] == 250
    want = np.mean([5 / 4, 13 / 10, 5 / 4, 12 / 10])
    assert r["score"] == pytest.approx(want)
    assert [c["score"] for c in r["scores"]] == sorted(c["score"] for c in r["scores"])
    # (two candidates at two strengths, each with its attention and without)
    assert len(r["scores"]) == 2 * 2 * 2 and r["folds"] == 2
    assert r["current_input"] is False and r["attention"] is True
    # With the current input (FoldScale.current_input): its candidates compete by name, and
    # the choice says which inputs the models for a new object take.
    for f, ft in zip(folds.values(), (((4, 12), (6, 14)), ((4, 10), (6, 14)))):
        f["physical_current"] = {"by_strength": {"0.0": _objects(9, 30),
                                                 "1.0": _objects(9, 30)}}
        f["fine_tuned_current"] = {"1000": {"by_strength": {"0.0": _objects(*ft[0]),
                                                            "1.0": _objects(*ft[1])}}}
    r = choose_recipe(folds)
    assert r["candidate"] == ("physical with the current input, servo part fine-tuned on "
                              "1000 real samples")
    assert r["current_input"] is True and r["finetune_samples"] == 1000
    assert r["session_strength"] == 0.0 and len(r["scores"]) == 16
    assert r["sessions_drawn"] is False
    # ... and trained on drawn recording sessions (FoldScale.session_draws): named apart,
    # and the choice says so (reproduce then draws sessions for models_real's data).
    for f in folds.values():
        f["fine_tuned_current_sessions"] = {"1000": {"by_strength": {
            "0.0": _objects(3, 9), "1.0": _objects(9, 30)}}}
    r = choose_recipe(folds)
    assert r["candidate"] == ("physical with the current input, sessions drawn, servo part "
                              "fine-tuned on 1000 real samples")
    assert r["sessions_drawn"] is True and r["current_input"] is True
    assert r["finetune_samples"] == 1000 and len(r["scores"]) == 20
    # Mass and COM judged apart (information only): each part's best and their mean. A
    # candidate with the best COM but a poor mass is not the recipe, but is the COM's best.
    for f in folds.values():
        f["physical_current_sessions"] = {"by_strength": {"0.0": _objects(20, 5),
                                                          "1.0": _objects(20, 5)}}
    r = choose_recipe(folds)
    assert r["sessions_drawn"] is True and "fine-tuned on 1000" in r["candidate"]
    part = r["by_part"]
    assert part["mass"]["candidate"] == r["candidate"]
    assert part["mass"]["score"] == pytest.approx(3 / 4)
    assert part["com"]["candidate"] == ("physical with the current input, sessions drawn, "
                                        "simulator only")
    assert part["com"]["score"] == pytest.approx(5 / 10)
    assert part["score"] == pytest.approx((3 / 4 + 5 / 10) / 2) and part["score"] < r["score"]
    assert part["mass"]["attention"] is True and part["com"]["attention"] is True
    # Without the attention (T), a candidate whose T is better than every T-A is chosen so,
    # and says so; scored against the released models' T-A all the same.
    for f in folds.values():
        f["physical_current"]["by_strength"]["1.0"] = _objects(9, 30, t=(2, 9))
    r = choose_recipe(folds)
    assert r["candidate"] == "physical with the current input, simulator only"
    assert r["attention"] is False and r["session_strength"] == 1.0
    assert r["score"] == pytest.approx((2 / 4 + 9 / 10) / 2)
    assert r["by_part"]["mass"]["attention"] is False
    assert r["by_part"]["mass"]["score"] == pytest.approx(2 / 4)
