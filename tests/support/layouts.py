"""A small copy of the real lbipe layout for the pipeline tests (fold, end to end)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from jaxinertia.samples import lbipe_arrays, load_lbipe

__all__ = ["N_REAL", "small_layout"]

#: Real samples kept per object: what the pipeline tests check does not depend on how many.
N_REAL = 120


def small_layout(lbipe_dir: Path, root: Path, n: int = N_REAL) -> Path:
    """``root`` holding the real cube and white files cut to their first ``n`` samples, and
    the released weights (no golden sets: they index the full files)."""
    (root / "data").mkdir(parents=True)
    for name in ("cube", "white"):
        full = load_lbipe(lbipe_dir / "data" / f"data_test_{name}.npz")
        np.savez(root / "data" / f"data_test_{name}.npz",
                 **lbipe_arrays(full.take(np.arange(n))))
    (root / "weights").symlink_to(lbipe_dir / "weights")
    return root
