"""Subcommands ``tag-pose`` and ``camera-calibrate``: a tag's pose in one image, and the
camera's pose in the robot base from images of the end-effector tag.

Errors are raised (:mod:`jaxinertia.errors`: a bad file, no tag in the image, a camera
pose the images cannot determine); ``main()`` prints them and exits with code 2.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import jax
import numpy as np

from jaxinertia.app.options import positive_float
from jaxinertia.errors import CameraError, FileFormatError, TagNotFoundError, UsageError
from jaxinertia.fileio import check_output
from jaxinertia.kinematics import ee_pose
from jaxinertia.robot import open_manipulator_x
from jaxinertia.vision.calibration import (
    calibrate_camera_pose,
    load_camera_pose,
    read_manifest,
    save_camera_pose,
)
from jaxinertia.vision.intrinsics import load_intrinsics
from jaxinertia.vision.tags import find_tag, make_detector, measure_tag, refine_corners_edges

__all__ = ["register"]

DEFAULT_TAG_SIZE = 0.04  # [m] edge of the black square; measure yours
DEFAULT_TAG_ID = 0


def _read_image(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise FileFormatError(path, None, "not a readable image")
    return img


def _rot_deg(R) -> list[float]:
    """Rotation vector [deg] of R (axis * angle)."""
    return (np.rad2deg(cv2.Rodrigues(np.asarray(R, float))[0].ravel())).tolist()


def cmd_tag_pose(args) -> int:
    intr = load_intrinsics(args.intrinsics)
    cam = load_camera_pose(args.camera_pose) if args.camera_pose else None
    img = _read_image(args.image)
    intr.check_size(img, str(args.image))
    tp = measure_tag(img, intr, args.tag_size, args.tag_id)
    out = {"tag_id": args.tag_id, "tag_size": args.tag_size,
           "R_cam_tag": tp.R_cam_tag.tolist(), "p_cam_tag": tp.p_cam_tag.tolist(),
           "reprojection_error_px": tp.reprojection_error, "ambiguity": tp.ambiguity,
           "corners_px": np.asarray(tp.corners).tolist()}
    if cam is not None:
        R_bt, p_bt = cam.tag_in_base(tp.R_cam_tag, tp.p_cam_tag)
        out["R_base_tag"], out["p_base_tag"] = R_bt.tolist(), p_bt.tolist()
    if args.json:
        print(json.dumps(out, indent=2))
        return 0
    p = tp.p_cam_tag * 1e3
    print(f"tag {args.tag_id} ({args.tag_size * 1e3:.1f} mm) in camera: "
          f"p = [{p[0]:.2f}, {p[1]:.2f}, {p[2]:.2f}] mm, "
          f"rotation vector = [{', '.join(f'{a:.2f}' for a in _rot_deg(tp.R_cam_tag))}] deg")
    if cam is not None:
        pb = np.asarray(out["p_base_tag"]) * 1e3
        print(f"tag in base: p = [{pb[0]:.2f}, {pb[1]:.2f}, {pb[2]:.2f}] mm, rotation vector = "
              f"[{', '.join(f'{a:.2f}' for a in _rot_deg(out['R_base_tag']))}] deg")
    amb = f"; ambiguity {tp.ambiguity:.2f}" if tp.ambiguity > 0.5 else ""
    print(f"reprojection error {tp.reprojection_error:.3f} px{amb}")
    return 0


def cmd_camera_calibrate(args) -> int:
    jax.config.update("jax_enable_x64", True)
    check_output(args.out, overwrite=args.overwrite)
    intr = load_intrinsics(args.intrinsics)
    rows = read_manifest(args.manifest)
    robot = open_manipulator_x()
    det = make_detector()
    qs, corners, names = [], [], []
    for img_path, q in rows:
        if len(q) != robot.n_joints:
            raise UsageError(f"{img_path.name}: {len(q)} joint angles, the robot has "
                             f"{robot.n_joints}")
        try:
            img = _read_image(img_path)
            c = find_tag(img, args.tag_id, det).corners
        except (FileFormatError, TagNotFoundError) as e:
            print(f"skipped {img_path.name}: {e}", file=sys.stderr)
            continue
        qs.append(q)
        corners.append(refine_corners_edges(img, c, intr))
        names.append(img_path.name)
    if len(names) < 3:
        raise CameraError(f"the tag was found in {len(names)} of {len(rows)} images; at "
                          "least 3 are needed (10 or more advised)")
    fk = jax.vmap(lambda q: ee_pose(robot, q))
    R_be, p_be = (np.asarray(a) for a in fk(np.asarray(qs, np.float64)))
    res = calibrate_camera_pose(R_be, p_be, np.asarray(corners).reshape(-1, 4, 2), intr,
                                args.tag_size)
    cp = res.camera_pose
    save_camera_pose(args.out, cp, extra={
        "tag_size": args.tag_size, "tag_id": args.tag_id, "n_images": len(names),
        "rms_reprojection_px": res.rms_px,
        "per_image_rms_px": dict(zip(names, res.per_image_rms_px.round(4).tolist())),
        "std_p_base_cam": res.std_p_base_cam.tolist(),
        "std_rot_base_cam_rad": res.std_rot_base_cam.tolist()})
    p = cp.p_base_cam * 1e3
    print(f"{len(names)} of {len(rows)} images used; RMS reprojection {res.rms_px:.3f} px "
          f"(worst {names[int(np.argmax(res.per_image_rms_px))]}: "
          f"{res.per_image_rms_px.max():.3f} px)")
    print(f"camera in base: p = [{p[0]:.1f}, {p[1]:.1f}, {p[2]:.1f}] mm "
          f"(+- {', '.join(f'{s * 1e3:.2f}' for s in res.std_p_base_cam)} mm)")
    pt = cp.p_ee_tag * 1e3
    print(f"tag in end effector: p = [{pt[0]:.1f}, {pt[1]:.1f}, {pt[2]:.1f}] mm, rotation "
          f"vector = [{', '.join(f'{a:.2f}' for a in _rot_deg(cp.R_ee_tag))}] deg")
    print(f"wrote {args.out}")
    return 0


def register(sub) -> None:
    """Adds this module's subcommands to the ``jaxinertia`` argparse subparsers."""
    t = sub.add_parser(
        "tag-pose",
        help="pose of a tag36h11 AprilTag in one image (camera frame, and base frame)",
        description="Detects the tag, refines its corners and solves its pose (IPPE square "
        "PnP). Exit code 2 when the tag is not found or a file is bad.",
    )
    t.add_argument("--image", required=True, type=Path)
    t.add_argument("--intrinsics", required=True, type=Path,
                   help="camera intrinsics: JSON (fx, fy, cx, cy, width, height, distortion) "
                   "or OpenCV FileStorage YAML/XML (camera_matrix, distortion_coefficients)")
    t.add_argument("--tag-size", type=positive_float, default=DEFAULT_TAG_SIZE,
                   help="edge of the black square [m] (default %(default)s)")
    t.add_argument("--tag-id", type=int, default=DEFAULT_TAG_ID)
    t.add_argument("--camera-pose", type=Path,
                   help="camera pose in base (from camera-calibrate): also print the tag in base")
    t.add_argument("--json", action="store_true", help="print JSON instead of text")
    t.set_defaults(func=cmd_tag_pose)

    c = sub.add_parser(
        "camera-calibrate",
        help="camera pose in the robot base from images of the end-effector tag",
        description="MANIFEST lists images with the joint angles [rad] at which each was "
        "taken: JSON {\"samples\": [{\"image\": \"a.png\", \"q\": [q1, q2, q3, q4]}, ...]} or "
        "CSV with header image,q1,q2,q3,q4 (paths relative to the manifest). Solves the "
        "camera pose and the tag's mounting on the end effector together, minimising the "
        "corners' reprojection error, and writes the camera-pose JSON.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    c.add_argument("--manifest", required=True, type=Path)
    c.add_argument("--intrinsics", required=True, type=Path)
    c.add_argument("--tag-size", type=positive_float, default=DEFAULT_TAG_SIZE,
                   help="edge of the black square [m] (default %(default)s)")
    c.add_argument("--tag-id", type=int, default=DEFAULT_TAG_ID)
    c.add_argument("--out", type=Path, default=Path("camera_pose.json"))
    c.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    c.set_defaults(func=cmd_camera_calibrate)
