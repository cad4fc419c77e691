"""The load regressor A and the link gravity base parameters, on the real data and in sim.

Real data (shared/lbipe, README there): A is rebuilt from q alone with one fitted tag pose,
tau_g is reproduced by 8 identified base parameters, and tau - tau_g == A x. Simulation:
the payload torques of MuJoCo C (an extra welded body) equal ``load_regressor @ x``, and
the base parameters reproduce :func:`gravity_torques`.
"""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from jax.test_util import check_grads
from support.asserts import assert_tree_close

from jaxinertia.kinematics import gravity_torques
from jaxinertia.robot import OPEN_MANIPULATOR_X_XML, data_path, load_robot, open_manipulator_x
from jaxinertia.samples import load_lbipe
from jaxinertia.statics import (
    fit_tag_pose,
    gravity_base_parameters,
    identify_gravity_base_parameters,
    link_gravity_parameters,
    link_gravity_regressor,
    load_regressor,
    load_regressor_fixed_tag,
    tag_pose,
    torque_scale_sensitivity,
)

OBJECTS = ["cube", "white"]
ARM6_XML = Path(__file__).parent / "assets" / "arm6.xml"
TICK = 2 * np.pi / 4096  # DYNAMIXEL XM430: 4096 ticks per revolution

# Documented thresholds for rebuilding lbipe's A from q with one fitted tag pose
# (measured: mass column max 0.0012, per-column max [0.0012, 0.0100, 0.0087, 0.0100]).
A_MASS_COL_MAX = 2e-3  # N m / kg
A_ALL_MAX = 0.015
A_MEAN_ABS = 0.005

# Tolerances, one per reference (max |error| unless rtol is given):
# shared/lbipe/README: the files' tau - tau_g == A x exactly to 1e-15 N m (both sides are
# float64 sums of a few O(0.1) terms).
LBIPE_IDENTITY_TOL = 1e-15
# The files' q (joint_data row 1) are encoder ticks stored through float32: on the tick grid
# to one float32 rounding, relative.
ENCODER_GRID_RTOL = 2.0**-23
# The files' own rows: q_d - q (rows 0, 1) == row 2 [rad], float64 rounding of O(1) numbers.
FILE_ROUNDING_TOL = 1e-12
# The fitted tag rotation against an exact rotation (R^T R = I, det R = 1).
ROTATION_TOL = 1e-12
# The files' tau_g against 8 base parameters identified on one object's file and applied to
# both [N m] (shared/lbipe/README: tau_g is reproduced by 8 identified base parameters).
LBIPE_TAU_G_TOL = 1e-6
# TagFit's own error report against the errors recomputed here (same float64 numbers,
# other summation order).
FIT_REPORT_TOL = {"rtol": 1e-9, "atol": 1e-15}
# MuJoCo C (a welded payload body's bias force) vs load_regressor @ x: the float64
# acceptance tolerance [N m], as in test_kinematics.
MUJOCO_TOL = 1e-9
# The link gravity regressors (full and base) vs gravity_torques, and the dependent columns
# vs their stated combination of the independent ones: float64 sums of 4N products.
REGRESSOR_TOL = 1e-9
# Identification of the base parameters from noiseless gravity_torques vs the true ones.
IDENTIFY_TOL = {"rtol": 1e-9, "atol": 1e-12}
# Two forms of the regressor from the same FK (tag pose in the base vs fixed in the EE).
FORMS_TOL = 1e-14
# load_regressor against itself under vmap, jit and eager: only the operation order differs.
TRANSFORM_TOL = 1e-15

_fixed_tag = jax.jit(jax.vmap(load_regressor_fixed_tag, in_axes=(None, 0, None, None)))
# Not jitted on purpose: identify_gravity_base_parameters and gravity_base_parameters run
# this same eager vmap, so at their batch sizes (S samples, 200) the ops are already compiled.
_link_Y = jax.vmap(link_gravity_regressor, in_axes=(None, 0))
_grav = jax.jit(jax.vmap(gravity_torques, in_axes=(None, 0)))


