"""A square tag's pose from its four corners (IPPE square PnP, polished by LM), with an
honest account of the planar pose ambiguity.

Tag frame (the AprilTag library's tag images, read upright): origin at the centre of the
black square, x to the right, y up, z out of the printed face (towards a camera that sees
it). The camera frame is OpenCV's: x right, y down, z along the optical axis.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from jaxinertia.errors import TagNotFoundError, UsageError
from jaxinertia.vision.intrinsics import CameraIntrinsics

__all__ = [
    "AMBIGUOUS_PX",
    "AMBIGUOUS_STD_DEG",
    "CORNER_NOISE_PX",
    "PoseSolution",
    "TagPose",
    "rotation_angle",
    "solve_tag_pose",
    "tag_object_points",
]

#: Corner noise [px RMS] assumed for the orientation uncertainty (edge-refined corners
#: of sharp synthetic images are good to 0.05 px, of real images 0.1-0.3 px).
CORNER_NOISE_PX = 0.1
#: A second pose that reprojects the corners within this RMS error [px] cannot be ruled out.
AMBIGUOUS_PX = 0.5
#: An orientation whose 1-sigma uncertainty exceeds this [deg] is not determined.
AMBIGUOUS_STD_DEG = 5.0


@dataclass(frozen=True)
class PoseSolution:
    """One PnP solution: tag pose in the camera frame and its RMS reprojection error [px]."""

    R_cam_tag: np.ndarray
    p_cam_tag: np.ndarray
    reprojection_error: float


@dataclass(frozen=True)
class TagPose:
    """The tag's pose in the camera frame.

    Attributes:
      R_cam_tag: (3, 3) tag orientation in the camera frame.
      p_cam_tag: (3,) tag centre in the camera frame [m].
      reprojection_error: RMS distance between detected and reprojected corners [px].
      alternative: the best solution with a distinctly different orientation (IPPE's
        second, the planar pose ambiguity), or None when the corners have one minimum.
      corners: (4, 2) the corners [px] the pose was solved from, official order.
      rotation_std: 1-sigma orientation uncertainty [rad] (largest axis) for corner noise
        of :data:`CORNER_NOISE_PX`, from the projection's Jacobian at the solution.
    """

    R_cam_tag: np.ndarray
    p_cam_tag: np.ndarray
    reprojection_error: float
    alternative: PoseSolution | None
    corners: np.ndarray
    rotation_std: float = 0.0

    @property
    def ambiguity(self) -> float:
        """Reprojection error ratio best / second (0 = no second solution, 1 = both fit
        equally well). Small tags seen nearly face-on can have no distinct second solution
        and still a poorly determined tilt: see :attr:`ambiguous`."""
        if self.alternative is None or self.alternative.reprojection_error <= 0:
            return 0.0
        return self.reprojection_error / self.alternative.reprojection_error

    @property
    def alternative_angle(self) -> float:
        """Angle [rad] between the best and the alternative orientation (0 if none)."""
        if self.alternative is None:
            return 0.0
        return rotation_angle(self.R_cam_tag, self.alternative.R_cam_tag)

    @property
    def ambiguous(self) -> bool:
        """True when the orientation is not determined by the corners: a distinct second
        pose reprojects them within :data:`AMBIGUOUS_PX`, or the orientation's 1-sigma
        uncertainty exceeds :data:`AMBIGUOUS_STD_DEG`."""
        alt_fits = (self.alternative is not None
                    and self.alternative.reprojection_error < AMBIGUOUS_PX)
        return bool(alt_fits or np.rad2deg(self.rotation_std) > AMBIGUOUS_STD_DEG)


def tag_object_points(tag_size: float) -> np.ndarray:
    """(4, 3) corners of the black square in the tag frame [m]: top-left, top-right,
    bottom-right, bottom-left of the upright tag, the order ``SOLVEPNP_IPPE_SQUARE``
    requires and :func:`jaxinertia.vision.tags.detect_tags` reports."""
    h = 0.5 * float(tag_size)
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


def rotation_angle(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Angle [rad] of the rotation between two orientations."""
    c = 0.5 * (np.trace(np.asarray(R_a).T @ np.asarray(R_b)) - 1.0)
    return float(np.arccos(np.clip(c, -1.0, 1.0)))


# Tag frame turned 180 deg about x: a tag facing the camera then has a rotation near the
# identity, far from the angle-pi singularity of rotation vectors (where Rodrigues round
# trips and the LM refinement break down).
_FLIP = np.diag([1.0, -1.0, -1.0])


def _project(obj, R, t, intrinsics):
    return cv2.projectPoints(obj, cv2.Rodrigues(R)[0], t, intrinsics.K,
                             intrinsics.dist)[0].reshape(-1, 2)


