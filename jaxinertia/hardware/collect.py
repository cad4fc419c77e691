"""Sample collection on the arm: the simulator's protocol, an append-only journal, resume.

For each planned sample ``(q_d, s)`` the arm moves to the pre-position ``q_d - s * delta``
and comes to rest, then moves to ``q_d`` (so every joint approaches its goal from its
direction ``s``, as :func:`jaxinertia.sim.sampling.simulate_samples` does) and is recorded
once at rest. Each record is appended to a JSON-lines journal (``<out>.journal.jsonl``)
and flushed to disk before the next move, so an interruption loses nothing; ``resume``
skips the plan indices already in the journal (a torn last line is discarded) and
never records an index twice. The journal file is created with the first sample: a
collection that stops before any sample leaves none behind. A journal damaged elsewhere
than its last line (a corrupt record, a torn header) is a :class:`JournalError` naming
the line. At the end the native sample file is written from the
journal, with ``A`` and ``tau_g`` of the bare arm computed at the measured ``q`` and
tag pose.

The current-based torque of a joint is its servo's torque constant times its Present
Current (:attr:`DynamixelArm.torque_constants`); a servo without a current sensor (the
XL430-W250) has none: its ``current`` and ``current_tau`` are ``null`` in the journal and
NaN in the sample file (the Sensor baseline is then unavailable, and says so).
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Callable
from pathlib import Path

import jax
import numpy as np
from tqdm.auto import tqdm

from jaxinertia.errors import FileFormatError, UsageError
from jaxinertia.fileio import nan_to_null, null_to_nan
from jaxinertia.hardware.driver import DynamixelArm
from jaxinertia.kinematics import gravity_torques
from jaxinertia.plans import Goals
from jaxinertia.robot import Robot
from jaxinertia.samples import Samples
from jaxinertia.statics import load_regressor, tag_pose

__all__ = [
    "DELTA",
    "Journal",
    "JournalError",
    "JournalExists",
    "JournalMismatch",
    "KinematicTagPose",
    "TagPoseSource",
    "collect",
    "journal_path",
    "plan_digest",
    "samples_from_records",
]

DELTA = 3.0 * np.pi / 180.0  # pre-position offset [rad], the simulator's default

#: A tag-pose source: joint angles q (N,) [rad] at rest -> (R_base_tag (3, 3), p_base_tag
#: (3,) [m]). The default is kinematic; a camera source may ignore q.
TagPoseSource = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


class KinematicTagPose:
    """The tag pose from forward kinematics of the measured q and a fixed tag-in-EE pose."""

    def __init__(self, robot: Robot, R_ee_tag: np.ndarray, p_ee_tag: np.ndarray) -> None:
        self._fn = jax.jit(lambda q: tag_pose(robot, q, R_ee_tag, p_ee_tag))

    def __call__(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        R, p = self._fn(np.asarray(q, np.float64))
        return np.asarray(R), np.asarray(p)


class JournalMismatch(UsageError):
    """The journal on disk belongs to another collection (plan, object or robot)."""


class JournalExists(UsageError, FileExistsError):
    """A journal is on disk and ``resume`` was not asked for (nothing is overwritten)."""


class JournalError(FileFormatError):
    """A journal that cannot be continued: a corrupt line before the last, a torn header,
    a record without its fields (exit code 2; names the file and the line)."""


#: The fields of a journal record (``samples_from_records`` reads them).
RECORD_FIELDS = ("index", "q_d", "q", "current_tau", "direction", "R_base_tag", "p_base_tag",
                 "at_rest", "settle_time", "timestamp", "temperature", "voltage")


def journal_path(out: str | os.PathLike) -> Path:
    out = Path(out)
    return out.with_name(out.name + ".journal.jsonl")


def plan_digest(q_d: np.ndarray, direction: np.ndarray) -> str:
    h = hashlib.sha256()
    for a in (q_d, direction):
        h.update(np.ascontiguousarray(a, np.float64).tobytes())
    return h.hexdigest()


def _parse_line(path: Path, number: int, line: bytes) -> dict:
    try:
        value = json.loads(line)
    except (UnicodeDecodeError, json.JSONDecodeError):
        what = "header" if number == 1 else "record"
        raise JournalError(path, f"line {number}",
                           f"corrupt {what} (not JSON); only a torn last line is repaired: "
                           "fix or remove the journal") from None
    if not isinstance(value, dict):
        raise JournalError(path, f"line {number}", "not a JSON object")
    return value


def _check_record(path: Path, number: int, rec: dict, n_samples: int) -> int:
    missing = [k for k in RECORD_FIELDS if k not in rec]
    if missing:
        raise JournalError(path, f"line {number}", f"record without {', '.join(missing)}")
    index = rec["index"]
    if not isinstance(index, int) or isinstance(index, bool) or not 0 <= index < n_samples:
        raise JournalError(path, f"line {number}",
                           f"index {index!r} is not a sample of the plan (0..{n_samples - 1})")
    return index


#: A joint angle beyond one turn either way is no reading of an XM430 (0..4095 ticks).
MAX_ABS_Q = 2 * np.pi


def _check_values(path: Path, number: int, rec: dict, n_joints: int,
                  plan: Goals | None) -> None:
    """A record's values as a sample file's are checked (shapes, finite, directions +-1, a
    rotation, angles a servo can read), and its goal the plan's: before anything moves, a
    damaged record is an error naming the line and the field, never a sample."""
    def bad(field, why):
        return JournalError(path, f"line {number} {field}", why)

    shapes = {"q_d": (n_joints,), "q": (n_joints,), "current_tau": (n_joints,),
              "direction": (n_joints,), "R_base_tag": (3, 3), "p_base_tag": (3,),
              "temperature": (n_joints,), "voltage": (n_joints,), "settle_time": (),
              "timestamp": ()}
    values = {}
    for field, shape in shapes.items():
        value = rec[field]
        # null: a joint whose servo senses no current (nothing else may be missing, and a
        # NaN written as a number is damage, not a missing reading)
        unread = ([v is None for v in value] if field == "current_tau"
                  and isinstance(value, list) else False)
        try:
            a = np.asarray([np.nan if u else v for u, v in zip(unread, value)]
                           if unread else value, np.float64)
        except (TypeError, ValueError):
            raise bad(field, f"not numbers: {rec[field]!r}"[:200]) from None
        if a.shape != shape:
            raise bad(field, f"shape {a.shape}, expected {shape}")
        if not np.all(np.isfinite(a) | np.asarray(unread)):
            raise bad(field, "holds non-finite values")
        values[field] = a
    if not isinstance(rec["at_rest"], bool):
        raise bad("at_rest", f"must be true or false, got {rec['at_rest']!r}")
    if not np.all(np.isin(values["direction"], (-1.0, 1.0))):
        raise bad("direction", f"must be +1 or -1, got {values['direction'].tolist()}")
    for field in ("q_d", "q"):
        if np.any(np.abs(values[field]) > MAX_ABS_Q):
            raise bad(field, f"{values[field].tolist()} rad: beyond one turn, no servo reading")
    R = values["R_base_tag"]
    if np.max(np.abs(R.T @ R - np.eye(3))) > 1e-6 or np.linalg.det(R) < 0:
        raise bad("R_base_tag", "not a rotation (R^T R != I or det R < 0)")
    if plan is not None:
        q_d, direction = plan
        i = rec["index"]
        if not (np.allclose(values["q_d"], q_d[i], rtol=0, atol=1e-9)
                and np.array_equal(values["direction"], direction[i])):
            raise bad("q_d", f"sample {i}'s goal or direction is not the plan's")


class Journal:
    """Append-only JSON lines: a header, then one record per sample (fsynced each). The
    file is created (with its header) by the first :meth:`append`."""

    def __init__(self, path: Path, header: dict, records: dict[int, dict]) -> None:
        self.path = path
        self.header = header
        self.records = records
        self._file = None  # opened by the first append

    @classmethod
    def open(cls, path: str | os.PathLike, header: dict, *, resume: bool,
             plan: Goals | None = None) -> Journal:
        """A new journal, or (``resume``) the existing one after checking its header.

        Raises :class:`JournalExists` (a FileExistsError) when a journal exists and
        ``resume`` is False (nothing is overwritten), :class:`JournalMismatch` when the
        header's identity differs, :class:`JournalError` when it is damaged elsewhere
        than in its last line or a record's values are not a sample's (``plan``, the
        goals and directions: each record's must be its index's). A new journal is not
        written here (the first :meth:`append` does); a torn last line of an existing one
        is cut off."""
        path = Path(path)
        records: dict[int, dict] = {}
        numbers: dict[int, int] = {}  # each record's line
        if path.exists() and path.stat().st_size:
            if not resume:
                raise JournalExists(f"{path} exists: pass `resume` to continue it, or "
                                      "remove it to start over")
            lines = path.read_bytes().split(b"\n")
            # A crash can tear the last line only (every line is flushed before the next);
            # drop a torn tail so the next record starts on its own line.
            complete, tail = lines[:-1], lines[-1]
            if not complete:
                raise JournalError(path, "line 1", "torn header (the collection stopped as "
                                   "it started): remove the journal to start over")
            old = _parse_line(path, 1, complete[0])
            if old.get("kind") != "header":
                raise JournalError(path, "line 1", "not a journal header")
            for key in ("plan_digest", "object", "n_samples"):
                if old.get(key) != header.get(key):
                    raise JournalMismatch(f"{path}: {key} is {old.get(key)!r} in the journal, "
                                          f"{header.get(key)!r} now")
            for number, line in enumerate(complete[1:], start=2):
                rec = _parse_line(path, number, line)
                index = _check_record(path, number, rec, int(old["n_samples"]))
                if index in records:
                    raise JournalMismatch(f"{path}: sample {index} recorded twice")
                records[index] = rec
                numbers[index] = number
            # Then the values, once every line is known to be a record.
            # The joint count: the header's servo IDs, else the plan's, else the first
            # record's (a library caller's header may name no IDs).
            ids = old.get("servo_ids") or header.get("servo_ids")
            n_joints = (len(ids) if ids else np.shape(plan[0])[1] if plan is not None else
                        len(next(iter(records.values()), {}).get("q") or ()))
            for index, rec in records.items():
                _check_values(path, numbers[index], rec, n_joints, plan)
            if tail:
                with open(path, "r+b") as f:
                    f.truncate(path.stat().st_size - len(tail))
            header = old
        return cls(path, header, records)

    def _open_for_append(self) -> None:
        if self.path.exists() and self.path.stat().st_size:
            self._file = open(self.path, "a", encoding="utf-8")  # noqa: SIM115 (close())
        else:
            self._file = open(self.path, "w", encoding="utf-8")  # noqa: SIM115 (close())
            self._file.write(json.dumps(self.header) + "\n")

    def append(self, record: dict) -> None:
        if record["index"] in self.records:
            raise ValueError(f"sample {record['index']} is already recorded")
        if self._file is None:
            self._open_for_append()
        self._file.write(json.dumps(record) + "\n")
        self._file.flush()
        os.fsync(self._file.fileno())
        self.records[record["index"]] = record

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None


def collect(
    arm: DynamixelArm,
    q_d: np.ndarray,
    direction: np.ndarray,
    journal: Journal,
    *,
    tag_pose: TagPoseSource,
    delta: float = DELTA,
    progress: bool = True,
) -> None:
    """Runs the plan's samples that are not in ``journal`` yet, appending each one."""
    todo = [i for i in range(len(q_d)) if i not in journal.records]
    # Check the whole remaining plan before anything moves.
    for i in todo:
        arm.check_goal(q_d[i] - direction[i] * delta)
        arm.check_goal(q_d[i])
    with tqdm(total=len(q_d), initial=len(q_d) - len(todo), desc="collecting", unit="sample",
              disable=not progress) as bar:
        for i in todo:
            goal, s = np.asarray(q_d[i], np.float64), np.asarray(direction[i], np.float64)
            _, ok_pre, _ = arm.move_and_settle(goal - s * delta)
            state, ok, settle = arm.move_and_settle(goal)
            R, p = tag_pose(state.q)
            journal.append({
                "index": i, "q_d": goal.tolist(), "q": state.q.tolist(),
                "current": nan_to_null(state.current),
                "current_tau": nan_to_null(arm.torque_constants * state.current),
                "direction": s.tolist(), "R_base_tag": np.asarray(R).tolist(),
                "p_base_tag": np.asarray(p).tolist(), "at_rest": bool(ok_pre and ok),
                "settle_time": settle, "timestamp": state.timestamp,
                "temperature": state.temperature.tolist(), "voltage": state.voltage.tolist(),
            })
            bar.update(1)


