"""Files for the camera code, read by Python and handed to OpenCV as bytes.

OpenCV's Python binding crashes the interpreter (a segmentation fault, OpenCV 5.0.0) when
given a path that is not valid UTF-8 (on Linux a file name may hold any bytes; Python
carries them as surrogate escapes). No path is therefore passed to OpenCV: images are
decoded from their bytes (``cv2.imdecode``) and FileStorage YAML/XML is parsed from memory.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from jaxinertia.errors import FileFormatError

__all__ = ["read_image", "read_text", "shown"]


def shown(path: str | os.PathLike) -> str:
    """``path`` printable on any stream: undecodable bytes as ``\\xNN``."""
    return os.fsencode(path).decode("utf-8", "backslashreplace")


def read_text(path: str | os.PathLike, error=FileFormatError, what: str = "file") -> str:
    """The UTF-8 text of ``path``; ``error(path, None, message)`` when it cannot be read."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise error(shown(path), None, f"no such {what}") from None
    except OSError as e:
        raise error(shown(path), None, f"cannot read the {what} ({e.strerror or e})") from None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise error(shown(path), None, f"not UTF-8 text (byte {e.start})") from None


def read_image(path: str | os.PathLike, *, grey: bool = True) -> np.ndarray:
    """The image at ``path`` (grey uint8 by default), decoded from its bytes.

    Raises:
      FileFormatError: missing, unreadable or not an image OpenCV can decode.
    """
    path = Path(path)
    try:
        data = np.fromfile(os.fsencode(path), dtype=np.uint8)
    except FileNotFoundError:
        raise FileFormatError(shown(path), None, "no such image") from None
    except OSError as e:
        raise FileFormatError(shown(path), None,
                              f"cannot read the image ({e.strerror or e})") from None
    img = None
    if data.size:
        img = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE if grey else cv2.IMREAD_COLOR)
    if img is None:
        raise FileFormatError(shown(path), None, "not a readable image")
    return img
