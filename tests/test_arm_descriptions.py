"""The SO-101 and Koch v1.1 published descriptions (meshes absent) through ``load_robot``.

Two oracles, neither going through :func:`jaxinertia.robot.compile_mujoco`:
* MuJoCo C on the same file with its meshes removed by plain text surgery here (xml.etree:
  ``<visual>``/``<collision>`` of a URDF, mesh geoms and mesh assets of an MJCF), the jaw
  joint kept at zero: FK of every arm body, Jacobians, gravity torques.
* An independent statics computation straight from the file's own numbers (xml.etree
  again: joint origins and axes, each link's ``<inertial>``), no MuJoCo: link masses, COMs
  and inertias (the jaw lumped into the link carrying it), and the gravity torque
  ``sum_i axis_j . ((c_i - o_j) x m_i g)`` over the links moved by joint j.
Torque sign: the torque gravity exerts on the joint (minus MuJoCo's ``qfrc_bias``).
"""

from __future__ import annotations

import functools
import xml.etree.ElementTree as ET

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from test_kinematics import MUJOCO_TOL, _assert_close, _body_ids, _mujoco_c, _ours_batch
from test_kinematics import Case as _Case

from jaxinertia.robot import RobotDescriptionError, data_path, load_robot

SO101_ARM = ("shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll")
KOCH_ARM = ("joint_1", "joint_2", "joint_3", "joint_4", "joint_5")
# name: (file under data/, arm joints, end effector {site or body}, jaw joint)
FILES = {
    "so101_mjcf": ("arms/so101/so101_new_calib.xml", SO101_ARM, {"ee_site": "gripperframe"},
                   "gripper"),
    "so101_urdf": ("arms/so101/so101_new_calib.urdf", SO101_ARM,
                   {"ee_body": "gripper_frame_link"}, "gripper"),
    "koch_urdf": ("arms/koch_v1_1/follower.urdf", KOCH_ARM, {"ee_body": "link_5"}, "joint_6"),
}
# Table-mounted arms: the pan joint's axis is vertical, so gravity as published loads it
# not at all; a tilted gravity (the same on every side) loads every joint.
G_TILTED = 9.81 * np.array([0.4, -0.3, -1.0]) / np.linalg.norm([0.4, -0.3, -1.0])
N_CONFIGS = 64
# Oracle from the file's digits vs MuJoCo's compiled model (URDF rpy -> quaternion ->
# matrix, full inertia -> principal axes -> back): rounding of float64 only.
FILE_TOL = 1e-12


def _strip_meshes(path) -> str:
    """The file's text without mesh geometry, by xml.etree alone."""
    root = ET.parse(path).getroot()
    if root.tag == "robot":  # URDF: visuals and collisions go, inertials stay
        for link in root.iter("link"):
            for child in list(link):
                if child.tag in ("visual", "collision"):
                    link.remove(child)
        for mj in root.findall("mujoco"):
            root.remove(mj)
    else:  # MJCF: mesh geoms (by type or the class that sets it) and the mesh assets
        for parent in root.iter():
            for child in list(parent):
                if child.tag == "geom" and ("mesh" in child.attrib
                                            or child.get("type") == "mesh"):
                    parent.remove(child)
                if child.tag == "mesh" and parent.tag == "asset":
                    parent.remove(child)
    return ET.tostring(root, encoding="unicode")


def _case(name: str, gravity) -> _Case:
    rel, arm, ee, _ = FILES[name]
    path = data_path(rel)
    robot = load_robot(path, arm_joints=arm, gravity=gravity, **ee)
    model = mujoco.MjModel.from_xml_string(_strip_meshes(path))  # jaw joint kept (at 0)
    model.opt.gravity[:] = gravity
    bodies = _body_ids(model, robot)
    if "ee_site" in ee:
        sid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, ee["ee_site"])
        return _Case(name, robot, model, bodies, sid, -1, np.eye(3), np.zeros(3))
    # MuJoCo's own URDF import fuses the massless gripper_frame_link into its parent: the
    # frame is then the fixed joint's origin in the parent (read from the file here).
    frame = _urdf_fixed_frames(path).get(ee["ee_body"])
    if frame is None:
        bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, ee["ee_body"])
        return _Case(name, robot, model, bodies, -1, bid, np.eye(3), np.zeros(3))
    parent, R, p = frame
    bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, parent)
    return _Case(name, robot, model, bodies, -1, bid, R, p)


def _ours(robot, q, r=None):
    """FK, Jacobians and gravity torques of a batch; the labels (static) are dropped so
    that every five-joint arm here shares one compiled program."""
    r = np.zeros((*q.shape, 3)) if r is None else r
    bare = robot.replace(name="arm", joint_names=(), body_names=())
    return jax.tree.map(np.asarray, _ours_batch(bare, jnp.asarray(q), jnp.asarray(r)))


def _sample(model, bodies, seed, n=N_CONFIGS):
    rng = np.random.default_rng(seed)
    jnt = model.body_jntadr[bodies]
    lo, hi = model.jnt_range[jnt, 0], model.jnt_range[jnt, 1]
    assert np.all(hi > lo)
    return rng.uniform(lo, hi, (n, len(jnt))), rng.uniform(-0.1, 0.1, (n, len(jnt), 3))


