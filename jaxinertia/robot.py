"""Robot descriptions: an immutable pytree built from MJCF or URDF through MuJoCo's compiler.

MuJoCo is touched only here (and in tests, as the oracle): it parses and compiles the
description; everything downstream is pure JAX on the :class:`Robot` pytree.

Frames: ``base`` is MuJoCo's world frame (for the OpenMANIPULATOR-X, the URDF's ``link1``).
Body ``i`` (0-based, one per joint) carries joint ``i``. All arrays are SI: m, kg, kg*m^2,
rad, m/s^2.
"""

from __future__ import annotations

import importlib.resources
import os
from collections.abc import Sequence
from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct

from jaxinertia.errors import JaxinertiaError

__all__ = [
    "Robot",
    "RobotDescriptionError",
    "from_mujoco",
    "load_robot",
    "open_manipulator_x",
    "OPEN_MANIPULATOR_X_XML",
]

OPEN_MANIPULATOR_X_XML = "open_manipulator_x.xml"


class RobotDescriptionError(JaxinertiaError, ValueError):
    """A robot description that is not a serial chain of revolute joints, or unreadable."""


@struct.dataclass
class Robot:
    """A serial chain of revolute joints as a pytree: arrays are leaves, topology is static.

    Attributes (N joints, one moving body per joint):
      body_pos: (N, 3) origin of body i in its parent's frame at q = 0 [m].
      body_rot: (N, 3, 3) orientation of body i in its parent's frame at q = 0.
      joint_axis: (N, 3) unit joint axis in body i's frame.
      joint_pos: (N, 3) a point on the joint axis in body i's frame [m].
      mass: (N,) link masses [kg].
      com: (N, 3) link centres of mass in body frames [m].
      inertia: (N, 3, 3) link inertia about the COM, body-frame axes [kg m^2].
      armature: (N,) reflected rotor inertia [kg m^2]; damping: (N,) viscous [N m s/rad].
      q_min, q_max: (N,) joint limits [rad].
      ee_pos: (3,) end-effector frame origin in body ``ee_body``'s frame [m].
      ee_rot: (3, 3) end-effector frame orientation in body ``ee_body``'s frame.
      gravity: (3,) gravitational acceleration in the base frame [m/s^2].
      parent: static tuple, parent body index of each body (-1 = base).
      ee_body: static int, the body carrying the end-effector frame.
      name, joint_names, body_names: static labels.
    """

    body_pos: jnp.ndarray
    body_rot: jnp.ndarray
    joint_axis: jnp.ndarray
    joint_pos: jnp.ndarray
    mass: jnp.ndarray
    com: jnp.ndarray
    inertia: jnp.ndarray
    armature: jnp.ndarray
    damping: jnp.ndarray
    q_min: jnp.ndarray
    q_max: jnp.ndarray
    ee_pos: jnp.ndarray
    ee_rot: jnp.ndarray
    gravity: jnp.ndarray
    parent: tuple[int, ...] = struct.field(pytree_node=False)
    ee_body: int = struct.field(pytree_node=False)
    name: str = struct.field(pytree_node=False, default="robot")
    joint_names: tuple[str, ...] = struct.field(pytree_node=False, default=())
    body_names: tuple[str, ...] = struct.field(pytree_node=False, default=())

    @property
    def n_joints(self) -> int:
        return len(self.parent)

    def ancestors(self, body: int) -> np.ndarray:
        """(N,) bool, static: joints whose motion moves ``body`` (the body's own joint included)."""
        mask = np.zeros(self.n_joints, dtype=bool)
        while body >= 0:
            mask[body] = True
            body = self.parent[body]
        return mask

    def subtree(self) -> np.ndarray:
        """(N, N) bool, static: ``[j, k]`` is True when body k moves with joint j."""
        return np.stack([self.ancestors(k) for k in range(self.n_joints)], axis=1)

    def astype(self, dtype) -> Robot:
        """The same robot with every array leaf cast to ``dtype`` (e.g. float32 for speed)."""
        return jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype=dtype), self)

    def with_gravity(self, gravity) -> Robot:
        return self.replace(gravity=jnp.asarray(gravity, dtype=self.gravity.dtype))


