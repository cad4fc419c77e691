"""AprilTag tag36h11 detection (OpenCV aruco) and single-tag pose (IPPE square PnP).

Tag frame (OpenCV's marker convention): origin at the centre of the black square, x to
the right and y up as the tag is read upright, z out of the printed face (towards a camera
that sees it). ``tag_size`` is the edge of the black square [m] (8 of the 10 cells of a
tag36h11 with its white border). The camera frame is OpenCV's: x right, y down, z along
the optical axis.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from jaxinertia.errors import TagNotFoundError, UsageError
from jaxinertia.vision.intrinsics import CameraIntrinsics

__all__ = [
    "TAG_FAMILY",
    "PoseSolution",
    "TagDetection",
    "TagNotFoundError",
    "TagPose",
    "detect_tags",
    "find_tag",
    "make_detector",
    "measure_tag",
    "refine_corners_edges",
    "solve_tag_pose",
    "tag_object_points",
]

#: The AprilTag family used by the paper's setup.
TAG_FAMILY = cv2.aruco.DICT_APRILTAG_36h11


@dataclass(frozen=True)
class TagDetection:
    """One decoded tag: ``corners`` (4, 2) [px] in OpenCV's order (top-left, top-right,
    bottom-right, bottom-left as the tag is read upright)."""

    tag_id: int
    corners: np.ndarray


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
      alternative: IPPE's second solution (the planar pose ambiguity); close to
        ``reprojection_error`` means the orientation is poorly determined (small or
        distant tag seen nearly face-on).
      corners: (4, 2) the detected corners [px] the pose was solved from.
    """

    R_cam_tag: np.ndarray
    p_cam_tag: np.ndarray
    reprojection_error: float
    alternative: PoseSolution | None
    corners: np.ndarray

    @property
    def ambiguity(self) -> float:
        """Reprojection error ratio best / second (0 = unambiguous, 1 = ambiguous)."""
        if self.alternative is None or self.alternative.reprojection_error <= 0:
            return 0.0
        return self.reprojection_error / self.alternative.reprojection_error


def tag_object_points(tag_size: float) -> np.ndarray:
    """(4, 3) corners of the black square in the tag frame, in the order aruco reports
    them and ``SOLVEPNP_IPPE_SQUARE`` requires [m]."""
    h = 0.5 * float(tag_size)
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


def make_detector(
    *, refine: str = "apriltag", dictionary: int = TAG_FAMILY
) -> cv2.aruco.ArucoDetector:
    """An aruco detector for tag36h11.

    Args:
      refine: corner refinement, ``"apriltag"`` (default: the AprilTag library's edge-line
        fit; on blurred, noisy synthetic images its corners err by about 0.2 px RMS once
        its half-pixel convention offset is removed, see :func:`detect_tags`),
        ``"subpix"`` (``cornerSubPix``, about 0.3 px and worse on oblique views),
        ``"contour"`` or ``"none"`` (corners then err by 0.5 px or more).
    """
    methods = {
        "apriltag": cv2.aruco.CORNER_REFINE_APRILTAG,
        "subpix": cv2.aruco.CORNER_REFINE_SUBPIX,
        "contour": cv2.aruco.CORNER_REFINE_CONTOUR,
        "none": cv2.aruco.CORNER_REFINE_NONE,
    }
    if refine not in methods:
        raise UsageError(f"refine must be one of {sorted(methods)}, got {refine!r}")
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = methods[refine]
    if refine == "subpix":
        params.cornerRefinementWinSize = 5
        params.cornerRefinementMinAccuracy = 0.01
        params.cornerRefinementMaxIterations = 50
    return cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(dictionary), params)


def _gray(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.ndim == 3 and image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY)
    if image.ndim == 3 and image.shape[2] == 1:
        return image[..., 0]
    if image.ndim != 2:
        raise UsageError(f"expected a grey (H, W) or BGR (H, W, 3) image, got shape {image.shape}")
    return image


