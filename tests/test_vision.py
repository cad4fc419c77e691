"""Camera: tag detection + pose against rendered ground truth, camera-pose calibration.

Images come from :func:`jaxinertia.vision.synthetic.render_tag`: the official tag image
(drawn from the family's code bits as the AprilTag library draws it, never with OpenCV's
``generateImageMarker``) warped by the homography fixed by ``cv2.projectPoints`` of the tag
plane (pinhole model), with lens distortion, blur and noise. The detector never sees the
ground truth.
"""

from __future__ import annotations

import json
import os

import cv2
import jax
import numpy as np
import pytest

from jaxinertia.app.cli import main
from jaxinertia.errors import CameraError, FileFormatError, UsageError
from jaxinertia.kinematics import ee_pose
from jaxinertia.open_manipulator_x import TAG_IN_EE, WORKSPACE_DEG
from jaxinertia.robot import open_manipulator_x
from jaxinertia.vision import families, tags
from jaxinertia.vision.calibration import (
    CameraPoseError,
    calibrate_camera_pose,
    load_camera_pose,
    read_manifest,
    save_camera_pose,
)
from jaxinertia.vision.families import FAMILIES, official_cells, tag_cells, tag_image
from jaxinertia.vision.intrinsics import CameraIntrinsics, IntrinsicsError, load_intrinsics
from jaxinertia.vision.source import CameraTagSource
from jaxinertia.vision.synthetic import look_at, photo_like, render_tag
from jaxinertia.vision.tags import TagNotFoundError, measure_tag, tag_object_points

TAG = 0.04  # [m]
TAG_ID = 7

#: The tolerances of this module (measurements against the rendered ground truth), by
#: what they bound.
TOL = {
    "tag_p": 1e-3,  # tag position, one image [m]
    "tag_R": np.deg2rad(0.5),  # tag orientation, one image [rad]
    "tag_reprojection": 0.5,  # RMS corner reprojection, one image [px]
    "corners": 0.1,  # edge-refined corners, face-on [px]
    "camera_p": 0.5e-3,  # calibrated p_base_cam and p_ee_tag [m]
    "camera_R": np.deg2rad(0.1),  # calibrated R_base_cam [rad]
    "mount_R": np.deg2rad(0.2),  # calibrated R_ee_tag [rad]
    "calibration_rms": 0.2,  # RMS corner reprojection of the calibration [px]
    "file": 1e-12,  # camera-pose file round trip
    "exact": 1e-6,  # noiseless corners: the algebra [m, rad]
}

PLAIN = CameraIntrinsics(600.0, 600.0, 319.5, 239.5, 640, 480)
DISTORTED = CameraIntrinsics(600.0, 602.0, 322.0, 236.0, 640, 480,
                             (-0.12, 0.05, 0.001, -0.0005, 0.0))
FACING = np.diag([1.0, -1.0, -1.0])  # tag face towards the camera


def rot(axis, deg: float) -> np.ndarray:
    a = np.asarray(axis, float)
    return cv2.Rodrigues(a / np.linalg.norm(a) * np.deg2rad(deg))[0]


def angle(R_a, R_b) -> float:
    return float(np.linalg.norm(cv2.Rodrigues(np.asarray(R_a).T @ R_b)[0]))


# Tag poses at 0.3 m: face-on (aligned with the pixel grid: the hardest case for corner
# quantisation), turned in plane, and tilted 35-60 deg about several axes.
POSES = {
    "face_on": (FACING, [0.0, 0.0, 0.3]),
    "in_plane_17": (FACING @ rot([0, 0, 1], 17), [0.01, 0.0, 0.3]),
    "upside_down": (FACING @ rot([0, 0, 1], 180), [0.0, 0.0, 0.3]),
    "tilt_x_35": (FACING @ rot([1, 0, 0], 35), [0.03, -0.02, 0.3]),
    "tilt_y_50": (FACING @ rot([0, 1, 0], 50) @ rot([0, 0, 1], 20), [-0.05, 0.04, 0.3]),
    "tilt_xy_45": (FACING @ rot([1, 1, 0], 45) @ rot([0, 0, 1], -70), [0.06, 0.05, 0.3]),
    "tilt_60": (FACING @ rot([1, -2, 0], 60), [-0.07, -0.05, 0.3]),
}