@pytest.fixture(scope="module")
def omx():
    return open_manipulator_x()


@pytest.fixture(scope="module")
def omx_base(omx):
    return gravity_base_parameters(omx)


@pytest.fixture(scope="module")
def real(lbipe_dir):
    return {n: load_lbipe(lbipe_dir / "data" / f"data_test_{n}.npz", n) for n in OBJECTS}


@pytest.fixture(scope="module")
def tag_fits(omx, real):
    return {n: fit_tag_pose(omx, jnp.asarray(ds.q), jnp.asarray(ds.A)) for n, ds in real.items()}


# --------------------------------------------------------------------------------------
# Real data.
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", OBJECTS)
def test_real_tau_minus_tau_g_equals_A_x(lbipe_dir, real, name):
    ds = real[name]
    resid = (ds.tau - ds.tau_g) - ds.A @ ds.x[0]
    assert np.abs(resid).max() <= LBIPE_IDENTITY_TOL
    assert np.abs(ds.tau - ds.tau_g).max() > 0.01  # not a vacuous identity
    # The file's own flattened `tau` is the same thing, row = joint, sample-major (as A).
    raw = np.load(lbipe_dir / "data" / f"data_test_{name}.npz")
    np.testing.assert_array_equal(raw["tau"], (ds.tau - ds.tau_g).ravel())
    np.testing.assert_array_equal(raw["A"], ds.A.reshape(-1, 4))


def _lstsq_answer(A, tau, tau_g, w):
    """x by weighted least squares over every sample, numpy's own solver."""
    sw = np.sqrt(w).reshape(-1)
    return np.linalg.lstsq(A.reshape(-1, 4) * sw[:, None], (tau - tau_g).reshape(-1) * sw,
                           rcond=None)[0]


@pytest.mark.parametrize("name", OBJECTS)
def test_one_per_cent_of_a_joints_torque_moves_the_answer_as_a_new_solve_does(real, name):
    """``torque_scale_sensitivity``: the answer's shift when one joint's torques are read
    1 % off equals solving again with those torques (numpy's lstsq), with and without
    weights; on the real files joint 2 (the arm's weight) costs 4.6 / 5.1 g of mass."""
    ds = real[name]
    x = ds.x[0]
    w = np.random.default_rng(0).uniform(0.05, 1.0, ds.tau.shape)
    for weights in (None, w):
        ones = np.ones_like(ds.tau) if weights is None else weights
        base = _lstsq_answer(ds.A, ds.tau, ds.tau_g, ones)
        np.testing.assert_allclose(base, x, atol=1e-12)  # the file's torques are tau_g + A x
        got = torque_scale_sensitivity(ds.A, ds.tau_g, x, weights, rel=0.01)
        for j in range(4):
            scale = np.ones(4)
            scale[j] = 1.01
            want = _lstsq_answer(ds.A, ds.tau * scale, ds.tau_g, ones) - base
            np.testing.assert_allclose(got[j], want, rtol=1e-8, atol=1e-12)
    mass = torque_scale_sensitivity(ds.A, ds.tau_g, x)[:, 0] * 1e3
    assert mass[1] == pytest.approx({"cube": 4.58, "white": 5.08}[name], abs=0.01)
    assert np.all(np.abs(mass[[0, 2, 3]]) < 0.25)  # the other joints: a fiftieth of it


@pytest.mark.parametrize("name", OBJECTS)
def test_real_q_is_the_present_position_row(lbipe_dir, real, name):
    """joint_data row 1 (q) is on the encoder grid (to float32 rounding), row 0 (q_d) is not."""
    ds = real[name]
    ticks = np.round(ds.q / TICK)
    np.testing.assert_allclose(ds.q, ticks * TICK, rtol=ENCODER_GRID_RTOL, atol=0)
    assert np.abs(ds.q_d / TICK - np.round(ds.q_d / TICK)).max() > 0.4
    raw = np.load(lbipe_dir / "data" / f"data_test_{name}.npz")["joint_data"]
    np.testing.assert_allclose(raw[:, 0] - raw[:, 1], raw[:, 2], rtol=0, atol=FILE_ROUNDING_TOL)
    np.testing.assert_array_equal(ds.q, raw[:, 1])


