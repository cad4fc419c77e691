"""Kinematics and gravity torques against MuJoCo C and MJX, URDF vs MJCF, payloads, errors.

Oracles are computed from ``mujoco.MjModel``/``MjData`` (and ``mujoco.mjx``) directly; our
side only goes through :mod:`jaxinertia.robot` / :mod:`jaxinertia.kinematics`. Everything
runs in float64 (conftest enables jax x64; MJX's model and data arrays are float64 then too).
Torque sign: ours is the torque gravity exerts, i.e. minus MuJoCo's ``qfrc_bias`` at rest.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from jax.test_util import check_grads
from mujoco import mjx
from support.asserts import assert_tree_close

from jaxinertia.kinematics import (
    ee_jacobian,
    ee_pose,
    forward_kinematics,
    gravity_torques,
    point_jacobian,
    point_mass_torques,
)
from jaxinertia.robot import (
    OPEN_MANIPULATOR_X_XML,
    Robot,
    RobotDescriptionError,
    data_path,
    load_robot,
    open_manipulator_x,
)

ASSETS = Path(__file__).parent / "assets"
ARM6_XML = ASSETS / "arm6.xml"
# shared/robots beside the repository (see shared/robots/README.md for its conventions).
URDF = Path(__file__).resolve().parents[2] / "shared" / "robots" / "open_manipulator_x.urdf"
# The paper's mounting: joint 1's axis horizontal, gravity along -x of the base (link1).
G_MOUNT = np.array([-9.81, 0.0, 0.0])
# shared/robots/README.md: end_effector_link is 0.126 m along x of link5.
URDF_EE_IN_LINK5 = np.array([0.126, 0.0, 0.0])

N_CONFIGS = 128  # >= 100 random configurations within the joint limits per arm

# Tolerances (max |error|, float64 throughout; m, rad, N m), one per reference:
# MuJoCo C (mj_kinematics, mj_jac, mj_rne, a welded payload body) and MJX: the acceptance
# tolerance. Both compute the same float64 chain products in another order and form.
MUJOCO_TOL = 1e-9
# The shared URDF through load_robot vs the embedded MJCF: the same digits through the same
# compiler (MuJoCo), so equal to rounding (measured: bit-equal).
URDF_MJCF_TOL = 1e-15
# Our own functions against themselves: vmap vs a loop, jit vs eager, and jax.jacfwd of the
# FK position vs the geometric Jacobian; only the order of float64 operations differs.
ROUNDING_TOL = 1e-14
# point_mass_torques at twice the mass vs twice the torques (exactly linear in the mass).
LINEARITY_TOL = {"rtol": 1e-13, "atol": 1e-15}


def _urdf_path() -> Path:
    if not URDF.exists():
        msg = f"shared/robots URDF not found at {URDF} (the project's shared/ folder)"
        if os.environ.get("CI"):
            pytest.fail("CI is set and " + msg)
        pytest.skip(msg)
    return URDF


# --------------------------------------------------------------------------------------
# Cases: our Robot + an independently compiled MjModel + where the end effector is in it.
# --------------------------------------------------------------------------------------


@dataclass
class Case:
    name: str
    robot: Robot
    model: mujoco.MjModel
    bodies: np.ndarray  # MuJoCo body id of each of our moving bodies (matched by name)
    ee_site: int  # MuJoCo site id of the end effector, or -1 ...
    ee_body: int  # ... then the end effector is (ee_rot, ee_pos) in this MuJoCo body
    ee_rot: np.ndarray
    ee_pos: np.ndarray

    def ee_from(self, xpos, xmat, site_xpos, site_xmat):
        """End-effector (R, p) from MuJoCo (C or MJX) world poses; xmat as (nbody, 3, 3)."""
        if self.ee_site >= 0:
            return site_xmat[self.ee_site], site_xpos[self.ee_site]
        b = self.ee_body
        return xmat[b] @ self.ee_rot, xmat[b] @ self.ee_pos + xpos[b]

    @property
    def ee_mj_body(self) -> int:
        return int(self.model.site_bodyid[self.ee_site]) if self.ee_site >= 0 else self.ee_body


def _body_ids(model, robot):
    return np.array(
        [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, n) for n in robot.body_names]
    )


def _site_case(name, robot, model, site):
    sid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, site)
    assert sid >= 0
    return Case(name, robot, model, _body_ids(model, robot), sid, -1, np.eye(3), np.zeros(3))


def _make_case(name: str) -> Case:
    if name == "omx_mjcf":
        model = mujoco.MjModel.from_xml_path(str(data_path(OPEN_MANIPULATOR_X_XML)))
        return _site_case(name, open_manipulator_x(), model, "end_effector")
    if name == "arm6":
        model = mujoco.MjModel.from_xml_path(str(ARM6_XML))
        return _site_case(name, load_robot(ARM6_XML, ee_site="tool"), model, "tool")
    if name == "omx_urdf":
        path = _urdf_path()
        robot = load_robot(path, ee_body="end_effector_link", gravity=G_MOUNT)
        # MuJoCo's own URDF import (default fusestatic: end_effector_link is fused into
        # link5), independent of jaxinertia.robot.compile_mujoco.
        model = mujoco.MjModel.from_xml_path(str(path))
        model.opt.gravity[:] = G_MOUNT
        link5 = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "link5")
        return Case(
            name, robot, model, _body_ids(model, robot), -1, link5, np.eye(3), URDF_EE_IN_LINK5
        )
    raise ValueError(name)


_CASES: dict[str, Case] = {}


def _case(name: str) -> Case:
    if name not in _CASES:
        _CASES[name] = _make_case(name)
    return _CASES[name]


def _sample(case: Case, seed: int, n: int = N_CONFIGS):
    """Random q within MuJoCo's joint ranges and one random local point per body per q."""
    rng = np.random.default_rng(seed)
    m = case.model
    jnt = m.body_jntadr[case.bodies]
    lo, hi = m.jnt_range[jnt, 0], m.jnt_range[jnt, 1]
    assert np.all(m.jnt_limited[jnt]) and np.all(hi > lo)
    q = rng.uniform(lo, hi, size=(n, len(jnt)))
    r_local = rng.uniform(-0.15, 0.15, size=(n, len(jnt), 3))
    return q, r_local


