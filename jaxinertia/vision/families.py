"""AprilTag families as the AprilTag library draws them, and OpenCV's copy of their codes.

The official tag images (AprilRobotics/apriltag-imgs, and ``apriltag_to_image`` of the
AprilTag library) are drawn from each family's codes: bit ``i`` of an ``n``-bit code (the
most significant bit first) is a white cell when set, at column ``bit_x[i]`` and row
``bit_y[i]`` of the black square (row 0 at the top, as the image is read upright); the black
square has a one-cell black border and a one-cell white margin around it.

OpenCV's aruco holds the same families (``DICT_APRILTAG_16h5``, ``25h9``, ``36h10``,
``36h11``) as byte lists whose rotation-0 bit grid (what ``generateImageMarker`` draws) is,
in OpenCV 5.0.0, every official code turned 180 degrees. The tag frame of this project is
the official one, so nothing here trusts that: :func:`opencv_turn` finds the turn by
comparing OpenCV's bits with official codes copied from the AprilTag library
(:data:`_OFFICIAL_CODES`) and fails loudly if no turn matches; :func:`tag_cells` then gives
the official cell grid of any id. :func:`jaxinertia.vision.tags.corner_order` checks the
detector itself against an image drawn from the official codes.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np

from jaxinertia.errors import CameraError, UsageError

__all__ = [
    "DEFAULT_FAMILY",
    "FAMILIES",
    "TagFamily",
    "bit_layout",
    "get_family",
    "official_cells",
    "opencv_turn",
    "tag_cells",
    "tag_image",
]

DEFAULT_FAMILY = "tag36h11"

# A few codes of each family, from the AprilTag library (AprilRobotics/apriltag, files
# tag16h5.c, tag25h9.c, tag36h10.c, tag36h11.c; Copyright (C) 2013-2016, The Regents of
# The University of Michigan; BSD 2-clause licence). They are the independent reference
# that OpenCV's byte lists are checked against; every other id is drawn from OpenCV's
# bytes, turned as these codes show.
_OFFICIAL_CODES: dict[str, dict[int, int]] = {
    "tag16h5": {0: 0x27C8, 1: 0x31B6, 2: 0x3859, 29: 0xB57A},
    "tag25h9": {0: 0x156F1F4, 1: 0x1F28CD5, 2: 0x16CE32C, 34: 0xA64F8D},
    "tag36h10": {0: 0x1A42F9469, 1: 0x21A48C08D, 2: 0x26DFDBC5D, 3: 0x2D19B78FB},
    "tag36h11": {0: 0xD7E00984B, 1: 0xDDA664CA7, 2: 0xDC4A1C821, 7: 0x1106CBA43,
                 100: 0x533FE2404, 586: 0xE8B772FE0},
}

# The first quarter of each family's bit layout (bit_x, bit_y of bits 0 .. n/4 - 1 in the
# library's files); the library's layout is rotationally symmetric: each following quarter
# is the previous one turned 90 degrees clockwise, and an odd-sized grid ends with its
# centre cell.
_FIRST_QUARTER = {
    4: ((1, 1), (2, 1), (3, 1), (2, 2)),
    5: ((1, 1), (2, 1), (3, 1), (4, 1), (2, 2), (3, 2)),
    6: ((1, 1), (2, 1), (3, 1), (4, 1), (5, 1), (2, 2), (3, 2), (4, 2), (3, 3)),
}


@dataclass(frozen=True)
class TagFamily:
    """An AprilTag family: its name, OpenCV dictionary and data grid (``data_cells`` x
    ``data_cells`` bits inside a one-cell black border: ``data_cells + 2`` cells span the
    black square)."""

    name: str
    dictionary: int
    data_cells: int

    @property
    def black_cells(self) -> int:
        """Cells across the black square (what ``--tag-size`` measures)."""
        return self.data_cells + 2

    @property
    def n_codes(self) -> int:
        return int(_dictionary(self.dictionary).bytesList.shape[0])

    def opencv_dictionary(self) -> cv2.aruco.Dictionary:
        return _dictionary(self.dictionary)


FAMILIES: dict[str, TagFamily] = {
    "tag16h5": TagFamily("tag16h5", cv2.aruco.DICT_APRILTAG_16h5, 4),
    "tag25h9": TagFamily("tag25h9", cv2.aruco.DICT_APRILTAG_25h9, 5),
    "tag36h10": TagFamily("tag36h10", cv2.aruco.DICT_APRILTAG_36h10, 6),
    "tag36h11": TagFamily("tag36h11", cv2.aruco.DICT_APRILTAG_36h11, 6),
}


def get_family(family: str | TagFamily) -> TagFamily:
    """The family named ``family`` (``tag36h11``; ``36h11`` also accepted)."""
    if isinstance(family, TagFamily):
        return family
    name = str(family).lower()
    name = name if name.startswith("tag") else "tag" + name
    if name not in FAMILIES:
        raise UsageError(f"unknown tag family {family!r}; OpenCV's aruco has "
                         f"{', '.join(FAMILIES)}")
    return FAMILIES[name]


@functools.lru_cache(maxsize=8)
def _dictionary(dictionary: int) -> cv2.aruco.Dictionary:
    return cv2.aruco.getPredefinedDictionary(dictionary)


def bit_layout(family: str | TagFamily) -> list[tuple[int, int]]:
    """``(bit_x, bit_y)`` of each code bit, most significant first, in cells of the black
    square (0 and ``black_cells - 1`` are its black border)."""
    d = get_family(family).data_cells
    quarter = list(_FIRST_QUARTER[d])
    out = list(quarter)
    for _ in range(3):
        quarter = [(d + 1 - y, x) for x, y in quarter]  # 90 degrees clockwise
        out += quarter
    if d % 2:
        out.append(((d + 1) // 2, (d + 1) // 2))
    return out


def official_cells(family: str | TagFamily, code: int) -> np.ndarray:
    """(black_cells, black_cells) uint8 grid, 1 = white, of ``code`` drawn as the AprilTag
    library draws it (row 0 at the top of the upright tag)."""
    fam = get_family(family)
    n = fam.data_cells ** 2
    g = np.zeros((fam.black_cells, fam.black_cells), np.uint8)
    for i, (x, y) in enumerate(bit_layout(fam)):
        g[y, x] = (int(code) >> (n - 1 - i)) & 1
    return g


def _opencv_bits(fam: TagFamily, tag_id: int) -> np.ndarray:
    d = fam.opencv_dictionary()
    return cv2.aruco.Dictionary.getBitsFromByteList(d.bytesList[tag_id:tag_id + 1],
                                                     fam.data_cells).astype(np.uint8)


@functools.lru_cache(maxsize=8)
def opencv_turn(family: str | TagFamily) -> int:
    """``k`` such that ``np.rot90(opencv_bits, k)`` is the official grid of every reference
    code (OpenCV 5.0.0: 2, a half turn).

    Raises:
      CameraError: no single turn matches every reference code (OpenCV's dictionary is not
        the official family in any rotation).
    """
    fam = get_family(family)
    turns = set(range(4))
    for tag_id, code in _OFFICIAL_CODES[fam.name].items():
        ref = official_cells(fam, code)[1:-1, 1:-1]
        bits = _opencv_bits(fam, tag_id)
        turns &= {k for k in range(4) if np.array_equal(np.rot90(bits, k), ref)}
    if len(turns) != 1:
        raise CameraError(f"OpenCV {cv2.__version__}'s {fam.name} dictionary does not hold the "
                          "AprilTag library's codes in one rotation; the tag frame cannot be "
                          "made the official one")
    return turns.pop()


def tag_cells(family: str | TagFamily, tag_id: int) -> np.ndarray:
    """The official (black_cells, black_cells) grid of ``tag_id``, 1 = white."""
    fam = get_family(family)
    if not 0 <= int(tag_id) < fam.n_codes:
        raise UsageError(f"{fam.name} ids are 0-{fam.n_codes - 1}, got {tag_id}")
    g = np.zeros((fam.black_cells, fam.black_cells), np.uint8)
    g[1:-1, 1:-1] = np.rot90(_opencv_bits(fam, int(tag_id)), opencv_turn(fam))
    return g


def tag_image(
    family: str | TagFamily, tag_id: int, *, cell_px: int = 1, margin_cells: float = 1.0,
    code: int | None = None,
) -> np.ndarray:
    """The official tag image (uint8, 0 black, 255 white): the black square with its white
    margin of ``margin_cells`` cells, each cell ``cell_px`` pixels (``cell_px=1``,
    ``margin_cells=1`` is the AprilTag library's own image). ``code`` draws an official code
    directly (bypassing OpenCV's dictionary)."""
    fam = get_family(family)
    g = official_cells(fam, code) if code is not None else tag_cells(fam, tag_id)
    img = np.kron(g * 255, np.ones((int(cell_px), int(cell_px)), np.uint8)).astype(np.uint8)
    pad = int(round(margin_cells * cell_px))
    return cv2.copyMakeBorder(img, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=255)