def _quat_to_mat(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def from_mujoco(
    model,
    *,
    ee_site: str | None = None,
    ee_body: str | None = None,
    name: str | None = None,
    dtype=None,
) -> Robot:
    """Builds a :class:`Robot` from a compiled ``mujoco.MjModel``.

    The end-effector frame is a site (``ee_site``) or a body's frame (``ee_body``); by default
    the first site, else the last body. Every moving body must hang on exactly one hinge.
    """
    m = model
    hinge = mujoco.mjtJoint.mjJNT_HINGE
    if m.njnt == 0:
        raise RobotDescriptionError(f"{name or 'model'}: no joints")
    for j in range(m.njnt):
        if m.jnt_type[j] != hinge:
            raise RobotDescriptionError(
                f"{name or 'model'}: joint {m.joint(j).name!r} is not revolute (hinge); "
                "only serial chains of revolute joints are supported"
            )
    # Moving bodies, in MuJoCo's order (parents come before children).
    body_ids = [b for b in range(1, m.nbody) if m.body_jntnum[b] > 0]
    for b in body_ids:
        if m.body_jntnum[b] != 1:
            raise RobotDescriptionError(
                f"{name or 'model'}: body {m.body(b).name!r} has {m.body_jntnum[b]} joints"
            )
    index = {b: i for i, b in enumerate(body_ids)}

    # Bodies without joints (welded) are folded into the nearest moving ancestor.
    def fold(b: int) -> tuple[int, np.ndarray, np.ndarray]:
        """(moving ancestor index or -1, R, p) of body b's frame in that ancestor's frame."""
        R, p = np.eye(3), np.zeros(3)
        while b != 0 and b not in index:
            Rb, pb = _quat_to_mat(m.body_quat[b]), m.body_pos[b]
            R, p = Rb @ R, Rb @ p + pb
            b = m.body_parentid[b]
        return (index[b] if b != 0 else -1), R, p

    n = len(body_ids)
    parent, body_pos, body_rot = [], np.zeros((n, 3)), np.zeros((n, 3, 3))
    for i, b in enumerate(body_ids):
        par, R_pp, p_pp = fold(m.body_parentid[b])
        R_b, p_b = _quat_to_mat(m.body_quat[b]), m.body_pos[b]
        parent.append(par)
        body_rot[i] = R_pp @ R_b
        body_pos[i] = R_pp @ p_b + p_pp
    chain_ok = all(parent[i] == i - 1 for i in range(n))
    if not chain_ok:
        raise RobotDescriptionError(f"{name or 'model'}: bodies do not form one serial chain")

    jnt = [m.body_jntadr[b] for b in body_ids]
    joint_axis = np.array([m.jnt_axis[j] for j in jnt], dtype=float)
    joint_axis /= np.linalg.norm(joint_axis, axis=1, keepdims=True)
    joint_pos = np.array([m.jnt_pos[j] for j in jnt], dtype=float)
    limited = np.array([bool(m.jnt_limited[j]) for j in jnt])
    rng = np.array([m.jnt_range[j] for j in jnt], dtype=float)
    q_min = np.where(limited, rng[:, 0], -np.inf)
    q_max = np.where(limited, rng[:, 1], np.inf)
    dof = [m.jnt_dofadr[j] for j in jnt]

    # Inertia of everything welded to a moving body (subtree without joints) is lumped into it.
    mass, first_moment, inertia_o = np.zeros(n), np.zeros((n, 3)), np.zeros((n, 3, 3))
    for b in range(1, m.nbody):
        owner, R, p = fold(b) if b not in index else (index[b], np.eye(3), np.zeros(3))
        if owner < 0 or m.body_mass[b] == 0.0:
            continue
        R_i = R @ _quat_to_mat(m.body_iquat[b])
        c = R @ m.body_ipos[b] + p
        I_c = R_i @ np.diag(m.body_inertia[b]) @ R_i.T
        mb = m.body_mass[b]
        mass[owner] += mb
        first_moment[owner] += mb * c
        # Parallel-axis theorem to the body origin, combined, then back to the lumped COM.
        inertia_o[owner] += I_c + mb * (c @ c * np.eye(3) - np.outer(c, c))
    com = np.divide(first_moment, mass[:, None], out=np.zeros_like(first_moment),
                    where=mass[:, None] > 0)
    cc = np.einsum("ni,ni->n", com, com)[:, None, None] * np.eye(3)
    inertia = inertia_o - mass[:, None, None] * (cc - np.einsum("ni,nj->nij", com, com))

    # End-effector frame.
    if ee_site is None and ee_body is None and m.nsite > 0:
        ee_site = m.site(0).name
    if ee_site is not None:
        sid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, ee_site)
        if sid < 0:
            raise RobotDescriptionError(f"{name or 'model'}: no site named {ee_site!r}")
        owner, R, p = fold(m.site_bodyid[sid]) if m.site_bodyid[sid] not in index else (
            index[m.site_bodyid[sid]], np.eye(3), np.zeros(3))
        ee_rot = R @ _quat_to_mat(m.site_quat[sid])
        ee_pos = R @ m.site_pos[sid] + p
    else:
        bname = ee_body
        bid = (m.nbody - 1) if bname is None else mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY,
                                                                   bname)
        if bid < 0:
            raise RobotDescriptionError(f"{name or 'model'}: no body named {bname!r}")
        owner, ee_rot, ee_pos = fold(bid) if bid not in index else (index[bid], np.eye(3),
                                                                    np.zeros(3))
    if owner < 0:
        raise RobotDescriptionError(f"{name or 'model'}: the end-effector is not on a moving body")

    if dtype is None:  # float64 when JAX allows it (jax_enable_x64), else float32
        dtype = jnp.float64 if jax.config.jax_enable_x64 else jnp.float32
    a = lambda x: jnp.asarray(x, dtype=dtype)  # noqa: E731
    return Robot(
        body_pos=a(body_pos),
        body_rot=a(body_rot),
        joint_axis=a(joint_axis),
        joint_pos=a(joint_pos),
        mass=a(mass),
        com=a(com),
        inertia=a(inertia),
        armature=a([m.dof_armature[d] for d in dof]),
        damping=a([m.dof_damping[d] for d in dof]),
        q_min=a(q_min),
        q_max=a(q_max),
        ee_pos=a(ee_pos),
        ee_rot=a(ee_rot),
        gravity=a(m.opt.gravity),
        parent=tuple(parent),
        ee_body=int(owner),
        name=name or (m.names[: m.names.find(b"\0")].decode() if m.names else "robot"),
        joint_names=tuple(m.joint(j).name for j in jnt),
        body_names=tuple(m.body(b).name for b in body_ids),
    )


