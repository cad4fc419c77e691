"""Pinhole camera intrinsics: the data type and its file formats.

Two formats are read:

* JSON (the project's own, written by :func:`save_intrinsics`)::

      {"width": 1280, "height": 720,
       "fx": 910.2, "fy": 909.8, "cx": 641.3, "cy": 362.0,
       "distortion": [k1, k2, p1, p2, k3]}

  ``distortion`` follows OpenCV's order (4, 5, 8, 12 or 14 coefficients; may be
  omitted or empty for an undistorted camera). Pixel coordinates are OpenCV's: the
  centre of the top-left pixel is (0, 0).
* OpenCV FileStorage YAML/XML as written by OpenCV's calibration samples
  (``camera_matrix``, ``distortion_coefficients``, ``image_width``, ``image_height``).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from jaxinertia.errors import ConfigError, UsageError
from jaxinertia.fileio import write_text
from jaxinertia.vision.files import read_text, shown

__all__ = [
    "CameraIntrinsics",
    "IntrinsicsError",
    "load_intrinsics",
    "save_intrinsics",
]

_N_DIST = (0, 4, 5, 8, 12, 14)  # the distortion vector lengths OpenCV accepts


class IntrinsicsError(ConfigError):
    """An intrinsics file is missing, unreadable or describes an impossible camera
    (``IntrinsicsError(path, field, message)``; exit code 2)."""


@dataclass(frozen=True)
class CameraIntrinsics:
    """A pinhole camera with OpenCV's lens distortion model. Impossible values raise
    :class:`jaxinertia.errors.UsageError` (a file of them, :class:`IntrinsicsError`).

    Attributes:
      fx, fy: focal lengths [px]; cx, cy: principal point [px], within the image.
      width, height: image size [px] the intrinsics belong to.
      distortion: (K,) OpenCV distortion coefficients, K in {0, 4, 5, 8, 12, 14}.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    distortion: tuple[float, ...] = field(default=())

    def __post_init__(self):
        vals = (self.fx, self.fy, self.cx, self.cy, *self.distortion)
        if not all(math.isfinite(v) for v in vals):
            raise UsageError(f"intrinsics must be finite numbers, got {self}")
        if not (self.fx > 0 and self.fy > 0):
            raise UsageError(f"focal lengths must be positive, got fx={self.fx}, "
                             f"fy={self.fy}")
        if not (self.width > 0 and self.height > 0):
            raise UsageError(f"image size must be positive, got {self.width}x{self.height}")
        # A principal point off the image (intrinsics of another resolution, or cx/cy
        # swapped) gives confident wrong poses: 2670 mm for a tag at 10 mm was seen.
        if not (0.0 <= self.cx <= self.width and 0.0 <= self.cy <= self.height):
            raise UsageError(f"principal point ({self.cx:g}, {self.cy:g}) px is outside the "
                             f"{self.width}x{self.height} image (intrinsics of another "
                             "resolution?)")
        if len(self.distortion) not in _N_DIST:
            raise UsageError(f"{len(self.distortion)} distortion coefficients; OpenCV "
                             f"accepts {', '.join(map(str, _N_DIST[1:]))} (or none)")

    @property
    def K(self) -> np.ndarray:
        """(3, 3) camera matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist(self) -> np.ndarray:
        """(K,) distortion coefficients as float64 (empty: none)."""
        return np.asarray(self.distortion, dtype=np.float64)

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) [px]."""
        return self.width, self.height

    def check_size(self, image: np.ndarray, what: str = "image") -> None:
        """Raises :class:`jaxinertia.errors.UsageError` unless ``image`` (H, W[, C]) has
        the size these intrinsics belong to."""
        if (image.shape[1], image.shape[0]) != self.size:
            raise UsageError(f"{what} is {image.shape[1]}x{image.shape[0]} px; the intrinsics "
                             f"are for {self.width}x{self.height}")

    def to_dict(self) -> dict:
        return {"width": self.width, "height": self.height, "fx": self.fx, "fy": self.fy,
                "cx": self.cx, "cy": self.cy, "distortion": list(self.distortion)}

    @classmethod
    def from_matrix(cls, K: np.ndarray, dist, width: int, height: int) -> CameraIntrinsics:
        """From a (3, 3) camera matrix (zero skew) and distortion coefficients."""
        K = np.asarray(K, dtype=np.float64)
        if K.shape != (3, 3):
            raise UsageError(f"camera matrix must be 3x3, got shape {K.shape}")
        if abs(K[0, 1]) > 1e-9 * abs(K[0, 0]) or not np.allclose(K[2], [0, 0, 1]):
            raise UsageError(f"camera matrix must be [[fx,0,cx],[0,fy,cy],[0,0,1]], got {K}")
        d = np.asarray(dist if dist is not None else [], dtype=np.float64).ravel()
        return cls(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]),
                   int(width), int(height), tuple(float(x) for x in d))