@pytest.mark.parametrize("intr", [PLAIN, DISTORTED], ids=["pinhole", "distorted"])
@pytest.mark.parametrize("name", list(POSES))
def test_tag_pose_matches_rendered_ground_truth(name, intr):
    R, p = POSES[name]
    p = np.asarray(p)
    rng = np.random.default_rng([list(POSES).index(name), int(intr is DISTORTED)])
    img = render_tag(intr, R, p, TAG, tag_id=TAG_ID, blur_sigma=0.8, noise_std=3.0, rng=rng)
    tp = measure_tag(img, intr, TAG, TAG_ID)
    dp, da = np.linalg.norm(tp.p_cam_tag - p), angle(tp.R_cam_tag, R)
    assert dp < TOL["tag_p"], f"{name}: p_cam_tag error {dp * 1e3:.3f} mm"
    assert da < TOL["tag_R"], f"{name}: R_cam_tag error {np.rad2deg(da):.3f} deg"
    assert tp.reprojection_error < TOL["tag_reprojection"], (
        f"{name}: reprojection_error {tp.reprojection_error:.3f} px")


def test_edge_refinement_beats_detector_corners_face_on():
    # Face-on with edges mid-pixel: OpenCV's AprilTag refinement quantises to about 0.5 px,
    # which costs degrees of tilt; the edge-line corners must not.
    R, p = FACING, np.array([0.0, 0.0, 0.3])
    img = render_tag(DISTORTED, R, p, TAG, tag_id=TAG_ID, blur_sigma=0.8, noise_std=3.0)
    truth = cv2.projectPoints(tag_object_points(TAG), cv2.Rodrigues(R)[0], p, DISTORTED.K,
                              DISTORTED.dist)[0].reshape(4, 2)
    raw = measure_tag(img, DISTORTED, TAG, TAG_ID, edge_refine=False)
    ref = measure_tag(img, DISTORTED, TAG, TAG_ID)
    err_raw = np.abs(raw.corners - truth).max()
    err_ref = np.abs(ref.corners - truth).max()
    assert err_ref < TOL["corners"], f"refined corners off by {err_ref:.3f} px"
    assert err_ref < 0.5 * err_raw, f"refined {err_ref:.3f} px vs detector {err_raw:.3f} px"


def _write_opencv_yaml(path, intrinsics) -> None:
    """Intrinsics as OpenCV's FileStorage writes them (the format camera tools produce)."""
    fs = cv2.FileStorage(str(path), cv2.FileStorage_WRITE)
    fs.write("image_width", 640)
    fs.write("image_height", 480)
    fs.write("camera_matrix", intrinsics.K)
    fs.write("distortion_coefficients", intrinsics.dist.reshape(1, 5))
    fs.release()


def test_no_tag_raises_tag_not_found():
    img = np.full((480, 640), 120, np.uint8)
    with pytest.raises(TagNotFoundError, match="not found"):
        measure_tag(img, PLAIN, TAG, TAG_ID)
    other = render_tag(PLAIN, FACING, np.array([0, 0, 0.3]), TAG, tag_id=3)
    with pytest.raises(TagNotFoundError, match=r"tags seen: \[3\]"):
        measure_tag(other, PLAIN, TAG, TAG_ID)


