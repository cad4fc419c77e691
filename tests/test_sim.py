"""The simulated arm: true sticking, the sampling protocol, and statics of a sample."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxinertia.kinematics import ee_pose, gravity_torques
from jaxinertia.robot import open_manipulator_x
from jaxinertia.sim.friction import FrictionParams, friction_bound, solve_box_friction
from jaxinertia.sim.servo import RAD_PER_TICK, ServoParams
from jaxinertia.sim.simulator import SimParams, SimState, attach_payload, hold, move_and_settle
from jaxinertia.statics import load_regressor

DEG = np.pi / 180
GOAL = jnp.array([10.0, -30.0, 30.0, 0.0]) * DEG
PAYLOAD_M = 0.1
R_EE_TAG = jnp.asarray(np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]))
P_EE_TAG = jnp.array([0.01, 0.0, 0.023])
COM_TAG = jnp.array([0.012, -0.004, -0.02])


@pytest.fixture(scope="module")
def params():
    robot = open_manipulator_x().replace(armature=jnp.full(4, 0.01))
    com_ee = R_EE_TAG @ COM_TAG + P_EE_TAG
    return SimParams(attach_payload(robot, PAYLOAD_M, com_ee), ServoParams.xm430_w350(),
                     FrictionParams.create())


@pytest.fixture(scope="module")
def rests(params):
    @jax.jit
    def approach(direction):
        pre = GOAL - direction * 3 * DEG
        s = SimState.at_rest(pre)
        s, ok1, _ = move_and_settle(params, s, pre, pre)
        s, ok2, _ = move_and_settle(params, s, pre, GOAL)
        s_after, ticks = hold(params, s, GOAL, 10.0)
        return s, ok1 & ok2, ticks

    return {d: approach(jnp.full(4, float(d))) for d in (1, -1)}


def test_box_friction_sticks_exactly_below_the_bound_and_slides_above():
    W = jnp.array([[2.0, 0.3], [0.3, 1.0]])
    f, v = solve_box_friction(W, jnp.array([0.1, -0.05]), jnp.array([1.0, 1.0]))
    np.testing.assert_allclose(v, 0.0, atol=1e-12)  # enough friction: both stick
    f, v = solve_box_friction(W, jnp.array([4.0, 0.0]), jnp.array([0.5, 10.0]))
    assert float(v[0]) > 0 and abs(float(f[0]) + 0.5) < 1e-12  # slides against the bound
    assert abs(float(v[1])) < 1e-12  # the other joint held
    fp = FrictionParams.create(coulomb=0.03, static=0.05, load_coefficient=0.3)
    b = friction_bound(fp, jnp.zeros(4), jnp.array([0.0, 1.0, 0.0, 0.0]),
                       jnp.array([0.0, 0.0, 1.0, 0.0]))
    np.testing.assert_allclose(b, [0.05, 0.03, 0.35, 0.05], atol=1e-12)


def test_both_directions_rest_apart_within_the_stiction_band_and_never_creep(params, rests):
    k_tick = float(ServoParams.xm430_w350().p_gain[0] / 128 / 885 * 12 / (12 / 2.3) * 4.1 / 2.3)
    e = {}
    for d, (s, ok, ticks) in rests.items():
        assert bool(ok), f"direction {d} did not come to rest"
        # Neither moves by a tick over a further 10 s.
        assert np.all(np.asarray(ticks) == np.asarray(ticks)[0]), f"direction {d} crept"
        e[d] = np.asarray((GOAL - s.q) / RAD_PER_TICK)
        # At rest: servo torque + friction = -gravity (statics), with |friction| <= bound.
        tau_g = np.asarray(gravity_torques(params.robot, s.q))
        np.testing.assert_allclose(np.asarray(s.servo.torque + s.friction), -tau_g, atol=1e-9)
        bound = np.asarray(friction_bound(params.friction, s.q, 0 * s.q, s.servo.torque))
        assert np.all(np.abs(np.asarray(s.friction)) <= bound + 1e-12)
    sep = e[1] - e[-1]
    # The heavily loaded joint 2 rests clearly apart (the lightly loaded ones may share a
    # tick: the servo's torque comes in steps of ~29 N mm per tick) ...
    assert abs(sep[1]) >= 3, sep
    # ... and no further apart than the band: (F+ + F-) / k, plus one tick of rounding
    # on each side.
    s_p, s_m = rests[1][0], rests[-1][0]
    band = (np.asarray(friction_bound(params.friction, s_p.q, 0 * s_p.q, s_p.servo.torque))
            + np.asarray(friction_bound(params.friction, s_m.q, 0 * s_m.q, s_m.servo.torque)))
    assert np.all(np.abs(sep) <= band / k_tick + 2), (sep, band / k_tick)


def test_a_sample_satisfies_tau_minus_tau_g_equals_A_x(params, rests):
    bare = open_manipulator_x()
    for s, _, _ in rests.values():
        tau = gravity_torques(params.robot, s.q)  # load torque of arm + object at rest
        tau_g = gravity_torques(bare, s.q)
        R_ee, p_ee = ee_pose(bare, s.q)
        A = load_regressor(bare, s.q, R_ee @ R_EE_TAG, R_ee @ P_EE_TAG + p_ee)
        x = jnp.concatenate([jnp.array([PAYLOAD_M]), PAYLOAD_M * COM_TAG])
        np.testing.assert_allclose(tau - tau_g, A @ x, atol=1e-12)
        # And the servo actually carries it: -(servo + friction) is that same torque.
        np.testing.assert_allclose(-(s.servo.torque + s.friction), tau, atol=1e-9)


def test_simulated_samples_follow_the_lbipe_conventions():
    from jaxinertia.features import LBIPE_FEATURES
    from jaxinertia.sim.sampling import HeldObject, simulate_samples

    robot = open_manipulator_x().replace(armature=jnp.full(4, 0.01))
    params = SimParams(robot, ServoParams.xm430_w350(), FrictionParams.create())
    obj = HeldObject(jnp.asarray(0.0881), COM_TAG, R_EE_TAG, P_EE_TAG, jnp.eye(3) * 2e-5)
    rng = np.random.default_rng(0)
    S = 48
    q_d = jnp.asarray(rng.uniform(np.asarray(LBIPE_FEATURES.q_min),
                                  np.asarray(LBIPE_FEATURES.q_max), (S, 4)))
    direction = jnp.asarray(rng.choice([-1.0, 1.0], (S, 4)))
    s = jax.jit(lambda a, b, k: simulate_samples(params, obj, a, b, k))(q_d, direction,
                                                                     jax.random.key(0))
    assert bool(jnp.all(s.at_rest))
    # Present position in whole ticks, current in 2.69 mA steps (times k_t).
    ticks = np.asarray(s.q) / RAD_PER_TICK
    np.testing.assert_allclose(ticks, np.round(ticks), atol=1e-9)
    lsb = 2.69e-3 * 4.1 / 2.3  # datasheet k_t: what a current-based torque assumes
    steps = np.asarray(s.current_tau) / lsb
    np.testing.assert_allclose(steps, np.round(steps), atol=1e-6)
    # tau - tau_g = A x exactly, with the foundation's A at the recorded q.
    np.testing.assert_allclose(s.tau - s.tau_g, jnp.einsum("snk,k->sn", s.A, obj.x), atol=1e-12)
    # The servo holds +tau (lbipe convention) up to friction and tick rounding of q.
    hold_err = np.asarray(s.servo_tau + s.friction_tau - s.tau)
    assert np.max(np.abs(hold_err)) < 0.01, np.max(np.abs(hold_err))
    # tau rises with q_d - q as on the real arm (k > 0 per joint, ~16 N m/rad at P = 800).
    qe = np.asarray(s.q_d - s.q)
    for j in range(4):
        X = np.column_stack([qe[:, j], -np.asarray(direction[:, j]), np.ones(S)])
        k, f, _ = np.linalg.lstsq(X, np.asarray(s.tau[:, j]), rcond=None)[0]
        assert 10 < k < 25 and f > 0, (j, k, f)


def test_shipped_link_gravity_reproduces_the_real_tau_g(lbipe_dir):
    """The simulated arm's gravity is the real arm's (base parameters fitted to lbipe)."""
    from jaxinertia.kinematics import gravity_torques
    from jaxinertia.lbipe import load_test_file
    from jaxinertia.sim.calibration import apply_calibration, fit_link_gravity, load_calibration

    robot = apply_calibration(open_manipulator_x(), load_calibration())
    urdf = open_manipulator_x()
    for name in ("cube", "white"):
        ds = load_test_file(lbipe_dir / "data" / f"data_test_{name}.npz")
        tg = jax.vmap(gravity_torques, (None, 0))(robot, jnp.asarray(ds.q))
        np.testing.assert_allclose(tg, ds.tau_g, atol=1e-9)
        # ... which the URDF inertials do not (joint 1 off by a factor ~1.7).
        tg0 = jax.vmap(gravity_torques, (None, 0))(urdf, jnp.asarray(ds.q))
        assert np.max(np.abs(np.asarray(tg0) - ds.tau_g)) > 0.01
    # The shipped file is what the fit gives today.
    fitted, _ = fit_link_gravity(urdf, lbipe_dir)
    np.testing.assert_allclose(fitted.mass, robot.mass, rtol=1e-9)
    np.testing.assert_allclose(fitted.com, robot.com, atol=1e-12)


@pytest.mark.parametrize("batch_last", [False, True], ids=["vmap", "batch-last"])
def test_streamed_lanes_give_the_samples_of_the_plain_vmap(batch_last):
    """The lane scheduler (lanes refill as samples finish, objects mixed) runs the same
    arithmetic as ``simulate_samples`` (one vmapped protocol per sample) with the same
    per-sample keys, so the samples agree; and they do not depend on the lane count.

    Stepped by ``vmap`` of the one-arm step, everything agrees to the bit across lane
    counts. Stepped batch-last (the default,
    ``jaxinertia.sim.batched``: the same physics, organised and so rounded differently),
    the ticks, rest flags and settle times still agree to the bit and the true state to
    1e-12; across lane counts only the state may differ, in its last bits (the compiled
    loops differ with the batch size)."""
    from jaxinertia.sim.run import default_sim_params, run_plans
    from jaxinertia.sim.sampling import simulate_samples
    from jaxinertia.sim.scenarios import lbipe_object, random_plan

    p = default_sim_params()
    plans = [(lbipe_object("cube"), *random_plan(5, 0), jax.random.key(3)),
             (lbipe_object("white"), *random_plan(4, 1), jax.random.key(4))]
    a = run_plans(p, plans, lanes=3, batch_last=batch_last, progress=False)
    b = run_plans(p, plans, lanes=8, batch_last=batch_last, progress=False)
    state = ("q_true", "servo_tau", "friction_tau")
    for obj, q_d, d, key in plans[::-1]:
        ref = simulate_samples(p, obj, jnp.asarray(q_d), jnp.asarray(d),
                               jax.random.split(key, len(q_d)))
        got_a, got_b = a.pop(), b.pop()
        for k, v in ref._asdict().items():
            v = np.asarray(v)
            if batch_last and k in state:
                np.testing.assert_allclose(got_a[k], got_b[k], rtol=0, atol=1e-15, err_msg=k)
            else:
                np.testing.assert_array_equal(got_a[k], got_b[k], err_msg=k)
            if k in ("q", "q_d", "direction", "at_rest", "settle_time"):  # to the bit
                np.testing.assert_array_equal(got_a[k], v, err_msg=k)
            elif k in state:  # the simulator's state
                np.testing.assert_allclose(got_a[k], v, rtol=0, atol=1e-12, err_msg=k)
            else:  # functions of the ticks, fused differently: to rounding
                np.testing.assert_allclose(got_a[k], v, rtol=1e-13, atol=1e-15, err_msg=k)
        assert got_a["at_rest"].all()


def test_the_stream_runs_the_stepping_program_precompiled_before_its_plans():
    """``precompile`` (what ``simulate_scenarios`` calls before building its plans) submits
    the stepping program for the same abstract lanes as the stream builds from real plans:
    the stream then compiles no second one."""
    from jaxinertia.sim import stream
    from jaxinertia.sim.run import default_sim_params, run_plans
    from jaxinertia.sim.scenarios import lbipe_object, random_plan

    def steps_programs():
        return {k for k in stream._PROGRAMS if k[0] == "steps"}

    p = default_sim_params()
    before = steps_programs()
    stream.precompile(p, lbipe_object("red"), lanes=5, batch_last=True)
    precompiled = steps_programs() - before
    assert len(precompiled) == 1
    out, = run_plans(p, [(lbipe_object("cube"), *random_plan(3, 2), jax.random.key(1))],
                     lanes=5, tail_lanes=0, batch_last=True, progress=False)
    assert steps_programs() == before | precompiled
    assert out["at_rest"].all()


def test_planning_grid_drops_configurations_at_the_mounting_surface():
    """The paper's 46,144 planning samples = 721 of the 875 grid configurations x 16
    directions x 4 loads; the end-effector positions that decide come from MuJoCo C."""
    import itertools

    import mujoco

    from jaxinertia.robot import data_path
    from jaxinertia.sim.scenarios import MOUNT_CLEARANCE_M, WORKSPACE_DEG, planning_plan

    q, d = planning_plan()
    assert q.shape == (11536, 4) and 4 * len(q) == 46144
    kept = np.unique(q, axis=0)
    assert len(kept) == 721
    assert len(np.unique(np.c_[q, d], axis=0)) == len(q)  # 16 distinct patterns each

    model = mujoco.MjModel.from_xml_path(str(data_path("open_manipulator_x.xml")))
    data = mujoco.MjData(model)
    site = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, "end_effector")
    axes = [np.deg2rad(np.arange(lo, hi + 1e-9, 10.0)) for lo, hi in WORKSPACE_DEG]
    z = {}
    for g in itertools.product(*axes):
        data.qpos[:4] = g
        mujoco.mj_kinematics(model, data)
        z[g] = data.site_xpos[site][2]
    clear = {g for g, zg in z.items() if zg >= MOUNT_CLEARANCE_M}
    assert {tuple(g) for g in kept} == clear
    # The threshold sits in a gap of the grid's heights: nothing within 2 mm of it.
    assert min(abs(zg - MOUNT_CLEARANCE_M) for zg in z.values()) > 0.002


def test_bad_plans_and_diverging_integration_name_the_scenario_and_sample():
    from jaxinertia.sim.run import SimulationError, default_sim_params, run_plan
    from jaxinertia.sim.scenarios import lbipe_object, random_plan

    params = default_sim_params()
    q, d = random_plan(4, seed=0)
    cube = lbipe_object("cube")

    def run(p, qq, dd):
        return run_plan(p, cube, qq, dd, jax.random.key(0), desc="test/cube", progress=False)

    outside = q.copy()
    outside[2, 3] = np.radians(150.0)  # joint 4's upper limit is 112.9 deg
    with pytest.raises(SimulationError, match=r"test/cube: sample 2: joint 4 goal 150\.00 deg "
                                              r"is outside its limits"):
        run(params, outside, d)
    nan = q.copy()
    nan[1, 0] = np.nan
    with pytest.raises(SimulationError, match="test/cube: sample 1: goal is not finite"):
        run(params, nan, d)
    with pytest.raises(SimulationError, match="test/cube: sample 0: direction"):
        run(params, q, np.zeros_like(d))
    # A 50 ms step makes the servo loop unstable: refused, not recorded.
    with pytest.raises(SimulationError, match="test/cube: the integration diverged at sample"):
        run(params.replace(dt=0.05), q, d)

    # An unknown object or scenario is refused before anything is compiled.
    from jaxinertia.sim import stream
    from jaxinertia.sim.run import ScenarioRequest, simulate_scenarios

    before = set(stream._PROGRAMS)
    with pytest.raises(ValueError, match=r"unknown test object\(s\) \['teapot'\]"):
        simulate_scenarios(params, [ScenarioRequest("random", 4),
                                    ScenarioRequest("test", 4, ["cube", "teapot"])], lanes=7)
    with pytest.raises(ValueError, match="unknown scenario 'grid'"):
        simulate_scenarios(params, [ScenarioRequest("grid")], lanes=7)
    assert set(stream._PROGRAMS) == before


def test_continuous_run_switches_objects_and_keeps_the_statics_of_each():
    """The switching-load scenario: the schedule and the random walk are recorded as
    planned, every sample obeys tau - tau_g = A x of the object held *at that sample*
    (the empty gripper: tau == tau_g), and the arm follows the walk without stopping."""
    from jaxinertia.sim.continuous import continuous_plan, simulate_continuous_run
    from jaxinertia.sim.run import default_sim_params

    f, meta = simulate_continuous_run(default_sim_params(), n=24,
                                      objects=["empty", "cube", "white"], switch_every=8,
                                      seed=3, progress=False)
    q_plan, d_plan = continuous_plan(24, 3)
    np.testing.assert_array_equal(f["object_id"], np.repeat([0, 1, 2], 8))
    np.testing.assert_array_equal(f["q_d"], q_plan)
    np.testing.assert_array_equal(f["direction"], d_plan)
    x = f["x"][f["object_id"]]
    np.testing.assert_allclose(f["tau"] - f["tau_g"], np.einsum("snk,sk->sn", f["A"], x),
                               atol=1e-12)
    np.testing.assert_array_equal(f["tau"][:8], f["tau_g"][:8])
    assert np.all(f["x"][1:, 0] > 0) and f["x"][0, 0] == 0
    # Every reading is taken after the same fixed move + dwell, not at rest by design.
    assert np.ptp(f["settle_time"]) == 0
    # The arm follows the walk: within the servo's compliance of each new goal (far below
    # the 0.5 rad of a diverged run) and tracking its changes.
    assert np.abs(f["q"] - f["q_d"]).max() < 0.1
    for j in range(4):
        assert np.corrcoef(np.diff(f["q"][:, j]), np.diff(q_plan[:, j]))[0, 1] > 0.8, j


def test_simulate_in_float32_rests_where_float64_does(tmp_path, monkeypatch):
    """``jaxinertia simulate --precision float32`` (2-3x faster on a CPU) runs the same
    physics: with the random friction jitter off (float32 draws different random numbers,
    so with it on the samples are another draw of the same distribution), the arm rests at
    the same ticks as in float64 on nearly every joint and never more than one tick away.
    Both files store float64 and name the precision simulated."""
    import json

    from jaxinertia import cli
    from jaxinertia.datasets import load_native
    from jaxinertia.robot import data_path

    monkeypatch.setenv("JAXINERTIA_CACHE_DIR", "off")
    calib = json.loads(data_path("open_manipulator_x_sim.json").read_text())
    calib["servo_friction"]["friction"]["jitter"] = [0.0] * 4
    (tmp_path / "calib.json").write_text(json.dumps(calib))
    out = {}
    try:
        for precision in ("float64", "float32"):
            path = tmp_path / f"{precision}.npz"
            assert cli.main(["simulate", "--scenario", "test", "--n", "32", "--objects",
                             "black", "--calibration", str(tmp_path / "calib.json"),
                             "--precision", precision, "--out", str(path)]) == 0
            out[precision] = load_native(path)
    finally:
        jax.config.update("jax_enable_x64", True)  # the suite's setting (conftest)
    (a, meta_a), (b, meta_b) = out["float64"], out["float32"]
    assert meta_a["simulator"]["precision"] == "float64"
    assert meta_b["simulator"]["precision"] == "float32"
    for k, v in b.items():
        assert v.dtype == a[k].dtype, k
    assert a["q"].dtype == np.float64
    np.testing.assert_allclose(b["q_d"], a["q_d"], rtol=0, atol=1e-6)
    np.testing.assert_array_equal(b["direction"], a["direction"])
    assert a["at_rest"].all() and b["at_rest"].all()
    ticks = np.rint((b["q"] - a["q"]) / (2 * np.pi / 4096))
    assert np.abs(ticks).max() <= 1
    assert np.mean(ticks == 0) >= 0.95
