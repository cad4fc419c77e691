"""Small synthetic inputs for tests: samples whose torque follows an exact position-error
law, untrained model pairs, a feature configuration."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxinertia.estimation import ModelPair
from jaxinertia.features import FeatureConfig
from jaxinertia.networks import AttentionModel, TorqueModel
from jaxinertia.samples import Samples

__all__ = ["feature_config", "synthetic_samples", "tiny_pair"]


def synthetic_samples(rng, n=400, n_obj=3, *, k=(16.0, 18.0, 17.0, 10.0),
                      f=(0.02, 0.05, 0.03, 0.01)) -> Samples:
    """Samples whose torque is an exact PE law of (q_d - q, s) and A a random regressor."""
    k, f = np.asarray(k), np.asarray(f)
    q = rng.uniform(-0.5, 0.5, (n, 4))
    s = rng.choice([-1.0, 1.0], (n, 4))
    A = rng.normal(size=(n, 4, 4)) * [1.0, 0.1, 0.1, 0.1]
    x = np.column_stack([rng.uniform(0.04, 0.15, n_obj), rng.normal(size=(n_obj, 3)) * 0.003])
    oid = np.arange(n) % n_obj
    tau_g = rng.normal(size=(n, 4)) * 0.2
    tau = tau_g + np.einsum("snp,sp->sn", A, x[oid])
    qe = (tau + s * f - 0.01) / k
    return Samples(q_d=q + qe, q=q, direction=s, current_tau=tau - 0.03 * s + 0.004,
                   tau=tau, tau_g=tau_g, A=A, object_id=oid, x=x,
                   names=tuple(f"o{i}" for i in range(n_obj)))


def tiny_pair(K=2, seed=0) -> ModelPair:
    """K untrained default-size model pairs."""
    tm, am = TorqueModel(), AttentionModel()
    feats = jnp.zeros((1, 4, 4), jnp.float32)
    keys = jax.random.split(jax.random.key(seed), K)
    return ModelPair(torque_vars=jax.vmap(lambda k: tm.init(k, feats))(keys),
                     attention_vars=jax.vmap(lambda k: am.init(k, feats))(keys),
                     tau_scale=jnp.asarray([0.4, 1.2, 0.6, 0.3], jnp.float32),
                     torque_model=tm, attention_model=am)


def feature_config() -> FeatureConfig:
    return FeatureConfig.create([-0.6] * 4, [0.6] * 4, [0.05] * 4, [0.4, 1.2, 0.6, 0.3])
