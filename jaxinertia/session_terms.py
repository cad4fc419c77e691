"""Per-session servo terms of a fine-tuning on several real files (issue 30, item 1).

A fine-tuning on real files of known objects sees each file's recording session: its
servos' effective gain (supply, winding temperature, wear) differs from the other files'
by a few per cent. Pooled, a fine-tuning has one servo for all of them, and where each
session holds its own objects (the paper's data: one object per file) it learns the
sessions' difference as a difference between the objects' loads: a light object's session
read stiffer than a heavy one's is, to a pooled model, a servo that softens with load. A
new object of another mass then inherits that false load law.

Here each file gets its own term: a factor ``u_p`` per joint on its discrepancy (the
servo's gain in this session relative to the sessions' common servo; it acts where
:func:`jaxinertia.session.adapt` acts, and the current cannot see all of it), fitted from
the file's known torques under the models being fine-tuned (least squares of their mean
torque, in their output units), and centred: the geometric mean over the files is 1,
so the common part of the sim-to-real difference stays for the fine-tuning's shared
servo parameters to learn. With one file the term is 1 and the fine-tuning is the pooled
one. The folder records the terms; a new file is read in the common session (its own
term is unknown: the session strength's current-gain rescaling is what estimates it).
"""

from __future__ import annotations

from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from jaxinertia.errors import UsageError
from jaxinertia.estimation import ModelPair, predict_torques
from jaxinertia.features import FeatureConfig, featurize
from jaxinertia.fileio import nan_to_null
from jaxinertia.samples import Samples
from jaxinertia.session import RATIO_RANGE

__all__ = ["apply_session_terms", "centred", "fit_discrepancy_factor", "fit_session_terms",
           "with_session_terms"]


def fit_session_terms(pair: ModelPair, fc: FeatureConfig, sessions: Sequence[Samples], *,
                      iters: int = 20) -> np.ndarray:
    """(P, N) per session and joint, the factor on the discrepancy that best explains the
    session's known torques under the mean of ``pair``'s K torque models (Gauss-Newton on
    its log, within :data:`jaxinertia.session.RATIO_RANGE`). Not centred."""
    if any(s.tau is None for s in sessions):
        raise ValueError("session terms need the files' known torques")
    scale = jnp.asarray(pair.tau_scale, jnp.float32)
    return np.stack([
        fit_discrepancy_factor(pair, fc, s, lambda tau_hat, tau: (tau_hat - tau) / scale,
                               jnp.asarray(s.tau, jnp.float32), iters=iters)
        for s in sessions])


def fit_discrepancy_factor(pair: ModelPair, fc: FeatureConfig, data: Samples, residual,
                           target, *, iters: int = 20) -> np.ndarray:
    """(N,) the factor per joint on ``data``'s discrepancy that minimises the sum of squares
    of ``residual(tau_hat, target)``, ``tau_hat`` (S, N) the mean torque of ``pair``'s K
    models [N m] (Gauss-Newton on the factor's log, within
    :data:`jaxinertia.session.RATIO_RANGE`; ``residual`` traceable by JAX)."""
    step = _gauss_newton_step(pair, fc, residual)
    lo, hi = np.log(RATIO_RANGE)
    q = np.asarray(data.q, np.float64)
    args = (jnp.asarray(q), jnp.asarray(np.asarray(data.q_d, np.float64) - q),
            jnp.asarray(data.direction), jnp.asarray(data.current_tau), target)
    v = jnp.zeros(data.n_joints, jnp.float32)
    for _ in range(iters):
        v_new = jnp.clip(step(v, *args), lo, hi)
        done = bool(jnp.max(jnp.abs(v_new - v)) < 1e-6)
        v = v_new
        if done:
            break
    return np.exp(np.asarray(v, np.float64))