def detect_tags(
    image: np.ndarray, detector: cv2.aruco.ArucoDetector | None = None
) -> list[TagDetection]:
    """All tag36h11 tags in ``image`` (grey or BGR uint8), sorted by id."""
    detector = detector or make_detector()
    corners, ids, _ = detector.detectMarkers(_gray(image))
    if ids is None:
        return []
    # The AprilTag edge fit works in the AprilTag library's pixel convention (the centre of
    # the top-left pixel at (0.5, 0.5)); OpenCV's projection and PnP put it at (0, 0). Left
    # uncorrected, every corner is 0.5 px off along x and y (about 0.35 mm of position error
    # for a 4 cm tag at 0.3 m; measured on synthetic images, tests/test_vision.py).
    shift = 0.5 if (detector.getDetectorParameters().cornerRefinementMethod
                    == cv2.aruco.CORNER_REFINE_APRILTAG) else 0.0
    out = [TagDetection(int(i), np.asarray(c, np.float64).reshape(4, 2) - shift)
           for c, i in zip(corners, ids.ravel())]
    return sorted(out, key=lambda d: d.tag_id)


def find_tag(
    image: np.ndarray, tag_id: int, detector: cv2.aruco.ArucoDetector | None = None
) -> TagDetection:
    """The detection of ``tag_id``.

    Raises:
      TagNotFoundError: the tag is absent, or present more than once (ambiguous).
    """
    dets = detect_tags(image, detector)
    hits = [d for d in dets if d.tag_id == tag_id]
    if not hits:
        seen = f"tags seen: {[d.tag_id for d in dets]}" if dets else "no tag36h11 tag seen"
        raise TagNotFoundError(f"tag36h11 id {tag_id} not found in the image ({seen})")
    if len(hits) > 1:
        raise TagNotFoundError(f"tag36h11 id {tag_id} seen {len(hits)} times; tag ids must be "
                               "unique in the view")
    return hits[0]