# --------------------------------------------------------------------------------------
# The independent oracle: the URDF's numbers, numpy only.
# --------------------------------------------------------------------------------------


def _vec(el, attr, default="0 0 0"):
    text = el.get(attr) if el is not None else None
    return np.array([float(x) for x in (text or default).split()])


def _rpy(r, p, y):
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx  # URDF: fixed-axis roll, then pitch, then yaw


def _axis_angle(axis, q):
    k = axis / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(q) * K + (1 - np.cos(q)) * K @ K


def _urdf_fixed_frames(path):
    """{child link of a fixed joint: (parent link, R, p)} from the URDF's text."""
    root = ET.parse(path).getroot()
    if root.tag != "robot":
        return {}
    out = {}
    for j in root.findall("joint"):
        if j.get("type") == "fixed":
            o = j.find("origin")
            out[j.find("child").get("link")] = (j.find("parent").get("link"),
                                                _rpy(*_vec(o, "rpy")), _vec(o, "xyz"))
    return out


@functools.cache
def _parse(path):
    return ET.parse(path).getroot()


def _urdf_statics(path, q_arm: dict[str, float], gravity):
    """Per link, from the URDF alone: world (R, p), mass, COM and inertia in the world;
    per arm joint: the torque gravity exerts on it."""
    root = _parse(path)
    joints = {j.find("child").get("link"): j for j in root.findall("joint")}
    links = {link.get("name"): link for link in root.findall("link")}
    pose = {}

    def world(name):
        if name not in pose:
            j = joints.get(name)
            if j is None:  # the root link is the base frame
                pose[name] = (np.eye(3), np.zeros(3))
            else:
                Rp, pp = world(j.find("parent").get("link"))
                o = j.find("origin")
                R0, p0 = _rpy(*_vec(o, "rpy")), _vec(o, "xyz")
                Rq = np.eye(3)
                if j.get("type") == "revolute":
                    Rq = _axis_angle(_vec(j.find("axis"), "xyz", "1 0 0"),
                                     q_arm.get(j.get("name"), 0.0))
                pose[name] = (Rp @ R0 @ Rq, Rp @ p0 + pp)
        return pose[name]

    def moved_by(joint_child):
        out, stack = [], [joint_child]
        while stack:
            c = stack.pop()
            out.append(c)
            stack += [k for k, j in joints.items() if j.find("parent").get("link") == c]
        return out

    inert = {}
    for name, link in links.items():
        el = link.find("inertial")
        R, p = world(name)
        o = el.find("origin")
        Ri = R @ _rpy(*_vec(o, "rpy"))
        t = el.find("inertia")
        ixx, ixy, ixz, iyy, iyz, izz = (float(t.get(k)) for k in
                                        ("ixx", "ixy", "ixz", "iyy", "iyz", "izz"))
        I = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
        inert[name] = (float(el.find("mass").get("value")), R @ _vec(o, "xyz") + p,
                       Ri @ I @ Ri.T)
    tau = {}
    for child, j in joints.items():
        if j.get("name") not in q_arm:
            continue
        R, p = world(child)
        axis = R @ _vec(j.find("axis"), "xyz", "1 0 0")
        axis = axis / np.linalg.norm(axis)
        tau[j.get("name")] = sum(axis @ np.cross(inert[c][1] - p, inert[c][0] * gravity)
                                 for c in moved_by(child))
    return pose, inert, tau, joints


def _lumped(inert, names):
    """Mass, COM and inertia about the COM of rigidly joined links (world frame)."""
    m = sum(inert[n][0] for n in names)
    c = sum(inert[n][0] * inert[n][1] for n in names) / m
    I = sum(inert[n][2] + inert[n][0] * ((inert[n][1] - c) @ (inert[n][1] - c) * np.eye(3)
                                         - np.outer(inert[n][1] - c, inert[n][1] - c))
            for n in names)
    return m, c, I


# --------------------------------------------------------------------------------------
# Tests.
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", list(FILES))
def test_arm_joints_and_jaw(name):
    rel, arm, ee, jaw = FILES[name]
    path = data_path(rel)
    robot = load_robot(path, arm_joints=arm, **ee)
    assert robot.joint_names == arm and robot.n_joints == 5
    assert jaw not in robot.joint_names
    assert robot.ee_body == 4  # the held object hangs from the last arm link (gripper)
    full = load_robot(path, **ee)  # every joint: the jaw is a sixth
    assert full.joint_names == arm + (jaw,)
    # Published gravity: MuJoCo's default (the files state none), base z up.
    np.testing.assert_array_equal(np.asarray(robot.gravity), [0.0, 0.0, -9.81])