def test_intrinsics_files(tmp_path):
    good = tmp_path / "cam.json"
    good.write_text(json.dumps(DISTORTED.to_dict()))
    assert load_intrinsics(good) == DISTORTED
    _write_opencv_yaml(tmp_path / "cam.yaml", DISTORTED)
    assert load_intrinsics(tmp_path / "cam.yaml") == DISTORTED
    bad = {"missing.json": None, "notjson.json": "{fx: 1",
           "nofx.json": json.dumps({"fy": 1, "cx": 1, "cy": 1, "width": 2, "height": 2}),
           "neg.json": json.dumps({**PLAIN.to_dict(), "fx": -600.0}),
           "dist3.json": json.dumps({**PLAIN.to_dict(), "distortion": [0.1, 0.0, 0.0]}),
           "cam.txt": "fx 600"}
    for name, text in bad.items():
        if text is not None:
            (tmp_path / name).write_text(text)
        with pytest.raises(IntrinsicsError):
            load_intrinsics(tmp_path / name)


def _calibration_scene(n: int, seed: int):
    """Arm poses in the paper's workspace (facing the camera), a camera above, a tag mount."""
    robot = open_manipulator_x()
    rng = np.random.default_rng(seed)
    lo, hi = np.deg2rad(np.array(WORKSPACE_DEG)).T
    q = rng.uniform(lo, hi, size=(10 * n, 4))
    q = q[np.abs(q[:, 1:].sum(axis=1)) < np.deg2rad(40)][:n]  # tag within 40 deg of facing
    R_be, p_be = (np.asarray(a) for a in jax.vmap(lambda x: ee_pose(robot, x))(q))
    p_bc = np.array([0.26, 0.03, 0.58])
    R_bc = look_at(p_bc, [0.22, 0.0, 0.2], up=[1.0, 0.0, 0.0])
    R_et = rot([0.5, -0.3, 1.0], 6.0)  # a mounting slightly off the nominal one
    p_et = TAG_IN_EE[1] + np.array([0.002, -0.001, 0.001])
    return robot, q, R_be, p_be, R_bc, p_bc, R_et, p_et, rng


def test_camera_calibration_end_to_end(tmp_path):
    robot, q, R_be, p_be, R_bc, p_bc, R_et, p_et, rng = _calibration_scene(10, seed=0)
    corners = []
    for i in range(len(q)):
        R_ct = R_bc.T @ R_be[i] @ R_et
        p_ct = R_bc.T @ (R_be[i] @ p_et + p_be[i] - p_bc)
        img = render_tag(DISTORTED, R_ct, p_ct, TAG, tag_id=TAG_ID, blur_sigma=0.8,
                         noise_std=3.0, rng=rng)
        corners.append(measure_tag(img, DISTORTED, TAG, TAG_ID).corners)
    res = calibrate_camera_pose(R_be, p_be, np.stack(corners), DISTORTED, TAG)
    cp = res.camera_pose
    assert np.linalg.norm(cp.p_base_cam - p_bc) < TOL["camera_p"], "p_base_cam"
    assert angle(cp.R_base_cam, R_bc) < TOL["camera_R"], "R_base_cam"
    assert np.linalg.norm(cp.p_ee_tag - p_et) < TOL["camera_p"], "p_ee_tag"
    assert angle(cp.R_ee_tag, R_et) < TOL["mount_R"], "R_ee_tag"
    assert res.rms_px < TOL["calibration_rms"], "rms_px"
    # The refinement improves on the closed-form start.
    assert (np.linalg.norm(cp.p_base_cam - p_bc)
            < np.linalg.norm(res.initial.p_base_cam - p_bc)), "p_base_cam: refined vs initial"
    # Round trip of the file, then a per-sample source on a fresh image.
    path = save_camera_pose(tmp_path / "camera_pose.json", cp)
    loaded = load_camera_pose(path)
    np.testing.assert_allclose(loaded.R_base_cam, cp.R_base_cam, atol=TOL["file"],
                               err_msg="R_base_cam")
    np.testing.assert_allclose(loaded.p_base_cam, cp.p_base_cam, atol=TOL["file"],
                               err_msg="p_base_cam")
    q_new = np.deg2rad([10.0, -30.0, 30.0, 5.0])
    R_e, p_e = (np.asarray(a) for a in ee_pose(robot, q_new))
    R_bt, p_bt = R_e @ R_et, R_e @ p_et + p_e
    img = render_tag(DISTORTED, R_bc.T @ R_bt, R_bc.T @ (p_bt - p_bc), TAG, tag_id=TAG_ID,
                     blur_sigma=0.8, noise_std=3.0, rng=rng)
    source = CameraTagSource(DISTORTED, loaded, TAG, TAG_ID, capture=lambda: img)
    R_meas, p_meas = source(q_new)
    assert np.linalg.norm(p_meas - p_bt) < TOL["tag_p"], "p_base_tag"
    assert angle(R_meas, R_bt) < TOL["tag_R"], "R_base_tag"


