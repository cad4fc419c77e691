"""AprilTag detection (OpenCV aruco, AprilTag families) in the official tag frame.

Corners are reported in the official order: top-left, top-right, bottom-right,
bottom-left of the tag as the AprilTag library draws it (its tag images, read upright),
which is the order of :func:`jaxinertia.vision.pose.tag_object_points`. OpenCV's aruco
holds every AprilTag code turned 180 degrees against those images (OpenCV 5.0.0), so its
corner 0 lands elsewhere; :func:`corner_order` finds out where, once per process and
family, by detecting an image drawn from the AprilTag library's own codes, and every
detection is re-indexed accordingly (or fails loudly, should no consistent order exist).

Small tags: aruco's bit reading fails on tags under about 20 px even when it found the
quad. Its rejected quads are therefore read again here (:func:`_decode_quad`: the cells
sampled at their centres against the tag's own black border and white margin, then the
nearest code within a few bits, as the AprilTag library does), and an image where no tag is
found at all is searched again upsampled twice.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np

from jaxinertia.errors import CameraError, TagNotFoundError, UsageError
from jaxinertia.vision.corners import gray as _gray
from jaxinertia.vision.corners import refine_corners_edges
from jaxinertia.vision.families import _OFFICIAL_CODES as _REFERENCE
from jaxinertia.vision.families import (
    DEFAULT_FAMILY,
    TagFamily,
    get_family,
    tag_cells,
    tag_image,
)
from jaxinertia.vision.intrinsics import CameraIntrinsics
from jaxinertia.vision.pose import PoseSolution, TagPose, solve_tag_pose, tag_object_points

__all__ = [
    "DEFAULT_FAMILY",
    "PoseSolution",
    "TagDetection",
    "TagDetector",
    "TagNotFoundError",
    "TagPose",
    "corner_order",
    "detect_tags",
    "find_tag",
    "make_detector",
    "no_tag_message",
    "measure_tag",
    "refine_corners_edges",
    "solve_tag_pose",
    "tag_object_points",
]

#: Bits a quad's reading may differ from its code and still be taken (by family; tag16h5's
#: distance of 5 leaves no room for a guess).
_MAX_HAMMING = {"tag16h5": -1, "tag25h9": 1, "tag36h10": 2, "tag36h11": 2}
_MIN_CONTRAST = 20.0  # grey levels between a tag's white margin and black border


@dataclass(frozen=True)
class TagDetection:
    """One decoded tag: ``corners`` (4, 2) [px] in the official order (top-left,
    top-right, bottom-right, bottom-left of the upright tag image); ``how`` says which
    path found it (``aruco``, ``decoded``: a quad aruco rejected, read here; ``upsampled``)."""

    tag_id: int
    corners: np.ndarray
    family: str = DEFAULT_FAMILY
    how: str = "aruco"

    @property
    def side_px(self) -> float:
        """Mean edge length of the black square in the image [px]."""
        return _side(self.corners)


class TagDetector:
    """An aruco detector for one AprilTag family, with the official corner order, the
    rescue of small tags and, when nothing is found, a second search upsampled twice.

    Args:
      refine: aruco's corner refinement, ``"apriltag"`` (default: the AprilTag library's
        edge-line fit, in its pixel convention, moved here to OpenCV's), ``"subpix"``,
        ``"contour"`` or ``"none"``.
      family: ``tag36h11`` (default), ``tag36h10``, ``tag25h9`` or ``tag16h5``.
      rescue: read the quads aruco rejected (small tags); upsample: search again at twice
        the size when nothing is found.
    """

    def __init__(self, *, refine: str = "apriltag", family: str | TagFamily = DEFAULT_FAMILY,
                 rescue: bool = True, upsample: bool = True):
        methods = {"apriltag": cv2.aruco.CORNER_REFINE_APRILTAG,
                   "subpix": cv2.aruco.CORNER_REFINE_SUBPIX,
                   "contour": cv2.aruco.CORNER_REFINE_CONTOUR,
                   "none": cv2.aruco.CORNER_REFINE_NONE}
        if refine not in methods:
            raise UsageError(f"refine must be one of {sorted(methods)}, got {refine!r}")
        self.family = get_family(family)
        self.rescue, self.upsample = bool(rescue), bool(upsample)
        p = cv2.aruco.DetectorParameters()
        p.cornerRefinementMethod = methods[refine]
        if refine == "subpix":
            p.cornerRefinementWinSize = 5
            p.cornerRefinementMinAccuracy = 0.01
            p.cornerRefinementMaxIterations = 50
        # Quads down to a perimeter of 1 % of the image's larger side (default 3 %: a
        # 1920 px image would ignore tags under 14 px before reading them).
        p.minMarkerPerimeterRate = 0.01
        self.params = p
        # The AprilTag edge fit puts the centre of the top-left pixel at (0.5, 0.5);
        # OpenCV's projection and PnP at (0, 0). Left uncorrected, every corner is 0.5 px
        # off along x and y (about 0.35 mm for a 4 cm tag at 0.3 m).
        self._shift = 0.5 if refine == "apriltag" else 0.0
        self.aruco = cv2.aruco.ArucoDetector(self.family.opencv_dictionary(), p)
        #: Mean edges [px] of tag-like squares that could not be read in the last image.
        self.unread_sides: list[float] = []
        self._saw_quads = False

    def _once(self, g: np.ndarray, how: str, scale: float = 1.0) -> list[TagDetection]:
        corners, ids, rejected = self.aruco.detectMarkers(g)
        if how == "aruco":
            self._saw_quads = len(rejected) > 0
        k = corner_order(self.family)
        out = []
        if ids is not None:
            for c, i in zip(corners, ids.ravel()):
                c = np.asarray(c, np.float64).reshape(4, 2) - self._shift
                out.append(TagDetection(int(i), np.roll(c, -k, axis=0), self.family.name, how))
        if self.rescue and len(rejected):
            gf = g.astype(np.float32)
            for q in rejected:
                q = np.asarray(q, np.float64).reshape(4, 2)
                if any(cv2.pointPolygonTest(d.corners.astype(np.float32),
                                            tuple(map(float, q.mean(axis=0))), False) >= 0
                       for d in out):
                    continue
                hit = _decode_quad(gf, q, self.family)
                if hit is None:
                    continue
                if hit[0] is None:  # dark square in a light margin, unreadable
                    self.unread_sides.append(_side(q) / scale)
                else:
                    out.append(TagDetection(hit[0], hit[1], self.family.name,
                                            "decoded" if how == "aruco" else how))
        return out

    def detect(self, image: np.ndarray) -> list[TagDetection]:
        """All tags of the family in ``image`` (grey or BGR uint8), sorted by id."""
        g = _gray(image)
        self.unread_sides = []
        out = self._once(g, "aruco")
        # Upsampled only where aruco saw some square outline (not in a blank image).
        if not out and self.upsample and self._saw_quads and max(g.shape) <= 4096:
            up = cv2.resize(g, None, fx=2, fy=2, interpolation=cv2.INTER_CUBIC)
            # Pixel centres: upsampled u maps to (u + 0.5) / 2 - 0.5.
            out = [TagDetection(d.tag_id, (d.corners + 0.5) / 2 - 0.5, d.family, "upsampled")
                   for d in self._once(up, "upsampled", 2.0)]
        return sorted(out, key=lambda d: d.tag_id)


def make_detector(
    *, refine: str = "apriltag", family: str | TagFamily = DEFAULT_FAMILY, **kw
) -> TagDetector:
    """A :class:`TagDetector` (kept for the earlier name)."""
    return TagDetector(refine=refine, family=family, **kw)


@functools.lru_cache(maxsize=8)
def _codes_table(fam: TagFamily) -> np.ndarray:
    """(4, N, d*d) bool: each id's official data bits, turned 0-3 quarter turns."""
    grids = np.stack([tag_cells(fam, i)[1:-1, 1:-1] for i in range(fam.n_codes)])
    return np.stack([np.rot90(grids, k, axes=(1, 2)).reshape(fam.n_codes, -1)
                     for k in range(4)]).astype(bool)


