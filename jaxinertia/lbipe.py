"""Reading the authors' (ChirikjianLab/lbipe) data layout, with one clear error per defect.

Two directory layouts are accepted:

* the project's ``shared/lbipe``: ``data/``, ``weights/`` (``.npz`` and ``.pt``), ``golden/``;
* a checkout of the authors' repository: ``data/`` and ``dicts/*.pt``.

A test file ``data/data_test_<name>.npz`` is read by :func:`jaxinertia.samples.load_lbipe`
(the file format lives with the other sample readers); this module finds the files, the
released weights and the golden outputs. See shared/lbipe/README.md.
"""

from __future__ import annotations

import os
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from jaxinertia.errors import FileFormatError, WeightsError
from jaxinertia.estimation import ModelPair
from jaxinertia.features import LBIPE_FEATURES, FeatureConfig
from jaxinertia.networks import load_released_pair, stack_params
from jaxinertia.samples import SampleFile, Samples, checked_array, load_lbipe, read_npz

__all__ = [
    "GET_IT",
    "LbipeLayout",
    "default_lbipe_dir",
    "find_layout",
    "golden_path",
    "load_golden",
    "load_released_models",
    "load_test_files",
    "read_released_pairs",
    "read_test_files",
]

GET_IT = (
    "get it from the public repository ChirikjianLab/lbipe (data/ and dicts/) and point "
    "JAXINERTIA_LBIPE_DIR (or `lbipe_dir`) at it, or place the project's shared/lbipe beside "
    "the repository"
)


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
    """Recognises either layout; raises :class:`FileFormatError` saying what is missing."""
    root = Path(root)
    if not root.is_dir():
        raise FileFormatError(root, None, f"no such directory; {GET_IT}")
    data = root / "data"
    tests = {
        p.stem[len("data_test_"):]: p for p in sorted(data.glob("data_test_*.npz"))
    } if data.is_dir() else {}
    if not tests:
        raise FileFormatError(data, None, "no data_test_<name>.npz files")
    if (root / "weights").is_dir():
        weights, prefer = root / "weights", "npz"
    elif (root / "dicts").is_dir():
        weights, prefer = root / "dicts", "pt"
    else:
        raise FileFormatError(root, None, "neither weights/ nor dicts/ found")
    golden = root / "golden"
    return LbipeLayout(root, tests, weights, golden if golden.is_dir() else None, prefer)


def load_test_files(layout: LbipeLayout) -> list[Samples]:
    """Every ``data/data_test_<name>.npz`` of the layout, read and validated."""
    return [f.samples for f in read_test_files(layout)]


def read_test_files(layout: LbipeLayout) -> list[SampleFile]:
    """Every ``data/data_test_<name>.npz`` of the layout, each read once, as records with
    their path and SHA-256 (what training on them records)."""
    out = []
    for name, p in layout.test_files.items():
        digest: dict = {}
        samples = load_lbipe(p, name, missing_hint=GET_IT, digest=digest)
        out.append(SampleFile(Path(p), samples, {"format": "lbipe", "objects": [name],
                                                 "source": "lbipe", **digest}))
    return out


def golden_path(layout: LbipeLayout, name: str) -> Path | None:
    """``golden/golden_<name>.npz`` of the layout, when it exists."""
    if layout.golden_dir is None:
        return None
    path = layout.golden_dir / f"golden_{name}.npz"
    return path if path.exists() else None


#: Model pairs the authors released.
N_RELEASED = 10


def read_released_pairs(weights_dir: str | os.PathLike, *, prefer: str = "npz",
                        n_models: int = N_RELEASED) -> list[tuple]:
    """The authors' released model pairs one by one (``weights/*.npz`` or
    ``dicts/*.pt``), each read and checked: a missing, torn or corrupt file, or a pair of
    another architecture, is a :class:`WeightsError` naming it. Tenths of a second: a
    run that uses them late can read them first and stop before its long work."""
    pairs = [_released_pair(weights_dir, k, prefer) for k in range(1, n_models + 1)]
    tm, am = pairs[0][0], pairs[0][2]
    for k, p in enumerate(pairs, start=1):
        if p[0] != tm or p[2] != am:
            raise WeightsError(f"{weights_dir}: model pair {k} has another architecture")
    return pairs


def load_released_models(weights_dir: str | os.PathLike, *, prefer: str = "npz",
                         n_models: int = N_RELEASED,
                         features: FeatureConfig = LBIPE_FEATURES,
                         pairs: list[tuple] | None = None) -> ModelPair:
    """The authors' released model pairs (``weights/*.npz`` or ``dicts/*.pt``), stacked;
    ``pairs``: as :func:`read_released_pairs` gave them, when already read."""
    if pairs is None:
        pairs = read_released_pairs(weights_dir, prefer=prefer, n_models=n_models)
    tm, am = pairs[0][0], pairs[0][2]
    return ModelPair(
        torque_vars=stack_params([p[1] for p in pairs]),
        attention_vars=stack_params([p[3] for p in pairs]),
        tau_scale=jnp.asarray(features.tau_scale, jnp.float32),
        torque_model=tm,
        attention_model=am,
    )


def _released_pair(weights_dir, k: int, prefer: str):
    """Pair ``k``; a torn weight file (a zip cut short or corrupted: numpy's reader lets
    zipfile's and zlib's errors through) is a :class:`WeightsError` naming the pair."""
    try:
        return load_released_pair(weights_dir, k, prefer=prefer)
    except (zipfile.BadZipFile, EOFError, zlib.error) as e:
        raise WeightsError(f"{weights_dir}: model pair {k} (dict_torque_{k}, dict_attn_{k}): "
                           f"unreadable weights, torn or corrupt ({type(e).__name__}: "
                           f"{e})") from None


def load_golden(path: str | os.PathLike, n_samples: int | None = None) -> dict[str, np.ndarray]:
    """Reads ``golden_<name>.npz``: features, tau_model, weights, sets (validated)."""
    path = Path(path)
    d = read_npz(path)
    out = {"sets": checked_array(d, path, "sets", (None, None)).astype(np.int64)}
    if not np.issubdtype(d["sets"].dtype, np.integer):
        raise FileFormatError(path, "sets", f"dtype {d['sets'].dtype} is not integer")
    if n_samples is not None and (out["sets"].min() < 0 or out["sets"].max() >= n_samples):
        raise FileFormatError(path, "sets", f"indices outside [0, {n_samples})")
    for k, shape in (("features", (None, None)), ("tau_model", (None, None, None)),
                     ("weights", (None, None, None))):
        if k in d:
            out[k] = checked_array(d, path, k, shape)
    return out
