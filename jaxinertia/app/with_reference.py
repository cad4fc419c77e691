"""``estimate --reference``: a file of known loads recorded in the unknown object's session
(:mod:`jaxinertia.reference`), read once and fitted by each model folder on its own
(the folder's session, its pairs); the networks read the object through the correction,
the baselines as recorded."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from jaxinertia.app.arm_options import samples_arm
from jaxinertia.app.pipeline import objects_at_rest
from jaxinertia.errors import FileFormatError, UsageError
from jaxinertia.fileio import nan_to_null
from jaxinertia.reference import corrected as fit_and_apply
from jaxinertia.reference import evaluate_corrected
from jaxinertia.samples import Samples
from jaxinertia.session import SessionReference, servo_session, servo_state_change
from jaxinertia.uncertainty import uncertainty_of

__all__ = ["ReferenceFile", "corrected", "evaluated", "read_reference", "same_session",
           "uncertainty"]

#: A joint's current gain that differs between the reference and the file by more than
#: this share and this many standard errors says another session. The dead-band fit's
#: standard errors understate the spread: a real file cut at random into 250 samples and
#: the rest differs from itself by up to 4.7 of them (100 cuts of the two files). The two
#: real files' sessions (2.6-5.8 % apart on every joint) stand 7.7-10 of them apart on
#: joints 1-2 with 1000 samples each, 3.5-7 with a reference of 250: a check that sees
#: another session only with references of about a thousand samples.
OTHER_SESSION_GAIN = 0.02
OTHER_SESSION_SIGMAS = 6.0
#: ... or a supply that differs by more than this share, or a temperature by more than
#: this many kelvin (where both files recorded them).
OTHER_SESSION_SUPPLY = 0.02
OTHER_SESSION_KELVIN = 5.0


def evaluated(obj: Samples, sets, *, pair, baselines, fc, raw: Samples) -> dict:
    """:func:`~jaxinertia.reference.evaluate_corrected` of one object (``raw``: as
    recorded, where a reference's correction made ``obj`` another record)."""
    objs = [obj]
    return evaluate_corrected(objs, objs if raw is obj else [raw], sets, pair=pair,
                              baselines=baselines, fc=fc, l_max=[np.nan])


def uncertainty(obj: Samples, sets, *, pair, baselines, fc, raw: Samples, floor) -> dict:
    """:func:`uncertainty_of` of one object, as :func:`evaluated` splits it."""
    if raw is obj:
        return uncertainty_of([obj], sets, pair=pair, fc=fc, baselines=baselines, floor=floor)
    return {**uncertainty_of([raw], sets, baselines=baselines),
            **uncertainty_of([obj], sets, pair=pair, fc=fc, floor=floor)}


class ReferenceFile(NamedTuple):
    """A file of known loads recorded in the unknown object's session (``estimate
    --reference``, ``evaluate --reference``)."""

    path: str
    sha256: str | None
    objects: list[Samples]

    def record(self) -> dict:
        """What an answer says of it."""
        return {"file": self.path, "sha256": self.sha256,
                "objects": [o.name for o in self.objects],
                "empty_gripper": any(not o.mass > 0 for o in self.objects),
                "n_samples": int(sum(o.n_samples for o in self.objects))}


def read_reference(path, arm) -> ReferenceFile:
    """The known objects of a reference file, at rest, with their truth."""
    try:
        objects, meta = objects_at_rest(path, need_truth=True)
    except FileFormatError as e:
        if e.field not in ("tau", "x"):
            raise
        raise UsageError(f"--reference {path}: a reference is a known load, its truth "
                         "recorded (collect --object with a known name or mass, such as "
                         "100g); this file's objects are unknown") from None
    samples_arm(path, meta, arm)  # another arm's file: one line, before any estimate
    if not any(o.mass > 0 for o in objects):
        raise UsageError(f"--reference {path}: the empty gripper alone is no reference: at no "
                         "load the correction fits the models' own errors there, and on the "
                         "simulator it made the answer worse (docs/results.md, 'A reference "
                         "in the same session'); record a known weight in the range of the "
                         "objects, e.g. collect --object 100g")
    return ReferenceFile(str(path), meta.get("sha256"), objects)


def corrected(folder, objects: list[Samples], ref: ReferenceFile | None, session, desc: str):
    """``folder``'s pair and ``objects`` read through the reference's correction, fitted on
    the reference read in ``session`` (the folder's own); without a reference, as they are.
    Returns the pair, the objects and the correction (None)."""
    try:
        return fit_and_apply(folder.pair, folder.features, objects,
                             None if ref is None else ref.objects, session)
    except UsageError as e:
        raise UsageError(f"--reference {ref.path} with {desc}: {e}") from None


def same_session(ref: ReferenceFile, obj: Samples) -> dict:
    """Whether the reference and an object's file (both as recorded) look like one session,
    from what needs no truth: each joint's current gain (:mod:`jaxinertia.session`) and,
    where both recorded them, the supply and temperature. The servo state of the file
    against the reference's (:func:`jaxinertia.session.servo_state_change`), the gain
    ratio's standard error, the joints that disagree and ``same_session`` (None: nothing
    to compare)."""
    mine, theirs = servo_session(obj), servo_session(ref.objects)
    state = servo_state_change(SessionReference.of(theirs), mine)
    ratio = SessionReference.of(theirs).gain_ratio(mine)
    rel = np.hypot(np.asarray(mine.current_gain_se) / np.abs(mine.current_gain),
                   np.asarray(theirs.current_gain_se) / np.abs(theirs.current_gain))
    se = np.where(np.isfinite(ratio), ratio * rel, np.nan)
    known = np.isfinite(ratio)
    off = known & (np.abs(ratio - 1) > np.maximum(OTHER_SESSION_SIGMAS * np.where(
        known, se, 0.0), OTHER_SESSION_GAIN))
    for k, limit in (("supply_ratio", OTHER_SESSION_SUPPLY),
                     ("temperature_change", OTHER_SESSION_KELVIN)):
        v = np.array([np.nan if x is None else x for x in state[k] or []], float)
        if v.size:
            known = known | np.isfinite(v)
            off = off | (np.abs(v - (1.0 if k == "supply_ratio" else 0.0)) > limit)
    state["current_gain_ratio_se"] = nan_to_null(se)
    state["other_session_joints"] = (np.flatnonzero(off) + 1).tolist()
    state["same_session"] = None if not known.any() else not off.any()
    return state