@jax.jit
def _statics(robot: Robot, q, R_base_tag, p_base_tag):
    """``A`` (S, N, 4) and ``tau_g`` (S, N) of the bare ``robot`` at the measured samples:
    one program (the robot an argument, not constants), kept in the compilation cache."""
    A = jax.vmap(load_regressor, in_axes=(None, 0, 0, 0))(robot, q, R_base_tag, p_base_tag)
    return A, jax.vmap(gravity_torques, in_axes=(None, 0))(robot, q)


def samples_from_records(records: dict[int, dict], robot: Robot, x: np.ndarray | None,
                         name: str) -> Samples:
    """The samples of the journal ``records`` (plan order) holding object ``name``: ``A``
    and ``tau_g`` of the bare ``robot`` at the measured q and tag pose, ``tau = tau_g + A x``
    (ground truth None when ``x`` is None); the other journal columns and ``plan_index`` in
    ``extra``."""
    idx = sorted(records)
    cols = ("q_d", "q", "current_tau", "direction", "R_base_tag", "p_base_tag", "at_rest",
            "settle_time", "timestamp", "temperature", "voltage")
    f = {k: np.asarray([records[i][k] for i in idx]) for k in cols if k != "current_tau"}
    f["current_tau"] = np.asarray([null_to_nan(records[i]["current_tau"]) for i in idx])
    f["at_rest"] = f["at_rest"].astype(bool)
    q = f["q"].astype(np.float64)
    A, tau_g = (np.asarray(v) for v in _statics(robot, q, f["R_base_tag"], f["p_base_tag"]))
    f["A"], f["tau_g"] = A, tau_g
    if x is not None:
        f["tau"] = tau_g + A @ x
        f["x"] = np.asarray(x, np.float64)[None]
    f["plan_index"] = np.asarray(idx)
    return Samples.from_fields(f, [name])