@pytest.mark.parametrize("name", OBJECTS)
def test_real_A_rebuilt_from_q_with_one_fitted_tag_pose(omx, real, tag_fits, name):
    ds, fit = real[name], tag_fits[name]
    R, p = np.asarray(fit.R_ee_tag), np.asarray(fit.p_ee_tag)
    np.testing.assert_allclose(R.T @ R, np.eye(3), rtol=0, atol=ROTATION_TOL)
    assert abs(np.linalg.det(R) - 1.0) <= ROTATION_TOL
    assert np.linalg.norm(p) < 0.1  # the tag sits in the gripper, within 10 cm of the EE
    # Rebuild A independently of the fit's own error report, from q (row 1) only.
    A = np.asarray(_fixed_tag(omx, jnp.asarray(ds.q), jnp.asarray(R), jnp.asarray(p)))
    err = np.abs(A - ds.A).reshape(-1, 4)
    col_max = err.max(axis=0)
    assert col_max[0] <= A_MASS_COL_MAX, col_max
    assert col_max.max() <= A_ALL_MAX, col_max
    assert err.mean() <= A_MEAN_ABS, err.mean(axis=0)
    assert_tree_close(
        {"max_abs_error": fit.max_abs_error, "mean_abs_error": fit.mean_abs_error},
        {"max_abs_error": col_max, "mean_abs_error": err.mean(axis=0)},
        **FIT_REPORT_TOL,
        what=f"{name}: TagFit's error report vs recomputed",
    )
    # The same regressor from the tag's base pose (load_regressor) agrees to rounding.
    Rb, pb = jax.vmap(tag_pose, in_axes=(None, 0, None, None))(
        omx, jnp.asarray(ds.q), jnp.asarray(R), jnp.asarray(p)
    )
    A2 = np.asarray(
        jax.jit(jax.vmap(load_regressor, in_axes=(None, 0, 0, 0)))(omx, jnp.asarray(ds.q), Rb, pb)
    )
    np.testing.assert_allclose(A2, A, rtol=0, atol=FORMS_TOL)
    # Torques of the object through the rebuilt A stay close to the data's tau - tau_g.
    assert np.abs(A @ ds.x[0] - (ds.tau - ds.tau_g)).max() <= A_ALL_MAX * np.abs(ds.x[0]).sum()


def test_real_A_is_evaluated_at_q_not_q_d(omx, real, tag_fits):
    """The same fit on the goal positions q_d cannot reproduce A: the data uses q (row 1)."""
    ds = real["cube"]
    at_qd = fit_tag_pose(omx, jnp.asarray(ds.q_d), jnp.asarray(ds.A), iterations=5)
    assert at_qd.max_abs_error[0] > 10 * tag_fits["cube"].max_abs_error[0]
    assert at_qd.max_abs_error[0] > A_MASS_COL_MAX


@pytest.mark.parametrize("fit_on,check_on", [("cube", "white"), ("white", "cube")])
def test_real_tau_g_reproduced_by_identified_base_parameters(omx, omx_base, real, fit_on, check_on):
    src, dst = real[fit_on], real[check_on]
    theta, base = identify_gravity_base_parameters(
        omx, jnp.asarray(src.q), jnp.asarray(src.tau_g), omx_base
    )
    assert theta.shape == base.independent.shape
    for ds in (src, dst):
        Y = _link_Y(omx, jnp.asarray(ds.q))
        pred = np.asarray(base.regressor(Y) @ theta)
        assert np.abs(pred - ds.tau_g).max() <= LBIPE_TAU_G_TOL, np.abs(pred - ds.tau_g).max()
    # The URDF's own inertials do not give tau_g (README): the identification is doing work.
    Y = _link_Y(omx, jnp.asarray(dst.q))
    urdf_err = np.abs(np.asarray(Y @ link_gravity_parameters(omx)) - dst.tau_g).max()
    assert urdf_err > 1e-3


