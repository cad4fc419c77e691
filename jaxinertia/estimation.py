"""Mass and COM from samples: torque model -> (attention) weights -> WLS, batched.

One jitted call evaluates O objects x K model pairs x B sample sets. Networks run in
float32 (as trained); identification runs in the dtype of ``A`` (float64 by default).
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
from flax import struct

from jaxinertia.compile_options import run_once_jit
from jaxinertia.identification import (
    DEFAULT_MAX_CONDITION,
    WLSResult,
    set_statistics,
    solve_normal,
)

__all__ = ["Estimates", "ModelPair", "estimate_sets", "predict_torques",
           "predict_torques_stacked", "predict_weights"]


@struct.dataclass
class ModelPair:
    """K stacked model pairs of one architecture (leading axis K on every variable leaf)."""

    torque_vars: dict
    attention_vars: dict
    tau_scale: jnp.ndarray  # (N,) [N m] per normalised unit of torque-model output
    torque_model: nn.Module = struct.field(pytree_node=False)
    attention_model: nn.Module = struct.field(pytree_node=False)

    @property
    def n_models(self) -> int:
        return int(jax.tree_util.tree_leaves(self.torque_vars)[0].shape[0])


def predict_torques(model: nn.Module, variables: dict, features, tau_scale) -> jnp.ndarray:
    """Joint torques [N m] (..., N) from features (..., N, 4) for one parameter set."""
    return model.apply(variables, features) * jnp.asarray(tau_scale, features.dtype)


def _predict_stacked(model: nn.Module, variables: dict, features, tau_scale) -> jnp.ndarray:
    return jax.vmap(lambda v: predict_torques(model, v, features, tau_scale))(variables)


_predict_stacked_jit = run_once_jit(_predict_stacked, static_argnums=0)


def predict_torques_stacked(model: nn.Module, variables: dict, features,
                            tau_scale) -> jnp.ndarray:
    """Joint torques [N m] (K, ..., N) of K stacked parameter sets (leading axis K) from
    features (..., N, 4): one program per model and shape (the features an argument, not a
    constant: found again in the persistent cache by later runs)."""
    return _predict_stacked_jit(model, variables, features,
                                jnp.asarray(tau_scale, features.dtype))


def predict_weights(model: nn.Module, variables: dict, features) -> jnp.ndarray:
    """Attention weights (..., N) from features (..., N, 4) for one parameter set."""
    return model.apply(variables, features)


class Estimates(NamedTuple):
    """Leading axes (O, K, B) for x, (O, K, S, N) for per-sample outputs."""

    T: WLSResult  # torque model, identity weights
    TA: WLSResult  # torque model, attention weights
    tau_hat: jnp.ndarray  # (O, K, S, N) [N m]
    weights: jnp.ndarray  # (O, K, S, N)


@partial(jax.jit, static_argnames=("max_condition",))
def estimate_sets(
    pair: ModelPair,
    features: jnp.ndarray,
    A: jnp.ndarray,
    tau_g: jnp.ndarray,
    sets: jnp.ndarray,
    *,
    max_condition: float = DEFAULT_MAX_CONDITION,
) -> Estimates:
    """Estimates ``x = [m, m p]`` for every object, model pair and sample set in one call.

    Args:
      pair: K stacked model pairs.
      features: (O, S, N, 4) network inputs (float32).
      A: (O, S, N, 4) load regressors; tau_g: (O, S, N) free-motion torques [N m].
      sets: (O, B, M) sample indices into S (objects with fewer samples are padded; sets
        must only index real samples).
    """

    def per_model(tv, av, feats, A_o, tau_g_o, sets_o):
        tau_hat = predict_torques(pair.torque_model, tv, feats, pair.tau_scale)
        w = predict_weights(pair.attention_model, av, feats)
        y = tau_hat.astype(A_o.dtype) - tau_g_o
        stats_T = set_statistics(A_o, y, None, sets_o)
        stats_TA = set_statistics(A_o, y, w.astype(A_o.dtype), sets_o)
        # One solve for both methods (stacked on a leading axis): half the compiled code.
        both = solve_normal(
            *(jnp.stack([jnp.broadcast_to(t, a.shape), a]) for t, a in zip(stats_T, stats_TA)),
            max_condition=max_condition,
        )
        T, TA = (jax.tree_util.tree_map(lambda r, i=i: r[i], both) for i in range(2))
        return T, TA, tau_hat, w

    over_models = jax.vmap(per_model, in_axes=(0, 0, None, None, None, None))
    over_objects = jax.vmap(over_models, in_axes=(None, None, 0, 0, 0, 0))
    T, TA, tau_hat, w = over_objects(
        pair.torque_vars, pair.attention_vars, features, A, tau_g, sets
    )
    return Estimates(T, TA, tau_hat, w)
