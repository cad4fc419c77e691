"""The simulated arm: true sticking, the sampling protocol, and statics of a sample."""

from __future__ import annotations

import itertools
import json
import subprocess
import sys
from concurrent.futures import Future
from functools import partial

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from jaxinertia import objects
from jaxinertia.app.cli import main as cli_main
from jaxinertia.design import PLAN_FORMAT, PLAN_FORMAT_VERSION
from jaxinertia.errors import SimulationError, UsageError
from jaxinertia.features import LBIPE_FEATURES
from jaxinertia.kinematics import ee_pose, gravity_torques
from jaxinertia.objects import HeldObject
from jaxinertia.open_manipulator_x import ARM as OMX
from jaxinertia.open_manipulator_x import MOUNT_CLEARANCE_M, WORKSPACE_DEG, sim_fit_robot
from jaxinertia.plans import continuous_plan, planning_plan, random_plan
from jaxinertia.robot import data_path, open_manipulator_x
from jaxinertia.samples import load_lbipe
from jaxinertia.sim import lanes, stream
from jaxinertia.sim.continuous import simulate_continuous, simulate_continuous_run
from jaxinertia.sim.friction import FrictionParams, friction_bound, solve_box_friction
from jaxinertia.sim.params import default_sim_params
from jaxinertia.sim.real_fit import fit_link_gravity, real_files
from jaxinertia.sim.run import ScenarioRequest, run_plan, run_plans, simulate_scenarios
from jaxinertia.sim.sampling import simulate_samples
from jaxinertia.sim.servo import RAD_PER_TICK, ServoParams
from jaxinertia.sim.simulator import SimParams, SimState, attach_payload, hold, move_and_settle
from jaxinertia.statics import load_regressor

#: The OpenMANIPULATOR-X's planning grid (its record's values).
WS, TAG = dict(workspace=OMX.workspace_deg), dict(tag_in_ee=OMX.tag_in_ee)
GRID = dict(step_deg=OMX.planning_step_deg, clearance=OMX.mount_clearance_m,
            robot=OMX.robot(), **WS)

#: Agreement with a float64 reference computation (the statics identity, the exact box
#: solution, the vmapped protocol ``simulate_samples``): rounding only. Checks against
#: the physics (rest, bands, ticks) state their own bounds.
TOL = 1e-12


def _assert_field(got, want, name: str, *, atol: float = 0.0, rtol: float = 0.0):
    """``got[name]`` equals ``want[name]`` (to the bit when no tolerance is given); the
    failure names the field."""
    a, b = np.asarray(got[name]), np.asarray(want[name])
    if atol == 0.0 and rtol == 0.0:
        np.testing.assert_array_equal(a, b, err_msg=f"mismatch: {name}")
    else:
        np.testing.assert_allclose(a, b, atol=atol, rtol=rtol, err_msg=f"mismatch: {name}")


DEG = np.pi / 180
GOAL = jnp.array([10.0, -30.0, 30.0, 0.0]) * DEG
PAYLOAD_M = 0.1
R_EE_TAG = jnp.asarray(np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]))
P_EE_TAG = jnp.array([0.01, 0.0, 0.023])
COM_TAG = jnp.array([0.012, -0.004, -0.02])


@pytest.fixture(scope="module")
def params():
    robot = open_manipulator_x()
    n = robot.n_joints
    robot = robot.replace(armature=jnp.full(n, 0.01))
    com_ee = R_EE_TAG @ COM_TAG + P_EE_TAG
    return SimParams(attach_payload(robot, PAYLOAD_M, com_ee), ServoParams.xm430_w350(n),
                     FrictionParams.create(n))


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
    np.testing.assert_allclose(v, 0.0, atol=TOL)  # enough friction: both stick
    f, v = solve_box_friction(W, jnp.array([4.0, 0.0]), jnp.array([0.5, 10.0]))
    assert float(v[0]) > 0 and abs(float(f[0]) + 0.5) < TOL  # slides against the bound
    assert abs(float(v[1])) < TOL  # the other joint held
    fp = FrictionParams.create(4, coulomb=0.03, static=0.05, load_coefficient=0.3)
    b = friction_bound(fp, jnp.zeros(4), jnp.array([0.0, 1.0, 0.0, 0.0]),
                       jnp.array([0.0, 0.0, 1.0, 0.0]))
    np.testing.assert_allclose(b, [0.05, 0.03, 0.35, 0.05], atol=TOL)