def test_camera_calibration_noiseless_exact():
    # Exact corners: both unknowns come back to numerical precision (checks the algebra).
    _, q, R_be, p_be, R_bc, p_bc, R_et, p_et, _ = _calibration_scene(6, seed=1)
    obj = tag_object_points(TAG)
    corners = []
    for i in range(len(q)):
        R_ct = R_bc.T @ R_be[i] @ R_et
        p_ct = R_bc.T @ (R_be[i] @ p_et + p_be[i] - p_bc)
        corners.append(cv2.projectPoints(obj, cv2.Rodrigues(R_ct)[0], p_ct, DISTORTED.K,
                                         DISTORTED.dist)[0].reshape(4, 2))
    res = calibrate_camera_pose(R_be, p_be, np.stack(corners), DISTORTED, TAG)
    assert np.linalg.norm(res.camera_pose.p_base_cam - p_bc) < TOL["exact"], "p_base_cam"
    assert angle(res.camera_pose.R_base_cam, R_bc) < TOL["exact"], "R_base_cam"
    # The closed form is exact too.
    assert np.linalg.norm(res.initial.p_base_cam - p_bc) < TOL["exact"], "initial p_base_cam"
    fixed = calibrate_camera_pose(R_be, p_be, np.stack(corners), DISTORTED, TAG,
                                  tag_in_ee=(R_et, p_et))
    assert np.linalg.norm(fixed.camera_pose.p_base_cam - p_bc) < TOL["exact"], (
        "p_base_cam with the mounting fixed")


def test_calibration_rejects_degenerate_motion():
    # Joint 1 fixed and the wrist pitch fixed: one rotation only, camera rotation undetermined.
    _, q, R_be, p_be, R_bc, p_bc, R_et, p_et, _ = _calibration_scene(6, seed=2)
    R_same = np.repeat(R_be[:1], 6, axis=0)
    corners = np.zeros((6, 4, 2)) + [[300, 200], [340, 200], [340, 240], [300, 240]]
    with pytest.raises(CameraPoseError):
        calibrate_camera_pose(R_same, p_be, corners, DISTORTED, TAG)


def test_bad_camera_pose_file(tmp_path):
    f = tmp_path / "cp.json"
    f.write_text(json.dumps({"R_base_cam": (2 * np.eye(3)).tolist(), "p_base_cam": [0, 0, 1]}))
    with pytest.raises(CameraPoseError, match="not a rotation"):
        load_camera_pose(f)