def _from_json(path: Path) -> CameraIntrinsics:
    where = shown(path)
    text = read_text(path, IntrinsicsError, "intrinsics file")
    try:
        d = json.loads(text)
    except json.JSONDecodeError as e:
        raise IntrinsicsError(where, None, f"not valid JSON ({e})") from e
    if not isinstance(d, dict):
        raise IntrinsicsError(where, None, "expected a JSON object with fx, fy, cx, cy, width, "
                              "height, distortion")
    missing = [k for k in ("fx", "fy", "cx", "cy", "width", "height") if k not in d]
    if missing:
        raise IntrinsicsError(where, None, f"missing {', '.join(missing)} (expected fx, fy, "
                              "cx, cy [px], width, height [px], distortion [OpenCV order])")
    try:
        dist = tuple(float(x) for x in (d.get("distortion") or []))
        w, h = d["width"], d["height"]
        if int(w) != w or int(h) != h:
            raise ValueError("width and height must be integers")
        return CameraIntrinsics(float(d["fx"]), float(d["fy"]), float(d["cx"]), float(d["cy"]),
                                int(w), int(h), dist)
    except UsageError as e:
        raise IntrinsicsError(where, None, str(e)) from e
    except (TypeError, ValueError) as e:
        raise IntrinsicsError(where, None, f"bad value ({e})") from e


def _from_filestorage(path: Path) -> CameraIntrinsics:
    where = shown(path)
    # Parsed from memory: OpenCV crashes on a path that is not UTF-8 (vision.files).
    text = read_text(path, IntrinsicsError, "intrinsics file")
    xml = path.suffix.lower() == ".xml"
    fmt = cv2.FileStorage_FORMAT_XML if xml else cv2.FileStorage_FORMAT_YAML
    try:
        fs = cv2.FileStorage(text, cv2.FileStorage_READ | cv2.FileStorage_MEMORY | fmt)
    except (cv2.error, SystemError) as e:  # the binding raises SystemError on a bad YAML
        why = getattr(e, "err", None) or getattr(e.__cause__, "err", None) or "malformed"
        raise IntrinsicsError(where, None, f"not valid OpenCV FileStorage YAML/XML "
                              f"(OpenCV: {why})") from None
    try:
        if not fs.isOpened():
            raise IntrinsicsError(where, None, "OpenCV cannot open it as FileStorage YAML/XML")
        K = fs.getNode("camera_matrix").mat()
        dist = fs.getNode("distortion_coefficients").mat()
        w, h = fs.getNode("image_width"), fs.getNode("image_height")
        if K is None or w.empty() or h.empty():
            raise IntrinsicsError(where, None, "needs camera_matrix, image_width, image_height "
                                  "(and distortion_coefficients)")
        try:
            return CameraIntrinsics.from_matrix(K, dist, int(w.real()), int(h.real()))
        except UsageError as e:
            raise IntrinsicsError(where, None, str(e)) from e
    finally:
        fs.release()


def load_intrinsics(path: str | os.PathLike) -> CameraIntrinsics:
    """Reads intrinsics from JSON (``.json``) or OpenCV FileStorage (``.yaml``/``.yml``/``.xml``).

    Raises:
      IntrinsicsError: the file is missing, unparsable or inconsistent.
    """
    path = Path(path)
    if not path.is_file():
        raise IntrinsicsError(shown(path), None, "no such intrinsics file")
    suffix = path.suffix.lower()
    if suffix == ".json":
        return _from_json(path)
    if suffix in (".yaml", ".yml", ".xml"):
        return _from_filestorage(path)
    raise IntrinsicsError(shown(path), None, f"unknown intrinsics format {suffix!r} (use .json, or "
                          "OpenCV .yaml/.yml/.xml)")


def save_intrinsics(path: str | os.PathLike, intrinsics: CameraIntrinsics) -> Path:
    """Writes the JSON format that :func:`load_intrinsics` reads."""
    path = Path(path)
    write_text(path, json.dumps(intrinsics.to_dict(), indent=2) + "\n")
    return path