# --------------------------------------------------------------------------------------
# The three sides.
# --------------------------------------------------------------------------------------


def _ours_one(robot: Robot, q, r_local):
    poses = forward_kinematics(robot, q)
    R_ee, p_ee = ee_pose(robot, q)
    pts = jnp.einsum("nij,nj->ni", poses.rot, r_local) + poses.pos
    J_pts = jnp.stack([point_jacobian(robot, q, k, pts[k]) for k in range(robot.n_joints)])
    return {
        "rot": poses.rot,
        "pos": poses.pos,
        "ee_rot": R_ee,
        "ee_pos": p_ee,
        "J_ee": ee_jacobian(robot, q),
        "J_pts": J_pts,
        "tau_g": gravity_torques(robot, q),
    }


_ours_batch = jax.jit(jax.vmap(_ours_one, in_axes=(None, 0, 0)))


def _mujoco_c(case: Case, q, r_local):
    """MuJoCo C: mj_kinematics, mj_comPos, mj_jac and qfrc_bias (mj_rne) at zero velocity."""
    m = case.model
    d = mujoco.MjData(m)
    S, N = q.shape
    out = {k: [] for k in ("rot", "pos", "ee_rot", "ee_pos", "J_ee", "J_pts", "tau_g")}
    jacp, jacr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
    dofs = m.jnt_dofadr[m.body_jntadr[case.bodies]]  # our joint order -> MuJoCo dof
    for s in range(S):
        d.qpos[m.jnt_qposadr[m.body_jntadr[case.bodies]]] = q[s]
        d.qvel[:] = 0.0
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        mujoco.mj_comVel(m, d)
        xmat = d.xmat.reshape(-1, 3, 3)
        out["rot"].append(xmat[case.bodies].copy())
        out["pos"].append(d.xpos[case.bodies].copy())
        R_ee, p_ee = case.ee_from(d.xpos, xmat, d.site_xpos, d.site_xmat.reshape(-1, 3, 3))
        out["ee_rot"].append(R_ee.copy())
        out["ee_pos"].append(p_ee.copy())
        mujoco.mj_jac(m, d, jacp, jacr, p_ee, case.ee_mj_body)
        out["J_ee"].append(np.concatenate([jacp, jacr])[:, dofs])
        J_pts = []
        for k, b in enumerate(case.bodies):
            p = xmat[b] @ r_local[s, k] + d.xpos[b]
            mujoco.mj_jac(m, d, jacp, jacr, p, b)
            J_pts.append(np.concatenate([jacp, jacr])[:, dofs])
        out["J_pts"].append(np.stack(J_pts))
        bias = np.zeros(m.nv)
        mujoco.mj_rne(m, d, 0, bias)
        out["tau_g"].append(-bias[dofs])
    return {k: np.stack(v) for k, v in out.items()}