def test_both_directions_rest_apart_within_the_stiction_band_and_never_creep(params, rests):
    k_tick = float(ServoParams.xm430_w350(4).p_gain[0] / 128 / 885 * 12 / (12 / 2.3) * 4.1 / 2.3)
    e = {}
    for d, (s, ok, ticks) in rests.items():
        assert bool(ok), f"direction {d} did not come to rest"
        # Neither moves by a tick over a further 10 s.
        assert np.all(np.asarray(ticks) == np.asarray(ticks)[0]), f"direction {d} crept"
        e[d] = np.asarray((GOAL - s.q) / RAD_PER_TICK)
        # At rest: servo torque + friction = -gravity (statics, to the friction sweeps'
        # convergence, 1e-9 N m), with |friction| <= bound.
        tau_g = np.asarray(gravity_torques(params.robot, s.q))
        np.testing.assert_allclose(np.asarray(s.servo.torque + s.friction), -tau_g,
                                   atol=1e3 * TOL, err_msg=f"direction {d}: statics at rest")
        bound = np.asarray(friction_bound(params.friction, s.q, 0 * s.q, s.servo.torque))
        assert np.all(np.abs(np.asarray(s.friction)) <= bound + TOL), f"direction {d}"
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
        np.testing.assert_allclose(tau - tau_g, A @ x, atol=TOL, err_msg="tau - tau_g")
        # And the servo actually carries it: -(servo + friction) is that same torque (to
        # the friction sweeps' convergence).
        np.testing.assert_allclose(-(s.servo.torque + s.friction), tau, atol=1e3 * TOL,
                                   err_msg="servo + friction")


def test_simulated_samples_follow_the_lbipe_conventions(stream_programs):
    robot = open_manipulator_x().replace(armature=jnp.full(4, 0.01))
    # No constant torque offset: zeros rather than None, so that the parameters have the
    # shipped ones' structure and the stream's programs (default lanes) compiled for the
    # other tests serve here too. The stream gives the samples of ``simulate_samples``
    # (test_streamed_lanes_give_the_samples_of_the_plain_vmap).
    params = SimParams(robot, ServoParams.xm430_w350(4), FrictionParams.create(4),
                       torque_offset=jnp.zeros(4))
    obj = HeldObject(jnp.asarray(0.0881), COM_TAG, R_EE_TAG, P_EE_TAG, jnp.eye(3) * 2e-5)
    rng = np.random.default_rng(0)
    S = 48
    q_d = rng.uniform(np.asarray(LBIPE_FEATURES.q_min), np.asarray(LBIPE_FEATURES.q_max), (S, 4))
    direction = rng.choice([-1.0, 1.0], (S, 4))
    s = run_plan(params, obj, q_d, direction, jax.random.key(0), programs=stream_programs,
                 progress=False)
    assert s["at_rest"].all()
    # Present position in whole ticks, current in 2.69 mA steps (times k_t).
    ticks = s["q"] / RAD_PER_TICK
    np.testing.assert_allclose(ticks, np.round(ticks), atol=1e-9)
    lsb = 2.69e-3 * 4.1 / 2.3  # datasheet k_t: what a current-based torque assumes
    steps = s["current_tau"] / lsb
    np.testing.assert_allclose(steps, np.round(steps), atol=1e-6)
    # tau - tau_g = A x exactly, with the foundation's A at the recorded q.
    np.testing.assert_allclose(s["tau"] - s["tau_g"], np.einsum("snk,k->sn", s["A"], obj.x),
                               atol=TOL, err_msg="tau - tau_g")
    # The servo holds +tau (lbipe convention) up to friction and tick rounding of q.
    hold_err = s["servo_tau"] + s["friction_tau"] - s["tau"]
    assert np.max(np.abs(hold_err)) < 0.01, np.max(np.abs(hold_err))
    # tau rises with q_d - q as on the real arm (k > 0 per joint, ~16 N m/rad at P = 800).
    qe = s["q_d"] - s["q"]
    for j in range(4):
        X = np.column_stack([qe[:, j], -direction[:, j], np.ones(S)])
        k, f, _ = np.linalg.lstsq(X, s["tau"][:, j], rcond=None)[0]
        assert 10 < k < 25 and f > 0, (j, k, f)