def _decode_quad(g: np.ndarray, quad: np.ndarray, fam: TagFamily):
    """``(tag_id, corners in official order)`` read from a quad; ``(None, quad)`` for a
    dark square in a light margin that cannot be read; None for anything else."""
    q = np.asarray(quad, np.float64)
    area2 = np.sum(q[:, 0] * np.roll(q[:, 1], -1) - np.roll(q[:, 0], -1) * q[:, 1])
    if area2 <= 0:  # counter-clockwise on screen: mirror it to the canonical order
        q = q[[0, 3, 2, 1]]
    b = fam.black_cells
    H = cv2.getPerspectiveTransform(
        np.float32([[0, 0], [b, 0], [b, b], [0, b]]), q.astype(np.float32))
    ij = np.arange(-1, b + 1) + 0.5  # cell centres, the white margin ring included
    u, v = np.meshgrid(ij, ij)
    pts = cv2.perspectiveTransform(np.stack([u, v], -1).reshape(-1, 1, 2), H).reshape(-1, 2)
    h, w = g.shape
    if (pts.min() < 0) or pts[:, 0].max() > w - 1 or pts[:, 1].max() > h - 1:
        return None
    s = cv2.remap(g, pts[:, 0].reshape(b + 2, b + 2).astype(np.float32),
                  pts[:, 1].reshape(b + 2, b + 2).astype(np.float32), cv2.INTER_LINEAR)
    ring = np.ones((b + 2, b + 2), bool)
    ring[1:-1, 1:-1] = False
    border = np.zeros((b, b), bool)
    border[[0, -1], :] = border[:, [0, -1]] = True
    white, black = float(np.median(s[ring])), float(np.median(s[1:-1, 1:-1][border]))
    if white - black < _MIN_CONTRAST:
        return None
    cells = s[1:-1, 1:-1] > 0.5 * (white + black)
    if cells[border].sum() > 1:
        return (None, q) if cells[border].mean() < 0.25 else None
    bits = cells[1:-1, 1:-1].ravel()
    ham = np.count_nonzero(_codes_table(fam) != bits, axis=2)  # (4, N)
    k, tag_id = np.unravel_index(np.argmin(ham), ham.shape)
    if ham[k, tag_id] > _MAX_HAMMING[fam.name]:
        return None, q
    # The reading is the official grid turned k quarter turns counter-clockwise: the
    # official top-left is corner -k of the quad.
    return int(tag_id), np.roll(q, int(k), axis=0)


