"""The attention training's epoch on this device (K = 10 models, 1000 sets of 64 from 40k
samples, batch 32), in float64 (what the command line trains in: ``enable_x64``) and in
float32, alone and G = 4 vmapped as one program; ratios against float64 alone, measured in
the same run.

    python experiments/attention_group_speed.py
"""


import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from group_speed import time_epochs  # noqa: E402 - the sibling script's epoch timer

from jaxinertia import training  # noqa: E402
from jaxinertia.networks import AttentionModel  # noqa: E402

K, N, E = 10, 40000, 10


def training_inputs(rng, ep, model, g: int, dtype):
    """One attention training's start, data and validation data (random, N samples,
    1000 sets of 64 and 200 validation sets)."""
    feats = jnp.asarray(rng.normal(size=(N, 4, 4)), jnp.float32)
    A = jnp.asarray(rng.normal(size=(N, 4, 4)), dtype)
    x_obj = jnp.asarray(rng.normal(size=(N, 4)) * 0.05 + [0.1, 0, 0, 0], dtype)
    sets = jnp.asarray(rng.integers(0, N, size=(1000, 64)), jnp.int32)
    y = jnp.asarray(rng.normal(size=(K, N, 4)), dtype)
    st = ep.init(training._start(model, jax.random.key(g), K, feats[:1], None), dtype)
    return st, ((feats, A, x_obj, sets), y), ((feats, A, x_obj, sets[:200]), y)


def main() -> None:
    rng = np.random.default_rng(0)
    am = AttentionModel(n_joints=4)
    ep = training._attention_epoch(am, 1e-4, "all", 32, 1.0, 0.3)
    grouped = jax.jit(jax.vmap(ep.update))
    print(f"device: {jax.devices()[0].device_kind}")
    base = None
    for dtype in (jnp.float64, jnp.float32):
        for G in (1, 4):
            parts = [training_inputs(rng, ep, am, g, dtype) for g in range(G)]
            if G == 1:
                upd, (st, data, val) = ep.update, parts[0]
                keys = jax.random.key(0)
            else:
                upd = grouped
                st, data, val = (jax.tree_util.tree_map(lambda *a: jnp.stack(a), *xs)
                                 for xs in zip(*parts))
                keys = jax.random.split(jax.random.key(0), G)
            first, w, _ = time_epochs(upd, st, keys, data, val, E)
            base = base or w
            print(f"{jnp.dtype(dtype).name} G={G}: first epoch {first:.1f} s, epoch "
                  f"{w * 1e3:.1f} ms ({w / base:.2f} x float64 alone), per training "
                  f"{w / G * 1e3:.1f} ms ({w / G / base:.2f} x)", flush=True)


if __name__ == "__main__":
    main()