def test_shipped_link_gravity_reproduces_the_real_tau_g(lbipe_dir):
    """The simulated arm's gravity is the real arm's (base parameters fitted to lbipe)."""
    robot = sim_fit_robot()
    urdf = open_manipulator_x()
    for name in ("cube", "white"):
        ds = load_lbipe(lbipe_dir / "data" / f"data_test_{name}.npz")
        tg = jax.vmap(gravity_torques, (None, 0))(robot, jnp.asarray(ds.q))
        np.testing.assert_allclose(tg, ds.tau_g, atol=1e-9, err_msg=f"{name}: tau_g")
        # ... which the URDF inertials do not (joint 1 off by a factor ~1.7).
        tg0 = jax.vmap(gravity_torques, (None, 0))(urdf, jnp.asarray(ds.q))
        assert np.max(np.abs(np.asarray(tg0) - ds.tau_g)) > 0.01
    # The shipped file is what the fit gives today.
    fitted, _ = fit_link_gravity(urdf, real_files(lbipe_dir))
    np.testing.assert_allclose(fitted.mass, robot.mass, rtol=1e-9, err_msg="mismatch: mass")
    np.testing.assert_allclose(fitted.com, robot.com, atol=TOL, err_msg="mismatch: com")


@pytest.fixture(scope="module")
def stream_case():
    """Two objects' plans and their samples from the plain vmap (:func:`simulate_samples`,
    one vmapped protocol per sample, the same per-sample keys as the stream), shared by
    both ways of stepping the lanes. The plans have equal sizes so that the reference is one
    compiled program; what is tested does not depend on the sizes: 10 samples refill 3
    lanes three times over, and on 8 lanes the last two wait for a lane to free."""
    p = default_sim_params()
    plans = [(objects.paper_object("cube", **TAG), *random_plan(5, 0, **WS), jax.random.key(3)),
             (objects.paper_object("white", **TAG), *random_plan(5, 1, **WS), jax.random.key(4))]
    refs = [jax.tree.map(np.asarray, simulate_samples(
        p, obj, jnp.asarray(q_d), jnp.asarray(d), jax.random.split(key, len(q_d)))._asdict())
        for obj, q_d, d, key in plans]
    return p, plans, refs


@pytest.mark.parametrize("batch_last", [False, True], ids=["vmap", "batch-last"])
def test_streamed_lanes_give_the_samples_of_the_plain_vmap(batch_last, stream_case,
                                                          stream_programs):
    """The lane scheduler (lanes refill as samples finish, objects mixed) runs the same
    arithmetic as ``simulate_samples`` (one vmapped protocol per sample) with the same
    per-sample keys, so the samples agree; and they do not depend on the lane count.

    Stepped by ``vmap`` of the one-arm step, everything agrees to the bit across lane
    counts. Stepped batch-last (the default,
    ``jaxinertia.sim.batched``: the same physics, organised and so rounded differently),
    the ticks, rest flags and settle times still agree to the bit and the true state to
    1e-12; across lane counts only the state may differ, in its last bits (the compiled
    loops differ with the batch size)."""
    p, plans, refs = stream_case
    a = run_plans(p, plans, lanes=3, batch_last=batch_last, programs=stream_programs,
                  progress=False)
    b = run_plans(p, plans, lanes=8, batch_last=batch_last, programs=stream_programs,
                  progress=False)
    state = ("q_true", "servo_tau", "friction_tau")
    for ref, got_a, got_b in zip(refs, a, b):
        for k in ref:
            if batch_last and k in state:
                _assert_field(got_a, got_b, k, atol=TOL / 1000)
            else:
                _assert_field(got_a, got_b, k)
            if k in ("q", "q_d", "direction", "at_rest", "settle_time"):  # to the bit
                _assert_field(got_a, ref, k)
            elif k in state:  # the simulator's state
                _assert_field(got_a, ref, k, atol=TOL)
            else:  # functions of the ticks, fused differently: to rounding
                _assert_field(got_a, ref, k, rtol=TOL / 10, atol=TOL / 1000)
        assert got_a["at_rest"].all()