def refine_corners_edges(
    image: np.ndarray,
    corners: np.ndarray,
    intrinsics: CameraIntrinsics | None = None,
    *,
    iterations: int = 2,
) -> np.ndarray:
    """Corners (4, 2) [px] re-estimated as intersections of sub-pixel edge lines.

    Along each side of the black square, intensity profiles across the edge are sampled
    (bilinear); the edge point is where a profile crosses midway between its dark and
    light levels (unbiased for a symmetric blur of a straight step edge). A line is fitted
    (total least squares) through each side's points and adjacent lines are intersected.
    With ``intrinsics`` the edge points are undistorted first (straight edges only exist in
    the undistorted image) and the corners distorted back. Profiles stay within the tag's
    one-cell black border and the white margin, so the margin must be at least about half a
    cell wide (a printed tag36h11 has one full cell).

    Why: OpenCV's AprilTag refinement quantises corners to about half a pixel when the
    edges are aligned with the pixel grid (a tag seen face-on), which costs degrees of
    orientation; ``cornerSubPix`` is biased by a few tenths of a pixel towards the inside.
    """
    # A light symmetric blur does not move a straight edge but makes the bilinear profiles
    # nearly linear across it (on a perfectly sharp edge they are biased by up to 0.08 px).
    gray = cv2.GaussianBlur(_gray(image).astype(np.float32), (0, 0), 0.7)
    c = np.asarray(corners, np.float64).reshape(4, 2).copy()
    for _ in range(iterations):
        sides = np.linalg.norm(c - np.roll(c, -1, axis=0), axis=1)  # side i: corner i -> i+1
        side = float(np.mean(sides))
        lines = []
        centre = c.mean(axis=0)
        for i in range(4):
            a, b = c[i], c[(i + 1) % 4]
            # Across side i the black border is one cell of the adjacent sides (tag_size / 8,
            # foreshortened); profiles reach 0.6 of the narrower one each way.
            cell = min(sides[(i - 1) % 4], sides[(i + 1) % 4]) / 8.0
            half = float(np.clip(0.6 * cell, 1.0, 8.0))
            n_along = int(np.clip(sides[i], 8, 60))
            t = np.linspace(0.15, 0.85, n_along)
            s = np.arange(-half, half + 1e-9, 0.25)
            d = (b - a) / np.linalg.norm(b - a)
            nrm = np.array([-d[1], d[0]])
            if np.dot(nrm, 0.5 * (a + b) - centre) < 0:
                nrm = -nrm  # outward: dark (inside) -> light (outside)
            base = a[None, :] + t[:, None] * (b - a)[None, :]
            pts = base[:, None, :] + s[None, :, None] * nrm[None, None, :]
            prof = cv2.remap(gray, pts[..., 0].astype(np.float32), pts[..., 1].astype(np.float32),
                             cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            lo = prof[:, : len(s) // 4 + 1].mean(axis=1)
            hi = prof[:, -(len(s) // 4 + 1):].mean(axis=1)
            edge_pts = []
            for k in range(n_along):
                if hi[k] - lo[k] < 20.0:  # too little contrast to locate an edge
                    continue
                f = prof[k] - 0.5 * (lo[k] + hi[k])
                idx = np.nonzero((f[:-1] < 0) & (f[1:] >= 0))[0]
                if idx.size == 0:
                    continue
                j = idx[np.argmin(np.abs(s[idx]))]  # the crossing nearest the guess
                off = s[j] - f[j] * (s[j + 1] - s[j]) / (f[j + 1] - f[j])
                edge_pts.append(base[k] + off * nrm)
            if len(edge_pts) < 4:
                return np.asarray(corners, np.float64).reshape(4, 2)
            e = np.asarray(edge_pts)
            if intrinsics is not None and intrinsics.dist.size:
                e = cv2.undistortPoints(e.reshape(-1, 1, 2), intrinsics.K, intrinsics.dist,
                                        P=intrinsics.K).reshape(-1, 2)
            m = e.mean(axis=0)
            _, _, vt = np.linalg.svd(e - m)
            lines.append((m, vt[0]))
        new = np.empty((4, 2))
        for i in range(4):
            (m0, d0), (m1, d1) = lines[(i - 1) % 4], lines[i]
            # corner i joins side i-1 (corner i-1 -> i) and side i (corner i -> i+1)
            ab = np.linalg.solve(np.column_stack([d0, -d1]), m1 - m0)
            new[i] = m0 + ab[0] * d0
        if intrinsics is not None and intrinsics.dist.size:
            xn = (new - [intrinsics.cx, intrinsics.cy]) / [intrinsics.fx, intrinsics.fy]
            obj = np.column_stack([xn, np.ones(4)])
            new = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), intrinsics.K,
                                    intrinsics.dist)[0].reshape(4, 2)
        if not np.all(np.isfinite(new)) or np.max(np.abs(new - c)) > 0.3 * side:
            return np.asarray(corners, np.float64).reshape(4, 2)
        c = new
    return c


# Tag frame turned 180 deg about x: a tag facing the camera then has a rotation near the
# identity, far from the angle-pi singularity of rotation vectors (where Rodrigues round
# trips and the LM refinement break down).
_FLIP = np.diag([1.0, -1.0, -1.0])


def _rmse(obj, rvec, tvec, corners, intrinsics):
    proj, _ = cv2.projectPoints(obj, rvec, tvec, intrinsics.K, intrinsics.dist)
    return float(np.sqrt(np.mean(np.sum((proj.reshape(4, 2) - corners) ** 2, axis=1))))


def solve_tag_pose(
    corners: np.ndarray, intrinsics: CameraIntrinsics, tag_size: float, *, refine: bool = True
) -> TagPose:
    """Tag pose in the camera frame from its four corners [px].

    ``SOLVEPNP_IPPE_SQUARE`` gives both planar solutions; the best (lowest reprojection
    error) is then polished by Levenberg-Marquardt on the reprojection error
    (``solvePnPRefineLM``) when ``refine``, which makes it the maximum-likelihood pose
    under isotropic corner noise (IPPE's homography-based solution is not exactly that).

    Args:
      corners: (4, 2) detected corners in aruco's order [px].
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
    others = [s for s in sols[1:] if _angle(s.R_cam_tag, best.R_cam_tag) > np.deg2rad(0.5)]
    return TagPose(best.R_cam_tag, best.p_cam_tag, best.reprojection_error,
                   others[0] if others else None, corners)


def _angle(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Angle [rad] of the rotation between two orientations."""
    c = 0.5 * (np.trace(R_a.T @ R_b) - 1.0)
    return float(np.arccos(np.clip(c, -1.0, 1.0)))


def measure_tag(
    image: np.ndarray,
    intrinsics: CameraIntrinsics,
    tag_size: float,
    tag_id: int,
    *,
    detector: cv2.aruco.ArucoDetector | None = None,
    edge_refine: bool = True,
) -> TagPose:
    """Detects tag ``tag_id`` and returns its pose in the camera frame.

    The pipeline: aruco detection (AprilTag corner refinement), sub-pixel edge-line
    corners (:func:`refine_corners_edges`, when ``edge_refine``), IPPE square PnP and LM
    polishing (:func:`solve_tag_pose`).

    Raises:
      TagNotFoundError: the tag is not in the image.
    """
    det = find_tag(image, tag_id, detector)
    corners = refine_corners_edges(image, det.corners, intrinsics) if edge_refine else det.corners
    return solve_tag_pose(corners, intrinsics, tag_size)