def _mjx(case: Case, q, r_local):
    """MJX (JAX implementation): kinematics, com_pos, jac, com_vel + rne at zero velocity."""
    m = case.model
    mx = mjx.put_model(m)
    d0 = mjx.make_data(mx)
    bodies = [int(b) for b in case.bodies]
    qadr = jnp.asarray(m.jnt_qposadr[m.body_jntadr[case.bodies]])
    dofs = jnp.asarray(m.jnt_dofadr[m.body_jntadr[case.bodies]])

    def one(q, r_local):
        d = d0.replace(qpos=d0.qpos.at[qadr].set(q))
        d = mjx.kinematics(mx, d)
        d = mjx.com_pos(mx, d)
        xmat = d.xmat.reshape(-1, 3, 3)
        R_ee, p_ee = case.ee_from(d.xpos, xmat, d.site_xpos, d.site_xmat.reshape(-1, 3, 3))
        # Jacobians of a random point on every body and of the EE: one vmapped mjx.jac
        # (body ids may be traced), compiled once.
        b_ids = jnp.asarray(bodies + [case.ee_mj_body])
        pts = jnp.einsum("nij,nj->ni", xmat[b_ids[:-1]], r_local) + d.xpos[b_ids[:-1]]
        pts = jnp.concatenate([pts, p_ee[None]])
        jp, jr = jax.vmap(mjx.jac, in_axes=(None, None, 0, 0))(mx, d, pts, b_ids)
        J = jnp.concatenate([jp, jr], axis=2).transpose(0, 2, 1)[:, :, dofs]  # (nb, 6, N)
        d = mjx.com_vel(mx, d)
        d = mjx.rne(mx, d)
        return {
            "rot": xmat[b_ids[:-1]],
            "pos": d.xpos[b_ids[:-1]],
            "ee_rot": R_ee,
            "ee_pos": p_ee,
            "J_ee": J[-1],
            "J_pts": J[:-1],
            "tau_g": -d.qfrc_bias[dofs],
        }

    return jax.jit(jax.vmap(one))(jnp.asarray(q), jnp.asarray(r_local))


def _assert_close(ours: dict, ref: dict, tol: float, what: str):
    """Same fields and shapes, ours in float64, every field within ``tol`` (max |error|);
    a failure names the fields (rot, pos, ee_rot, ee_pos, J_ee, J_pts, tau_g)."""
    assert set(ours) == set(ref)
    for k in ours:
        assert np.asarray(ours[k]).shape == np.asarray(ref[k]).shape, k
        assert np.asarray(ours[k]).dtype == np.float64, k
    assert_tree_close(ours, ref, rtol=0, atol=tol, equal_nan=False, what=what)


# --------------------------------------------------------------------------------------
# Acceptance: FK of every body, Jacobians (EE site + random points), gravity torques.
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["omx_mjcf", "arm6", "omx_urdf"])
def test_kinematics_and_gravity_equal_mujoco_c(name):
    case = _case(name)
    q, r = _sample(case, seed=1)
    ours = jax.tree.map(np.asarray, _ours_batch(case.robot, jnp.asarray(q), jnp.asarray(r)))
    ref = _mujoco_c(case, q, r)
    # Not vacuous: the arms move and gravity loads every joint somewhere in the sample.
    assert np.ptp(ref["pos"][:, -1], axis=0).max() > 0.05
    assert np.all(np.abs(ref["tau_g"]).max(axis=0) > 1e-3)
    _assert_close(ours, ref, MUJOCO_TOL, f"{name} vs MuJoCo C")


@pytest.mark.parametrize("name", ["omx_mjcf", "arm6"])
def test_kinematics_and_gravity_equal_mjx(name):
    case = _case(name)
    q, r = _sample(case, seed=2)
    ref = jax.tree.map(np.asarray, _mjx(case, q, r))
    # MJX keeps float64 under jax x64 (checked here, so the tolerance below is honest).
    for k, v in ref.items():
        assert v.dtype == np.float64, k
    ours = jax.tree.map(np.asarray, _ours_batch(case.robot, jnp.asarray(q), jnp.asarray(r)))
    assert np.all(np.abs(ref["tau_g"]).max(axis=0) > 1e-3)
    _assert_close(ours, ref, MUJOCO_TOL, f"{name} vs MJX")


# --------------------------------------------------------------------------------------
# The shared URDF (MuJoCo-compiled through load_robot) against the embedded MJCF.
# --------------------------------------------------------------------------------------