def test_a_short_stream_steps_as_many_lanes_as_it_has_samples(monkeypatch):
    """On an accelerator (16,384 lanes) a real file's 1,000-sample plan steps 1,024 lanes,
    not 16,384; a stream of more than a sixteenth of the lanes steps them all. On a CPU
    (256 lanes) every stream steps 256."""
    from jaxinertia.sim import stream

    assert [stream.stream_lanes(n) for n in (1, 24, 1000, 40_000)] == [
        stream.default_lanes()] * 4 == [256] * 4
    monkeypatch.setattr(stream, "default_lanes", lambda: 16384)
    assert [stream.stream_lanes(n) for n in (1, 24, 256, 257, 1000, 1024, 1025, 40_000)] == [
        256, 256, 256, 512, 1024, 1024, 16384, 16384]


def test_scenarios_precompile_the_stepping_program_for_the_lanes_they_stream(monkeypatch):
    """``simulate_scenarios`` starts the stepping program before its plans exist: for the
    lanes its stream will step (:func:`stream.stream_lanes` of the samples the requests make;
    the default when a planning grid's size is unknown), so that a small simulation on an
    accelerator compiles one program, not the default lanes' too. The counts are those of
    the plans built."""
    from jaxinertia.sim import run as sim_run

    monkeypatch.setattr(stream, "default_lanes", lambda: 16384)  # an accelerator's
    precompiled, streamed = [], []
    monkeypatch.setattr(stream.StreamPrograms, "precompile",
                        lambda self, params, obj, *, lanes=None, **kw: precompiled.append(lanes))

    def fake_run_plans(params, plans, **kw):
        streamed.append(sum(len(q_d) for _, q_d, _, _ in plans))
        return [{} for _ in plans]

    monkeypatch.setattr(sim_run, "run_plans", fake_run_plans)
    p, goals = default_sim_params(), random_plan(7, 0, **WS)
    for requests, want in (([ScenarioRequest("test", 10, ["cube"])], 256),
                            ([ScenarioRequest("random", 100), ScenarioRequest("test", 50)], 1024),
                            ([ScenarioRequest("random", 300)], 16384),
                            ([ScenarioRequest("random", None, plan=goals)], 256),
                            ([ScenarioRequest("planning", 5)], None)):
        precompiled.clear(), streamed.clear()
        simulate_scenarios(p, requests, programs=stream.StreamPrograms(), progress=False)
        assert precompiled == [want], (requests, precompiled)
        counts = [sim_run._request_samples(r) for r in requests]
        if None not in counts:
            assert streamed == [sum(counts)], (requests, streamed)


def test_the_stream_runs_the_stepping_program_precompiled_before_its_plans():
    """``precompile`` (what ``simulate_scenarios`` calls before building its plans) submits
    the stepping program for the same abstract lanes as the stream builds from real plans:
    the stream then compiles no second one."""

    def steps_programs():
        return {k for k in programs.keys() if k[0] == "steps"}

    # A fresh registry: 3 lanes, as in test_streamed_lanes_give_the_samples_of_the_plain_vmap,
    # is new to it here (XLA's part comes from the session's compilation cache).
    with stream.StreamPrograms() as programs:
        p = default_sim_params()
        before = steps_programs()
        programs.precompile(p, objects.paper_object("red", **TAG), lanes=3, batch_last=True)
        precompiled = steps_programs() - before
        assert len(precompiled) == 1
        # 9 samples: the sample table (padded to 16) is the other stream tests' one, so that
        # the record program compiled for them serves (the session's compilation cache).
        out, = run_plans(p, [(objects.paper_object("cube", **TAG), *random_plan(9, 2, **WS),
                              jax.random.key(1))],
                         lanes=3, tail_lanes=0, batch_last=True, programs=programs,
                         progress=False)
        assert steps_programs() == before | precompiled
        assert out["at_rest"].all()


def test_a_simulator_without_joint_offsets_streams_with_the_fitted_ones_programs():
    """The datasheet simulator (no constant joint torques: ``torque_offset`` None), where a
    held-out fold's calibration starts, has the signature of the fitted simulators (the
    shipped fit, a fold's after its offset iterations) in the stream: one set of compiled
    programs serves both (a second stepping program cost ~5 s on the 2-core CPU). Only the
    absent offset becomes zeros (added to the servo torque: the same sums)."""
    from jaxinertia.sim.params import arm_sim_params, datasheet_sim_params

    bare, fitted = datasheet_sim_params(), arm_sim_params()
    assert bare.torque_offset is None and fitted.torque_offset is not None
    same = stream._one_signature(bare)
    assert stream._signature(same) == stream._signature(fitted)
    assert np.array_equal(np.asarray(same.torque_offset), np.zeros(bare.robot.n_joints))
    rest = lambda p: jax.tree.leaves(p.replace(torque_offset=None))  # noqa: E731
    assert all(a is b for a, b in zip(rest(same), rest(bare)))
    assert stream._one_signature(fitted) is fitted


