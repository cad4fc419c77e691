"""Sample files: the project's native format and the authors' lbipe layout.

Native (``.npz``): one named array per field of :class:`jaxinertia.sim.sampling.Samples`
(leading axis S), plus ``object_id`` (S,) indexing ``metadata["objects"]``, ``x`` (O, 4)
per object, and ``metadata``: a JSON string with the robot, simulator parameters (and
``simulator.precision``, the arithmetic simulated in), seeds, scenario and the package
version. SI units throughout; floating arrays are float64 whatever the precision.

lbipe (``data_<split>_<object>.npz``, the authors' layout, one file per object):
``joint_data`` (S, 9, N) rows q_d, q, q_d - q, 0, current torque, direction, tau, tau_g,
agreement flag; ``A`` (S*N, 4); ``x`` (4,); ``tau`` (S*N,) = tau - tau_g.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

__all__ = ["load_native", "load_samples", "save_lbipe", "save_native", "to_lbipe_arrays"]

FORMAT_VERSION = 1


def save_native(path: str | os.PathLike, fields: dict[str, np.ndarray], metadata: dict) -> Path:
    """Writes a native sample file atomically (a temporary file, then a rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = {"format": "jaxinertia-samples", "format_version": FORMAT_VERSION, **metadata}
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez_compressed(tmp, metadata=np.asarray(json.dumps(meta)),
                        **{k: np.asarray(v) for k, v in fields.items()})
    os.replace(tmp, path)
    return path


def load_native(path: str | os.PathLike) -> tuple[dict[str, np.ndarray], dict]:
    from jaxinertia.lbipe import LbipeFormatError

    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            fields = {k: z[k] for k in z.files}
    except Exception as e:
        raise LbipeFormatError(path, None, f"not a readable .npz file ({e})") from e
    if "metadata" not in fields:
        raise LbipeFormatError(path, "metadata", "missing: not a jaxinertia sample file")
    meta = json.loads(str(fields.pop("metadata")))
    return fields, meta


def to_lbipe_arrays(fields: dict[str, np.ndarray], x: np.ndarray) -> dict[str, np.ndarray]:
    """The authors' arrays for one object's samples."""
    q_d, q = fields["q_d"], fields["q"]
    S, N = q.shape
    qe = q_d - q
    rows = [q_d, q, qe, np.zeros_like(q), fields["current_tau"], fields["direction"],
            fields["tau"], fields["tau_g"], (fields["direction"] == np.sign(qe)).astype(float)]
    A = np.asarray(fields["A"]).reshape(S * N, 4)
    return {
        "joint_data": np.stack(rows, axis=1),
        "A": A,
        "x": np.asarray(x, np.float64),
        "tau": (np.asarray(fields["tau"]) - np.asarray(fields["tau_g"])).reshape(S * N),
    }


def save_lbipe(directory: str | os.PathLike, split: str, name: str, fields, x) -> Path:
    path = Path(directory) / f"data_{split}_{name}.npz"
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **to_lbipe_arrays(fields, x))
    return path


#: Fields every sample file needs for training and evaluation; ``tau`` only for known
#: objects (training, evaluation), not for estimation.
SAMPLE_FIELDS = ("q_d", "q", "direction", "current_tau", "tau_g", "A")


def load_samples(path: str | os.PathLike, *, need_tau: bool = True, only_at_rest: bool = True):
    """A native sample file as a :class:`jaxinertia.training.SampleSet` plus its metadata.

    Samples flagged ``at_rest = False`` (timed out) are dropped unless ``only_at_rest`` is
    False (the continuous run, read without waiting for rest). Missing or malformed
    fields raise :class:`jaxinertia.lbipe.LbipeFormatError` naming the file and field.
    """
    from jaxinertia.lbipe import LbipeFormatError
    from jaxinertia.training import SampleSet

    path = Path(path)
    fields, meta = load_native(path)
    need = SAMPLE_FIELDS + (("tau", "object_id", "x") if need_tau else ())
    missing = [k for k in need if k not in fields]
    if missing:
        raise LbipeFormatError(path, missing[0], f"missing (this file has "
                               f"{sorted(fields)}); needed: {list(need)}")
    q = np.asarray(fields["q"], np.float64)
    if q.ndim != 2:
        raise LbipeFormatError(path, "q", f"expected (S, N), got shape {q.shape}")
    S, N = q.shape
    shapes = {"q_d": (S, N), "direction": (S, N), "current_tau": (S, N), "tau_g": (S, N),
              "A": (S, N, 4), "tau": (S, N), "object_id": (S,)}
    for k, shape in shapes.items():
        if k in fields and np.shape(fields[k]) != shape:
            raise LbipeFormatError(path, k, f"expected shape {shape}, got "
                                   f"{np.shape(fields[k])}")
    for k in ("q_d", "q", "direction", "tau_g", "A"):
        if not np.all(np.isfinite(fields[k])):
            raise LbipeFormatError(path, k, "holds non-finite values")
    if not np.all(np.isin(fields["direction"], (-1, 1))):
        raise LbipeFormatError(path, "direction", "must be +1 or -1")
    keep = np.asarray(fields.get("at_rest", np.ones(S, bool)), bool) | (not only_at_rest)
    object_id = np.asarray(fields.get("object_id", np.zeros(S, int)), np.int64)
    x = np.asarray(fields.get("x", np.full((int(object_id.max()) + 1, 4), np.nan)), np.float64)
    if x.ndim != 2 or x.shape[1] != 4 or object_id.min() < 0 or object_id.max() >= len(x):
        raise LbipeFormatError(path, "x", f"shape {x.shape} does not cover object ids "
                               f"0..{object_id.max()}")
    tau = np.asarray(fields.get("tau", np.full((S, N), np.nan)), np.float64)
    data = SampleSet(
        q_d=np.asarray(fields["q_d"], np.float64), q=q,
        direction=np.asarray(fields["direction"], np.float64),
        current_tau=np.asarray(fields["current_tau"], np.float64), tau=tau,
        tau_g=np.asarray(fields["tau_g"], np.float64),
        A=np.asarray(fields["A"], np.float64), object_id=object_id, x=x,
    ).take(np.flatnonzero(keep))
    if need_tau and not np.all(np.isfinite(data.tau)):
        raise LbipeFormatError(path, "tau", "holds non-finite values (unknown objects cannot "
                               "be used for training or evaluation)")
    return data, meta
