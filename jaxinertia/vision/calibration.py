"""Camera pose in the robot base frame from tag observations at known arm poses.

The camera is fixed; the tag is fixed on the end effector. At arm pose i (forward
kinematics) the camera sees the tag at

    T_cam_tag_i = inv(T_base_cam) @ T_base_ee_i @ T_ee_tag,

an ``A X = Z B`` problem (robot-world/hand-eye) with unknowns ``T_base_cam`` and
``T_ee_tag``. OpenCV's ``calibrateRobotWorldHandEye`` solves it, but OpenCV 5.0.0's
Python package does not expose it (opencv/opencv#29565), so it is solved here:

1. closed-form start (Li et al. 2010): rotations from the null space of the stacked
   Kronecker equations ``R_ee_i R_Y = R_X R_cam_i``, projected onto SO(3); translations
   by linear least squares;
2. maximum likelihood refinement: both transforms minimise the *reprojection error of the
   detected corners* over all images (a robust soft-L1 loss, scale 1 px).

Step 2 is why this beats a pose-space solver (OpenCV's included): a single tag's pose is
much less certain along the optical axis and in tilt than across the image, and corner
pixels are where the measurement noise actually is; pose-space averaging weights the
poorly determined directions as much as the good ones.

The OpenMANIPULATOR-X has 4 joints, so the end effector turns about two axes only (joint 1
and the parallel pitch joints); that suffices, provided the calibration poses vary both.
"""

from __future__ import annotations

import csv
import io
import json
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from jaxinertia.errors import CameraError, FileFormatError, UsageError
from jaxinertia.fileio import write_text
from jaxinertia.vision.files import read_text, shown
from jaxinertia.vision.intrinsics import CameraIntrinsics
from jaxinertia.vision.pose import solve_tag_pose, tag_object_points

__all__ = [
    "CameraPose",
    "CameraPoseError",
    "CalibrationResult",
    "calibrate_camera_pose",
    "load_camera_pose",
    "read_manifest",
    "save_camera_pose",
    "solve_ax_zb",
]


class CameraPoseError(CameraError):
    """A camera-pose file is unreadable, or the calibration data cannot determine it
    (exit code 2)."""


