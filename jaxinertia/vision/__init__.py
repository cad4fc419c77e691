"""Camera: AprilTag detection, tag pose and camera-to-base calibration.

Modules: ``intrinsics`` (camera model files), ``tags`` (tag36h11 detection, corners,
PnP), ``calibration`` (camera pose in the robot base), ``source`` (per-sample tag pose
for data collection), ``synthetic`` (rendered test images), ``commands`` (CLI).

Names are re-exported lazily: the CLI imports ``jaxinertia.vision.commands`` to build its
parser, and ``jaxinertia --help`` should not pay for importing OpenCV.
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "CalibrationResult": "calibration",
    "CameraPose": "calibration",
    "CameraPoseError": "calibration",
    "calibrate_camera_pose": "calibration",
    "load_camera_pose": "calibration",
    "save_camera_pose": "calibration",
    "CameraIntrinsics": "intrinsics",
    "IntrinsicsError": "intrinsics",
    "load_intrinsics": "intrinsics",
    "save_intrinsics": "intrinsics",
    "CameraTagSource": "source",
    "opencv_capture": "source",
    "TagNotFoundError": "tags",
    "TagPose": "tags",
    "detect_tags": "tags",
    "measure_tag": "tags",
    "render_tag": "synthetic",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(f"jaxinertia.vision.{_EXPORTS[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