def centred(u: np.ndarray) -> np.ndarray:
    """``u`` (P, N) divided per joint by its geometric mean over the sessions."""
    log_u = np.log(np.asarray(u, np.float64))
    return np.exp(log_u - log_u.mean(axis=0, keepdims=True))


def apply_session_terms(data: Samples, session_of_sample: np.ndarray,
                        u: np.ndarray) -> Samples:
    """``data`` with each sample's discrepancy times its session's factor
    (``session_of_sample`` (S,) indexes the rows of ``u`` (P, N))."""
    q = np.asarray(data.q)
    f = np.asarray(u, q.dtype)[np.asarray(session_of_sample)]
    return data.replace(q_d=q + (np.asarray(data.q_d) - q) * f)


def _gauss_newton_step(pair: ModelPair, fc: FeatureConfig, residual):
    def residuals(v, q, e, direction, current, target):
        feats = featurize(fc, q, q + e * jnp.exp(v.astype(q.dtype)), direction, current)
        feats = feats.astype(jnp.float32)
        tau_hat = jax.vmap(lambda tv: predict_torques(pair.torque_model, tv, feats,
                                                      pair.tau_scale))(pair.torque_vars)
        return residual(tau_hat.mean(axis=0), target).reshape(-1)

    @jax.jit
    def step(v, *data):
        r = residuals(v, *data)
        J = jax.jacfwd(residuals)(v, *data)
        JtJ = J.T @ J
        damping = 1e-6 * jnp.trace(JtJ) / JtJ.shape[0] * jnp.eye(JtJ.shape[0], dtype=JtJ.dtype)
        return v - jnp.linalg.solve(JtJ + damping, J.T @ r)

    return step


def with_session_terms(start, parts: Sequence[Samples], train_set: Samples,
                       val_set: Samples) -> tuple[Samples, Samples, dict]:
    """A fine-tuning's training and validation splits with each file its own servo term
    (``train --session-terms``): fitted on the file's training samples under the start
    models (``start``: the loaded model folder; ``parts``: the files' records, in the
    order their objects were concatenated), centred over the files, applied to
    the file's training and validation samples alike (one file: no term, the samples as
    they are). Returns both splits and the record (per file: the raw and the centred
    factors)."""
    if start is None:
        raise UsageError("session terms are a fine-tuning's (train --init): they are fitted "
                         "under the models being fine-tuned")
    if not train_set.known:
        raise UsageError("session terms need the files' known torques")
    file_of_object = np.repeat(np.arange(len(parts)), [p.n_objects for p in parts])
    files = file_of_object[np.asarray(train_set.object_id)]
    present = np.unique(files)
    if len(present) < 2:  # one session: no term to tell apart, the pooled fine-tuning
        ones = np.ones((len(parts), train_set.n_joints)).tolist()
        return train_set, val_set, {"raw": None, "factor": ones}
    raw = fit_session_terms(start.pair, start.features,
                            [train_set.take(files == p) for p in present])
    clipped = np.isclose(np.log(raw), np.log(RATIO_RANGE)[0]) | np.isclose(
        np.log(raw), np.log(RATIO_RANGE)[1])
    if clipped.any():
        p, j = np.argwhere(clipped)[0]
        raise UsageError(
            f"--session-terms: the start models' torque does not follow the discrepancy of "
            f"{parts[present[p]].names[0]!r}'s file on joint {j + 1} (its factor reaches "
            f"the {RATIO_RANGE[0]:g}-{RATIO_RANGE[1]:g} limit): they cannot tell its session "
            "from the others'; fine-tune without session terms, or from better models")
    u = np.ones((len(parts), train_set.n_joints))
    u[present] = centred(raw)
    split = [apply_session_terms(s, file_of_object[np.asarray(s.object_id)], u)
             for s in (train_set, val_set)]
    raw_all = np.full_like(u, np.nan)
    raw_all[present] = raw
    return *split, {"raw": [nan_to_null(r) for r in raw_all], "factor": u.tolist()}
