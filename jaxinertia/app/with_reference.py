"""``estimate --reference``: a file of known loads recorded in the unknown object's session
(:mod:`jaxinertia.reference`), read once and fitted by each model folder on its own
(the folder's session, its pairs); the networks read the object through the correction,
the baselines as recorded."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from jaxinertia.app.arm_options import samples_arm
from jaxinertia.app.pipeline import adapt_objects, objects_at_rest
from jaxinertia.errors import FileFormatError, UsageError
from jaxinertia.evaluation import evaluate
from jaxinertia.reference import apply_reference, reference_correction
from jaxinertia.samples import Samples
from jaxinertia.uncertainty import uncertainty_of

__all__ = ["ReferenceFile", "corrected", "evaluated", "read_reference", "uncertainty"]


def evaluated(obj: Samples, sets, *, pair, baselines, fc, raw: Samples) -> dict:
    """:func:`evaluate` of one object: the networks on ``obj``, the baselines on ``raw``
    (the object as recorded, where a reference's correction made ``obj`` another record)."""
    if raw is obj:
        return evaluate([obj], sets, pair=pair, baselines=baselines, fc=fc, l_max=[np.nan])
    net = evaluate([obj], sets, pair=pair, fc=fc, l_max=[np.nan])
    base = evaluate([raw], sets, baselines=baselines, l_max=[np.nan])
    name = obj.name
    return {**net, "estimates": {**base["estimates"], **net["estimates"]},
            "objects": {name: {**base["objects"][name], **net["objects"][name]}},
            "unavailable": base["unavailable"]}


def uncertainty(obj: Samples, sets, *, pair, baselines, fc, raw: Samples, floor) -> dict:
    """:func:`uncertainty_of` of one object, as :func:`evaluated` splits it."""
    if raw is obj:
        return uncertainty_of([obj], sets, pair=pair, fc=fc, baselines=baselines, floor=floor)
    return {**uncertainty_of([raw], sets, baselines=baselines),
            **uncertainty_of([obj], sets, pair=pair, fc=fc, floor=floor)}


class ReferenceFile(NamedTuple):
    """A file of known loads recorded in the unknown object's session (``estimate
    --reference``)."""

    path: str
    sha256: str | None
    objects: list[Samples]


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
    if ref is None:
        return folder.pair, objects, None
    known, _ = adapt_objects(ref.objects, session)
    try:
        corr = reference_correction(folder.pair, folder.features, Samples.concatenate(known))
    except UsageError as e:
        raise UsageError(f"--reference {ref.path} with {desc}: {e}") from None
    pair, objects = apply_reference(folder.pair, objects, corr)
    return pair, objects, corr