def test_urdf_equals_embedded_mjcf():
    urdf = _case("omx_urdf").robot
    mjcf = _case("omx_mjcf").robot
    assert urdf.n_joints == mjcf.n_joints == 4
    assert urdf.joint_names == mjcf.joint_names == ("joint1", "joint2", "joint3", "joint4")
    assert urdf.parent == mjcf.parent and urdf.ee_body == mjcf.ee_body
    # Same digits through the same compiler (MuJoCo): every array field equal to rounding.
    assert_tree_close(urdf, mjcf, rtol=0, atol=URDF_MJCF_TOL, static=False, what="URDF vs MJCF")
    q, r = _sample(_case("omx_mjcf"), seed=3)
    out_u = jax.tree.map(np.asarray, _ours_batch(urdf, jnp.asarray(q), jnp.asarray(r)))
    out_m = jax.tree.map(np.asarray, _ours_batch(mjcf, jnp.asarray(q), jnp.asarray(r)))
    _assert_close(out_u, out_m, URDF_MJCF_TOL, "URDF vs MJCF")


# --------------------------------------------------------------------------------------
# jit / vmap / grad.
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["omx_mjcf", "arm6"])
def test_jit_equals_eager_and_vmap_equals_loop(name):
    case = _case(name)
    q, r = _sample(case, seed=1)  # same shapes as above: the batched program is reused
    robot = case.robot
    batched = jax.tree.map(np.asarray, _ours_batch(robot, jnp.asarray(q), jnp.asarray(r)))
    jitted = jax.jit(_ours_one)
    for s in range(16):
        one_jit = jax.tree.map(np.asarray, jitted(robot, jnp.asarray(q[s]), jnp.asarray(r[s])))
        row = {k: v[s] for k, v in batched.items()}
        # vmap == a Python loop over the same (jitted) function, to rounding.
        _assert_close(one_jit, row, ROUNDING_TOL, "vmap vs loop")
        if s < 2:  # eager runs op by op (slow): two configurations suffice
            eager = jax.tree.map(np.asarray, _ours_one(robot, jnp.asarray(q[s]), jnp.asarray(r[s])))
            _assert_close(eager, one_jit, ROUNDING_TOL, "jit vs eager")


@pytest.mark.parametrize("name", ["omx_mjcf", "arm6"])
def test_gradients_equal_finite_differences(name):
    case = _case(name)
    robot = case.robot
    q, r = _sample(case, seed=5, n=1)
    qs, rs = jnp.asarray(q[0]), jnp.asarray(r[0])
    k = robot.n_joints - 2  # a random point on an inner link, too

    def stacked(q):
        """FK positions of every body and the EE, EE and point Jacobians, gravity torques."""
        poses = forward_kinematics(robot, q)
        return jnp.concatenate(
            [
                poses.pos.ravel(),
                ee_pose(robot, q)[1],
                ee_jacobian(robot, q).ravel(),
                point_jacobian(robot, q, k, poses.rot[k] @ rs[k] + poses.pos[k]).ravel(),
                gravity_torques(robot, q),
            ]
        )

    # One call on everything: check_grads compiles per call, which is what costs here.
    check_grads(stacked, (qs,), order=1, modes=("fwd", "rev"))
    # The geometric Jacobian's linear rows are the derivative of the FK position.
    dp = jax.jacfwd(lambda q: ee_pose(robot, q)[1])(qs)
    np.testing.assert_allclose(
        np.asarray(dp), np.asarray(ee_jacobian(robot, qs)[:3]), rtol=0, atol=ROUNDING_TOL
    )


# --------------------------------------------------------------------------------------
# Payload: a point mass held in the end-effector frame vs MuJoCo with a welded body.
# --------------------------------------------------------------------------------------


def _with_payload(path: Path, site: str, mass: float, com_ee: np.ndarray) -> mujoco.MjModel:
    spec = mujoco.MjSpec.from_file(str(path))
    s = spec.site(site)
    body = s.parent.add_body(name="payload", pos=s.pos, quat=s.quat)
    body.explicitinertial = True
    body.mass = mass
    body.ipos = com_ee
    body.inertia = [1e-7, 1e-7, 1e-7]  # irrelevant at rest; a point mass
    return spec.compile()


def _bias(model, qs):
    d = mujoco.MjData(model)
    out = []
    for q in qs:
        d.qpos[:] = q
        d.qvel[:] = 0.0
        mujoco.mj_forward(model, d)
        out.append(d.qfrc_bias.copy())
    return np.array(out)


