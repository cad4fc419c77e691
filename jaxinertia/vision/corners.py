"""Sub-pixel tag corners from the black square's edges (:func:`refine_corners_edges`)."""

from __future__ import annotations

import cv2
import numpy as np

from jaxinertia.errors import UsageError
from jaxinertia.vision.intrinsics import CameraIntrinsics

__all__ = ["gray", "refine_corners_edges"]


def gray(image: np.ndarray) -> np.ndarray:
    """``image`` as a grey (H, W) array (from grey, BGR or BGRA)."""
    image = np.asarray(image)
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.ndim == 3 and image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY)
    if image.ndim == 3 and image.shape[2] == 1:
        return image[..., 0]
    if image.ndim != 2:
        raise UsageError(f"expected a grey (H, W) or BGR (H, W, 3) image, got shape {image.shape}")
    return image


def refine_corners_edges(
    image: np.ndarray,
    corners: np.ndarray,
    intrinsics: CameraIntrinsics | None = None,
    *,
    iterations: int = 2,
) -> np.ndarray:
    """Corners (4, 2) [px] re-estimated as intersections of sub-pixel edge lines.

    Along each side of the black square, intensity profiles across the edge are sampled
    (bilinear); the edge point is where a profile crosses midway between its dark and
    light levels (unbiased for a symmetric blur of a straight step edge). A line is fitted
    (total least squares) through each side's points and adjacent lines are intersected.
    With ``intrinsics`` the edge points are undistorted first (straight edges only exist in
    the undistorted image) and the corners distorted back. Profiles stay within the tag's
    one-cell black border and the white margin, so the margin must be at least about half a
    cell wide (a printed tag36h11 has one full cell).

    Why: OpenCV's AprilTag refinement quantises corners to about half a pixel when the
    edges are aligned with the pixel grid (a tag seen face-on), which costs degrees of
    orientation; ``cornerSubPix`` is biased by a few tenths of a pixel towards the inside.
    """
    # A light symmetric blur does not move a straight edge but makes the bilinear profiles
    # nearly linear across it (on a perfectly sharp edge they are biased by up to 0.08 px).
    g = cv2.GaussianBlur(gray(image).astype(np.float32), (0, 0), 0.7)
    c = np.asarray(corners, np.float64).reshape(4, 2).copy()
    for _ in range(iterations):
        sides = np.linalg.norm(c - np.roll(c, -1, axis=0), axis=1)  # side i: corner i -> i+1
        side = float(np.mean(sides))
        lines = []
        centre = c.mean(axis=0)
        for i in range(4):
            a, b = c[i], c[(i + 1) % 4]
            # Across side i the black border is one cell of the adjacent sides (tag_size / 8,
            # foreshortened); profiles reach 0.6 of the narrower one each way.
            cell = min(sides[(i - 1) % 4], sides[(i + 1) % 4]) / 8.0
            half = float(np.clip(0.6 * cell, 1.0, 8.0))
            n_along = int(np.clip(sides[i], 8, 60))
            t = np.linspace(0.15, 0.85, n_along)
            s = np.arange(-half, half + 1e-9, 0.25)
            d = (b - a) / np.linalg.norm(b - a)
            nrm = np.array([-d[1], d[0]])
            if np.dot(nrm, 0.5 * (a + b) - centre) < 0:
                nrm = -nrm  # outward: dark (inside) -> light (outside)
            base = a[None, :] + t[:, None] * (b - a)[None, :]
            pts = base[:, None, :] + s[None, :, None] * nrm[None, None, :]
            prof = cv2.remap(g, pts[..., 0].astype(np.float32), pts[..., 1].astype(np.float32),
                             cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            lo = prof[:, : len(s) // 4 + 1].mean(axis=1)
            hi = prof[:, -(len(s) // 4 + 1):].mean(axis=1)
            edge_pts = []
            for k in range(n_along):
                if hi[k] - lo[k] < 20.0:  # too little contrast to locate an edge
                    continue
                f = prof[k] - 0.5 * (lo[k] + hi[k])
                idx = np.nonzero((f[:-1] < 0) & (f[1:] >= 0))[0]
                if idx.size == 0:
                    continue
                j = idx[np.argmin(np.abs(s[idx]))]  # the crossing nearest the guess
                off = s[j] - f[j] * (s[j + 1] - s[j]) / (f[j + 1] - f[j])
                edge_pts.append(base[k] + off * nrm)
            if len(edge_pts) < 4:
                return np.asarray(corners, np.float64).reshape(4, 2)
            e = np.asarray(edge_pts)
            if intrinsics is not None and intrinsics.dist.size:
                e = cv2.undistortPoints(e.reshape(-1, 1, 2), intrinsics.K, intrinsics.dist,
                                        P=intrinsics.K).reshape(-1, 2)
            m = e.mean(axis=0)
            _, _, vt = np.linalg.svd(e - m)
            lines.append((m, vt[0]))
        new = np.empty((4, 2))
        for i in range(4):
            (m0, d0), (m1, d1) = lines[(i - 1) % 4], lines[i]
            # corner i joins side i-1 (corner i-1 -> i) and side i (corner i -> i+1)
            ab = np.linalg.solve(np.column_stack([d0, -d1]), m1 - m0)
            new[i] = m0 + ab[0] * d0
        if intrinsics is not None and intrinsics.dist.size:
            xn = (new - [intrinsics.cx, intrinsics.cy]) / [intrinsics.fx, intrinsics.fy]
            obj = np.column_stack([xn, np.ones(4)])
            new = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), intrinsics.K,
                                    intrinsics.dist)[0].reshape(4, 2)
        if not np.all(np.isfinite(new)) or np.max(np.abs(new - c)) > 0.3 * side:
            return np.asarray(corners, np.float64).reshape(4, 2)
        c = new
    return c