# --------------------------------------------------------------------------------------
# Simulation: payload torques of MuJoCo C vs the load regressor.
# --------------------------------------------------------------------------------------


def _random_rotation(rng):
    quat = rng.standard_normal(4)
    return quat / np.linalg.norm(quat)


def _payload_case(path, site, rng):
    """MuJoCo with a welded payload (mass m, COM p in a tag frame at a random EE pose)."""
    m = float(rng.uniform(0.02, 0.5))
    p_tag = rng.uniform(-0.05, 0.05, 3)
    tag_quat, tag_pos = _random_rotation(rng), rng.uniform(-0.05, 0.05, 3)
    spec = mujoco.MjSpec.from_file(str(path))
    ee = spec.site(site)
    ee_frame = ee.parent.add_body(name="ee_frame", pos=ee.pos, quat=ee.quat)
    tag = ee_frame.add_body(name="tag", pos=tag_pos, quat=tag_quat)
    tag.explicitinertial = True
    tag.mass, tag.ipos, tag.inertia = m, p_tag, [1e-6, 2e-6, 3e-6]
    tag.add_site(name="tag")
    model = spec.compile()
    R_ee_tag = np.zeros(9)
    mujoco.mju_quat2Mat(R_ee_tag, tag_quat)
    return model, m, p_tag, R_ee_tag.reshape(3, 3), tag_pos


def _rest_bias(model, q):
    d = mujoco.MjData(model)
    d.qpos[:] = q
    mujoco.mj_kinematics(model, d)
    mujoco.mj_comPos(model, d)
    mujoco.mj_comVel(model, d)
    out = np.zeros(model.nv)
    mujoco.mj_rne(model, d, 0, out)
    return out, d


@pytest.mark.parametrize("which", ["omx", "arm6"])
def test_payload_torques_of_mujoco_equal_load_regressor_times_x(which):
    if which == "omx":
        path, site, robot = data_path(OPEN_MANIPULATOR_X_XML), "end_effector", open_manipulator_x()
    else:
        path, site, robot = ARM6_XML, "tool", load_robot(ARM6_XML, ee_site="tool")
    rng = np.random.default_rng(11)
    bare = mujoco.MjModel.from_xml_path(str(path))
    lo, hi = bare.jnt_range[:, 0], bare.jnt_range[:, 1]
    n_payloads, per = 5, 24
    qs, xs, R_tags, p_tags, R_ee_tags, p_ee_tags, ref = [], [], [], [], [], [], []
    for _ in range(n_payloads):
        model, m, p_tag, R_ee_tag, p_ee_tag = _payload_case(path, site, rng)
        sid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, "tag")
        for q in rng.uniform(lo, hi, size=(per, bare.nv)):
            with_load, d = _rest_bias(model, q)
            without, _ = _rest_bias(bare, q)
            ref.append(-(with_load - without))  # torque the payload exerts (our sign)
            qs.append(q)
            xs.append(np.concatenate([[m], m * p_tag]))
            R_tags.append(d.site_xmat[sid].reshape(3, 3).copy())  # MuJoCo's tag pose in base
            p_tags.append(d.site_xpos[sid].copy())
            R_ee_tags.append(R_ee_tag)
            p_ee_tags.append(p_ee_tag)
    ref, xs = np.array(ref), np.array(xs)
    assert np.abs(ref).max() > 1e-2
    A = np.asarray(
        jax.jit(jax.vmap(load_regressor, in_axes=(None, 0, 0, 0)))(
            robot,
            jnp.asarray(np.array(qs)),
            jnp.asarray(np.array(R_tags)),
            jnp.asarray(np.array(p_tags)),
        )
    )
    err = np.abs(np.einsum("snk,sk->sn", A, xs) - ref).max()
    assert err <= MUJOCO_TOL, err
    # The fixed-tag form (tag pose from our FK instead of MuJoCo's) gives the same.
    A_fixed = np.asarray(
        jax.jit(jax.vmap(load_regressor_fixed_tag, in_axes=(None, 0, 0, 0)))(
            robot,
            jnp.asarray(np.array(qs)),
            jnp.asarray(np.array(R_ee_tags)),
            jnp.asarray(np.array(p_ee_tags)),
        )
    )
    assert np.abs(np.einsum("snk,sk->sn", A_fixed, xs) - ref).max() <= MUJOCO_TOL


