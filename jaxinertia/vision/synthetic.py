"""Synthetic camera images of a tag at a known pose (tests, demos, a virtual camera).

Honest pinhole geometry, independent of the detector: the official tag image (drawn from
the family's code bits as the AprilTag library draws it,
:func:`jaxinertia.vision.families.tag_image`, plus its white border) is a texture on the
tag plane;
the homography from that texture to the image is fixed by projecting four tag-plane
points with ``cv2.projectPoints`` (the pinhole model; exact for a plane). Rendering is
supersampled and area-averaged (pixels integrate light), lens distortion is applied by
resampling through ``cv2.undistortPoints``, then optical blur and sensor noise.
"""

from __future__ import annotations

import functools

import cv2
import numpy as np

from jaxinertia.errors import UsageError
from jaxinertia.vision.families import DEFAULT_FAMILY, get_family, tag_image
from jaxinertia.vision.intrinsics import CameraIntrinsics

__all__ = ["look_at", "photo_like", "render_tag"]

def look_at(p_cam: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, 0.0, 1.0)) -> np.ndarray:
    """R (3, 3) of an OpenCV camera (z forward, y down) at ``p_cam`` looking at ``target``;
    ``up`` is a direction that should point up in the image."""
    z = np.asarray(target, float) - np.asarray(p_cam, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, float))
    if np.linalg.norm(x) < 1e-9:
        raise UsageError("up is parallel to the viewing direction")
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], axis=1)


@functools.lru_cache(maxsize=4)
def _distortion_map(intrinsics: CameraIntrinsics) -> tuple[np.ndarray, np.ndarray]:
    # Each distorted pixel samples the ideal image where its ray would land without
    # distortion: undistortPoints inverts OpenCV's model (iteratively).
    w, h = intrinsics.width, intrinsics.height
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pts = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
    und = cv2.undistortPoints(
        pts, intrinsics.K, intrinsics.dist, R=None, P=intrinsics.K,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-9)).reshape(h, w, 2)
    return und[..., 0].astype(np.float32), und[..., 1].astype(np.float32)


def render_tag(
    intrinsics: CameraIntrinsics,
    R_cam_tag: np.ndarray,
    p_cam_tag: np.ndarray,
    tag_size: float,
    *,
    tag_id: int = 0,
    family: str = DEFAULT_FAMILY,
    marker: np.ndarray | None = None,
    border_cells: float = 1.0,
    black: float = 25.0,
    white: float = 225.0,
    background: float = 120.0,
    blur_sigma: float = 0.0,
    noise_std: float = 0.0,
    supersample: int = 4,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """A grey uint8 image (height, width) of tag ``tag_id`` seen at the given pose.

    Args:
      R_cam_tag: (3, 3), p_cam_tag: (3,) [m] tag pose in the camera frame (tag frame as in
        :mod:`jaxinertia.vision.tags`).
      tag_size: edge of the black square [m].
      family: the tag family; marker: a black square image to use instead of the official
        one (e.g. ``cv2.aruco.generateImageMarker``'s, without its white margin).
      border_cells: white margin around the black square, in cells.
      blur_sigma: Gaussian optical blur [px]; noise_std: additive Gaussian noise [grey levels].
    """
    s = int(supersample)
    cell_px = 32
    cells = get_family(family).black_cells
    if marker is None:
        marker = tag_image(family, tag_id, cell_px=cell_px, margin_cells=0)
    marker = cv2.resize(np.asarray(marker, np.uint8), (cells * cell_px,) * 2,
                        interpolation=cv2.INTER_NEAREST)
    pad = int(round(border_cells * cell_px))
    tex = cv2.copyMakeBorder(marker, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=255)
    tex = (black + (white - black) * (tex.astype(np.float32) / 255.0)).astype(np.float32)
    n = tex.shape[0]
    # Texture pixel centres are integers (OpenCV's convention); texture coordinate u maps
    # to tag x = (u - c) * m and v to tag y = -(v - c) * m, c the texture's centre.
    m = tag_size / (cells * cell_px)
    c = (n - 1) / 2.0
    uv = np.array([[-0.5, -0.5], [n - 0.5, -0.5], [n - 0.5, n - 0.5], [-0.5, n - 0.5]])
    xyz = np.column_stack([(uv[:, 0] - c) * m, -(uv[:, 1] - c) * m, np.zeros(4)])
    if np.any((R_cam_tag @ xyz.T).T[:, 2] + p_cam_tag[2] <= 1e-3):
        raise UsageError("the tag is (partly) behind the camera")
    # Supersampled ideal (undistorted) image: pixel centre u maps to s*u + (s-1)/2.
    K_hi = intrinsics.K.copy()
    K_hi[:2] *= s
    K_hi[0, 2] += (s - 1) / 2.0
    K_hi[1, 2] += (s - 1) / 2.0
    img_pts, _ = cv2.projectPoints(xyz, cv2.Rodrigues(np.asarray(R_cam_tag, float))[0],
                                   np.asarray(p_cam_tag, float), K_hi, None)
    H = cv2.getPerspectiveTransform(uv.astype(np.float32), img_pts.reshape(4, 2).astype(np.float32))
    w, h = intrinsics.width, intrinsics.height
    ideal = cv2.warpPerspective(tex, H, (w * s, h * s), flags=cv2.INTER_LINEAR,
                                borderMode=cv2.BORDER_CONSTANT, borderValue=background)
    ideal = cv2.resize(ideal, (w, h), interpolation=cv2.INTER_AREA)
    if np.any(intrinsics.dist != 0):
        map_u, map_v = _distortion_map(intrinsics)
        ideal = cv2.remap(ideal, map_u, map_v, cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=background)
    if blur_sigma > 0:
        ideal = cv2.GaussianBlur(ideal, (0, 0), blur_sigma)
    if noise_std > 0:
        rng = rng if rng is not None else np.random.default_rng(0)
        ideal = ideal + rng.normal(0.0, noise_std, ideal.shape).astype(np.float32)
    return np.clip(np.rint(ideal), 0, 255).astype(np.uint8)


def photo_like(
    image: np.ndarray,
    rng: np.random.Generator,
    *,
    light: tuple[float, float] = (0.45, 1.0),
    vignette: float = 0.35,
    shot_noise: float = 0.6,
    jpeg_quality: int = 80,
) -> np.ndarray:
    """What a camera does to a rendered image beyond optics: light falling off across the
    scene (a linear ramp from ``light[0]`` to ``light[1]`` of full brightness in a random
    direction), vignetting (``1 - vignette * r^2`` of the normalised radius r), photon shot
    noise (standard deviation ``shot_noise * sqrt(level)`` grey levels) and JPEG
    compression at ``jpeg_quality``. Returns a grey uint8 image."""
    h, w = image.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    a = rng.uniform(0, 2 * np.pi)
    t = ((u - w / 2) * np.cos(a) + (v - h / 2) * np.sin(a)) / np.hypot(w, h) + 0.5
    gain = light[0] + (light[1] - light[0]) * np.clip(t, 0, 1)
    r2 = ((u - w / 2) ** 2 + (v - h / 2) ** 2) / ((w / 2) ** 2 + (h / 2) ** 2)
    img = image.astype(np.float32) * gain * (1.0 - vignette * r2)
    img += rng.normal(0.0, 1.0, img.shape).astype(np.float32) * shot_noise * np.sqrt(
        np.maximum(img, 0.0))
    img = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
    return cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
