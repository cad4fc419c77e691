"""Samples: the one record of what the arm measured at rest, with readers and writers.

A :class:`Samples` holds S samples of N joints, taken while holding one or more objects:
per-sample leaves with leading axis S, ``object_id`` (S,) indexing ``names`` and, when the
objects are known, their ``x = [m, m p_tag]`` (O, 4) and the true joint torques ``tau``.
Unknown ground truth is ``None``, never a NaN stand-in. SI units throughout.

Two file layouts, both read by :func:`load_samples` (it tells them apart by content):

* native (``.npz``): one named array per field (leading axis S), ``object_id``, ``x`` (O, 4)
  when known, and ``metadata``: a JSON string with the object names, the robot, the
  simulator parameters or the collection, seeds, scenario and the package version.
  Floating arrays are stored float64.
* the authors' lbipe layout (``data_<split>_<object>.npz``, one object per file):
  ``joint_data`` (S, 9, N) rows q_d, q, q_d - q, 0, current torque, direction, tau, tau_g,
  agreement flag; ``A`` (S*N, 4); ``x`` (4,); ``tau`` (S*N,) = tau - tau_g.

Every sample file reaches the library through this module's readers, so the validation
(one error naming the file and the field) is written once; the record itself is
:mod:`jaxinertia.sample_record` (re-exported here).
"""

from __future__ import annotations

import hashlib
import io
import json
import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

from jaxinertia.errors import FileFormatError, UsageError
from jaxinertia.fileio import replacing
from jaxinertia.sample_record import Samples
from jaxinertia.sample_record import check_names as _check_names

__all__ = [
    "FORMAT_VERSION",
    "SampleFile",
    "Samples",
    "checked_array",
    "lbipe_name",
    "load_lbipe",
    "load_native",
    "load_samples",
    "lbipe_arrays",
    "read_npz",
    "read_sample_file",
    "save_lbipe",
    "save_native",
    "write_sample_file",
]

FORMAT_VERSION = 1


#: Rows of the authors' ``joint_data``.
ROW_Q_D, ROW_Q, ROW_QE, ROW_CURRENT_TAU, ROW_DIRECTION, ROW_TAU, ROW_TAU_G = 0, 1, 2, 4, 5, 6, 7


