"""What XLA's GPU autotuner costs and gives the trainings' epoch programs: each epoch kind
of the held-out folds, one training alone and G = 4 vmapped as one program
(``training_group``), compiled with the autotuner (XLA's default) and without
(``xla_gpu_autotune_level=0``), then run; compile seconds and milliseconds per epoch, ratios
against the autotuned program in the same run. On a CPU there is no autotuner: both rows
are the same program (compiled once).

    python experiments/epoch_compile.py [--epochs 20]

Kinds: the physical torque model from scratch (40k samples, batch 256), its servo part
fine-tuned (900 samples), the attention model (``attention_group_speed``'s inputs: 1000
sets of 64 of 40k samples, batch 32, float64 as the command line trains it). Random inputs
of the folds' shapes: what is timed does not depend on the values.
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
from jaxinertia.networks import AttentionModel, PhysicalTorqueModel  # noqa: E402

K, G = 10, 4  # models per training; trainings per group (the kinds' inputs: G of them)


def _stack(parts):
    return jax.tree_util.tree_map(lambda *a: jnp.stack(a), *parts)


def _torque(rng, S: int, trainable: str, **epoch_kw):
    """G trainings of the physical torque model on random inputs of S samples (``epoch_kw``:
    ``training._torque_epoch``'s options)."""
    model = PhysicalTorqueModel(n_joints=4)
    ep = training._torque_epoch(model, 3e-4, trainable, min(256, S), **epoch_kw)

    def one(g):
        X = jnp.asarray(rng.normal(size=(S, 4, 4)), jnp.float32)
        Y = jnp.asarray(rng.normal(size=(S, 4)), jnp.float32)
        st = ep.init(training._start(model, jax.random.key(g), K, X[:1], None), jnp.float32)
        return st, ((X, Y), None), ((X[: S // 9], Y[: S // 9]), None)
    return ep, [one(g) for g in range(G)]


def _attention(rng, **epoch_kw):
    model = AttentionModel(n_joints=4)
    ep = training._attention_epoch(model, 1e-4, "all", 32, 1.0, 0.3, **epoch_kw)
    return ep, [training_inputs(rng, ep, model, g, jnp.float64) for g in range(G)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--epochs", type=int, default=20)
    ap.add_argument("--as-trained", action="store_true",
                    help="the epochs as the command line builds them on this backend "
                         "(training.accelerated_epochs: on a GPU the stacked joints and the "
                         "flat Adam)")
    args = ap.parse_args()
    gpu = jax.default_backend() == "gpu"
    print(f"device: {jax.devices()[0].device_kind}, K = {K} models per training")
    rng = np.random.default_rng(0)
    acc = training.accelerated_epochs() if args.as_trained else {}
    kinds = {"physical torque, from scratch (40k samples)": _torque(rng, 40000, "all", **acc),
             "physical torque, servo fine-tuning (900 samples)": _torque(rng, 900, "servo",
                                                                         **acc),
             "attention (1000 sets, float64)": _attention(rng, **acc)}
    for name, (ep, parts) in kinds.items():
        for g in (1, G):  # one training alone (as the simulated stages train), a group
            fn, args_g = group_inputs(ep, parts, g)
            base = None
            for label, options in (("autotuned", None),
                                   ("no autotuning", {"xla_gpu_autotune_level": 0} if gpu
                                    else None)):
                c, e = compile_and_time(fn, options, args_g, args.epochs)
                base = base or (c, e)
                print(f"{name}, G = {g}, {label}: compile {c:.2f} s ({c / base[0]:.2f} x), "
                      f"epoch {e * 1e3:.1f} ms ({e / base[1]:.2f} x)", flush=True)


def group_inputs(ep, parts, g: int):
    """The epoch function and its arguments (state, keys, data, validation data) for one
    training alone (``g`` = 1, the first of ``parts``) or the G of ``parts`` vmapped."""
    if g == 1:
        state, data, val = parts[0]
        return ep.update_fn, (state, jax.random.key(0), data, val)
    state, data, val = (_stack(x) for x in zip(*parts))
    return jax.vmap(ep.update_fn), (state, jax.random.split(jax.random.key(0), G), data, val)


def compile_and_time(fn, options, args, epochs: int) -> tuple[float, float]:
    """Seconds to compile ``fn`` with the compiler ``options`` for ``args``, and seconds per
    epoch over ``epochs`` epochs after a first one."""
    update = jax.jit(fn, compiler_options=options)
    t = time.perf_counter()
    compiled = update.lower(*args).compile()
    c = time.perf_counter() - t
    st, keys, data, val = args
    st, loss, _ = compiled(st, keys, data, val)
    np.asarray(loss)
    t = time.perf_counter()
    for _ in range(epochs):
        st, loss, _ = compiled(st, keys, data, val)
        np.asarray(loss)
    return c, (time.perf_counter() - t) / epochs

if __name__ == "__main__":
    main()