def test_a_failed_compilation_leaves_the_other_stream_programs_usable():
    """A stream program whose compilation fails is forgotten alone: its error reaches the
    caller, the programs compiled beside it stay held (a later stream does not compile
    them again) and the failed one is submitted afresh when next needed. (A stand-in
    compiler: the registry is under test, not XLA; only the preparation is traced.)"""

    class StubCompiler:
        def __init__(self):
            self.submitted, self.fail = [], {"finish"}

        def submit(self, fn, *args, untimed=False, **static):  # noqa: ARG002
            self.submitted.append(fn.__name__)
            out = Future()
            if fn.__name__ in self.fail:
                out.set_exception(RuntimeError(f"{fn.__name__}: the compiler crashed"))
            else:
                out.set_result(f"compiled {fn.__name__}")
            return out

    p, stub = default_sim_params(), StubCompiler()
    programs = stream.StreamPrograms(stub)
    plan = stream.LanePlan(objects.paper_object("cube", **TAG), *random_plan(9, 2, **WS),
                           jax.random.key(1))
    args, sizes = stream._assemble(p, [plan], 3, keys=False)
    table, carry = jax.eval_shape(partial(stream._prepare, sizes=sizes, lanes=3), *args)
    first = programs.programs(p, table, carry, 0, 32, True)
    assert programs.result(first["main"]) == ("compiled refill", "compiled steps")
    with pytest.raises(RuntimeError, match="finish: the compiler crashed"):
        programs.result([first["finish"]])
    assert sorted(k[0] for k in programs.keys()) == ["refill", "steps"]
    stub.fail.clear()
    again = programs.programs(p, table, carry, 0, 32, True)
    assert again["main"] == first["main"], "a program that compiled was submitted again"
    assert programs.result(again["main"] + (again["finish"],))[-1] == "compiled finish"
    assert sorted(stub.submitted) == ["finish", "finish", "refill", "steps"]


def test_planning_grid_drops_configurations_at_the_mounting_surface():
    """The paper's 46,144 planning samples = 721 of the 875 grid configurations x 16
    directions x 4 loads; the end-effector positions that decide come from MuJoCo C."""
    q, d = planning_plan(**GRID)
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


def test_bad_plans_and_diverging_integration_name_the_scenario_and_sample(stream_programs):
    params = default_sim_params()
    q, d = random_plan(4, seed=0, **WS)
    cube = objects.paper_object("cube", **TAG)

    def run(p, qq, dd):
        return run_plan(p, cube, qq, dd, jax.random.key(0), desc="test/cube",
                        programs=stream_programs, progress=False)

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
    before = stream_programs.keys()
    with pytest.raises(UsageError, match=r"unknown test object\(s\) \['teapot'\]"):
        simulate_scenarios(params, [ScenarioRequest("random", 4),
                                    ScenarioRequest("test", 4, ["cube", "teapot"])], lanes=7,
                           programs=stream_programs)
    with pytest.raises(UsageError, match="unknown scenario 'grid'"):
        simulate_scenarios(params, [ScenarioRequest("grid")], lanes=7, programs=stream_programs)
    assert stream_programs.keys() == before


