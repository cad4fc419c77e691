"""Per-session servo terms of a fine-tuning (issue 30, item 1): each file's factor on its
discrepancy, fitted from its known torques under the models being fine-tuned (the
fine-tuning itself: tests/test_finetune.py)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from support.synthetic import feature_config, synthetic_samples

from jaxinertia.estimation import ModelPair, predict_torques
from jaxinertia.features import featurize
from jaxinertia.networks import AttentionModel, PhysicalTorqueModel
from jaxinertia.session_terms import apply_session_terms, centred, fit_session_terms


def _physical_pair(K=2, seed=0) -> ModelPair:
    """K physical torque models with a servo law and a random residual network."""
    tm, am = PhysicalTorqueModel(), AttentionModel()
    feats = jnp.zeros((1, 4, 4), jnp.float32)
    keys = jax.random.split(jax.random.key(seed), K)
    tv = jax.vmap(lambda k: tm.init(k, feats))(keys)
    p = dict(tv["params"])
    p["stiffness"] = jnp.asarray([[0.9, 1.1, 1.0, 0.8]] * K, jnp.float32)
    p["friction"] = jnp.full((K, 4), 0.05, jnp.float32)
    return ModelPair(torque_vars={"params": p},
                     attention_vars=jax.vmap(lambda k: am.init(k, feats))(keys),
                     tau_scale=jnp.asarray([0.4, 1.2, 0.6, 0.3], jnp.float32),
                     torque_model=tm, attention_model=am)


def test_the_fit_recovers_each_sessions_factor_on_its_discrepancy():
    """Torques that the models give at the discrepancy times a known factor per joint: the
    fit finds that factor (the model is not linear in it: the residual network)."""
    pair, fc = _physical_pair(), feature_config()
    rng = np.random.default_rng(3)
    truth = np.array([[1.12, 0.93, 1.0, 1.25], [0.85, 1.05, 0.97, 1.0]])
    sessions = []
    for u in truth:
        d = synthetic_samples(rng, n=300)
        feats = featurize(fc, jnp.asarray(d.q), d.q + (d.q_d - d.q) * u,
                          d.direction).astype(jnp.float32)
        tau = jax.vmap(lambda tv, f=feats: predict_torques(
            pair.torque_model, tv, f, pair.tau_scale))(pair.torque_vars).mean(axis=0)
        sessions.append(d.replace(tau=np.asarray(tau, np.float64)))
    raw = fit_session_terms(pair, fc, sessions)
    np.testing.assert_allclose(raw, truth, rtol=2e-3)
    c = centred(raw)
    np.testing.assert_allclose(np.exp(np.log(c).mean(axis=0)), 1.0, atol=1e-12)
    np.testing.assert_allclose(c[0] / c[1], truth[0] / truth[1], rtol=2e-3)
    np.testing.assert_allclose(centred(raw[:1]), 1.0)  # one session: no term
    # Applied per sample: the first session's discrepancy scaled, the second's not.
    both = apply_session_terms(sessions[0], np.zeros(300, int), np.array([[2.0] * 4]))
    np.testing.assert_allclose(both.q_d - both.q, 2.0 * (sessions[0].q_d - sessions[0].q))