def read_npz(path: str | os.PathLike, *, missing_hint: str = "",
             digest: dict | None = None) -> dict[str, np.ndarray]:
    """Every array of an ``.npz`` file, the file read once; a missing or unreadable file is
    a :class:`FileFormatError` naming it. ``digest``: receives the SHA-256 of the bytes
    read (``digest["sha256"]``), so that a caller recording the file needs no second read."""
    path = Path(path)
    if not path.exists():
        raise FileFormatError(path, None, "no such file" + (f"; {missing_hint}"
                                                            if missing_hint else ""))
    try:
        raw = path.read_bytes()
        if digest is not None:
            digest["sha256"] = hashlib.sha256(raw).hexdigest()
        if not raw.startswith(b"PK"):  # numpy would take it for a pickle and say so
            raise FileFormatError(path, None, "not an .npz file (not a zip archive of arrays): "
                                  "a sample file of jaxinertia simulate or collect, or the "
                                  "authors' data_test_<name>.npz, is needed")
        with np.load(io.BytesIO(raw), allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except FileFormatError:
        raise
    except Exception as e:  # zipfile/format errors all mean "unreadable"
        raise FileFormatError(path, None, f"not a readable .npz file ({e})") from e




def save_native(path: str | os.PathLike, samples: Samples, metadata: dict) -> Path:
    """Writes a native sample file atomically (a temporary file, then a rename); the
    object names go into ``metadata["objects"]`` and must be distinct."""
    _write_native(Path(path), samples, metadata)
    return Path(path)


def _write_native(path: Path, samples: Samples, metadata: dict) -> bytes:
    """The file's bytes, written atomically."""
    _check_names(samples.names, path)
    meta = {"format": "jaxinertia-samples", "format_version": FORMAT_VERSION, **metadata,
            "objects": list(samples.names)}
    fields = {k: (v.astype(np.float64) if np.issubdtype(v.dtype, np.floating) else v)
              for k, v in samples.fields().items()}
    buf = io.BytesIO()
    np.savez_compressed(buf, metadata=np.asarray(json.dumps(meta)), **fields)
    raw = buf.getvalue()
    with replacing(path, suffix=".npz") as tmp:
        tmp.write_bytes(raw)
    return raw


def write_sample_file(path: str | os.PathLike, samples: Samples, metadata: dict, *,
                      only_at_rest: bool = True) -> SampleFile:
    """:func:`save_native`, returning the file as :func:`read_sample_file` would read it
    (the same bytes parsed in memory, their SHA-256): whoever made a file need not read it
    back."""
    path = Path(path)
    raw = _write_native(path, samples, metadata)
    with np.load(io.BytesIO(raw), allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    back, meta = _native(path, arrays, need_truth=samples.known, only_at_rest=only_at_rest)
    return SampleFile(path, back, {**meta, "sha256": hashlib.sha256(raw).hexdigest()})


def load_native(path: str | os.PathLike, *, need_truth: bool = True,
                only_at_rest: bool = True) -> tuple[Samples, dict]:
    """A native sample file and its metadata.

    Samples flagged ``at_rest = False`` (timed out) are dropped unless ``only_at_rest`` is
    False (the continuous run, read without waiting for rest).
    """
    return _native(Path(path), read_npz(path), need_truth=need_truth,
                   only_at_rest=only_at_rest)


def _native(path: Path, fields: dict, *, need_truth: bool,
            only_at_rest: bool) -> tuple[Samples, dict]:
    if "metadata" not in fields:
        raise FileFormatError(path, "metadata", "missing: not a jaxinertia sample file")
    try:
        meta = json.loads(str(fields.pop("metadata")))
    except ValueError as e:
        raise FileFormatError(path, "metadata", f"not JSON ({e})") from e
    names = meta.get("objects") if isinstance(meta, dict) else None
    if not isinstance(meta, dict) or not (names is None or (
            isinstance(names, list) and all(isinstance(n, str) for n in names))):
        raise FileFormatError(path, "metadata", "must be a JSON object whose 'objects' is a "
                              "list of names")
    samples = Samples.from_fields(fields, names, path=path, need_truth=need_truth)
    return (samples.at_rest_only() if only_at_rest else samples), meta


def checked_array(d: dict, path: Path, key: str, shape: tuple) -> np.ndarray:
    """``d[key]``, checked: present, of ``shape`` (None: any size), numeric and finite."""
    if key not in d:
        raise FileFormatError(path, key, f"missing (has {sorted(d)})")
    a = d[key]
    if a.ndim != len(shape) or any(s is not None and s != t for s, t in zip(shape, a.shape)):
        want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
        raise FileFormatError(path, key, f"shape {a.shape}, expected {want}")
    if not np.issubdtype(a.dtype, np.number):
        raise FileFormatError(path, key, f"dtype {a.dtype} is not numeric")
    if not np.all(np.isfinite(a)):
        bad = np.argwhere(~np.isfinite(a))[0]
        raise FileFormatError(path, key, f"non-finite value at index {tuple(bad)}")
    return a


def lbipe_name(path: str | os.PathLike) -> str:
    """``cube`` for ``data_test_cube.npz`` (or ``data_train_cube.npz``)."""
    stem = Path(path).stem
    for prefix in ("data_test_", "data_train_"):
        if stem.startswith(prefix):
            return stem[len(prefix):]
    return stem


def _from_lbipe(d: dict, path: Path, name: str | None) -> Samples:
    jd = checked_array(d, path, "joint_data", (None, 9, None)).astype(np.float64)
    s, _, n = jd.shape
    A = checked_array(d, path, "A", (s * n, 4)).astype(np.float64)
    x = checked_array(d, path, "x", (4,)).astype(np.float64)
    checked_array(d, path, "tau", (s * n,))
    # A mass of 0 is the empty gripper (the authors' data_train_0g.npz), with no COM.
    if x[0] < 0 or (x[0] == 0 and np.any(x[1:] != 0)):
        raise FileFormatError(path, "x", f"mass x[0] = {x[0]} must be positive (or 0 with "
                              f"x[1:] = 0: the empty gripper), got x = {x.tolist()}")
    direction = jd[:, ROW_DIRECTION]
    if not np.all(np.abs(direction) == 1):
        bad = np.argwhere(np.abs(direction) != 1)[0]
        raise FileFormatError(
            path, "joint_data", f"row {ROW_DIRECTION} (direction) must be +1/-1, sample "
            f"{bad[0]} joint {bad[1]} is {direction[tuple(bad)]}")
    return Samples(q_d=jd[:, ROW_Q_D], q=jd[:, ROW_Q], direction=direction,
                   current_tau=jd[:, ROW_CURRENT_TAU], tau_g=jd[:, ROW_TAU_G],
                   A=A.reshape(s, n, 4), object_id=np.zeros(s, np.int64), x=x[None],
                   tau=jd[:, ROW_TAU], names=(name or lbipe_name(path),))


def load_lbipe(path: str | os.PathLike, name: str | None = None, *,
               missing_hint: str = "", digest: dict | None = None) -> Samples:
    """One object's file of the authors' layout (``data_test_<name>.npz`` or
    ``data_train_<name>.npz``), validated; the object is called ``name`` (default: from
    the file name). ``digest``: receives the SHA-256 of the bytes read."""
    path = Path(path)
    return _from_lbipe(read_npz(path, missing_hint=missing_hint, digest=digest), path, name)


class SampleFile(NamedTuple):
    """A sample file as read once: where it was, its samples and its metadata (with the
    SHA-256 of the bytes read): what a command hands down instead of reading it again."""

    path: Path
    samples: Samples
    meta: dict


def read_sample_file(path: str | os.PathLike, **kw) -> SampleFile:
    """:func:`load_samples` as a :class:`SampleFile` (``kw``: its options)."""
    samples, meta = load_samples(path, **kw)
    return SampleFile(Path(path), samples, meta)


def load_samples(path: str | os.PathLike, *, need_truth: bool = True,
                 only_at_rest: bool = True) -> tuple[Samples, dict]:
    """A sample file of either layout, read once, and its metadata (for the authors'
    layout: ``{"format": "lbipe", "objects": [name]}``), with the SHA-256 of the bytes read
    under ``"sha256"``."""
    path = Path(path)
    digest: dict = {}
    fields = read_npz(path, digest=digest)
    if "metadata" in fields:
        samples, meta = _native(path, fields, need_truth=need_truth, only_at_rest=only_at_rest)
        return samples, {**meta, **digest}
    if "joint_data" in fields:
        s = _from_lbipe(fields, path, None)
        return s, {"format": "lbipe", "objects": list(s.names), "source": "lbipe", **digest}
    raise FileFormatError(path, "metadata", "missing: neither a jaxinertia sample file nor "
                          "the authors' layout (joint_data, A, x)")


def lbipe_arrays(samples: Samples) -> dict[str, np.ndarray]:
    """The authors' arrays for one known object's samples."""
    if not samples.known:
        raise UsageError("the authors' layout needs known objects (x and tau)")
    q_d, q = samples.q_d, samples.q
    S, N = q.shape
    qe = q_d - q
    rows = [q_d, q, qe, np.zeros_like(q), samples.current_tau, samples.direction,
            samples.tau, samples.tau_g, (samples.direction == np.sign(qe)).astype(float)]
    return {
        "joint_data": np.stack(rows, axis=1).astype(np.float64),
        "A": np.asarray(samples.A, np.float64).reshape(S * N, 4),
        "x": np.asarray(samples.x[0], np.float64),
        "tau": (np.asarray(samples.tau) - np.asarray(samples.tau_g)).reshape(S * N)
        .astype(np.float64),
    }


def save_lbipe(directory: str | os.PathLike, split: str, samples: Samples) -> list[Path]:
    """One ``data_<split>_<object>.npz`` per object of ``samples`` (names distinct: a
    repeated one would replace the other's file)."""
    _check_names(samples.names, directory)
    out = []
    for part in samples.by_object():
        path = Path(directory) / f"data_{split}_{part.name}.npz"
        with replacing(path, suffix=".npz") as tmp:
            np.savez(tmp, **lbipe_arrays(part))
        out.append(path)
    return out
