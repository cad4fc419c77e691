"""The paper's two networks (Flax linen) and loading of the authors' released weights.

TorqueModel: per joint an MLP 4 -> hidden -> embed (ReLU between), the N embeddings
concatenated, then a head MLP (ReLU) to N normalised torques. PhysicalTorqueModel (an
option, not the paper's): a per-joint servo part (stiffness, offset, friction by approach
direction and load) plus a TorqueModel residual.

AttentionModel: per joint an MLP of the same shape (its own parameters), the embedding
concatenated with the joint's one-hot index, a scorer MLP to one score per joint, and a
softmax over the joints.

Linen is used (not nnx) because parameters are then a plain pytree: ten released model
pairs stack into one pytree and ``jax.vmap`` evaluates all of them in one call.
"""

from __future__ import annotations

import functools
import os
import re
from collections.abc import Sequence
from pathlib import Path

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from jaxinertia.errors import WeightsError
from jaxinertia.torch_state_dict import StateDictError
from jaxinertia.torch_state_dict import load_state_dict as load_pt

__all__ = [
    "AttentionModel",
    "JointEmbedding",
    "PhysicalTorqueModel",
    "TORQUE_MODELS",
    "TorqueModel",
    "WeightsError",
    "attention_params_from_torch",
    "load_released_pair",
    "parameter_shapes",
    "load_state_dict",
    "stack_params",
    "torque_model_kind",
    "torque_params_from_torch",
]


class JointEmbedding(nn.Module):
    """4 -> hidden -> embed MLP for one joint's state."""

    hidden: int = 12
    embed: int = 12

    @nn.compact
    def __call__(self, x):
        x = nn.relu(nn.Dense(self.hidden, name="hidden")(x))
        return nn.Dense(self.embed, name="embed")(x)


def _joint_embeddings(module: nn.Module, features, hidden: int, embed: int, stacked: bool):
    """(..., N, F) features -> N arrays (..., embed): joint j's :class:`JointEmbedding`
    ``joint{j}`` on its own features, or, ``stacked`` (once the parameters exist), the N
    joints' layers as one batched product each: their parameters stacked on the fly, the
    same parameters, fewer and larger kernels, equal to the per-joint products up to float
    rounding; returned (..., N, embed)."""
    N = features.shape[-2]
    if not stacked or module.is_initializing():
        return [JointEmbedding(hidden, embed, name=f"joint{j}")(features[..., j, :])
                for j in range(N)]
    p = module.variables["params"]

    def layer(x, name):
        W = jnp.stack([p[f"joint{j}"][name]["kernel"] for j in range(N)])
        b = jnp.stack([p[f"joint{j}"][name]["bias"] for j in range(N)])
        return jnp.einsum("...nf,nfh->...nh", x, W) + b

    return layer(nn.relu(layer(features, "hidden")), "embed")


class TorqueModel(nn.Module):
    """(..., N, 4) features -> (..., N) normalised joint torques (times tau_scale = N m)."""

    n_joints: int = 4
    hidden: int = 12
    embed: int = 12
    head: Sequence[int] = (64, 64)
    #: The joints' embeddings as batched products (:func:`_joint_embeddings`).
    stacked_joints: bool = False

    @nn.compact
    def __call__(self, features):
        h = _joint_embeddings(self, features, self.hidden, self.embed, self.stacked_joints)
        x = (jnp.concatenate(h, axis=-1) if isinstance(h, list)
             else h.reshape(h.shape[:-2] + (h.shape[-2] * h.shape[-1],)))
        for i, width in enumerate(self.head):
            x = nn.relu(nn.Dense(width, name=f"head{i}")(x))
        return nn.Dense(self.n_joints, name="out")(x)


class PhysicalTorqueModel(nn.Module):
    """A physics-structured torque model: per joint a servo part plus the paper's network
    as a residual, so that the torque extrapolates in load like the servo does.

    In the features' normalised units (``e`` the scaled discrepancy ``q_d - q``, ``s`` the
    approach direction +1 / -1, output times ``tau_scale`` = N m), per joint j::

        tau_j = k_j e_j + c_j + s_j (f_j + g_j |k_j e_j|) + r_j(features)

    with a stiffness ``k`` (starts at 1: the scales map the largest discrepancy to the
    largest torque), a constant torque ``c`` (cables, offsets), a direction-dependent
    friction ``f`` and its load-proportional part ``g`` (the friction of a loaded gear
    train grows with the torque it carries), and ``r`` the paper's network
    (:class:`TorqueModel`, same shape) for what the servo part does not describe.
    """

    n_joints: int = 4
    hidden: int = 12
    embed: int = 12
    head: Sequence[int] = (64, 64)
    stacked_joints: bool = False  # the residual's, as TorqueModel's

    @nn.compact
    def __call__(self, features):
        N = self.n_joints
        e = features[..., 1]
        s = features[..., 2] - features[..., 3]
        k = self.param("stiffness", nn.initializers.ones, (N,), features.dtype)
        c = self.param("offset", nn.initializers.zeros, (N,), features.dtype)
        f = self.param("friction", nn.initializers.zeros, (N,), features.dtype)
        g = self.param("load_friction", nn.initializers.zeros, (N,), features.dtype)
        servo = k * e
        residual = TorqueModel(N, self.hidden, self.embed, self.head, self.stacked_joints,
                               name="residual")(features)
        return servo + c + s * (f + g * jnp.abs(servo)) + residual