def test_continuous_run_switches_objects_and_keeps_the_statics_of_each():
    """The switching-load scenario: the schedule and the random walk are recorded as
    planned, every sample obeys tau - tau_g = A x of the object held *at that sample*
    (the empty gripper: tau == tau_g), and the arm follows the walk without stopping."""
    f, meta = simulate_continuous_run(default_sim_params(), n=24,
                                      objects=["empty", "cube", "white"], switch_every=8,
                                      seed=3, progress=False)
    q_plan, d_plan = continuous_plan(24, 3, **WS)
    planned = {"object_id": np.repeat([0, 1, 2], 8), "q_d": q_plan, "direction": d_plan}
    for k in planned:
        _assert_field(f, planned, k)
    x = f["x"][f["object_id"]]
    np.testing.assert_allclose(f["tau"] - f["tau_g"], np.einsum("snk,sk->sn", f["A"], x),
                               atol=TOL, err_msg="tau - tau_g")
    np.testing.assert_array_equal(f["tau"][:8], f["tau_g"][:8], err_msg="empty gripper: tau")
    assert np.all(f["x"][1:, 0] > 0) and f["x"][0, 0] == 0
    # Every reading is taken after the same fixed move + dwell, not at rest by design.
    assert np.ptp(f["settle_time"]) == 0
    # The arm follows the walk: within the servo's compliance of each new goal (far below
    # the 0.5 rad of a diverged run) and tracking its changes.
    assert np.abs(f["q"] - f["q_d"]).max() < 0.1
    for j in range(4):
        assert np.corrcoef(np.diff(f["q"][:, j]), np.diff(q_plan[:, j]))[0, 1] > 0.8, j


def test_continuous_walk_in_lanes_is_the_single_walk(monkeypatch):
    """The walk cut into 3 segments stepped side by side (each starting 2 samples early, at
    rest) gives the single walk's samples: segment 0 exactly (it is the same arithmetic),
    the others within a small fraction of an encoder tick of the true position (the
    friction's stick point keeps a trace of where the arm came from). Without the warm-up
    a segment's first sample starts from rest instead of from the walk: ~8x further off.
    The lanes step in calls of at most 4 samples (the state carried from call to call), as
    even as their count allows; a walk shorter than a call is one call of its length."""
    from jaxinertia.sim import continuous

    calls, stepping_jit = [], continuous.stepping_jit

    def recording(fn, **kw):
        run = stepping_jit(fn, **kw)

        def call(state, xs):
            calls.append(np.shape(xs[0])[:2])  # (lanes, steps)
            return run(state, xs)
        return call

    monkeypatch.setattr(continuous, "stepping_jit", recording)
    kw = dict(n=24, objects=["empty", "cube", "white"], switch_every=8, seed=3,
              progress=False)
    params = default_sim_params()
    one, _ = simulate_continuous_run(params, **kw)
    assert calls == [(1, 26)]  # one call: the 24 samples after 2 warm-up steps, no padding
    tick = 2 * np.pi / 4096

    def lanes(warmup):
        calls.clear()
        objs = jax.tree.map(lambda *a: jnp.stack(a), *[objects.resolve(o, **TAG) for o in
                                                       kw["objects"]])
        q, d = continuous_plan(24, 3, **WS)
        rec = simulate_continuous(params, objs, np.repeat([0, 1, 2], 8), q, d,
                                  jax.random.key(3 + 99), lanes=3, warmup=warmup,
                                  chunk=4, progress=False)
        return rec._asdict()

    three = lanes(2)
    assert calls == [(3, 4)] * 3  # 10 steps a lane: 3 calls of 4, 2 steps padded
    for k in ("q_true", "q", "current_tau", "servo_tau"):
        np.testing.assert_allclose(three[k][:8], one[k][:8], rtol=0, atol=1e-12, err_msg=k)
    off = np.abs(three["q_true"] - one["q_true"]).max(axis=1) / tick
    assert off.max() < 0.05, off
    # The encoder reading flips at most by one tick where the truth sits on a tick's edge.
    assert np.abs(np.round((three["q"] - one["q"]) / tick)).max() <= 1
    np.testing.assert_array_equal(three["q_d"], one["q_d"])
    cold = np.abs(lanes(0)["q_true"] - one["q_true"]).max(axis=1) / tick
    assert calls == [(3, 4)] * 2  # 8 steps a lane: 2 calls of 4
    assert max(cold[8], cold[16]) > 4 * max(off[8], off[16]), (cold, off)


def test_simulate_walks_in_the_lanes_reproduce_uses(tmp_path, monkeypatch):
    """``simulate --scenario continuous`` and ``reproduce`` cut the walk alike
    (``walk_lanes``): up to 128 segments of at least 16 samples each."""
    from jaxinertia.sim import continuous

    assert [continuous.walk_lanes(n) for n in (1, 31, 32, 2048, 4096, 10**6)] == \
        [1, 1, 2, 128, 128, 128]
    asked = {}

    class Asked(Exception):
        pass

    def walk(params, **kw):  # what the command asks for; no simulation
        asked.update(kw)
        raise Asked

    monkeypatch.setattr(continuous, "simulate_continuous_run", walk)
    for n, want in ((None, 128), ("40", 2)):
        with pytest.raises(Asked):
            cli_main(["simulate", "--scenario", "continuous", "--out", str(tmp_path / "c.npz"),
                      *(["--n", n] if n else [])])
        assert (asked["n"], asked["lanes"]) == (int(n or 2048), want)