@functools.lru_cache(maxsize=8)
def corner_order(family: str | TagFamily = DEFAULT_FAMILY) -> int:
    """How far aruco's corner 0 is from the official top-left: aruco's corners rolled by
    ``-corner_order`` are in the official order (OpenCV 5.0.0: 2).

    Measured, once per process and family, on a tag drawn from one of the AprilTag
    library's own codes (not from OpenCV's dictionary).

    Raises:
      CameraError: aruco does not find the official tag, reads another id, or reports
        corners that no re-indexing puts in the official order (a mirrored tag).
    """
    fam = get_family(family)
    tag_id, code = next(iter(_REFERENCE[fam.name].items()))
    cell = 12
    img = tag_image(fam, tag_id, code=code, cell_px=cell, margin_cells=2)
    p = cv2.aruco.DetectorParameters()
    p.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_NONE
    corners, ids, _ = cv2.aruco.ArucoDetector(fam.opencv_dictionary(), p).detectMarkers(img)
    found = [] if ids is None else ids.ravel().tolist()
    if found != [tag_id]:
        raise CameraError(f"OpenCV {cv2.__version__} reads the official {fam.name} id {tag_id} "
                          f"as {found or 'nothing'}; the tag frame cannot be checked")
    lo, hi = 2 * cell - 0.5, (2 + fam.black_cells) * cell - 0.5
    official = np.array([[lo, lo], [hi, lo], [hi, hi], [lo, hi]])
    c = np.asarray(corners[0], np.float64).reshape(4, 2)
    dist = np.linalg.norm(c[:, None, :] - official[None, :, :], axis=2)
    nearest = dist.argmin(axis=1)  # aruco corner j lies at official corner nearest[j]
    k = int(nearest.tolist().index(0))
    if (not np.all(dist.min(axis=1) < cell)
            or not np.array_equal(nearest, (np.arange(4) - k) % 4)):
        raise CameraError(f"OpenCV {cv2.__version__}'s corners of the official {fam.name} tag "
                          "are in no rotation of the official order; the tag frame cannot be "
                          "made the official one")
    return k


