"""Reading the authors' (ChirikjianLab/lbipe) data layout, with one clear error per defect.

Two directory layouts are accepted:

* the project's ``shared/lbipe``: ``data/``, ``weights/`` (``.npz`` and ``.pt``), ``golden/``;
* a checkout of the authors' repository: ``data/`` and ``dicts/*.pt``.

A test file ``data/data_test_<name>.npz`` holds ``joint_data`` (S, 9, N) with rows
q_d, q, q_d - q, 0, current torque, direction, tau, tau_g, agreement flag; ``A`` (S*N, 4);
``x`` (4,) = [m, m*p_tag]; ``tau`` (S*N,) = tau - tau_g. See shared/lbipe/README.md.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = [
    "BOUNDING_BOX_DIAGONALS",
    "LbipeDataset",
    "LbipeFormatError",
    "LbipeLayout",
    "find_layout",
    "load_golden",
    "load_test_file",
    "default_lbipe_dir",
]

#: Diagonal of the smallest box enclosing each test object [m] (COM error normaliser).
BOUNDING_BOX_DIAGONALS = {
    "cube": 0.0692820,
    "red": 0.0665808,
    "white": 0.0755513,
    "black": 0.0851880,
}

#: Rows of ``joint_data``.
ROW_Q_D, ROW_Q, ROW_QE, ROW_CURRENT_TAU, ROW_DIRECTION, ROW_TAU, ROW_TAU_G = 0, 1, 2, 4, 5, 6, 7

GET_IT = (
    "get it from the public repository ChirikjianLab/lbipe (data/ and dicts/) and point "
    "JAXINERTIA_LBIPE_DIR (or --lbipe-dir) at it, or place the project's shared/lbipe beside "
    "the repository"
)


class LbipeFormatError(ValueError):
    """A file of the lbipe layout that is missing, unreadable or malformed."""

    def __init__(self, path, field: str | None, message: str):
        self.path, self.field = str(path), field
        where = f"{path}" + (f" [{field}]" if field else "")
        super().__init__(f"{where}: {message}")


def default_lbipe_dir() -> Path:
    """``$JAXINERTIA_LBIPE_DIR``, else ``../shared/lbipe`` beside the repository (or beside
    the working directory, for an installed, non-editable package)."""
    env = os.environ.get("JAXINERTIA_LBIPE_DIR")
    if env:
        return Path(env)
    repo = Path(__file__).resolve().parent.parent.parent / "shared" / "lbipe"
    cwd = Path.cwd().parent / "shared" / "lbipe"
    return repo if repo.is_dir() or not cwd.is_dir() else cwd


@dataclass(frozen=True)
class LbipeLayout:
    root: Path
    test_files: dict[str, Path]
    weights_dir: Path
    golden_dir: Path | None
    prefer: str  # "npz" or "pt"


def find_layout(root: str | os.PathLike) -> LbipeLayout:
    """Recognises either layout; raises :class:`LbipeFormatError` saying what is missing."""
    root = Path(root)
    if not root.is_dir():
        raise LbipeFormatError(root, None, f"no such directory; {GET_IT}")
    data = root / "data"
    tests = {
        p.stem[len("data_test_"):]: p for p in sorted(data.glob("data_test_*.npz"))
    } if data.is_dir() else {}
    if not tests:
        raise LbipeFormatError(data, None, "no data_test_<name>.npz files")
    if (root / "weights").is_dir():
        weights, prefer = root / "weights", "npz"
    elif (root / "dicts").is_dir():
        weights, prefer = root / "dicts", "pt"
    else:
        raise LbipeFormatError(root, None, "neither weights/ nor dicts/ found")
    golden = root / "golden"
    return LbipeLayout(root, tests, weights, golden if golden.is_dir() else None, prefer)


@dataclass(frozen=True)
class LbipeDataset:
    """One object's real samples, split into named SI arrays (S samples, N joints)."""

    name: str
    q_d: np.ndarray  # (S, N) goal [rad]
    q: np.ndarray  # (S, N) present position [rad]
    current_tau: np.ndarray  # (S, N) torque from present current [N m]
    direction: np.ndarray  # (S, N) +1 / -1
    tau: np.ndarray  # (S, N) ground-truth joint torque [N m]
    tau_g: np.ndarray  # (S, N) free-motion torque [N m]
    A: np.ndarray  # (S, N, 4) load regressor
    x: np.ndarray  # (4,) [m, m p_tag] [kg, kg m]

    @property
    def n_samples(self) -> int:
        return self.q.shape[0]

    @property
    def n_joints(self) -> int:
        return self.q.shape[1]

    @property
    def mass(self) -> float:
        return float(self.x[0])

    @property
    def com(self) -> np.ndarray:
        return self.x[1:] / self.x[0]


