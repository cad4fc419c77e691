"""The measurements behind docs/hardware.md's "Small tags" and "photo-like" tables.

``python -m jaxinertia.vision.benchmark small --n 20`` counts, per black-square edge, the
images of a tag36h11 found by aruco as it was (default parameters, AprilTag corner
refinement), by :class:`jaxinertia.vision.tags.TagDetector` and, when the
``pupil_apriltags`` package is importable (not a dependency), by the AprilTag 3 library.
``python -m jaxinertia.vision.benchmark photo --n 30`` measures pose errors on photo-like
images (:func:`jaxinertia.vision.synthetic.photo_like`) against their ground truth. Both
print one line per row; nothing here depends on timing. (pupil-apriltags 1.0.4 may crash
with a segmentation fault when its detector is freed, after the last row is printed.)
"""

from __future__ import annotations

import argparse

import cv2
import numpy as np

from jaxinertia.vision.families import get_family
from jaxinertia.vision.intrinsics import CameraIntrinsics
from jaxinertia.vision.pose import rotation_angle
from jaxinertia.vision.synthetic import photo_like, render_tag
from jaxinertia.vision.tags import TagDetector, find_tag, measure_tag

__all__ = ["photo_errors", "small_tag_counts"]

_FACING = np.diag([1.0, -1.0, -1.0])
_TAG, _ID = 0.04, 7


def _rot(axis, deg: float) -> np.ndarray:
    a = np.asarray(axis, float)
    return cv2.Rodrigues(a / np.linalg.norm(a) * np.deg2rad(deg))[0]


def _pose(rng, z: float, max_tilt: float, spread=(0.3, 0.25)):
    R = (_FACING @ _rot([0, 0, 1], rng.uniform(0, 360))
         @ _rot(np.r_[rng.normal(size=2), 0.0], rng.uniform(0, max_tilt)))
    p = np.array([rng.uniform(-spread[0], spread[0]) * z,
                  rng.uniform(-spread[1], spread[1]) * z, z])
    return R, p


def small_tag_counts(sizes, n: int = 20, *, blur: float = 0.8, noise: float = 3.0,
                     seed: int = 0, report=None) -> dict[str, dict[int, int]]:
    """Images (of ``n`` per size) where tag36h11 id 7 is found, by detector and edge [px];
    ``report(side, {detector: count})`` is called after each size."""
    intr = CameraIntrinsics(600.0, 600.0, 319.5, 239.5, 640, 480)
    p = cv2.aruco.DetectorParameters()
    p.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_APRILTAG
    before = cv2.aruco.ArucoDetector(get_family("tag36h11").opencv_dictionary(), p)
    def aruco_alone(im) -> bool:
        ids = before.detectMarkers(im)[1]
        return ids is not None and _ID in ids.ravel()

    finders = {"before": aruco_alone,
               "now": lambda im: any(d.tag_id == _ID for d in TagDetector().detect(im))}
    try:
        import pupil_apriltags

        at3 = pupil_apriltags.Detector(families="tag36h11", quad_decimate=1.0, refine_edges=1)
        finders["apriltag3"] = lambda im: any(d.tag_id == _ID for d in at3.detect(im))
    except ImportError:
        pass
    counts = {k: {} for k in finders}
    for side in sizes:
        rng = np.random.default_rng([seed, int(side)])
        images = []
        for _ in range(n):
            z = intr.fx * _TAG / side
            R, pos = _pose(rng, z, 40.0)
            images.append(render_tag(intr, R, pos, _TAG, tag_id=_ID, blur_sigma=blur,
                                     noise_std=noise, rng=rng))
        for k, found in finders.items():
            counts[k][int(side)] = int(sum(bool(found(im)) for im in images))
        if report is not None:
            report(int(side), {k: counts[k][int(side)] for k in counts})
    return counts


def photo_errors(n: int = 30, *, seed: int = 1) -> np.ndarray:
    """(n, 4): edge [px], tilt [deg], position error [mm], orientation error [deg] of
    photo-like images through a wide-angle lens (1280x720; NaN errors: not found)."""
    intr = CameraIntrinsics(900.0, 902.0, 648.0, 355.0, 1280, 720,
                            (-0.28, 0.11, 0.0008, -0.0006, -0.02))
    rng = np.random.default_rng(seed)
    rows = []
    for _ in range(n):
        z, tilt = rng.uniform(0.3, 0.6), rng.uniform(0, 50)
        R = (_FACING @ _rot([0, 0, 1], rng.uniform(0, 360))
             @ _rot(np.r_[rng.normal(size=2), 0.0], tilt))
        pos = np.array([rng.uniform(-0.35, 0.35) * z, rng.uniform(-0.2, 0.2) * z, z])
        img = render_tag(intr, R, pos, _TAG, tag_id=_ID, blur_sigma=rng.uniform(0.6, 1.2),
                         noise_std=1.0, black=30, white=200,
                         background=rng.uniform(60, 180), rng=rng)
        img = photo_like(img, rng)
        try:
            side = find_tag(img, _ID).side_px
            tp = measure_tag(img, intr, _TAG, _ID)
            rows.append((side, tilt, np.linalg.norm(tp.p_cam_tag - pos) * 1e3,
                         np.rad2deg(rotation_angle(tp.R_cam_tag, R))))
        except LookupError:
            rows.append((np.nan, tilt, np.nan, np.nan))
    return np.asarray(rows)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="python -m jaxinertia.vision.benchmark")
    ap.add_argument("what", choices=["small", "photo"])
    ap.add_argument("--n", type=int, default=20)
    ap.add_argument("--sizes", default="12,13,14,15,16,18,20,22,24")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    if args.what == "small":
        sizes = [int(s) for s in args.sizes.split(",")]
        print(f"tag36h11 found, of {args.n} images per edge of the black square:", flush=True)
        small_tag_counts(sizes, args.n, seed=args.seed, report=lambda side, row: print(
            f"{side:3d} px: " + ", ".join(f"{k} {v}" for k, v in row.items()), flush=True))
    else:
        r = photo_errors(args.n, seed=args.seed)
        ok = r[np.isfinite(r[:, 2])]
        print(f"{len(ok)} of {len(r)} found; edges {np.nanmin(r[:, 0]):.0f}-"
              f"{np.nanmax(r[:, 0]):.0f} px; position error median {np.median(ok[:, 2]):.2f} "
              f"mm, 90 % {np.percentile(ok[:, 2], 90):.2f}, max {ok[:, 2].max():.2f}; "
              f"orientation error median {np.median(ok[:, 3]):.2f} deg, max {ok[:, 3].max():.2f}")


if __name__ == "__main__":
    main()
