"""The authors' test procedure, one set and one model at a time, in plain numpy.

An independent reference for the batched evaluator (:func:`jaxinertia.evaluation.evaluate`):
explicit ``(A^T W A)^-1 A^T W y`` per set as in the paper's eq. 15, with the networks
re-implemented as numpy MLPs from the same parameters. Also the per-set loop that
``experiments/bench_lbipe.py`` times the batched call against.
"""

from __future__ import annotations

import jax
import numpy as np

from jaxinertia.estimation import ModelPair

__all__ = ["reference_loop"]


def _np_mlp(layers, x):
    for i, (w, b) in enumerate(layers):
        x = x @ w + b
        if i < len(layers) - 1:
            x = np.maximum(x, 0.0)
    return x


def _np_params(pair: ModelPair, k: int):
    tv = jax.tree_util.tree_map(lambda a: np.asarray(a[k]), pair.torque_vars)["params"]
    av = jax.tree_util.tree_map(lambda a: np.asarray(a[k]), pair.attention_vars)["params"]

    def lyr(d):
        return (d["kernel"], d["bias"])

    n = pair.torque_model.n_joints
    t_joint = [[lyr(tv[f"joint{j}"]["hidden"]), lyr(tv[f"joint{j}"]["embed"])] for j in range(n)]
    t_head = [lyr(tv[f"head{i}"]) for i in range(len(pair.torque_model.head))] + [lyr(tv["out"])]
    a_joint = [[lyr(av[f"joint{j}"]["hidden"]), lyr(av[f"joint{j}"]["embed"])] for j in range(n)]
    a_score = [lyr(av[f"scorer{i}"]) for i in range(len(pair.attention_model.scorer))]
    a_score.append(lyr(av["score"]))
    return t_joint, t_head, a_joint, a_score


def reference_loop(pair: ModelPair, features: np.ndarray, A: np.ndarray, tau_g: np.ndarray,
                   sets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """x of T and T-A, (K, B, 4) each, set by set as the authors' test loop computes them.

    Args:
      features: (S, N, 4) float32 network inputs of one object's samples.
      A: (S, N, 4) load regressor; tau_g: (S, N); sets: (B, M) sample indices.
    """
    feats, A, tau_g = np.asarray(features), np.asarray(A), np.asarray(tau_g)
    scale = np.asarray(pair.tau_scale)
    n = A.shape[1]
    xs_t, xs_ta = [], []
    for k in range(pair.n_models):
        t_joint, t_head, a_joint, a_score = _np_params(pair, k)
        xt, xta = [], []
        for idx in np.asarray(sets):
            f = feats[idx]
            h = np.concatenate([_np_mlp(t_joint[j], f[:, j]) for j in range(n)], axis=-1)
            tau_hat = _np_mlp(t_head, h) * scale
            e = np.stack([_np_mlp(a_joint[j], f[:, j]) for j in range(n)], axis=1)
            z = np.broadcast_to(np.eye(n, dtype=e.dtype), e.shape[:2] + (n,))
            s = _np_mlp(a_score, np.concatenate([e, z], axis=-1))[..., 0]
            w = np.exp(s - s.max(axis=1, keepdims=True))
            w = w / w.sum(axis=1, keepdims=True)
            A_s = A[idx].reshape(-1, 4)
            y = (tau_hat.astype(np.float64) - tau_g[idx]).reshape(-1)
            for W, out in ((np.eye(A_s.shape[0]), xt), (np.diag(w.reshape(-1)), xta)):
                out.append(np.linalg.inv(A_s.T @ W @ A_s) @ A_s.T @ W @ y)
        xs_t.append(xt)
        xs_ta.append(xta)
    return np.asarray(xs_t), np.asarray(xs_ta)