def test_cli_tag_pose_and_calibrate(tmp_path, capsys):
    intr_file = tmp_path / "intr.json"
    intr_file.write_text(json.dumps(DISTORTED.to_dict()))
    R, p = POSES["tilt_x_35"]
    img = render_tag(DISTORTED, R, np.asarray(p), TAG, tag_id=TAG_ID, blur_sigma=0.8,
                     noise_std=3.0)
    cv2.imwrite(str(tmp_path / "tag.png"), img)
    args = ["tag-pose", "--image", str(tmp_path / "tag.png"), "--intrinsics", str(intr_file),
            "--tag-size", str(TAG), "--tag-id", str(TAG_ID)]
    assert main([*args, "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert np.linalg.norm(np.asarray(out["p_cam_tag"]) - p) < TOL["tag_p"], "p_cam_tag"
    cv2.imwrite(str(tmp_path / "empty.png"), np.full((480, 640), 120, np.uint8))
    args[2] = str(tmp_path / "empty.png")
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not found" in err[0], err
    (tmp_path / "bad.json").write_text("{}")
    args[4] = str(tmp_path / "bad.json")
    assert main(args) == 2

    # camera-calibrate from a CSV manifest of rendered images.
    _, q, R_be, p_be, R_bc, p_bc, R_et, p_et, rng = _calibration_scene(8, seed=3)
    lines = ["image,q1,q2,q3,q4"]
    for i in range(len(q)):
        R_ct = R_bc.T @ R_be[i] @ R_et
        p_ct = R_bc.T @ (R_be[i] @ p_et + p_be[i] - p_bc)
        cv2.imwrite(str(tmp_path / f"c{i}.png"),
                    render_tag(DISTORTED, R_ct, p_ct, TAG, tag_id=TAG_ID, blur_sigma=0.8,
                               noise_std=3.0, rng=rng))
        lines.append(f"c{i}.png," + ",".join(f"{x:.12f}" for x in q[i]))
    (tmp_path / "manifest.csv").write_text("\n".join(lines) + "\n")
    out_file = tmp_path / "camera_pose.json"
    assert main(["camera-calibrate", "--manifest", str(tmp_path / "manifest.csv"),
                 "--intrinsics", str(intr_file), "--tag-size", str(TAG), "--tag-id",
                 str(TAG_ID), "--out", str(out_file)]) == 0
    cp = load_camera_pose(out_file)
    assert np.linalg.norm(cp.p_base_cam - p_bc) < TOL["camera_p"], "p_base_cam"
    assert angle(cp.R_base_cam, R_bc) < TOL["camera_R"], "R_base_cam"


def test_manifest_json(tmp_path):
    (tmp_path / "m.json").write_text(json.dumps({"samples": [{"image": "a.png",
                                                              "q": [0, 0.1, 0.2, 0.3]}]}))
    rows = read_manifest(tmp_path / "m.json")
    assert rows == [(tmp_path / "a.png", [0.0, 0.1, 0.2, 0.3])]
    (tmp_path / "bad.json").write_text(json.dumps({"samples": [{"img": "a.png"}]}))
    with pytest.raises(ValueError, match="bad manifest"):
        read_manifest(tmp_path / "bad.json")


# --- The official tag frame, whatever OpenCV's dictionary does --------------------------


def test_tag_bits_are_the_official_codes():
    # Codes copied from the AprilTag library are the reference; OpenCV's dictionary, turned
    # as families.opencv_turn found, must give the same cells for each, in every family.
    for name, codes in families._OFFICIAL_CODES.items():
        for tag_id, code in codes.items():
            np.testing.assert_array_equal(tag_cells(name, tag_id), official_cells(name, code),
                                          err_msg=f"{name} id {tag_id}")
    # tag36h11 id 0 decoded by hand from 0xd7e00984b and the library's bit_x/bit_y: its
    # top data row holds bits 0-4 and 9, the next bits 31, 5, 6, 7, 14, 10 (1 = white).
    top_rows = tag_image("tag36h11", 0)[2:4, 2:8] // 255
    np.testing.assert_array_equal(top_rows, [[1, 1, 0, 1, 0, 1], [0, 1, 1, 1, 0, 1]])
    assert tag_image("tag36h11", 0).shape == (10, 10)  # total_width of the library


@pytest.mark.parametrize("family", list(FAMILIES))
def test_documented_frame_on_official_tags(family):
    # An official tag facing the camera, upright: its x axis points right in the image and
    # its y axis up (R_cam_tag = diag(1, -1, -1)), corner 0 at the image's top left.
    R, p = FACING @ rot([0, 0, 1], 10), np.array([0.01, 0.005, 0.3])
    img = render_tag(SMALL, R, p, TAG, tag_id=1, family=family, blur_sigma=0.8,
                     noise_std=3.0)
    det = tags.make_detector(family=family)
    tp = measure_tag(img, SMALL, TAG, 1, detector=det)
    assert angle(tp.R_cam_tag, R) < TOL["tag_R"], np.rad2deg(angle(tp.R_cam_tag, R))
    assert np.linalg.norm(tp.p_cam_tag - p) < TOL["tag_p"]
    c = tp.corners
    assert c[0, 0] < c[1, 0] and c[0, 1] < c[3, 1], "corner 0 is not the top left"


def test_generate_image_marker_is_the_official_tag_turned():
    # OpenCV's own drawing of the same id is the official image turned 180 degrees
    # (OpenCV 5.0.0): its frame comes out turned about z. Official prints are the reference.
    D = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    marker = cv2.aruco.generateImageMarker(D, TAG_ID, 80, borderBits=1)
    turn = families.opencv_turn("tag36h11")
    np.testing.assert_array_equal(np.rot90(marker[::10, ::10] // 255, turn),
                                  tag_cells("tag36h11", TAG_ID))
    R, p = POSES["tilt_x_35"]
    img = render_tag(PLAIN, R, np.asarray(p), TAG, tag_id=TAG_ID, marker=marker,
                     blur_sigma=0.8, noise_std=3.0)
    tp = measure_tag(img, PLAIN, TAG, TAG_ID)
    assert angle(tp.R_cam_tag, R @ rot([0, 0, 1], 90 * turn)) < TOL["tag_R"]


def test_corner_order_fails_loudly_without_the_official_tag(monkeypatch):
    # Should OpenCV stop reading the official codes, the check refuses rather than guess.
    tags.corner_order.cache_clear()
    families.opencv_turn.cache_clear()
    monkeypatch.setitem(families._OFFICIAL_CODES, "tag25h9", {0: 0x1F28CD5})  # id 1's code
    try:
        with pytest.raises(CameraError, match="official tag25h9 id 0"):
            tags.corner_order("tag25h9")
        with pytest.raises(CameraError, match="rotation"):
            families.opencv_turn("tag25h9")
    finally:
        monkeypatch.undo()
        tags.corner_order.cache_clear()
        families.opencv_turn.cache_clear()
    assert tags.corner_order("tag25h9") in range(4)


# --- Small tags, ambiguity, several tags, families ------------------------------------

SMALL = CameraIntrinsics(600.0, 600.0, 159.5, 119.5, 320, 240)


def _small_scene(side_px: float, in_plane: float, seed: int):
    z = 600.0 * TAG / side_px
    R, p = FACING @ rot([0, 0, 1], in_plane) @ rot([1, 0.3, 0], 20), np.array([0.01 * z, 0, z])
    img = render_tag(SMALL, R, p, TAG, tag_id=TAG_ID, blur_sigma=0.8, noise_std=3.0,
                     rng=np.random.default_rng(seed))
    truth = cv2.projectPoints(tag_object_points(TAG), cv2.Rodrigues(R)[0], p, SMALL.K,
                              None)[0].reshape(4, 2)
    return img, truth


@pytest.mark.parametrize("in_plane", [90, 270])
def test_small_tag_found_in_the_official_corner_order(in_plane):
    # 16 px: aruco alone reads it in 1 of 10 such images (docs/hardware.md, "Small tags");
    # read from its rejected quad or upsampled, with every corner where it belongs.
    img, truth = _small_scene(16, in_plane, in_plane)
    det = tags.find_tag(img, TAG_ID)
    assert np.abs(det.corners - truth).max() < 1.0, (det.how, det.corners - truth)
    assert 14 < det.side_px < 18
    tp = measure_tag(img, SMALL, TAG, TAG_ID)
    assert tp.ambiguous, "a 16 px tag's tilt is not determined; it must say so"


def test_too_small_tag_says_so():
    img, _ = _small_scene(9, 30, 0)
    with pytest.raises(TagNotFoundError, match=r"tag too small \(\d+ px\)"):
        measure_tag(img, SMALL, TAG, TAG_ID)


def _two_tags(intr=PLAIN):
    a = render_tag(intr, FACING @ rot([0, 1, 0], 30), np.array([-0.06, 0, 0.3]), TAG, tag_id=3,
                   blur_sigma=0.8, noise_std=3.0)
    b = render_tag(intr, FACING @ rot([1, 0, 0], -25), np.array([0.06, 0.01, 0.3]), TAG,
                   tag_id=TAG_ID, blur_sigma=0.8, noise_std=3.0)
    img = a.copy()
    img[:, intr.width // 2:] = b[:, intr.width // 2:]
    return img


def test_cli_tag_pose_list_family_and_tag_image(tmp_path, capsys):
    intr_file = tmp_path / "intr.json"
    intr_file.write_text(json.dumps(PLAIN.to_dict()))
    cv2.imwrite(str(tmp_path / "two.png"), _two_tags())
    base = ["tag-pose", "--image", str(tmp_path / "two.png"), "--intrinsics", str(intr_file),
            "--tag-size", str(TAG)]
    assert main([*base, "--list", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert [t["tag_id"] for t in out["tags"]] == [3, TAG_ID]
    assert np.allclose([t["p_cam_tag"][0] for t in out["tags"]], [-0.06, 0.06], atol=1e-3)
    assert all(not t["ambiguous"] and 70 < t["size_px"] < 85 for t in out["tags"])
    assert main([*base, "--list"]) == 0
    text = capsys.readouterr().out
    assert "2 tag36h11 tag(s) seen" in text and "tag 3 (tag36h11" in text
    # Another family: a tag25h9 is not a tag36h11.
    img = render_tag(PLAIN, FACING, np.array([0.0, 0.0, 0.3]), TAG, tag_id=5, family="tag25h9",
                     blur_sigma=0.8, noise_std=3.0)
    cv2.imwrite(str(tmp_path / "t25.png"), img)
    base[2] = str(tmp_path / "t25.png")
    assert main([*base, "--tag-id", "5", "--family", "25h9", "--json"]) == 0
    assert np.linalg.norm(np.asarray(json.loads(capsys.readouterr().out)["p_cam_tag"])
                          - [0, 0, 0.3]) < TOL["tag_p"]
    assert main([*base, "--tag-id", "5"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no tag36h11 tag seen" in err[0], err
    assert main([*base, "--family", "tag99h1"]) == 2
    assert main([*base, "--tag-id", "600"]) == 2
    assert "ids are 0-586" in capsys.readouterr().err
    # tag-image writes the official image; aruco + corner_order find its top-left corner.
    out_png = tmp_path / "tag.png"
    assert main(["tag-image", "--id", str(TAG_ID), "--cell-px", "8", "--out", str(out_png)]) == 0
    written = cv2.imread(str(out_png), cv2.IMREAD_GRAYSCALE)
    np.testing.assert_array_equal(written, tag_image("tag36h11", TAG_ID, cell_px=8))
    det = tags.find_tag(cv2.copyMakeBorder(written, 8, 8, 8, 8, cv2.BORDER_CONSTANT, value=255),
                        TAG_ID)
    assert np.abs(det.corners[0] - [15.5, 15.5]).max() < 1.0, det.corners
    assert main(["tag-image", "--id", "1", "--out", str(out_png)]) == 2  # exists


def test_non_utf8_paths_and_bytes_end_in_one_line(tmp_path, capsys):
    # OpenCV 5.0.0 segfaults when handed a path that is not UTF-8; no path reaches it.
    d = os.fsencode(tmp_path)
    img_p, yaml_p = os.fsdecode(d + b"/tag\xff.png"), os.fsdecode(d + b"/cam\xfe.yaml")
    R, p = POSES["tilt_x_35"]
    ok, buf = cv2.imencode(".png", render_tag(DISTORTED, R, np.asarray(p), TAG, tag_id=TAG_ID,
                                              blur_sigma=0.8, noise_std=3.0))
    with open(os.fsencode(img_p), "wb") as f:
        f.write(buf.tobytes())
    _write_opencv_yaml(tmp_path / "cam.yaml", DISTORTED)
    os.rename(tmp_path / "cam.yaml", os.fsencode(yaml_p))
    args = ["tag-pose", "--image", img_p, "--intrinsics", yaml_p, "--tag-size", str(TAG),
            "--tag-id", str(TAG_ID), "--json"]
    assert main(args) == 0
    assert np.linalg.norm(np.asarray(json.loads(capsys.readouterr().out)["p_cam_tag"])
                          - p) < TOL["tag_p"]
    bad = {"--image": [(b"/missing\xff.png", None, "no such image"),
                       (b"/junk\xff.png", b"\x89PNG\xff\xfe", "not a readable image")],
           "--intrinsics": [(b"/latin1.json", b'{"fx": "\xe9"}', "not UTF-8"),
                            (b"/junk\xfd.yaml", b"%YAML:1.0\n[[[", "not valid OpenCV FileStorage"),
                            (b"/missing\xfc.yaml", None, "no such")]}
    for option, cases in bad.items():
        for name, data, words in cases:
            if data is not None:
                with open(d + name, "wb") as f:
                    f.write(data)
            a = list(args)
            a[a.index(option) + 1] = os.fsdecode(d + name)
            assert main(a) == 2, name
            err = capsys.readouterr().err.strip().splitlines()
            assert len(err) == 1 and "Traceback" not in err[0], err
            assert words in err[0], err
    # A manifest and a camera pose that are not UTF-8 text.
    (tmp_path / "m.csv").write_bytes(b"image,q1,q2,q3,q4\n\xff.png,0,0,0,0\n")
    with pytest.raises(FileFormatError, match="not UTF-8"):
        read_manifest(tmp_path / "m.csv")
    (tmp_path / "cp.json").write_bytes(b'{"R_base_cam": "\xff"}')
    with pytest.raises(CameraPoseError, match="not UTF-8"):
        load_camera_pose(tmp_path / "cp.json")


def test_principal_point_outside_the_image_is_refused():
    with pytest.raises(UsageError, match="principal point"):
        CameraIntrinsics(600.0, 600.0, 3000.0, 240.0, 640, 480)


# --- Photo-like images of official tags against ground truth ---------------------------

WIDE = CameraIntrinsics(450.0, 451.0, 324.0, 236.0, 640, 480, (-0.28, 0.11, 0.0008, -0.0006, -0.02))


@pytest.mark.parametrize("seed", [0, 1])
def test_photo_like_official_tag_pose_against_ground_truth(seed):
    # Real photographs of official tags could not be obtained here (docs/hardware.md); a
    # wide-angle lens, uneven light, vignetting, shot noise and JPEG on an official tag.
    rng = np.random.default_rng(seed)
    R = FACING @ rot([0, 0, 1], 150 * seed + 20) @ rot([1, 2 * seed - 1, 0], 35)
    p = np.array([0.08 - 0.16 * seed, 0.04, 0.3])
    img = photo_like(render_tag(WIDE, R, p, TAG, tag_id=TAG_ID, blur_sigma=1.0, noise_std=1.0,
                                black=30, white=200, background=90 + 60 * seed, rng=rng), rng)
    tp = measure_tag(img, WIDE, TAG, TAG_ID)
    assert np.linalg.norm(tp.p_cam_tag - p) < TOL["tag_p"], tp.p_cam_tag - p
    assert angle(tp.R_cam_tag, R) < 2 * TOL["tag_R"], np.rad2deg(angle(tp.R_cam_tag, R))
    assert not tp.ambiguous
