"""Subcommands of ``jaxinertia`` provided by this package: ``tag-pose``, ``camera-calibrate``.

Heavy imports (OpenCV, JAX) happen inside the command functions.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

__all__ = ["read_manifest", "register"]

DEFAULT_TAG_SIZE = 0.04  # [m] edge of the black square; measure yours
DEFAULT_TAG_ID = 0


def _err(cmd: str, msg: str) -> int:
    print(f"jaxinertia {cmd}: error: {msg}", file=sys.stderr)
    return 2


def _read_image(path: Path):
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise FileNotFoundError(f"{path}: not a readable image")
    return img


def _rot_deg(R) -> list[float]:
    """Rotation vector [deg] of R (axis * angle)."""
    import cv2
    import numpy as np

    return (np.rad2deg(cv2.Rodrigues(np.asarray(R, float))[0].ravel())).tolist()


def cmd_tag_pose(args) -> int:
    import numpy as np

    from jaxinertia.vision.calibration import CameraPoseError, load_camera_pose
    from jaxinertia.vision.intrinsics import IntrinsicsError, load_intrinsics
    from jaxinertia.vision.tags import TagNotFoundError, measure_tag

    try:
        intr = load_intrinsics(args.intrinsics)
        cam = load_camera_pose(args.camera_pose) if args.camera_pose else None
        img = _read_image(args.image)
        if (img.shape[1], img.shape[0]) != intr.size:
            return _err("tag-pose", f"{args.image} is {img.shape[1]}x{img.shape[0]} px; the "
                        f"intrinsics are for {intr.width}x{intr.height}")
        tp = measure_tag(img, intr, args.tag_size, args.tag_id)
    except (IntrinsicsError, CameraPoseError, TagNotFoundError, FileNotFoundError) as e:
        return _err("tag-pose", str(e))
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


def read_manifest(path: Path) -> list[tuple[Path, list[float]]]:
    """Images and joint angles [rad] from a JSON or CSV manifest (paths relative to it).

    JSON: ``{"samples": [{"image": "img_000.png", "q": [q1, q2, q3, q4]}, ...]}``;
    CSV: a header ``image,q1,q2,q3,q4`` then one row per image.
    """
    import csv

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: no such manifest")
    rows: list[tuple[Path, list[float]]] = []
    try:
        if path.suffix.lower() == ".json":
            d = json.loads(path.read_text())
            for s in d["samples"]:
                rows.append((path.parent / s["image"], [float(x) for x in s["q"]]))
        else:
            with path.open(newline="") as f:
                for r in csv.DictReader(f):
                    qs = sorted((k for k in r if k and k.startswith("q")), key=lambda k: int(k[1:]))
                    rows.append((path.parent / r["image"], [float(r[k]) for k in qs]))
    except (KeyError, TypeError, ValueError, json.JSONDecodeError) as e:
        raise ValueError(f"{path}: bad manifest ({e!r}); see jaxinertia camera-calibrate "
                         "--help") from e
    if not rows:
        raise ValueError(f"{path}: the manifest lists no images")
    return rows


def cmd_camera_calibrate(args) -> int:
    import jax

    jax.config.update("jax_enable_x64", True)
    import numpy as np

    from jaxinertia.kinematics import ee_pose
    from jaxinertia.robot import open_manipulator_x
    from jaxinertia.vision.calibration import (
        CameraPoseError,
        calibrate_camera_pose,
        save_camera_pose,
    )
    from jaxinertia.vision.intrinsics import IntrinsicsError, load_intrinsics
    from jaxinertia.vision.tags import (
        TagNotFoundError,
        find_tag,
        make_detector,
        refine_corners_edges,
    )

    try:
        intr = load_intrinsics(args.intrinsics)
        rows = read_manifest(args.manifest)
    except (IntrinsicsError, ValueError) as e:
        return _err("camera-calibrate", str(e))
    robot = open_manipulator_x()
    det = make_detector()
    qs, corners, names = [], [], []
    for img_path, q in rows:
        if len(q) != robot.n_joints:
            return _err("camera-calibrate", f"{img_path.name}: {len(q)} joint angles, the robot "
                        f"has {robot.n_joints}")
        try:
            img = _read_image(img_path)
            c = find_tag(img, args.tag_id, det).corners
        except (FileNotFoundError, TagNotFoundError) as e:
            print(f"skipped {img_path.name}: {e}", file=sys.stderr)
            continue
        qs.append(q)
        corners.append(refine_corners_edges(img, c, intr))
        names.append(img_path.name)
    if len(names) < 3:
        return _err("camera-calibrate", f"the tag was found in {len(names)} of {len(rows)} "
                    "images; at least 3 are needed (10 or more advised)")
    fk = jax.vmap(lambda q: ee_pose(robot, q))
    R_be, p_be = (np.asarray(a) for a in fk(np.asarray(qs, np.float64)))
    try:
        res = calibrate_camera_pose(R_be, p_be, np.asarray(corners).reshape(-1, 4, 2), intr,
                                    args.tag_size)
    except CameraPoseError as e:
        return _err("camera-calibrate", str(e))
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
    """Adds this package's subcommands to the ``jaxinertia`` argparse subparsers."""
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
    t.add_argument("--tag-size", type=float, default=DEFAULT_TAG_SIZE,
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
    c.add_argument("--tag-size", type=float, default=DEFAULT_TAG_SIZE,
                   help="edge of the black square [m] (default %(default)s)")
    c.add_argument("--tag-id", type=int, default=DEFAULT_TAG_ID)
    c.add_argument("--out", type=Path, default=Path("camera_pose.json"))
    c.set_defaults(func=cmd_camera_calibrate)
