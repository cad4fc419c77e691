"""Subcommands ``tag-pose``, ``tag-image`` and ``camera-calibrate``: the pose of the tags
in one image, an official tag image to print, and the camera's pose in the robot base from
images of the end-effector tag.

Errors are raised (:mod:`jaxinertia.errors`: a bad file, no tag in the image, a camera
pose the images cannot determine); ``main()`` prints them as one line and exits with code 2.
OpenCV, JAX and the robot model are imported where a command starts, not to build the
parser.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from jaxinertia.app.options import positive_float
from jaxinertia.errors import CameraError, FileFormatError, TagNotFoundError, UsageError
from jaxinertia.fileio import check_output, replacing

__all__ = ["register"]

DEFAULT_TAG_SIZE = 0.04  # [m] edge of the black square; measure yours
DEFAULT_TAG_ID = 0
FAMILY_NAMES = ("tag36h11", "tag36h10", "tag25h9", "tag16h5")


def _vision():
    """The camera package (OpenCV), imported when a command runs, not to build the parser."""
    # Local: importing OpenCV would slow every --help.
    import jaxinertia.vision

    return jaxinertia.vision


def _cv2():
    # Local: importing OpenCV would slow every --help.
    import cv2

    return cv2


def _rot_deg(R) -> list[float]:
    """Rotation vector [deg] of R (axis * angle)."""
    cv2 = _cv2()
    return (np.rad2deg(cv2.Rodrigues(np.asarray(R, float))[0].ravel())).tolist()


def _pose_dict(det, tp, cam) -> dict:
    out = {"tag_id": det.tag_id, "family": det.family, "size_px": det.side_px,
           "found_by": det.how, "R_cam_tag": tp.R_cam_tag.tolist(),
           "p_cam_tag": tp.p_cam_tag.tolist(), "reprojection_error_px": tp.reprojection_error,
           "ambiguous": tp.ambiguous, "ambiguity": tp.ambiguity,
           "rotation_std_deg": float(np.rad2deg(tp.rotation_std)),
           "corners_px": np.asarray(tp.corners).tolist()}
    if tp.alternative is not None:
        out["alternative"] = {"R_cam_tag": tp.alternative.R_cam_tag.tolist(),
                              "p_cam_tag": tp.alternative.p_cam_tag.tolist(),
                              "reprojection_error_px": tp.alternative.reprojection_error,
                              "angle_deg": float(np.rad2deg(tp.alternative_angle))}
    if cam is not None:
        R_bt, p_bt = cam.tag_in_base(tp.R_cam_tag, tp.p_cam_tag)
        out["R_base_tag"], out["p_base_tag"] = R_bt.tolist(), p_bt.tolist()
    return out


def _pose_lines(d: dict, tag_size: float) -> list[str]:
    p = np.asarray(d["p_cam_tag"]) * 1e3
    lines = [f"tag {d['tag_id']} ({d['family']}, {tag_size * 1e3:.1f} mm, {d['size_px']:.0f} px) "
             f"in camera: p = [{p[0]:.2f}, {p[1]:.2f}, {p[2]:.2f}] mm, rotation vector = "
             f"[{', '.join(f'{a:.2f}' for a in _rot_deg(d['R_cam_tag']))}] deg"]
    if "p_base_tag" in d:
        pb = np.asarray(d["p_base_tag"]) * 1e3
        lines.append(f"  tag in base: p = [{pb[0]:.2f}, {pb[1]:.2f}, {pb[2]:.2f}] mm, rotation "
                     f"vector = [{', '.join(f'{a:.2f}' for a in _rot_deg(d['R_base_tag']))}] deg")
    lines.append(f"  reprojection error {d['reprojection_error_px']:.3f} px, orientation "
                 f"+-{d['rotation_std_deg']:.1f} deg (1 sigma for 0.1 px corners)")
    if d["ambiguous"]:
        alt = d.get("alternative")
        why = (f"a second pose {alt['angle_deg']:.0f} deg away fits the corners within "
               f"{alt['reprojection_error_px']:.2f} px" if alt is not None
               and alt["reprojection_error_px"] < 0.5 else
               f"the orientation is uncertain by +-{d['rotation_std_deg']:.0f} deg")
        lines.append(f"  POSE AMBIGUOUS: {why}; the tag is too small or too far for its tilt "
                     "(position is still usable)")
    return lines


def cmd_tag_pose(args) -> int:
    v = _vision()
    load_camera_pose, read_image = v.calibration.load_camera_pose, v.files.read_image
    load_intrinsics, solve_tag_pose = v.intrinsics.load_intrinsics, v.pose.solve_tag_pose
    TagDetector, find_tag = v.tags.TagDetector, v.tags.find_tag
    no_tag_message, refine_corners_edges = v.tags.no_tag_message, v.tags.refine_corners_edges
    intr = load_intrinsics(args.intrinsics)
    cam = load_camera_pose(args.camera_pose) if args.camera_pose else None
    img = read_image(args.image)
    intr.check_size(img, "image")
    det = TagDetector(family=args.family)
    if args.list:
        dets = det.detect(img)
        if not dets:
            raise TagNotFoundError(no_tag_message(img, det))
    else:
        dets = [find_tag(img, args.tag_id, det)]
    found = []
    for d in dets:
        tp = solve_tag_pose(refine_corners_edges(img, d.corners, intr), intr, args.tag_size)
        found.append(_pose_dict(d, tp, cam))
    if args.json:
        out = {"family": args.family, "tag_size": args.tag_size, "tags": found}
        if not args.list:
            out = {**found[0], "tag_size": args.tag_size}
        print(json.dumps(out, indent=2))
        return 0
    if args.list:
        print(f"{len(found)} {args.family} tag(s) seen")
    for d in found:
        print("\n".join(_pose_lines(d, args.tag_size)))
    return 0


def cmd_tag_image(args) -> int:
    v = _vision()
    cv2, tag_image, shown = _cv2(), v.families.tag_image, v.files.shown
    check_output(args.out, overwrite=args.overwrite)
    if args.out.suffix.lower() not in (".png", ".pgm", ".bmp", ".tif", ".tiff"):
        raise UsageError(f"--out {shown(args.out)}: use a lossless image format (.png, .pgm, "
                         ".bmp, .tif)")
    img = tag_image(args.family, args.id, cell_px=args.cell_px, margin_cells=args.margin_cells)
    ok, buf = cv2.imencode(args.out.suffix.lower(), img)
    if not ok:
        raise UsageError(f"--out {shown(args.out)}: OpenCV cannot write this format")
    with replacing(args.out) as tmp:
        tmp.write_bytes(buf.tobytes())
    print(f"wrote {shown(args.out)}: {args.family} id {args.id}, {img.shape[1]} px square, "
          f"the black square {(img.shape[1] - 2 * round(args.margin_cells * args.cell_px))} px; "
          "print at 100 % and measure its edge for --tag-size")
    return 0


def cmd_camera_calibrate(args) -> int:
    import jax  # local: JAX loads when this command runs, not for --help

    from jaxinertia.kinematics import ee_pose  # local: imports JAX
    from jaxinertia.robot import open_manipulator_x  # local: imports JAX

    v = _vision()
    calibrate_camera_pose, save_camera_pose = (v.calibration.calibrate_camera_pose,
                                               v.calibration.save_camera_pose)
    read_manifest = v.calibration.read_manifest
    read_image, shown = v.files.read_image, v.files.shown
    load_intrinsics, TagDetector = v.intrinsics.load_intrinsics, v.tags.TagDetector
    find_tag, refine_corners_edges = v.tags.find_tag, v.tags.refine_corners_edges
    jax.config.update("jax_enable_x64", True)
    check_output(args.out, overwrite=args.overwrite)
    intr = load_intrinsics(args.intrinsics)
    rows = read_manifest(args.manifest)
    robot = open_manipulator_x()
    det = TagDetector(family=args.family)
    qs, corners, names = [], [], []
    for img_path, q in rows:
        if len(q) != robot.n_joints:
            raise UsageError(f"{shown(img_path.name)}: {len(q)} joint angles, the robot has "
                             f"{robot.n_joints}")
        try:
            img = read_image(img_path)
            intr.check_size(img, shown(img_path.name))
            c = find_tag(img, args.tag_id, det).corners
        except (FileFormatError, TagNotFoundError, UsageError) as e:
            print(f"skipped {shown(img_path.name)}: {e}", file=sys.stderr)
            continue
        qs.append(q)
        corners.append(refine_corners_edges(img, c, intr))
        names.append(shown(img_path.name))
    if len(names) < 3:
        raise CameraError(f"the tag was found in {len(names)} of {len(rows)} images; at "
                          "least 3 are needed (10 or more advised)")
    fk = jax.vmap(lambda q: ee_pose(robot, q))
    R_be, p_be = (np.asarray(a) for a in fk(np.asarray(qs, np.float64)))
    res = calibrate_camera_pose(R_be, p_be, np.asarray(corners).reshape(-1, 4, 2), intr,
                                args.tag_size)
    cp = res.camera_pose
    save_camera_pose(args.out, cp, extra={
        "tag_size": args.tag_size, "tag_id": args.tag_id, "family": args.family,
        "n_images": len(names), "rms_reprojection_px": res.rms_px,
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
    print(f"wrote {shown(args.out)}")
    return 0


def _family(text: str) -> str:
    name = text.lower() if text.lower().startswith("tag") else "tag" + text.lower()
    if name not in FAMILY_NAMES:
        raise argparse.ArgumentTypeError(f"unknown tag family {text!r}; OpenCV's aruco has "
                                         f"{', '.join(FAMILY_NAMES)}")
    return name


def _tag_id(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a tag id (0, 1, ...), got {text!r}") from None
    if v < 0:
        raise argparse.ArgumentTypeError(f"must be a tag id (0, 1, ...), got {text!r}")
    return v


def _cell_px(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        v = 0
    if not 1 <= v <= 1000:
        raise argparse.ArgumentTypeError(f"must be 1-1000 pixels per cell, got {text!r}")
    return v


def register(sub) -> None:
    """Adds this module's subcommands to the ``jaxinertia`` argparse subparsers."""
    fam_help = ("AprilTag family: tag36h11 (default), tag36h10, tag25h9, tag16h5 (the ones "
                "OpenCV's aruco reads)")
    t = sub.add_parser(
        "tag-pose",
        help="pose of an AprilTag (or of every tag with --list) in one image",
        description="Detects the tag, refines its corners and solves its pose (IPPE square "
        "PnP) in the official AprilTag frame: x right, y up as the AprilTag library's tag "
        "image is read upright, z out of the printed face. Flags a pose whose orientation the "
        "corners do not determine (small or distant tags). Exit code 2 when the tag is not "
        "found or a file is bad.",
    )
    t.add_argument("--image", required=True, type=Path)
    t.add_argument("--intrinsics", required=True, type=Path,
                   help="camera intrinsics: JSON (fx, fy, cx, cy, width, height, distortion) "
                   "or OpenCV FileStorage YAML/XML (camera_matrix, distortion_coefficients)")
    t.add_argument("--tag-size", type=positive_float, default=DEFAULT_TAG_SIZE,
                   help="edge of the black square [m] (default %(default)s; with --list, "
                   "the same for every tag)")
    t.add_argument("--tag-id", type=_tag_id, default=DEFAULT_TAG_ID)
    t.add_argument("--family", type=_family, default="tag36h11", help=fam_help)
    t.add_argument("--list", action="store_true",
                   help="every tag seen: id, size in pixels and pose (--tag-id is ignored)")
    t.add_argument("--camera-pose", type=Path,
                   help="camera pose in base (from camera-calibrate): also print the tag in base")
    t.add_argument("--json", action="store_true", help="print JSON instead of text")
    t.set_defaults(func=cmd_tag_pose)

    g = sub.add_parser(
        "tag-image",
        help="write an official AprilTag image to print",
        description="Draws the tag from its family's code bits exactly as the AprilTag "
        "library's own images (the official frame: x right, y up as printed), with a white "
        "margin. Print at 100 % and measure the black square for --tag-size.",
    )
    g.add_argument("--id", type=_tag_id, default=DEFAULT_TAG_ID)
    g.add_argument("--family", type=_family, default="tag36h11", help=fam_help)
    g.add_argument("--cell-px", type=_cell_px, default=50,
                   help="pixels per cell (default %(default)s)")
    g.add_argument("--margin-cells", type=positive_float, default=1.0,
                   help="white margin around the black square, in cells (default 1)")
    g.add_argument("--out", required=True, type=Path)
    g.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    g.set_defaults(func=cmd_tag_image)

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
    c.add_argument("--tag-id", type=_tag_id, default=DEFAULT_TAG_ID)
    c.add_argument("--family", type=_family, default="tag36h11", help=fam_help)
    c.add_argument("--out", type=Path, default=Path("camera_pose.json"),
                   help="camera-pose JSON to write (default camera_pose.json)")
    c.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    c.set_defaults(func=cmd_camera_calibrate)
