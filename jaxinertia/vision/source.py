"""Per-sample tag pose in the robot base frame, as a callable for data collection.

``CameraTagSource(...)(q) -> (R_base_tag, p_base_tag)`` feeds
``jaxinertia.statics.load_regressor(robot, q, R_base_tag, p_base_tag)`` exactly as the
simulator's tag pose does.
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

from jaxinertia.errors import HardwareError, UsageError
from jaxinertia.vision.calibration import CameraPose
from jaxinertia.vision.intrinsics import CameraIntrinsics
from jaxinertia.vision.tags import (
    TagPose,
    find_tag,
    make_detector,
    refine_corners_edges,
    solve_tag_pose,
)

__all__ = ["CameraTagSource", "opencv_capture"]


def opencv_capture(
    index: int = 0, *, width: int | None = None, height: int | None = None, flush: int = 4
) -> Callable[[], np.ndarray]:
    """A function returning a fresh frame from ``cv2.VideoCapture(index)``.

    Cameras queue a few frames; ``flush`` frames are grabbed and dropped first so that the
    returned image shows the arm where it is now, not where it was before it moved.
    """
    cap = cv2.VideoCapture(index)
    if not cap.isOpened():
        raise HardwareError(f"cannot open camera {index} (cv2.VideoCapture)")
    if width:
        cap.set(cv2.CAP_PROP_FRAME_WIDTH, width)
    if height:
        cap.set(cv2.CAP_PROP_FRAME_HEIGHT, height)

    def capture() -> np.ndarray:
        for _ in range(flush):
            cap.grab()
        ok, frame = cap.read()
        if not ok:
            raise HardwareError(f"camera {index} returned no frame")
        return frame

    capture.release = cap.release  # type: ignore[attr-defined]
    return capture


class CameraTagSource:
    """Tag pose in the base frame from a fixed, calibrated camera.

    Args:
      intrinsics: the camera's intrinsics (must match the capture's image size).
      camera_pose: ``T_base_cam`` (:func:`jaxinertia.vision.load_camera_pose`).
      tag_size: edge of the black square [m]; tag_id: the tag's id on the object; family:
        its AprilTag family (tag36h11 default). The pose is in the official tag frame.
      capture: ``() -> image`` (default: ``opencv_capture(0)``, opened on first use).
      n_frames: frames per sample whose corners are averaged (the scene is static).
      prior: optional ``q -> (R_base_tag, p_base_tag)`` prediction (e.g. forward
        kinematics with the calibrated ``T_ee_tag``); when given, the planar pose
        ambiguity is resolved by taking the PnP solution closest to it in orientation.

    Calling it with the joint angles ``q`` (N,) [rad] of the sample returns
    ``(R_base_tag (3, 3), p_base_tag (3,) [m])``; the last :class:`TagPose` (camera
    frame, reprojection error) is kept in ``last``. Raises
    :class:`jaxinertia.vision.TagNotFoundError` when the tag is not seen.
    """

    def __init__(
        self,
        intrinsics: CameraIntrinsics,
        camera_pose: CameraPose,
        tag_size: float,
        tag_id: int = 0,
        *,
        capture: Callable[[], np.ndarray] | None = None,
        n_frames: int = 1,
        prior: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None,
        family: str = "tag36h11",
    ):
        if not tag_size > 0:
            raise UsageError(f"tag_size must be positive [m], got {tag_size}")
        self.intrinsics = intrinsics
        self.camera_pose = camera_pose
        self.tag_size = float(tag_size)
        self.tag_id = int(tag_id)
        self._capture = capture
        self.n_frames = int(n_frames)
        self.prior = prior
        self._detector = make_detector(family=family)
        self.last: TagPose | None = None

    def measure(self, image: np.ndarray | None = None) -> TagPose:
        """Tag pose in the camera frame from ``image`` (default: ``n_frames`` captures)."""
        if self._capture is None and image is None:
            self._capture = opencv_capture(0)
        images = [image] if image is not None else [self._capture() for _ in range(self.n_frames)]
        corners = []
        for img in images:
            self.intrinsics.check_size(img)
            det = find_tag(img, self.tag_id, self._detector)
            corners.append(refine_corners_edges(img, det.corners, self.intrinsics))
        return solve_tag_pose(np.mean(corners, axis=0), self.intrinsics, self.tag_size)

    def __call__(
        self, q: np.ndarray | None = None, image: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        tp = self.measure(image)
        R_ct, p_ct = tp.R_cam_tag, tp.p_cam_tag
        if self.prior is not None and q is not None and tp.alternative is not None:
            R_pred, _ = self.prior(np.asarray(q))
            R_pred = self.camera_pose.R_base_cam.T @ np.asarray(R_pred)
            alt = tp.alternative
            if np.trace(R_pred.T @ alt.R_cam_tag) > np.trace(R_pred.T @ R_ct):
                R_ct, p_ct = alt.R_cam_tag, alt.p_cam_tag
        self.last = tp
        return self.camera_pose.tag_in_base(R_ct, p_ct)