def _strip_files(spec, where) -> None:
    """Removes what would make MuJoCo's compiler open files: mesh and height-field geoms and
    assets, skins, and textures (materials keep their colours). They play no part in
    kinematics or statics; the links' inertials are the file's explicit ``<inertial>``.

    A body that states no inertial would take its mass from the removed geometry: that is an
    error, not a silent zero."""
    t = mujoco.mjtGeom
    file_geoms = (t.mjGEOM_MESH, t.mjGEOM_HFIELD, t.mjGEOM_SDF)
    removed_from: set[str] = set()
    for geom in list(spec.geoms):
        if geom.type in file_geoms:
            removed_from.add(geom.parent.name)
            spec.delete(geom)
    for kind in (spec.meshes, spec.hfields, spec.skins, spec.textures):
        for element in list(kind):
            spec.delete(element)
    for material in spec.materials:
        material.textures = [""] * len(material.textures)
    implicit = [b.name for b in spec.bodies if b.name in removed_from and not b.explicitinertial]
    if implicit:
        raise RobotDescriptionError(
            f"{where}: bodies {implicit} state no <inertial>; their mass would come from mesh "
            "files, which the loader does not read (add an <inertial> to each)")
    from_geom = mujoco.mjtInertiaFromGeom
    if removed_from and spec.compiler.inertiafromgeom == from_geom.mjINERTIAFROMGEOM_TRUE:
        # With the meshes gone the explicit inertials are the only mass data left.
        spec.compiler.inertiafromgeom = from_geom.mjINERTIAFROMGEOM_AUTO