@dataclass(frozen=True)
class CameraPose:
    """Pose of the camera in the robot base frame (``R_base_cam`` (3, 3), ``p_base_cam`` (3,)
    [m]) and, when calibrated, the tag's mounting in the end-effector frame."""

    R_base_cam: np.ndarray
    p_base_cam: np.ndarray
    R_ee_tag: np.ndarray | None = None
    p_ee_tag: np.ndarray | None = None

    def tag_in_base(
        self, R_cam_tag: np.ndarray, p_cam_tag: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """``(R_base_tag, p_base_tag)`` from a tag pose in the camera frame."""
        return self.R_base_cam @ R_cam_tag, self.R_base_cam @ p_cam_tag + self.p_base_cam


@dataclass(frozen=True)
class CalibrationResult:
    """A calibrated :class:`CameraPose` with its fit statistics.

    Attributes:
      rms_px: RMS corner reprojection error over all images [px].
      per_image_rms_px: (M,) per image [px] (a large one flags a bad detection or joint read).
      std_p_base_cam: (3,) standard deviation of ``p_base_cam`` [m] (from the Jacobian);
      std_rot_base_cam: (3,) of the camera rotation (small angles about base axes) [rad].
      initial: the closed-form start, for comparison.
    """

    camera_pose: CameraPose
    rms_px: float
    per_image_rms_px: np.ndarray
    std_p_base_cam: np.ndarray
    std_rot_base_cam: np.ndarray
    initial: CameraPose


def _project_to_so3(M: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def solve_ax_zb(
    R_base_ee: np.ndarray, p_base_ee: np.ndarray, R_cam_tag: np.ndarray, p_cam_tag: np.ndarray
) -> CameraPose:
    """Closed-form ``T_base_ee_i @ T_ee_tag = T_base_cam @ T_cam_tag_i`` (Li et al. 2010).

    Args:
      R_base_ee: (M, 3, 3), p_base_ee: (M, 3) arm poses; R_cam_tag, p_cam_tag the same for
        the observed tag poses. M >= 3 with rotations about two non-parallel axes.
    """
    M = len(R_base_ee)
    I3 = np.eye(3)
    # Column-major vec: vec(A X B) = (B^T kron A) vec(X). Unknown u = [vec R_Y; vec R_X].
    rows = [np.hstack([np.kron(I3, R_base_ee[i]), -np.kron(R_cam_tag[i].T, I3)])
            for i in range(M)]
    _, sv, Vt = np.linalg.svd(np.vstack(rows))
    if sv[-2] < 1e-6 * sv[0]:
        raise CameraPoseError("the arm poses do not determine the camera rotation: vary both "
                              "joint 1 and the wrist pitch (joints 2-4) between images")
    u = Vt[-1]
    R_Y = u[:9].reshape(3, 3, order="F")
    R_X = u[9:].reshape(3, 3, order="F")
    scale = np.cbrt(np.linalg.det(R_X))  # the null vector's scale and sign
    R_X, R_Y = _project_to_so3(R_X / scale), _project_to_so3(R_Y / scale)
    # Translations: R_ee_i p_Y + p_ee_i = R_X p_cam_i + p_X.
    A = np.vstack([np.hstack([R_base_ee[i], -I3]) for i in range(M)])
    b = np.concatenate([R_X @ p_cam_tag[i] - p_base_ee[i] for i in range(M)])
    sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    return CameraPose(R_X, sol[3:], R_Y, sol[:3])


def _rodrigues(v: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(v, np.float64).reshape(3, 1))[0]


def calibrate_camera_pose(
    R_base_ee: np.ndarray,
    p_base_ee: np.ndarray,
    corners: np.ndarray,
    intrinsics: CameraIntrinsics,
    tag_size: float,
    *,
    tag_in_ee: tuple[np.ndarray, np.ndarray] | None = None,
    loss_scale_px: float = 1.0,
) -> CalibrationResult:
    """Camera pose in base from M images of the end-effector tag at known arm poses.

    Args:
      R_base_ee: (M, 3, 3), p_base_ee: (M, 3) [m] end-effector poses from forward
        kinematics at the measured joint angles.
      corners: (M, 4, 2) detected tag corners [px] (aruco order).
      tag_size: edge of the black square [m].
      tag_in_ee: a known tag mounting ``(R_ee_tag, p_ee_tag)`` to hold fixed; default:
        estimated along with the camera.
    """
    R_base_ee = np.asarray(R_base_ee, np.float64)
    p_base_ee = np.asarray(p_base_ee, np.float64)
    corners = np.asarray(corners, np.float64)
    M = len(R_base_ee)
    if not (R_base_ee.shape == (M, 3, 3) and p_base_ee.shape == (M, 3)
            and corners.shape == (M, 4, 2)):
        raise UsageError(f"shapes: R_base_ee {R_base_ee.shape}, p_base_ee {p_base_ee.shape}, "
                         f"corners {corners.shape}; expected (M,3,3), (M,3), (M,4,2)")
    if M < 3:
        raise CameraPoseError(f"{M} usable images; at least 3 are needed (10 or more advised)")

    tags = [solve_tag_pose(c, intrinsics, tag_size) for c in corners]
    R_ct = np.stack([t.R_cam_tag for t in tags])
    p_ct = np.stack([t.p_cam_tag for t in tags])
    if tag_in_ee is None:
        init = solve_ax_zb(R_base_ee, p_base_ee, R_ct, p_ct)
    else:
        # Known mounting: each image gives T_base_cam directly; average them.
        R_y, p_y = (np.asarray(a, np.float64) for a in tag_in_ee)
        Rs = R_base_ee @ R_y @ np.transpose(R_ct, (0, 2, 1))
        R_x = _project_to_so3(Rs.sum(axis=0))
        p_x = np.mean(R_base_ee @ p_y + p_base_ee - np.einsum("ij,mj->mi", R_x, p_ct), axis=0)
        init = CameraPose(R_x, p_x, R_y, p_y)

    obj = tag_object_points(tag_size)
    fixed_y = tag_in_ee is not None

    def unpack(z):
        R_x = _rodrigues(z[:3]) @ init.R_base_cam
        p_x = init.p_base_cam + z[3:6]
        if fixed_y:
            return R_x, p_x, init.R_ee_tag, init.p_ee_tag
        return R_x, p_x, _rodrigues(z[6:9]) @ init.R_ee_tag, init.p_ee_tag + z[9:12]

    def residuals(z):
        R_x, p_x, R_y, p_y = unpack(z)
        out = []
        for i in range(M):
            R_bt = R_base_ee[i] @ R_y
            p_bt = R_base_ee[i] @ p_y + p_base_ee[i]
            R_c = R_x.T @ R_bt
            p_c = R_x.T @ (p_bt - p_x)
            proj, _ = cv2.projectPoints(obj, cv2.Rodrigues(R_c)[0], p_c, intrinsics.K,
                                        intrinsics.dist)
            out.append((proj.reshape(4, 2) - corners[i]).ravel())
        return np.concatenate(out)

    # Rotations are perturbations on the left of the start (no angle-pi singularity).
    n = 6 if fixed_y else 12
    from scipy.optimize import least_squares  # (half a second to import: only here)

    sol = least_squares(residuals, np.zeros(n), loss="soft_l1", f_scale=loss_scale_px,
                        x_scale=np.tile([1e-2, 1e-2, 1e-2, 1e-3, 1e-3, 1e-3], n // 6))
    R_x, p_x, R_y, p_y = unpack(sol.x)
    r = residuals(sol.x).reshape(M, 8)
    per_image = np.sqrt(np.mean(r.reshape(M, 4, 2) ** 2, axis=(1, 2)) * 2)
    rms = float(np.sqrt(np.mean(np.sum(r.reshape(-1, 2) ** 2, axis=1))))
    # Gauss-Newton covariance with the residual variance per coordinate.
    J = sol.jac
    dof = max(r.size - n, 1)
    sigma2 = float(np.sum(r ** 2) / dof)
    try:
        cov = np.linalg.inv(J.T @ J) * sigma2
        std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    except np.linalg.LinAlgError:
        std = np.full(n, np.inf)
    pose = CameraPose(R_x, p_x, R_y, p_y)
    return CalibrationResult(pose, rms, per_image, std[3:6], std[0:3], init)


def save_camera_pose(
    path: str | os.PathLike, pose: CameraPose, *, extra: dict | None = None
) -> Path:
    """Writes ``{"R_base_cam", "p_base_cam"[, "R_ee_tag", "p_ee_tag"], ...}`` as JSON."""
    d = {"frame": "T_base_cam: camera (OpenCV: x right, y down, z forward) in robot base "
         "(URDF link1); metres",
         "R_base_cam": np.asarray(pose.R_base_cam).tolist(),
         "p_base_cam": np.asarray(pose.p_base_cam).tolist()}
    if pose.R_ee_tag is not None:
        d["R_ee_tag"] = np.asarray(pose.R_ee_tag).tolist()
        d["p_ee_tag"] = np.asarray(pose.p_ee_tag).tolist()
    d.update(extra or {})
    path = Path(path)
    write_text(path, json.dumps(d, indent=2) + "\n")
    return path


def _rotation(d: dict, key: str, path: Path) -> np.ndarray:
    R = np.asarray(d[key], np.float64)
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        raise CameraPoseError(f"{shown(path)}: {key} must be a 3x3 matrix of numbers")
    if np.max(np.abs(R.T @ R - np.eye(3))) > 1e-6 or np.linalg.det(R) < 0:
        raise CameraPoseError(f"{shown(path)}: {key} is not a rotation matrix")
    return R


def _vector(d: dict, key: str, path: Path) -> np.ndarray:
    p = np.asarray(d[key], np.float64)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise CameraPoseError(f"{shown(path)}: {key} must be 3 numbers [m]")
    return p


def load_camera_pose(path: str | os.PathLike) -> CameraPose:
    """Reads a file written by :func:`save_camera_pose`.

    Raises:
      CameraPoseError: missing file, bad JSON, missing keys or a non-rotation matrix.
    """
    path = Path(path)
    if not path.is_file():
        raise CameraPoseError(f"{shown(path)}: no such camera-pose file")
    try:
        d = json.loads(read_text(path, what="camera-pose file"))
    except FileFormatError as e:
        raise CameraPoseError(str(e)) from None
    except json.JSONDecodeError as e:
        raise CameraPoseError(f"{shown(path)}: not valid JSON ({e})") from e
    if not isinstance(d, dict) or "R_base_cam" not in d or "p_base_cam" not in d:
        raise CameraPoseError(f"{shown(path)}: needs R_base_cam (3x3) and p_base_cam (3,)")
    try:
        R, p = _rotation(d, "R_base_cam", path), _vector(d, "p_base_cam", path)
        if "R_ee_tag" in d and "p_ee_tag" in d:
            return CameraPose(R, p, _rotation(d, "R_ee_tag", path), _vector(d, "p_ee_tag", path))
    except (TypeError, ValueError) as e:
        if isinstance(e, CameraPoseError):
            raise
        raise CameraPoseError(f"{shown(path)}: bad value ({e})") from e
    return CameraPose(R, p)


def read_manifest(path: str | os.PathLike) -> list[tuple[Path, list[float]]]:
    """Images and joint angles [rad] from a JSON or CSV manifest (paths relative to it).

    JSON: ``{"samples": [{"image": "img_000.png", "q": [q1, q2, q3, q4]}, ...]}``;
    CSV: a header ``image,q1,q2,q3,q4`` then one row per image.

    Raises:
      FileFormatError: a missing, malformed or empty manifest.
    """
    path = Path(path)
    if not path.is_file():
        raise FileFormatError(shown(path), None, "no such manifest")
    rows: list[tuple[Path, list[float]]] = []
    text = read_text(path, what="manifest")
    try:
        if path.suffix.lower() == ".json":
            d = json.loads(text)
            for s in d["samples"]:
                rows.append((path.parent / s["image"], [float(x) for x in s["q"]]))
        else:
            for r in csv.DictReader(io.StringIO(text, newline="")):
                qs = sorted((k for k in r if k and k.startswith("q")), key=lambda k: int(k[1:]))
                rows.append((path.parent / r["image"], [float(r[k]) for k in qs]))
    except (KeyError, TypeError, ValueError, json.JSONDecodeError) as e:
        raise FileFormatError(shown(path), None, f"bad manifest ({e!r}): JSON {{'samples': "
                              "[{'image': ..., 'q': [...]}, ...]} or CSV columns "
                              "image,q1,...,qN expected") from e
    if not rows:
        raise FileFormatError(shown(path), None, "the manifest lists no images")
    for image, q in rows:
        if not np.all(np.isfinite(q)):
            raise FileFormatError(shown(path), None,
                                  f"{shown(image.name)}: joint angles {q} are not finite")
    return rows