def _open_npz(path: Path) -> dict[str, np.ndarray]:
    if not path.exists():
        raise LbipeFormatError(path, None, f"no such file; {GET_IT}")
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except Exception as e:  # zipfile/pickle/format errors all mean "unreadable"
        raise LbipeFormatError(path, None, f"not a readable .npz file ({e})") from e


def _field(d: dict, path: Path, key: str, shape: tuple, *, finite: bool = True) -> np.ndarray:
    if key not in d:
        raise LbipeFormatError(path, key, f"missing (has {sorted(d)})")
    a = d[key]
    if a.ndim != len(shape) or any(s is not None and s != t for s, t in zip(shape, a.shape)):
        want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
        raise LbipeFormatError(path, key, f"shape {a.shape}, expected {want}")
    if not np.issubdtype(a.dtype, np.number):
        raise LbipeFormatError(path, key, f"dtype {a.dtype} is not numeric")
    if finite and not np.all(np.isfinite(a)):
        bad = np.argwhere(~np.isfinite(a))[0]
        raise LbipeFormatError(path, key, f"non-finite value at index {tuple(bad)}")
    return a


def load_test_file(path: str | os.PathLike, name: str | None = None) -> LbipeDataset:
    """Reads and validates one ``data_test_<name>.npz``."""
    path = Path(path)
    d = _open_npz(path)
    jd = _field(d, path, "joint_data", (None, 9, None)).astype(np.float64)
    s, _, n = jd.shape
    A = _field(d, path, "A", (s * n, 4)).astype(np.float64)
    x = _field(d, path, "x", (4,)).astype(np.float64)
    _field(d, path, "tau", (s * n,))
    if x[0] <= 0:
        raise LbipeFormatError(path, "x", f"mass x[0] = {x[0]} must be positive")
    direction = jd[:, ROW_DIRECTION]
    if not np.all(np.abs(direction) == 1):
        bad = np.argwhere(np.abs(direction) != 1)[0]
        raise LbipeFormatError(
            path, "joint_data", f"row {ROW_DIRECTION} (direction) must be +1/-1, sample "
            f"{bad[0]} joint {bad[1]} is {direction[tuple(bad)]}"
        )
    return LbipeDataset(
        name=name or path.stem.removeprefix("data_test_"),
        q_d=jd[:, ROW_Q_D],
        q=jd[:, ROW_Q],
        current_tau=jd[:, ROW_CURRENT_TAU],
        direction=direction,
        tau=jd[:, ROW_TAU],
        tau_g=jd[:, ROW_TAU_G],
        A=A.reshape(s, n, 4),
        x=x,
    )


def load_golden(path: str | os.PathLike, n_samples: int | None = None) -> dict[str, np.ndarray]:
    """Reads ``golden_<name>.npz``: features, tau_model, weights, sets (validated)."""
    path = Path(path)
    d = _open_npz(path)
    out = {"sets": _field(d, path, "sets", (None, None)).astype(np.int64)}
    if not np.issubdtype(d["sets"].dtype, np.integer):
        raise LbipeFormatError(path, "sets", f"dtype {d['sets'].dtype} is not integer")
    if n_samples is not None and (out["sets"].min() < 0 or out["sets"].max() >= n_samples):
        raise LbipeFormatError(path, "sets", f"indices outside [0, {n_samples})")
    for k, shape in (("features", (None, None)), ("tau_model", (None, None, None)),
                     ("weights", (None, None, None))):
        if k in d:
            out[k] = _field(d, path, k, shape)
    return out