def test_load_regressor_is_jit_vmap_and_grad_safe(omx):
    rng = np.random.default_rng(12)
    S = 8
    q = jnp.asarray(rng.uniform(np.asarray(omx.q_min), np.asarray(omx.q_max), (S, 4)))
    R = jnp.asarray(np.array([np.linalg.qr(rng.standard_normal((3, 3)))[0] for _ in range(S)]))
    R = R * jnp.sign(jnp.linalg.det(R))[:, None, None]
    p = jnp.asarray(rng.uniform(-0.3, 0.3, (S, 3)))
    batched = np.asarray(jax.jit(jax.vmap(load_regressor, in_axes=(None, 0, 0, 0)))(omx, q, R, p))
    jitted = jax.jit(load_regressor)
    for s in range(S):
        one = np.asarray(jitted(omx, q[s], R[s], p[s]))
        np.testing.assert_allclose(batched[s], one, rtol=0, atol=TRANSFORM_TOL)
        if s == 0:
            np.testing.assert_allclose(
                np.asarray(load_regressor(omx, q[s], R[s], p[s])), one, rtol=0, atol=TRANSFORM_TOL
            )
    assert np.abs(batched).max() > 1e-2
    R_et, p_et = R[0], p[0] * 0.1
    check_grads(
        lambda q, p: load_regressor_fixed_tag(omx, q, R_et, p),
        (q[1], p_et),
        order=1,
        modes=("fwd", "rev"),
    )


# --------------------------------------------------------------------------------------
# Base parameters of the simulated robots.
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("which", ["omx", "arm6"])
def test_gravity_base_parameters_reproduce_gravity_torques(which, omx, omx_base):
    robot = omx if which == "omx" else load_robot(ARM6_XML, ee_site="tool")
    n = robot.n_joints
    base = omx_base if which == "omx" else gravity_base_parameters(robot)
    rng = np.random.default_rng(13)
    q = jnp.asarray(rng.uniform(np.asarray(robot.q_min), np.asarray(robot.q_max), (200, n)))
    Y = _link_Y(robot, q)
    theta = link_gravity_parameters(robot)
    tau = np.asarray(_grav(robot, q))
    assert np.abs(tau).max() > 1e-2
    # the full regressor and the base regressor both reproduce gravity_torques
    by_base = np.asarray(base.regressor(Y) @ base.from_full(theta))
    assert_tree_close(
        {"full": np.asarray(Y @ theta), "base": by_base},
        {"full": tau, "base": tau},
        rtol=0,
        atol=REGRESSOR_TOL,
        what=f"{which}: link gravity regressors vs gravity_torques",
    )
    # the number of base parameters is the rank of the stacked regressor: an SVD on other
    # samples (within the joint limits here) agrees with the pivoted QR
    Ys = np.asarray(Y).reshape(-1, 4 * n)
    sv = np.linalg.svd(Ys, compute_uv=False)
    rank = int(np.sum(sv > sv[0] * 1e-9))
    assert base.independent.size == rank
    assert sv[rank - 1] > 1e-6 * sv[0] and (rank == 4 * n or sv[rank] < 1e-12 * sv[0])
    assert sorted(np.concatenate([base.independent, base.dependent]).tolist()) == list(range(4 * n))
    # and the dependent columns are the stated combinations of the independent ones
    np.testing.assert_allclose(
        Ys[:, base.dependent], Ys[:, base.independent] @ base.K, rtol=0, atol=REGRESSOR_TOL
    )
    if which == "omx":
        assert base.independent.size == 8  # shared/lbipe/README: 8 identifiable parameters
    # identification from noiseless simulated torques recovers the base parameters
    theta_hat, _ = identify_gravity_base_parameters(robot, q, tau, base)
    np.testing.assert_allclose(theta_hat, np.asarray(base.from_full(theta)), **IDENTIFY_TOL)