def _weld_joints(spec, arm_joints, where) -> None:
    """Removes every joint not named in ``arm_joints`` (a gripper's, say): its body is welded
    to its parent at the joint's zero, its inertia lumped into the arm link that carries it.
    Actuators, sensors, tendons, equalities and keyframes go too (they may name a removed
    joint, and statics uses none of them)."""
    names = [j.name for j in spec.joints]
    missing = [n for n in arm_joints if n not in names]
    if missing:
        raise RobotDescriptionError(f"{where}: no joints named {missing} (it has {names})")
    for kind in (spec.actuators, spec.sensors, spec.tendons, spec.equalities, spec.keys):
        for element in list(kind):
            spec.delete(element)
    for joint in list(spec.joints):
        if joint.name not in arm_joints:
            spec.delete(joint)


def compile_mujoco(path: str | os.PathLike, *, arm_joints: Sequence[str] | None = None):
    """Compiles an MJCF or URDF file with MuJoCo, without the mesh (or texture) files it
    names: published descriptions load as they are, meshes absent (:func:`_strip_files`).

    URDF links are kept as separate bodies (``fusestatic="false"``) so that massless frames
    such as an ``end_effector_link`` survive compilation. ``arm_joints``: the joints to
    keep (default: all); the others are welded at zero (:func:`_weld_joints`).
    """
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as e:
        raise RobotDescriptionError(f"{path}: cannot read robot description ({e})") from e
    try:
        if path.suffix.lower() == ".urdf":
            if text.find("<robot") < 0:
                raise RobotDescriptionError(f"{path}: no <robot> element")
            spec = mujoco.MjSpec.from_string(text)
            spec.compiler.fusestatic = False
            spec.compiler.discardvisual = True
            spec.compiler.balanceinertia = False
        else:
            spec = mujoco.MjSpec.from_file(str(path))
        _strip_files(spec, path)
        if arm_joints is not None:
            _weld_joints(spec, tuple(arm_joints), path)
        return spec.compile()
    except ValueError as e:
        if isinstance(e, RobotDescriptionError):
            raise
        raise RobotDescriptionError(f"{path}: MuJoCo could not compile it: {e}") from e


def load_robot(
    path: str | os.PathLike,
    *,
    ee_site: str | None = None,
    ee_body: str | None = None,
    arm_joints: Sequence[str] | None = None,
    gravity=None,
    dtype=None,
) -> Robot:
    """Loads a serial arm from an MJCF (``.xml``) or URDF (``.urdf``) file; the mesh files
    it names need not exist.

    ``arm_joints`` names the arm's joints (default: every joint); any other joint (a
    gripper's jaw) is welded at its zero and its link's inertia lumped into the arm link
    carrying it. ``gravity`` (3,) overrides the file's (URDF has none; MuJoCo's default is
    [0, 0, -9.81]).
    """
    path = Path(path)
    robot = from_mujoco(
        compile_mujoco(path, arm_joints=arm_joints), ee_site=ee_site, ee_body=ee_body,
        name=path.stem, dtype=dtype
    )
    return robot if gravity is None else robot.with_gravity(gravity)


def data_path(name: str) -> Path:
    """Path of a resource shipped with the package (the repository's ``data/`` folder).

    A source checkout (editable install) reads ``data/`` directly; a wheel ships the same
    files as the resource package ``jaxinertia._data``.
    """
    local = Path(__file__).resolve().parent.parent / "data" / name
    if local.exists():
        return local
    return Path(str(importlib.resources.files("jaxinertia._data").joinpath(name)))


def open_manipulator_x(*, dtype=None) -> Robot:
    """The embedded OpenMANIPULATOR-X, mounted as in the paper (gravity [-9.81, 0, 0] in base)."""
    return load_robot(data_path(OPEN_MANIPULATOR_X_XML), ee_site="end_effector", dtype=dtype)
