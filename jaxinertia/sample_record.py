"""The :class:`Samples` record: what the arm measured at rest.

A :class:`Samples` holds S samples of N joints, taken while holding one or more objects:
per-sample leaves with leading axis S, ``object_id`` (S,) indexing ``names`` and, when the
objects are known, their ``x = [m, m p_tag]`` (O, 4) and the true joint torques ``tau``.
Unknown ground truth is ``None``, never a NaN stand-in. SI units throughout. Its files (the
native layout and the authors') are read and written by :mod:`jaxinertia.samples`, which
re-exports it.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np
from flax import struct

from jaxinertia.errors import FileFormatError, UsageError

__all__ = ["Samples", "check_names"]

#: Per-sample fields with a named place in the record; the rest of a file's per-sample
#: arrays (simulator diagnostics, collection timestamps) travel in ``Samples.extra``.
_REQUIRED = ("q_d", "q", "direction", "current_tau", "tau_g", "A")
_OPTIONAL = ("tau", "R_base_tag", "p_base_tag", "at_rest")


def check_names(names: Sequence[str], path) -> None:
    """A sample's object is its id; its name must say which one: names are distinct."""
    dup = sorted({n for n in names if list(names).count(n) > 1})
    if dup:
        ids = [i for i, n in enumerate(names) if n == dup[0]]
        raise FileFormatError(path, "metadata", f"object name {dup[0]!r} names objects "
                              f"{ids} (of {list(names)}): each object needs its own name "
                              "(e.g. unknown-1, unknown-2)")


