"""Camera: AprilTag detection, tag pose and camera-to-base calibration."""