@pytest.mark.parametrize(
    "name,path,site",
    [
        ("omx_mjcf", None, "end_effector"),
        ("arm6", ARM6_XML, "tool"),
    ],
)
def test_point_mass_torques_equal_mujoco_welded_body(name, path, site):
    case = _case(name)
    path = path or data_path(OPEN_MANIPULATOR_X_XML)
    rng = np.random.default_rng(6)
    n_payloads, per = 6, 20
    q_all, _ = _sample(case, seed=7, n=n_payloads * per)
    masses = rng.uniform(0.02, 0.5, n_payloads)
    coms = rng.uniform(-0.06, 0.06, (n_payloads, 3))
    bare = _bias(case.model, q_all)
    ref = []
    for i in range(n_payloads):
        qs = q_all[i * per : (i + 1) * per]
        ref.append(
            -(
                _bias(_with_payload(path, site, masses[i], coms[i]), qs)
                - bare[i * per : (i + 1) * per]
            )
        )
    ref = np.concatenate(ref)
    m_rep = jnp.asarray(np.repeat(masses, per))
    c_rep = jnp.asarray(np.repeat(coms, per, axis=0))
    batched = jax.jit(jax.vmap(point_mass_torques, in_axes=(None, 0, 0, 0)))
    ours = np.asarray(batched(case.robot, jnp.asarray(q_all), m_rep, c_rep))
    assert np.abs(ref).max() > 1e-2  # the payload loads the joints
    err = np.abs(ours - ref).max()
    assert err <= MUJOCO_TOL, err
    # linear in the mass
    doubled = np.asarray(batched(case.robot, jnp.asarray(q_all), 2.0 * m_rep, c_rep))
    np.testing.assert_allclose(doubled, 2.0 * ours, **LINEARITY_TOL)


# --------------------------------------------------------------------------------------
# Bad input.
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("shape", [(3,), (5,), (2, 4), ()])
def test_wrong_q_shape_raises(shape):
    robot = _case("omx_mjcf").robot
    q = jnp.zeros(shape)
    for f in (forward_kinematics, ee_jacobian, gravity_torques, ee_pose):
        with pytest.raises(ValueError, match=r"q has shape .*needs \(4,\)"):
            f(robot, q)
    with pytest.raises(ValueError, match=r"needs \(4,\)"):
        point_mass_torques(robot, q, 0.1, jnp.zeros(3))
    # also under jit: shapes are static, so the same error at trace time
    with pytest.raises(ValueError, match=r"needs \(4,\)"):
        jax.jit(gravity_torques)(robot, q)


_ARM2 = """<mujoco><worldbody>
  <body name="a" pos="0 0 0.1"><inertial pos="0 0 0.05" mass="0.2" diaginertia="1e-4 1e-4 1e-4"/>
    <joint name="j1" {j1}/>
    <body name="b" pos="0 0 0.2"><inertial pos="0.05 0 0" mass="0.1" diaginertia="1e-4 1e-4 1e-4"/>
      <joint name="j2" axis="0 1 0"/><site name="tip" pos="0.1 0 0"/></body>
    {extra}
  </body></worldbody></mujoco>"""

_BRANCH = (
    '<body name="c" pos="0 0.1 0"><inertial pos="0 0 0" mass="0.1" '
    'diaginertia="1e-4 1e-4 1e-4"/><joint name="j3" axis="1 0 0"/></body>'
)


@pytest.mark.parametrize(
    "text,kwargs,match",
    [
        (_ARM2.format(j1='axis="0 0 1"', extra=""), {"ee_site": "nope"}, "no site named 'nope'"),
        (_ARM2.format(j1='axis="0 0 1"', extra=""), {"ee_body": "nope"}, "no body named 'nope'"),
        (_ARM2.format(j1='type="slide" axis="0 0 1"', extra=""), {}, "not revolute"),
        (_ARM2.format(j1='axis="0 0 1"', extra=_BRANCH), {}, "one serial chain"),
        (
            "<mujoco><worldbody><body><geom size='0.1'/></body></worldbody></mujoco>",
            {},
            "no joints",
        ),
        ("<mujoco><worldbody><body", {}, "could not compile"),
    ],
)
def test_bad_descriptions_raise_robot_description_error(tmp_path, text, kwargs, match):
    path = tmp_path / "arm.xml"
    path.write_text(text)
    with pytest.raises(RobotDescriptionError, match=match):
        load_robot(path, **kwargs)


def test_good_two_link_description_loads_and_missing_file_raises(tmp_path):
    path = tmp_path / "arm.xml"
    path.write_text(_ARM2.format(j1='axis="0 0 1"', extra=""))
    robot = load_robot(path, ee_site="tip")
    assert robot.n_joints == 2 and robot.body_names == ("a", "b")
    assert issubclass(RobotDescriptionError, ValueError)
    with pytest.raises(RobotDescriptionError, match="cannot read"):
        load_robot(tmp_path / "missing.urdf")