@struct.dataclass
class Samples:
    """S samples of an N-joint arm holding one of O objects each (SI units)."""

    q_d: np.ndarray  # (S, N) commanded goal [rad]
    q: np.ndarray  # (S, N) present position [rad]
    direction: np.ndarray  # (S, N) approach direction, +1 / -1
    #: (S, N) torque from the present current, k_t * I [N m]; NaN on a joint whose servo
    #: senses no current (XL430-W250: Present Load only; the Sensor baseline then refuses)
    current_tau: np.ndarray
    tau_g: np.ndarray  # (S, N) load torque of the bare arm at q [N m]
    A: np.ndarray  # (S, N, 4) load regressor: tau - tau_g = A x
    object_id: np.ndarray  # (S,) index into names (and x)
    x: np.ndarray | None = None  # (O, 4) [m, m p_tag] [kg, kg m]; None: unknown objects
    tau: np.ndarray | None = None  # (S, N) true joint torque [N m]; None: unknown
    R_base_tag: np.ndarray | None = None  # (S, 3, 3) tag orientation in the base frame
    p_base_tag: np.ndarray | None = None  # (S, 3) tag origin in the base frame [m]
    at_rest: np.ndarray | None = None  # (S,) False: timed out before rest
    extra: dict = struct.field(default_factory=dict)  # other (S, ...) fields, kept as read
    names: tuple[str, ...] = struct.field(pytree_node=False, default=("object",))

    # ---- shape ---------------------------------------------------------------------

    @property
    def n_samples(self) -> int:
        return int(np.shape(self.q)[0])

    @property
    def n_joints(self) -> int:
        return int(np.shape(self.q)[1])

    @property
    def n_objects(self) -> int:
        return len(self.names)

    @property
    def known(self) -> bool:
        """Whether the objects' ``x`` and the true torques are known."""
        return self.x is not None and self.tau is not None

    @property
    def name(self) -> str:
        """The object's name, for a record of one object."""
        if self.n_objects != 1:
            raise UsageError(f"samples of {self.n_objects} objects {list(self.names)} have no "
                             "single name")
        return self.names[0]

    @property
    def has_current(self) -> bool:
        """Whether every joint's current-based torque was read (no servo without a current
        sensor): what the Sensor baseline needs."""
        return bool(np.all(np.isfinite(self.current_tau)))

    @property
    def mass(self) -> float:
        """The mass of the one known object [kg]."""
        return float(self._one_x()[0])

    @property
    def com(self) -> np.ndarray:
        """(3,) the COM of the one known object in its tag frame [m]."""
        x = self._one_x()
        return x[1:] / x[0]

    def _one_x(self) -> np.ndarray:
        if self.x is None or self.n_objects != 1:
            raise UsageError(f"samples of {self.n_objects} object(s), truth "
                             f"{'unknown' if self.x is None else 'known'}: no single mass")
        return np.asarray(self.x[0], np.float64)

    # ---- selection -----------------------------------------------------------------

    def take(self, idx) -> Samples:
        """The samples ``idx`` (indices or a boolean mask); objects and x unchanged."""
        def pick(a):
            return None if a is None else np.asarray(a)[idx]
        return self.replace(
            q_d=pick(self.q_d), q=pick(self.q), direction=pick(self.direction),
            current_tau=pick(self.current_tau), tau_g=pick(self.tau_g), A=pick(self.A),
            object_id=pick(self.object_id), tau=pick(self.tau),
            R_base_tag=pick(self.R_base_tag), p_base_tag=pick(self.p_base_tag),
            at_rest=pick(self.at_rest), extra={k: pick(v) for k, v in self.extra.items()})

    def at_rest_only(self) -> Samples:
        """Without the samples flagged as timed out (``at_rest`` False)."""
        return self if self.at_rest is None else self.take(np.flatnonzero(self.at_rest))

    def object(self, o: int) -> Samples:
        """The samples of object ``o`` as a record of one object."""
        part = self.take(np.flatnonzero(np.asarray(self.object_id) == o))
        return part.replace(object_id=np.zeros(part.n_samples, np.int64),
                            x=None if self.x is None else np.asarray(self.x)[o:o + 1],
                            names=(self.names[o],))

    def by_object(self) -> list[Samples]:
        """One record per object that has samples, in the order of ``names``."""
        present = set(np.unique(np.asarray(self.object_id)).tolist())
        return [self.object(o) for o in range(self.n_objects) if o in present]

    def without_truth(self) -> Samples:
        """The same measurements with the ground truth forgotten (as for an unknown object)."""
        return self.replace(x=None, tau=None)

    @staticmethod
    def concatenate(parts: Sequence[Samples]) -> Samples:
        """The samples of ``parts`` in order; their objects are kept apart (ids offset).
        The truth is known only if every part knows it."""
        if not parts:
            raise UsageError("no samples to concatenate")
        n = {p.n_joints for p in parts}
        if len(n) != 1:
            raise UsageError(f"samples of arms with different joint counts {sorted(n)}")
        offsets = np.cumsum([0] + [p.n_objects for p in parts])[:-1]

        def cat(key):
            vals = [getattr(p, key) for p in parts]
            return None if any(v is None for v in vals) else np.concatenate(vals)

        extra_keys = set.intersection(*(set(p.extra) for p in parts))
        known = all(p.known for p in parts)
        return Samples(
            q_d=cat("q_d"), q=cat("q"), direction=cat("direction"),
            current_tau=cat("current_tau"), tau_g=cat("tau_g"), A=cat("A"),
            object_id=np.concatenate([np.asarray(p.object_id) + o
                                      for p, o in zip(parts, offsets)]),
            x=np.concatenate([p.x for p in parts]) if known else None,
            tau=cat("tau") if known else None, R_base_tag=cat("R_base_tag"),
            p_base_tag=cat("p_base_tag"), at_rest=cat("at_rest"),
            extra={k: np.concatenate([p.extra[k] for p in parts]) for k in sorted(extra_keys)},
            names=tuple(n for p in parts for n in p.names))

    # ---- conversion ----------------------------------------------------------------

    @classmethod
    def from_fields(cls, fields: dict, names: Sequence[str] | None = None, *,
                    path: str | os.PathLike = "<samples>", need_truth: bool = False) -> Samples:
        """A validated record from named per-sample arrays (the native layout's fields:
        ``q_d``, ``q``, ..., ``object_id``, ``x``); errors name ``path`` and the field.

        Ground truth (``tau`` and ``x``) that is absent or not finite means unknown objects
        (``None``), unless ``need_truth``: then it is an error.
        """
        fields = dict(fields)
        need = _REQUIRED + (("tau", "x") if need_truth else ())
        missing = [k for k in need if k not in fields]
        if missing and not set(missing) - {"tau", "x"}:  # only the ground truth
            raise FileFormatError(path, missing[0], "missing: the objects' true torques and "
                                  "mass are unknown here (collected with --object unknown?); "
                                  "training and evaluation need known objects, "
                                  "`jaxinertia estimate` answers for unknown ones")
        if missing:
            raise FileFormatError(path, missing[0], f"missing (this file has "
                                  f"{sorted(fields)}); needed: {list(need)}")
        for k, a in fields.items():
            if k in _REQUIRED + _OPTIONAL + ("x", "object_id") and not (
                    np.issubdtype(np.asarray(a).dtype, np.number)
                    or np.asarray(a).dtype == bool):
                raise FileFormatError(path, k, f"dtype {np.asarray(a).dtype} is not numeric")
        q = np.asarray(fields["q"], np.float64)
        if q.ndim != 2:
            raise FileFormatError(path, "q", f"expected (S, N), got shape {q.shape}")
        S, N = q.shape
        object_id = np.asarray(fields.pop("object_id", np.zeros(S, np.int64)))
        shapes = {"q_d": (S, N), "direction": (S, N), "current_tau": (S, N), "tau_g": (S, N),
                  "A": (S, N, 4), "tau": (S, N), "object_id": (S,), "R_base_tag": (S, 3, 3),
                  "p_base_tag": (S, 3), "at_rest": (S,)}
        for k, shape in shapes.items():
            a = object_id if k == "object_id" else fields.get(k)
            if a is not None and np.shape(a) != shape:
                raise FileFormatError(path, k, f"expected shape {shape}, got {np.shape(a)}")
        for k in ("q_d", "q", "direction", "current_tau", "tau_g", "A"):
            a = np.asarray(fields[k])
            # current_tau: NaN is "no current sensor on that joint"; nothing else is missing
            if not np.all(np.isfinite(a) | ((k == "current_tau") & np.isnan(a))):
                raise FileFormatError(path, k, "holds non-finite values")
        if not np.all(np.isin(fields["direction"], (-1, 1))):
            raise FileFormatError(path, "direction", "must be +1 or -1")
        if not np.issubdtype(object_id.dtype, np.integer) or (S and object_id.min() < 0):
            raise FileFormatError(path, "object_id", "must be non-negative integers")
        n_obj = int(object_id.max()) + 1 if S else 0
        names = tuple(names) if names else tuple(f"object{i}" for i in range(n_obj))
        x = fields.pop("x", None)
        if x is not None:
            x = np.asarray(x, np.float64)
            if x.ndim != 2 or x.shape[1] != 4 or n_obj > len(x):
                raise FileFormatError(path, "x", f"shape {x.shape} does not cover object ids "
                                      f"0..{n_obj - 1}")
        if len(names) < n_obj or (x is not None and len(names) != len(x)):
            raise FileFormatError(path, "metadata", f"names {list(names)} do not match the "
                                  f"objects (ids 0..{n_obj - 1}, x for "
                                  f"{None if x is None else len(x)})")
        check_names(names, path)
        tau = fields.pop("tau", None)
        known = (tau is not None and x is not None and np.all(np.isfinite(tau))
                 and np.all(np.isfinite(x)))
        if need_truth and not known:
            bad = "x" if x is None or not np.all(np.isfinite(x)) else "tau"
            raise FileFormatError(path, bad, "holds non-finite values (unknown objects cannot "
                                  "be used for training or evaluation)")
        # A mass of 0 is the empty gripper (as in the authors' data_train_0g.npz), no COM.
        bad_mass = (x[:, 0] < 0) | ((x[:, 0] == 0) & np.any(x[:, 1:] != 0, axis=1)) if known \
            else np.zeros(0, bool)
        if np.any(bad_mass):
            o = int(np.flatnonzero(bad_mass)[0])
            raise FileFormatError(path, "x", f"object {names[o]!r}: mass {x[o, 0]} kg must be "
                                  "positive (or 0 with x[1:] = 0: the empty gripper), got x = "
                                  f"{x[o].tolist()}")

        def f64(k):
            a = fields.pop(k, None)
            return None if a is None else np.asarray(a, np.float64)

        at_rest = fields.pop("at_rest", None)
        out = cls(q_d=f64("q_d"), q=q, direction=f64("direction"),
                  current_tau=f64("current_tau"), tau_g=f64("tau_g"), A=f64("A"),
                  object_id=object_id.astype(np.int64),
                  x=x if known else None,
                  tau=np.asarray(tau, np.float64) if known else None,
                  R_base_tag=f64("R_base_tag"), p_base_tag=f64("p_base_tag"),
                  at_rest=None if at_rest is None else np.asarray(at_rest, bool),
                  names=names)
        fields.pop("q", None)
        return out.replace(extra={k: np.asarray(v) for k, v in fields.items()
                                  if np.ndim(v) >= 1 and np.shape(v)[0] == S})

    def fields(self) -> dict[str, np.ndarray]:
        """The native layout's per-sample arrays (and ``object_id``, ``x`` when known)."""
        out = {k: getattr(self, k) for k in ("q_d", "q", "current_tau", "direction", "tau",
                                             "tau_g", "A", "R_base_tag", "p_base_tag",
                                             "at_rest")}
        out.update(self.extra)
        out["object_id"] = self.object_id
        out["x"] = self.x
        return {k: np.asarray(v) for k, v in out.items() if v is not None}


# ---- files -----------------------------------------------------------------------------
