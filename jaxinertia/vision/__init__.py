"""Camera: AprilTag detection, tag pose and camera-to-base calibration.

Modules: ``intrinsics`` (camera model files), ``families`` (the AprilTag families as the
AprilTag library draws them), ``tags`` (detection in the official tag frame), ``corners``
(sub-pixel corners), ``pose`` (PnP and its ambiguity), ``calibration`` (camera pose in the
robot base, calibration manifests), ``source`` (per-sample tag pose for data collection),
``synthetic`` (rendered test images). The commands ``tag-pose``, ``tag-image`` and
``camera-calibrate`` are in :mod:`jaxinertia.app.vision_commands`.
"""

from jaxinertia.errors import TagNotFoundError
from jaxinertia.vision.calibration import (
    CalibrationResult,
    CameraPose,
    CameraPoseError,
    calibrate_camera_pose,
    load_camera_pose,
    read_manifest,
    save_camera_pose,
)
from jaxinertia.vision.families import FAMILIES, get_family, tag_image
from jaxinertia.vision.intrinsics import (
    CameraIntrinsics,
    IntrinsicsError,
    load_intrinsics,
    save_intrinsics,
)
from jaxinertia.vision.pose import TagPose, solve_tag_pose
from jaxinertia.vision.source import CameraTagSource, opencv_capture
from jaxinertia.vision.synthetic import render_tag
from jaxinertia.vision.tags import TagDetection, TagDetector, detect_tags, find_tag, measure_tag

__all__ = [
    "CalibrationResult",
    "CameraIntrinsics",
    "CameraPose",
    "CameraPoseError",
    "CameraTagSource",
    "FAMILIES",
    "IntrinsicsError",
    "TagNotFoundError",
    "TagDetection",
    "TagDetector",
    "TagPose",
    "calibrate_camera_pose",
    "detect_tags",
    "find_tag",
    "get_family",
    "load_camera_pose",
    "load_intrinsics",
    "measure_tag",
    "opencv_capture",
    "read_manifest",
    "render_tag",
    "save_camera_pose",
    "save_intrinsics",
    "solve_tag_pose",
    "tag_image",
]