@pytest.mark.parametrize("name", list(FILES))
@pytest.mark.parametrize("gravity", ["published", "tilted"])
def test_kinematics_and_gravity_equal_mujoco_c(name, gravity):
    g = np.array([0.0, 0.0, -9.81]) if gravity == "published" else G_TILTED
    case = _case(name, g)
    q, r = _sample(case.model, case.bodies, seed=11)
    ours = _ours(case.robot, q, r)
    ref = _mujoco_c(case, q, r)
    assert np.ptp(ref["ee_pos"], axis=0).max() > 0.05  # the arm moves
    loaded = np.abs(ref["tau_g"]).max(axis=0) > 1e-4
    # Table-mounted: only the pan joint (vertical axis) carries no torque, and only then.
    assert np.all(loaded[1:]) and loaded[0] == (gravity == "tilted")
    _assert_close(ours, ref, MUJOCO_TOL, f"{name} ({gravity} gravity) vs MuJoCo C")


@pytest.mark.parametrize("name", ["so101_urdf", "koch_urdf"])
def test_inertials_and_gravity_equal_the_files_own_numbers(name):
    rel, arm, ee, jaw = FILES[name]
    path = data_path(rel)
    robot = load_robot(path, arm_joints=arm, gravity=G_TILTED, **ee)
    # Links as the file states them, at q = 0 (body frames = URDF link frames, base = root).
    pose, inert, _, joints = _urdf_statics(path, dict.fromkeys(arm, 0.0), G_TILTED)
    by_joint = {j.get("name"): child for child, j in joints.items()}
    jaw_link = by_joint[jaw]
    fixed = [c for c, j in joints.items() if j.get("type") == "fixed"]
    for i, jname in enumerate(arm):
        link = by_joint[jname]
        group = [link] + [c for c in [jaw_link, *fixed]
                          if joints[c].find("parent").get("link") == link]
        m, c, I = _lumped(inert, group)
        R, p = pose[link]
        assert abs(float(robot.mass[i]) - m) <= 1e-15, (jname, group)
        np.testing.assert_allclose(np.asarray(robot.com[i]), R.T @ (c - p), rtol=0,
                                   atol=FILE_TOL, err_msg=jname)
        np.testing.assert_allclose(np.asarray(robot.inertia[i]), R.T @ I @ R, rtol=0,
                                   atol=FILE_TOL, err_msg=jname)
    # Gravity torques on random configurations: ours vs the file's numbers, every joint.
    case = _case(name, G_TILTED)
    q, _ = _sample(case.model, case.bodies, seed=12)
    ours = _ours(robot, q)["tau_g"]
    oracle = np.array([[_urdf_statics(path, dict(zip(arm, qs)), G_TILTED)[2][j] for j in arm]
                       for qs in q])
    assert np.all(np.abs(oracle).max(axis=0) > 1e-4)
    np.testing.assert_allclose(ours, oracle, rtol=0, atol=MUJOCO_TOL)


def test_so101_mjcf_and_urdf_are_one_arm():
    """The two published SO-101 files describe the same arm, to their printed digits."""
    mj = load_robot(data_path(FILES["so101_mjcf"][0]), arm_joints=SO101_ARM,
                    ee_site="gripperframe", gravity=G_TILTED)
    ur = load_robot(data_path(FILES["so101_urdf"][0]), arm_joints=SO101_ARM,
                    ee_body="gripper_frame_link", gravity=G_TILTED)
    case = _case("so101_mjcf", G_TILTED)
    q, _ = _sample(case.model, case.bodies, seed=13)
    # rpy and positions printed to 6 significant digits: agreement to ~1e-6 N m.
    np.testing.assert_allclose(_ours(mj, q)["tau_g"], _ours(ur, q)["tau_g"], rtol=0,
                               atol=2e-5)


_MESHED = """<mujoco><asset><mesh file="absent.stl"/><texture name="t" type="2d"
  file="absent.png"/><material name="m" texture="t"/></asset><worldbody>
  <body name="a"><joint name="j1" axis="0 0 1"/>{inertial}
    <geom type="mesh" mesh="absent" material="m"/><geom type="sphere" size="0.01" mass="0"/>
    <site name="tip" pos="0.1 0 0"/></body></worldbody></mujoco>"""


def test_absent_mesh_files_and_a_body_without_inertial(tmp_path):
    path = tmp_path / "arm.xml"
    path.write_text(_MESHED.format(
        inertial='<inertial pos="0.1 0 0" mass="0.2" diaginertia="1e-4 2e-4 3e-4"/>'))
    robot = load_robot(path, ee_site="tip")  # neither the mesh nor the texture is read
    assert float(robot.mass[0]) == 0.2
    np.testing.assert_allclose(np.asarray(robot.com[0]), [0.1, 0.0, 0.0], rtol=0, atol=FILE_TOL)
    np.testing.assert_allclose(np.asarray(robot.inertia[0]), np.diag([1e-4, 2e-4, 3e-4]),
                               rtol=0, atol=FILE_TOL)
    with pytest.raises(RobotDescriptionError, match="no joints named"):
        load_robot(path, arm_joints=("j1", "elbow"))
    path.write_text(_MESHED.format(inertial=""))  # its mass would have come from the mesh
    with pytest.raises(RobotDescriptionError, match="state no <inertial>"):
        load_robot(path, ee_site="tip")