#: Torque model architectures by the name ``train --torque-model`` and model folders use.
TORQUE_MODELS = {"paper": TorqueModel, "physical": PhysicalTorqueModel}


def torque_model_kind(model: nn.Module) -> str:
    return next(k for k, cls in TORQUE_MODELS.items() if type(model) is cls)


class AttentionModel(nn.Module):
    """(..., N, 4) features -> (..., N) joint weights, positive, summing to one per sample."""

    n_joints: int = 4
    hidden: int = 12
    embed: int = 12
    scorer: Sequence[int] = (32,)
    stacked_joints: bool = False  # as TorqueModel's

    def scores(self, features):
        h = _joint_embeddings(self, features, self.hidden, self.embed, self.stacked_joints)
        h = jnp.stack(h, axis=-2) if isinstance(h, list) else h
        onehot = jnp.broadcast_to(
            jnp.eye(self.n_joints, dtype=h.dtype), h.shape[:-1] + (self.n_joints,)
        )
        x = jnp.concatenate([h, onehot], axis=-1)
        for i, width in enumerate(self.scorer):
            x = nn.relu(nn.Dense(width, name=f"scorer{i}")(x))
        return nn.Dense(1, name="score")(x)[..., 0]

    @nn.compact
    def __call__(self, features):
        return jax.nn.softmax(self.scores(features), axis=-1)


def uniform_attention(variables: dict) -> dict:
    """An attention model's variables (stacked or not) with its last layer (``score``)
    zeroed: every joint of every sample then gets the weight 1/N whatever the features, so
    the weighted least squares of T-A solves T's unweighted one."""
    params = dict(variables["params"])
    params["score"] = jax.tree.map(jnp.zeros_like, params["score"])
    return {**variables, "params": params}