def _read_npz(path) -> tuple[dict, dict]:
    """A native sample file as written: its arrays and its metadata (read raw, so that the
    stored dtypes are what is checked)."""
    with np.load(path, allow_pickle=False) as z:
        fields = {k: z[k] for k in z.files}
    return fields, json.loads(str(fields.pop("metadata")))


def test_simulate_in_float32_rests_where_float64_does(tmp_path):
    """``jaxinertia simulate --precision float32`` (2-3x faster on a CPU) runs the same
    physics: with the random friction jitter off (float32 draws different random numbers,
    so with it on the samples are another draw of the same distribution), the arm rests at
    the same ticks as in float64 on nearly every joint and never more than one tick away.
    Both files store float64 and name the precision simulated. (The float32 command runs in
    its own process: it sets JAX's precision for the whole process.)"""
    calib = json.loads(data_path("open_manipulator_x_sim.json").read_text())
    calib["servo_friction"]["friction"]["jitter"] = [0.0] * 4
    (tmp_path / "calib.json").write_text(json.dumps(calib))
    out = {}
    for precision in ("float64", "float32"):
        path = tmp_path / f"{precision}.npz"
        argv = ["simulate", "--scenario", "test", "--n", "32", "--objects", "black",
                "--calibration", str(tmp_path / "calib.json"), "--precision", precision,
                "--out", str(path)]
        if precision == "float64":  # the test process's own precision: run in it, with
            assert cli_main(argv) == 0  # the stream programs the tests before compiled
        else:
            run = subprocess.run([sys.executable, "-m", "jaxinertia", *argv],
                                 capture_output=True, text=True)
            assert run.returncode == 0, run.stderr[-2000:]
        out[precision] = _read_npz(path)
    (a, meta_a), (b, meta_b) = out["float64"], out["float32"]
    assert meta_a["simulator"]["precision"] == "float64"
    assert meta_b["simulator"]["precision"] == "float32"
    for k, v in b.items():
        assert v.dtype == a[k].dtype, k
    assert a["q"].dtype == np.float64
    np.testing.assert_allclose(b["q_d"], a["q_d"], rtol=0, atol=1e-6, err_msg="mismatch: q_d")
    _assert_field(b, a, "direction")
    assert a["at_rest"].all() and b["at_rest"].all()
    ticks = np.rint((b["q"] - a["q"]) / (2 * np.pi / 4096))
    assert np.abs(ticks).max() <= 1
    assert np.mean(ticks == 0) >= 0.95


def _write_plan(path, q_d, direction):
    path.write_text(json.dumps({"format": PLAN_FORMAT, "format_version": PLAN_FORMAT_VERSION,
                                "q_d": np.asarray(q_d).tolist(),
                                "direction": np.asarray(direction).tolist()}))
    return path