def detect_tags(
    image: np.ndarray, detector: TagDetector | None = None
) -> list[TagDetection]:
    """All tags (default family tag36h11) in ``image`` (grey or BGR uint8), sorted by id."""
    return (detector or TagDetector()).detect(image)


def _side(quad) -> float:
    q = np.asarray(quad, np.float64).reshape(4, 2)
    return float(np.mean(np.linalg.norm(q - np.roll(q, -1, axis=0), axis=1)))


#: Below this edge [px] of the black square a tag36h11 is not read reliably (blur 0.8 px, noise
#: 3 grey levels; docs/hardware.md "Small tags").
MIN_READABLE_PX = 16


def no_tag_message(image: np.ndarray, detector: TagDetector) -> str:
    """``no tag36h11 tag seen`` and, when the detector found square outlines too small to
    read in ``image`` (its last), ``; tag too small (N px) ...``."""
    small = [s for s in detector.unread_sides if s < 2 * MIN_READABLE_PX]
    msg = f"no {detector.family.name} tag seen"
    if small:
        msg += (f"; tag too small ({max(small):.0f} px)? a square of that size was found but "
                f"not read (a tag needs about {MIN_READABLE_PX} px or more: move the camera "
                "closer or use a larger tag)")
    return msg


def find_tag(
    image: np.ndarray, tag_id: int, detector: TagDetector | None = None
) -> TagDetection:
    """The detection of ``tag_id``.

    Raises:
      TagNotFoundError: the tag is absent, or present more than once (ambiguous).
      UsageError: ``tag_id`` is not an id of the detector's family.
    """
    detector = detector or TagDetector()
    fam = detector.family
    if not 0 <= int(tag_id) < fam.n_codes:
        raise UsageError(f"{fam.name} ids are 0-{fam.n_codes - 1}, got {tag_id}")
    dets = detector.detect(image)
    hits = [d for d in dets if d.tag_id == tag_id]
    if not hits:
        seen = (f"tags seen: {[d.tag_id for d in dets]}" if dets
                else no_tag_message(image, detector))
        raise TagNotFoundError(f"{fam.name} id {tag_id} not found in the image ({seen})")
    if len(hits) > 1:
        raise TagNotFoundError(f"{fam.name} id {tag_id} seen {len(hits)} times; tag ids must "
                               "be unique in the view")
    return hits[0]


def measure_tag(
    image: np.ndarray,
    intrinsics: CameraIntrinsics,
    tag_size: float,
    tag_id: int,
    *,
    detector: TagDetector | None = None,
    edge_refine: bool = True,
) -> TagPose:
    """Detects tag ``tag_id`` and returns its pose in the camera frame.

    The pipeline: detection (:class:`TagDetector`), sub-pixel edge-line corners
    (:func:`refine_corners_edges`, when ``edge_refine``), IPPE square PnP and LM polishing
    (:func:`jaxinertia.vision.pose.solve_tag_pose`).

    Raises:
      TagNotFoundError: the tag is not in the image.
    """
    det = find_tag(image, tag_id, detector)
    corners = refine_corners_edges(image, det.corners, intrinsics) if edge_refine else det.corners
    return solve_tag_pose(corners, intrinsics, tag_size)
