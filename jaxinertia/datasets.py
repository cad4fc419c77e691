"""Sample files: the project's native format and the authors' lbipe layout.

Native (``.npz``): one named array per field of :class:`jaxinertia.sim.sampling.Samples`
(leading axis S), plus ``object_id`` (S,) indexing ``metadata["objects"]``, ``x`` (O, 4)
per object, and ``metadata``: a JSON string with the robot, simulator parameters, seeds,
scenario and the package version. SI units throughout.

lbipe (``data_<split>_<object>.npz``, the authors' layout, one file per object):
``joint_data`` (S, 9, N) rows q_d, q, q_d - q, 0, current torque, direction, tau, tau_g,
agreement flag; ``A`` (S*N, 4); ``x`` (4,); ``tau`` (S*N,) = tau - tau_g.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

__all__ = ["load_native", "save_lbipe", "save_native", "to_lbipe_arrays"]

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
