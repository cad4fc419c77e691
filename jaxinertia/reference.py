"""A known load recorded in the same session as the unknown object: the servo's state of
the day measured, not inferred.

A recording session scales the torque one tick of error buys (supply, winding
temperature, wear; :mod:`jaxinertia.session`). The current gain sees the electrical part
of it and nothing of a change of the torque constant, and on the OpenMANIPULATOR-X 1 % of
joint 2's torque is about 5 g of the object's mass. A *reference*, a known weight in the
range of the objects (its joint torques known), recorded at a few hundred poses in the
same session, measures it: per joint, the models' torques against the true ones,

    tau = g * tau_hat + b        (least squares over the reference's samples),

and the unknown object's are read as ``g * tau_hat + b``. The load's known torques fix
the gain (unlike a gain fitted together with an unknown object, where the object's mass
absorbs it: docs/results.md, "Adaptation from the statics alone"). The empty gripper is no
reference: at no load the fit takes the models' own errors there for the session's, and
on the simulator it made the answer worse (docs/results.md, "A reference in the same
session"; ``estimate`` refuses it). A reference from
another session carries that session's state instead (docs/results.md, "A known object at
the same poses as a reference": it made the real files' answers worse).

The correction enters the estimate without new programs: the gain scales the models'
torque output (``ModelPair.tau_scale``), the offset moves the free-motion torque that the
least squares subtracts (``tau - tau_g = A x`` with ``tau_g - b``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from flax import struct

from jaxinertia.errors import UsageError
from jaxinertia.estimation import ModelPair
from jaxinertia.evaluation import evaluate
from jaxinertia.features import FeatureConfig
from jaxinertia.fileio import nan_to_null
from jaxinertia.samples import Samples
from jaxinertia.session import SessionReference, adapt
from jaxinertia.training import torque_predictions

__all__ = ["ReferenceCorrection", "apply_reference", "corrected", "evaluate_corrected",
           "reference_correction"]

#: A joint's gain is used only within this range (beyond it the reference is another
#: servo, another arm or a broken recording, not a day's state).
GAIN_RANGE = (0.7, 1.4)


@struct.dataclass
class ReferenceCorrection:
    """Per joint (N,): ``tau = gain * tau_hat + offset`` fitted on a reference."""

    gain: np.ndarray
    offset: np.ndarray  # [N m]
    gain_se: np.ndarray
    offset_se: np.ndarray  # [N m]
    #: The reference's torque error left after the correction, RMS per joint [N m].
    residual: np.ndarray
    n_samples: int = struct.field(pytree_node=False, default=0)

    def to_dict(self) -> dict:
        return {"gain": nan_to_null(self.gain), "gain_se": nan_to_null(self.gain_se),
                "offset_Nm": nan_to_null(self.offset),
                "offset_se_Nm": nan_to_null(self.offset_se),
                "residual_Nm": nan_to_null(self.residual), "n_samples": self.n_samples}


def predicted_torques(pair: ModelPair, fc: FeatureConfig, data: Samples) -> np.ndarray:
    """(S, N) the mean of the K model pairs' torques on ``data`` [N m], as the estimate
    computes them (the pair's own output scale)."""
    fc = fc.replace(tau_scale=np.asarray(pair.tau_scale))
    return np.asarray(torque_predictions(pair.torque_model, pair.torque_vars, fc, data),
                      np.float64).mean(axis=0)


def reference_correction(pair: ModelPair, fc: FeatureConfig, reference: Samples, *,
                         offset: bool = True) -> ReferenceCorrection:
    """The per-joint gain (and, ``offset``, offset) that takes the models' torques on
    ``reference`` (samples whose true torques are known, recorded in the unknown object's
    session) to the truth, by least squares per joint."""
    if reference.tau is None:
        raise UsageError("a reference needs its true joint torques: a known object or the "
                         "empty gripper (its file's truth), not an unknown object")
    n = reference.n_samples
    if n < 8:
        raise UsageError(f"a reference of {n} samples: at least 8 are needed to fit a gain "
                         "and an offset per joint (a few hundred determine them)")
    tau_hat = predicted_torques(pair, fc, reference)
    tau = np.asarray(reference.tau, np.float64)
    N = tau.shape[1]
    gain, off = np.ones(N), np.zeros(N)
    gain_se, off_se, resid = np.zeros(N), np.zeros(N), np.zeros(N)
    for j in range(N):
        X = np.column_stack([tau_hat[:, j], np.ones(n)]) if offset else tau_hat[:, j:j + 1]
        coef, *_ = np.linalg.lstsq(X, tau[:, j], rcond=None)
        r = tau[:, j] - X @ coef
        dof = max(n - X.shape[1], 1)
        cov = np.linalg.pinv(X.T @ X) * (r @ r / dof)
        gain[j], gain_se[j] = coef[0], np.sqrt(cov[0, 0])
        if offset:
            off[j], off_se[j] = coef[1], np.sqrt(cov[1, 1])
        resid[j] = np.sqrt(np.mean(r ** 2))
    bad = ~((gain >= GAIN_RANGE[0]) & (gain <= GAIN_RANGE[1]))
    if bad.any():
        raise UsageError(
            f"the reference's gain of joint(s) {(np.flatnonzero(bad) + 1).tolist()} is "
            f"{np.round(gain[bad], 3).tolist()}, outside {GAIN_RANGE}: not a servo's day but "
            "another arm, another servo or a recording without the load it names")
    return ReferenceCorrection(gain, off, gain_se, off_se, resid, n_samples=n)


def apply_reference(pair: ModelPair, objects: Sequence[Samples],
                    correction: ReferenceCorrection) -> tuple[ModelPair, list[Samples]]:
    """The pair and objects whose estimate reads the torques as ``gain * tau_hat +
    offset``: the gain on the pair's output scale, the offset on each object's free-motion
    torque (``tau_hat + offset - tau_g = tau_hat - (tau_g - offset)``)."""
    dtype = np.asarray(pair.tau_scale).dtype
    pair = pair.replace(tau_scale=(np.asarray(pair.tau_scale, np.float64)
                                   * correction.gain).astype(dtype))
    return pair, [o.replace(tau_g=np.asarray(o.tau_g, np.float64) - correction.offset)
                  for o in objects]


def corrected(pair: ModelPair, fc: FeatureConfig, objects: Sequence[Samples],
              known: Sequence[Samples] | None, session: SessionReference | None
              ) -> tuple[ModelPair, list[Samples], ReferenceCorrection | None]:
    """``pair`` and ``objects`` (already read in ``session``) read through the correction
    fitted on the known loads ``known`` read in the same ``session``; without ``known``, as
    they are (correction None)."""
    if known is None:
        return pair, objects, None
    corr = reference_correction(pair, fc, Samples.concatenate([adapt(k, session)[0]
                                                                for k in known]))
    pair, objects = apply_reference(pair, objects, corr)
    return pair, objects, corr


def evaluate_corrected(objects: Sequence[Samples], raw: Sequence[Samples], sets, *,
                       pair: ModelPair | None, baselines, fc: FeatureConfig | None,
                       l_max) -> dict:
    """:func:`jaxinertia.evaluation.evaluate` with the networks on ``objects`` (read
    through a reference's correction) and the baselines on ``raw`` (the same objects as
    recorded); ``objects is raw``: one evaluation, as without a reference."""
    if objects is raw:
        return evaluate(objects, sets, pair=pair, baselines=baselines, fc=fc, l_max=l_max)
    net = evaluate(objects, sets, pair=pair, fc=fc, l_max=l_max)
    base = evaluate(raw, sets, baselines=baselines, l_max=l_max)
    return {**net, "estimates": {**base["estimates"], **net["estimates"]},
            "torque": {**base["torque"], **net["torque"]},
            "objects": {n: {**base["objects"][n], **net["objects"][n]} for n in net["objects"]},
            "diagnostics": {n: {**base["diagnostics"][n], **net["diagnostics"][n]}
                            for n in net["diagnostics"]},
            "unavailable": base["unavailable"]}
