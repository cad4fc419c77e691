"""What one minibatch step of the trainings costs on this device, and ways to make it
cheaper without changing the model: Adam on the parameters raveled into one vector
(``optax.flatten``: a few update kernels instead of a few per parameter), the joints'
embedding layers as batched products (``stacked_joints``: one kernel per layer instead of
one per joint), and both (``training.accelerated_epochs``: what a GPU trains with). (The
scan's loop unrolled gained nothing: 0.99-1.17 x an epoch on an H100, 1.0-2.3 x the compile;
``experiments/train_step_flags.py`` found the same on an H200.) Per epoch kind and group
size G (``training_group``'s vmapped program): compile seconds and milliseconds per
epoch, ratios against the plain epoch in the same run, and whether the variant's
parameters after two epochs equal the plain one's bit for bit.

    python experiments/epoch_step.py [--epochs 10] [--samples 74000]

Shapes of ``reproduce --full``'s held-out folds: K = 10 models per training, 74k training
samples (82,144 simulated, 10 % for validation), batch 256; the attention as
``attention_group_speed`` draws it (1000 sets of 64, batch 32, float64). Random inputs:
the step's cost does not depend on the values (but see docs/benchmarks.md on what random
inputs did not predict about the autotuner).
"""

from __future__ import annotations

import argparse
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from attention_group_speed import training_inputs  # noqa: E402 - the sibling's inputs

from jaxinertia import training  # noqa: E402
from jaxinertia.networks import AttentionModel, PhysicalTorqueModel, TorqueModel  # noqa: E402

K = 10
VARIANTS = {"plain": {}, "flat Adam": dict(flat=True), "stacked joints": dict(stacked=True),
            "both (a GPU's epochs)": training.accelerated_epochs("gpu")}


def _stack(parts):
    return jax.tree_util.tree_map(lambda *a: jnp.stack(a), *parts)


def _torque_parts(rng, model, S: int, G: int):
    def one(g):
        X = jnp.asarray(rng.normal(size=(S, 4, 4)), jnp.float32)
        Y = jnp.asarray(rng.normal(size=(S, 4)), jnp.float32)
        st = training._start(model, jax.random.key(g), K, X[:1], None)
        return st, ((X, Y), None), ((X[: S // 9], Y[: S // 9]), None)
    return [one(g) for g in range(G)]


def _measure(make, parts, epochs: int, loss_dtype):
    """Per variant: compile s, epoch s, parameters after two epochs."""
    G = len(parts)
    out = {}
    for name, kw in VARIANTS.items():
        ep = make(**kw)
        starts = [ep.init(p, loss_dtype) for p, *_ in parts]
        state, data, val = _stack(starts), _stack([d for _, d, _ in parts]), \
            _stack([v for *_, v in parts])
        keys = jax.random.split(jax.random.key(0), G)
        update = jax.jit(jax.vmap(ep.update_fn))
        t = time.perf_counter()
        compiled = update.lower(state, keys, data, val).compile()
        c = time.perf_counter() - t
        st, loss, _ = compiled(state, keys, data, val)
        st, loss, _ = compiled(st, keys, data, val)
        after_two = jax.device_get(st.params)
        t = time.perf_counter()
        for _ in range(epochs):
            st, loss, _ = compiled(st, keys, data, val)
            np.asarray(loss)
        out[name] = (c, (time.perf_counter() - t) / epochs, after_two)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--epochs", type=int, default=10)
    ap.add_argument("--samples", type=int, default=74000)
    args = ap.parse_args()
    print(f"device: {jax.devices()[0].device_kind}, K = {K} models per training", flush=True)
    rng = np.random.default_rng(0)
    am = AttentionModel(n_joints=4)
    kinds = []
    for mname, cls in (("paper", TorqueModel), ("physical", PhysicalTorqueModel)):
        for G in (2, 4):
            kinds.append((f"{mname} torque from scratch, G = {G}",
                          lambda cls=cls, **kw: training._torque_epoch(
                              cls(), 3e-4, "all", 256, **kw),
                          _torque_parts(rng, cls(), args.samples, G), jnp.float32))
    ep0 = training._attention_epoch(am, 1e-4, "all", 32, 1.0, 0.3)
    att = [training_inputs(rng, ep0, am, g, jnp.float64) for g in range(4)]
    kinds.append(("attention, G = 4",
                  lambda **kw: training._attention_epoch(am, 1e-4, "all", 32, 1.0, 0.3, **kw),
                  [(st.params, d, v) for st, d, v in att], jnp.float64))
    for name, make, parts, dtype in kinds:
        res = _measure(make, parts, args.epochs, dtype)
        c0, e0, p0 = res["plain"]
        for v, (c, e, p) in res.items():
            same = all(np.array_equal(a, b) for a, b in zip(jax.tree_util.tree_leaves(p0),
                                                             jax.tree_util.tree_leaves(p)))
            print(f"{name}, {v}: compile {c:.2f} s ({c / c0:.2f} x), epoch {e * 1e3:.1f} ms "
                  f"({e / e0:.2f} x), parameters after two epochs "
                  f"{'the same bit for bit' if same else 'differ'}", flush=True)


if __name__ == "__main__":
    main()