def test_simulate_visits_the_poses_of_a_plan_file(tmp_path, capsys):
    """``simulate --plan`` (a ``plan-poses`` file): every object visits the plan's goals
    with its approach directions, in order, repeated cyclically to ``--n``; the file names
    the plan. (32 samples of black: the shapes the stream compiled for the test above.)"""
    q_d, d = random_plan(12, 5, **WS)
    plan = _write_plan(tmp_path / "plan.json", q_d, d)
    out = tmp_path / "planned.npz"
    assert cli_main(["simulate", "--scenario", "test", "--n", "32", "--objects", "black",
                     "--plan", str(plan), "--out", str(out)]) == 0
    fields, meta = _read_npz(out)
    reps = np.arange(32) % 12
    np.testing.assert_allclose(fields["q_d"], q_d[reps], rtol=0, atol=0)
    np.testing.assert_array_equal(fields["direction"], d[reps])
    assert meta["plan"] == str(plan.resolve()) and fields["at_rest"].all()
    capsys.readouterr()
    bad = _write_plan(tmp_path / "three.json", q_d[:, :3], d[:, :3])
    for argv, words in (
            (["--scenario", "test", "--plan", str(bad)], ["3 joints", "has 4"]),
            (["--scenario", "continuous", "--plan", str(plan)], ["--plan", "continuous"]),
            (["--scenario", "test", "--plan", str(tmp_path / "none.json")], ["none.json"])):
        assert cli_main(["simulate", *argv, "--out", str(tmp_path / "x.npz")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and all(w in err[0] for w in words), err
    assert not (tmp_path / "x.npz").exists()


def test_simulate_draws_recording_sessions_on_request(tmp_path, capsys):
    """``simulate --sessions N``: the random scenario drawn over N recording sessions
    (each its own supply per joint), --n / N per load from each, the spread recorded in the
    file; options that cannot go with it are refused before any work."""
    from jaxinertia.sim.randomize import SESSION_PRIOR_REL

    out = tmp_path / "sessions.npz"
    assert cli_main(["simulate", "--scenario", "random", "--n", "8", "--sessions", "2",
                     "--out", str(out)]) == 0
    assert "2 recording sessions drawn" in capsys.readouterr().out
    fields, meta = _read_npz(out)
    assert len(fields["q"]) == 8 * 4 and fields["at_rest"].all()
    drawn = meta["domain_randomization"]
    assert drawn["draws"] == 2
    spread = drawn["spread"]
    np.testing.assert_allclose(spread["electrical_rel"], [SESSION_PRIOR_REL] * 4)
    np.testing.assert_array_equal(spread["torque_rel"], [0.0] * 4)
    for argv, words in (
            (["--scenario", "test", "--n", "8"], ["--sessions", "random"]),
            (["--scenario", "random"], ["--sessions", "--n"]),
            (["--scenario", "random", "--n", "8", "--objects", "cube"], ["--objects"]),
            (["--scenario", "random", "--n", "8", "--format", "lbipe"], ["lbipe"])):
        assert cli_main(["simulate", *argv, "--sessions", "2",
                         "--out", str(tmp_path / "x.npz")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and all(w in err[0] for w in words), err
    assert not (tmp_path / "x.npz").exists()


def test_the_stream_traces_and_compiles_its_programs_once_for_new_data(monkeypatch):
    """A second stream with new data of the same shapes (other goals, directions, objects
    and keys) reuses every program: the lane step is traced once and nothing compiles
    again (a recompilation per call would cost seconds on a CPU, more on a GPU). A fresh
    registry: the record program (whose shapes do not depend on the lanes) may be held by
    the session's from the other tests; XLA's part comes from the session's cache."""
    traces, submitted = [], []
    programs = stream.StreamPrograms()
    lane_step, submit = lanes.lane_step, programs.compiler.submit

    def counted_step(*args, **kw):  # runs only while a program is traced
        traces.append(kw.get("batch_last", False))
        return lane_step(*args, **kw)

    def counted_submit(fn, *args, **kw):
        submitted.append(fn.__name__)
        return submit(fn, *args, **kw)

    monkeypatch.setattr(lanes, "lane_step", counted_step)
    monkeypatch.setattr(programs.compiler, "submit", counted_submit)
    p = default_sim_params()
    lanes_n = 13  # a lane count no other test uses: its programs are new here

    def run(seed, names):
        plans = [(objects.paper_object(o, **TAG), *random_plan(n, seed + i, **WS),
                  jax.random.key(seed + i))
                 for i, (o, n) in enumerate(zip(names, (5, 4)))]
        return run_plans(p, plans, lanes=lanes_n, tail_lanes=0, batch_last=True,
                         programs=programs, progress=False)

    with programs:
        prepared = stream._prepare._cache_size()
        first = run(0, ("cube", "white"))
        assert traces == [True] and sorted(submitted) == ["finish", "refill", "steps"]
        assert stream._prepare._cache_size() == prepared + 1
        second = run(10, ("black", "red"))
        assert traces == [True], "the lane step was traced again"
        assert sorted(submitted) == ["finish", "refill", "steps"], "a program compiled again"
        assert stream._prepare._cache_size() == prepared + 1, "the preparation compiled again"
    assert not np.array_equal(first[0]["q"], second[0]["q"])  # the new data were used
    assert all(r["at_rest"].all() for r in first + second)