def load_state_dict(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Reads a state dict from ``.npz`` or a PyTorch ``.pt`` (without importing torch)."""
    path = Path(path)
    if path.suffix == ".pt":
        try:
            return load_pt(path)
        except StateDictError as e:
            raise WeightsError(str(e)) from e
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: np.asarray(z[k]) for k in z.files}
    except (OSError, ValueError) as e:
        raise WeightsError(f"{path}: cannot read weights ({e})") from e


def _dense(sd, prefix, path, shape_in=None, shape_out=None):
    try:
        w, b = sd[f"{prefix}.weight"], sd[f"{prefix}.bias"]
    except KeyError as e:
        raise WeightsError(f"{path}: missing tensor {e.args[0]!r}") from None
    if w.ndim != 2 or b.shape != (w.shape[0],):
        raise WeightsError(f"{path}: {prefix}: bad shapes weight {w.shape}, bias {b.shape}")
    if (shape_in is not None and w.shape[1] != shape_in) or (
        shape_out is not None and w.shape[0] != shape_out
    ):
        raise WeightsError(
            f"{path}: {prefix}.weight has shape {w.shape}, expected ({shape_out}, {shape_in})"
        )
    for name, a in (("weight", w), ("bias", b)):
        if not np.all(np.isfinite(a)):
            raise WeightsError(f"{path}: {prefix}.{name} holds non-finite values")
    # PyTorch Linear stores (out, in) and computes x W^T + b; Dense's kernel is (in, out).
    # Host arrays: reading and checking a file touches no device (stacking puts them there).
    return {"kernel": np.ascontiguousarray(w.T), "bias": np.ascontiguousarray(b)}


def _joint_prefixes(sd, pattern):
    idx = sorted({int(m.group(1)) for k in sd if (m := re.match(pattern, k))})
    if not idx or idx != list(range(1, len(idx) + 1)):
        raise WeightsError(f"joint modules {idx} are not numbered 1..N")
    return idx


def _from_torch(sd: dict, path: str, joint: str, stack: str, names: tuple[str, str],
                shape_out: int | None) -> tuple[dict, int, int, int, tuple[int, ...]]:
    """Flax parameters of a per-joint MLP (``{joint}.{0,2}`` per joint, numbered from 1)
    followed by a stack of dense layers (``{stack}.{k}``): the layout of both of the
    authors' networks. Returns the parameters, N, the joint MLPs' hidden and embedding
    widths, and the widths of the stack's hidden layers."""
    try:
        joints = _joint_prefixes(sd, joint.replace("{j}", r"(\d+)") + r"\.0\.weight$")
    except WeightsError as e:
        raise WeightsError(f"{path}: {e}") from None
    n = len(joints)
    params = {}
    for j in joints:
        prefix = joint.format(j=j)
        params[f"joint{j - 1}"] = {"hidden": _dense(sd, f"{prefix}.0", path, shape_in=4),
                                   "embed": _dense(sd, f"{prefix}.2", path)}
    layers = sorted(int(m.group(1)) for k in sd
                    if (m := re.match(re.escape(stack) + r"\.(\d+)\.weight$", k)))
    if len(layers) < 1:
        raise WeightsError(f"{path}: missing tensor '{stack}.0.weight'")
    hidden_name, out_name = names
    for i, h in enumerate(layers[:-1]):
        params[f"{hidden_name}{i}"] = _dense(sd, f"{stack}.{h}", path)
    params[out_name] = _dense(sd, f"{stack}.{layers[-1]}", path,
                              shape_out=n if shape_out is None else shape_out)
    widths = tuple(params[f"{hidden_name}{i}"]["kernel"].shape[1]
                   for i in range(len(layers) - 1))
    return (params, n, params["joint0"]["hidden"]["kernel"].shape[1],
            params["joint0"]["embed"]["kernel"].shape[1], widths)


def torque_params_from_torch(sd: dict, path: str = "<state dict>") -> tuple[TorqueModel, dict]:
    """The authors' ``TorqueModel`` state dict (``j{1..N}.{0,2}``, ``tau.{0,2,4}``) -> Flax."""
    params, n, hidden, embed, head = _from_torch(sd, path, "j{j}", "tau", ("head", "out"), None)
    model = TorqueModel(n_joints=n, hidden=hidden, embed=embed, head=head)
    _check_against_init(model, {"params": params}, n, path)
    return model, {"params": params}


def attention_params_from_torch(
    sd: dict, path: str = "<state dict>"
) -> tuple[AttentionModel, dict]:
    """The authors' attention state dict (``joint{j}_feature.{0,2}``, ``scorer.{0,2}``) -> Flax."""
    params, n, hidden, embed, scorer = _from_torch(sd, path, "joint{j}_feature", "scorer",
                                                   ("scorer", "score"), 1)
    model = AttentionModel(n_joints=n, hidden=hidden, embed=embed, scorer=scorer)
    _check_against_init(model, {"params": params}, n, path)
    return model, {"params": params}


def _check_against_init(model, variables, n, path):
    """Every tensor must have exactly the shape the architecture initialises."""
    ref_shapes = jax.tree_util.tree_map(lambda s: s.shape, parameter_shapes(model, n))
    got_shapes = jax.tree_util.tree_map(lambda a: a.shape, variables)
    if ref_shapes != got_shapes:
        raise WeightsError(f"{path}: tensors do not fit {model}: {got_shapes} vs {ref_shapes}")


def parameter_shapes(model, n_joints: int, n_models: int | None = None,
                     dtype=jnp.float32, n_inputs: int = 4):
    """The parameters ``model`` initialises for ``n_joints`` joints (``n_inputs`` features
    of ``dtype`` each), as :class:`jax.ShapeDtypeStruct` leaves (nothing computed), stacked
    ``n_models`` deep when given: what released weights, a model folder and a fine-tuning
    start must fit."""
    ref = _init_structs(model, n_joints, jnp.dtype(dtype).name, n_inputs)
    lead = () if n_models is None else (n_models,)
    return jax.tree_util.tree_map(lambda s: jax.ShapeDtypeStruct(lead + s.shape, s.dtype), ref)


@functools.lru_cache(maxsize=64)
def _init_structs(model, n: int, dtype: str, n_inputs: int = 4):
    """Traced once per architecture (a Flax module is a frozen dataclass, hashed by its
    fields), not once per weight file (the ten released pairs took a second to check)."""
    # The key and the input made inside the traced function: nothing runs on a device.
    return jax.eval_shape(lambda: model.init(jax.random.key(0),
                                             jnp.zeros((1, n, n_inputs), dtype)))


def load_released_pair(weights_dir: str | os.PathLike, index: int, *, prefer: str = "npz"):
    """One released model pair ``dict_torque_{index}`` / ``dict_attn_{index}``.

    Looks for ``.npz`` (or ``.pt`` with ``prefer="pt"``) and falls back to the other.
    Returns ``(torque_model, torque_vars, attention_model, attention_vars)``.
    """
    weights_dir = Path(weights_dir)
    out = []
    for stem, convert in (("dict_torque", torque_params_from_torch),
                          ("dict_attn", attention_params_from_torch)):
        exts = (".npz", ".pt") if prefer == "npz" else (".pt", ".npz")
        cands = [weights_dir / f"{stem}_{index}{e}" for e in exts]
        path = next((c for c in cands if c.exists()), None)
        if path is None:
            raise WeightsError(f"{cands[0]}: no such file (nor {cands[1].name})")
        out.extend(convert(load_state_dict(path), str(path)))
    return tuple(out)


def stack_params(variables: Sequence[dict]) -> dict:
    """Stacks K parameter pytrees of one architecture along a new leading axis (for vmap)."""
    return jax.tree_util.tree_map(lambda *a: jnp.stack(a), *variables)