def _rmse(obj, rvec, tvec, corners, intrinsics):
    proj, _ = cv2.projectPoints(obj, rvec, tvec, intrinsics.K, intrinsics.dist)
    return float(np.sqrt(np.mean(np.sum((proj.reshape(4, 2) - corners) ** 2, axis=1))))


def _rotation_std(obj, R, t, intrinsics) -> float:
    """Largest 1-sigma orientation uncertainty [rad] for isotropic corner noise
    :data:`CORNER_NOISE_PX`: Gauss-Newton covariance of the 6 pose parameters (rotation
    as a small turn ``R exp([w])``), its rotation block's largest eigenvalue."""
    base = _project(obj, R, t, intrinsics).ravel()
    J = np.empty((base.size, 6))
    eps = 1e-6
    for k in range(6):
        d = np.zeros(6)
        d[k] = eps
        Rk = R @ cv2.Rodrigues(d[:3])[0]
        J[:, k] = (_project(obj, Rk, t + d[3:], intrinsics).ravel() - base) / eps
    try:
        cov = CORNER_NOISE_PX ** 2 * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return float(np.pi)
    ev = np.linalg.eigvalsh(0.5 * (cov[:3, :3] + cov[:3, :3].T))
    return float(np.sqrt(max(ev.max(), 0.0))) if np.all(np.isfinite(ev)) else float(np.pi)


def solve_tag_pose(
    corners: np.ndarray, intrinsics: CameraIntrinsics, tag_size: float, *, refine: bool = True
) -> TagPose:
    """Tag pose in the camera frame from its four corners [px].

    ``SOLVEPNP_IPPE_SQUARE`` gives both planar solutions; the best (lowest reprojection
    error) is then polished by Levenberg-Marquardt on the reprojection error
    (``solvePnPRefineLM``) when ``refine``, which makes it the maximum-likelihood pose
    under isotropic corner noise (IPPE's homography-based solution is not exactly that).

    Args:
      corners: (4, 2) corners in the official order (:func:`tag_object_points`) [px].
      tag_size: edge of the black square [m].
    """
    if not tag_size > 0:
        raise UsageError(f"tag_size must be positive [m], got {tag_size}")
    corners = np.ascontiguousarray(np.asarray(corners, np.float64).reshape(4, 2))
    obj = tag_object_points(tag_size)
    n, rvecs, tvecs, _ = cv2.solvePnPGeneric(
        obj, corners, intrinsics.K, intrinsics.dist, flags=cv2.SOLVEPNP_IPPE_SQUARE)
    cands = [(np.asarray(r, np.float64).reshape(3), np.asarray(t, np.float64).reshape(3))
             for r, t in zip(rvecs, tvecs)]
    # IPPE's two solutions merge for a tag exactly face-on, and there OpenCV 5.0 returns
    # NaN or the identity rotation (a lost 180-degree turn). SQPNP, a globally optimal
    # solver without that degeneracy, joins the candidates; the best reprojection wins.
    ok, r, t = cv2.solvePnP(obj, corners, intrinsics.K, intrinsics.dist, flags=cv2.SOLVEPNP_SQPNP)
    if ok:
        cands.append((r.reshape(3), t.reshape(3)))
    cands = [(r, t) for r, t in cands if np.all(np.isfinite(r)) and np.all(np.isfinite(t))]
    if not cands:
        raise TagNotFoundError("PnP found no pose for the tag's corners")
    obj_f = obj @ _FLIP  # the same points in the flipped tag frame (_FLIP is symmetric)
    sols = []
    for rv, tv in cands:
        rv_f = cv2.Rodrigues(cv2.Rodrigues(rv)[0] @ _FLIP)[0]
        tv = tv.reshape(3, 1).copy()
        if refine:
            rv_f, tv = cv2.solvePnPRefineLM(obj_f, corners, intrinsics.K, intrinsics.dist,
                                            rv_f, tv)
        R = cv2.Rodrigues(rv_f)[0] @ _FLIP
        sols.append(PoseSolution(R, tv.ravel(), _rmse(obj_f, rv_f, tv, corners, intrinsics)))
    sols.sort(key=lambda s: s.reprojection_error)
    best = sols[0]
    # The alternative is the best solution with a distinctly different orientation.
    others = [s for s in sols[1:]
              if rotation_angle(s.R_cam_tag, best.R_cam_tag) > np.deg2rad(0.5)]
    return TagPose(best.R_cam_tag, best.p_cam_tag, best.reprojection_error,
                   others[0] if others else None, corners,
                   _rotation_std(obj, best.R_cam_tag, best.p_cam_tag, intrinsics))
