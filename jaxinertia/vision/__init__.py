"""Camera: AprilTag detection, tag pose and camera-to-base calibration.

Modules: ``intrinsics`` (camera model files), ``tags`` (tag36h11 detection, corners,
PnP), ``calibration`` (camera pose in the robot base, calibration manifests), ``source``
(per-sample tag pose for data collection), ``synthetic`` (rendered test images). The
commands ``tag-pose`` and ``camera-calibrate`` are in :mod:`jaxinertia.app.vision_commands`.
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
from jaxinertia.vision.intrinsics import (
    CameraIntrinsics,
    IntrinsicsError,
    load_intrinsics,
    save_intrinsics,
)
from jaxinertia.vision.source import CameraTagSource, opencv_capture
from jaxinertia.vision.synthetic import render_tag
from jaxinertia.vision.tags import TagPose, detect_tags, measure_tag

__all__ = [
    "CalibrationResult",
    "CameraIntrinsics",
    "CameraPose",
    "CameraPoseError",
    "CameraTagSource",
    "IntrinsicsError",
    "TagNotFoundError",
    "TagPose",
    "calibrate_camera_pose",
    "detect_tags",
    "load_camera_pose",
    "load_intrinsics",
    "measure_tag",
    "opencv_capture",
    "read_manifest",
    "render_tag",
    "save_camera_pose",
    "save_intrinsics",
]
