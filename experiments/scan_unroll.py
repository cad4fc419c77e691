"""Does unrolling the epoch's minibatch loop speed the trainings on a GPU? One minibatch step
of K small MLPs is a chain of small kernels; XLA runs ``lax.scan`` as a while loop whose
predicate the host reads back every iteration. Unrolling by ``u`` runs ``u`` steps per
iteration. Each kind of the held-out folds' epochs (the physical torque model from scratch
on the folds' 74k samples, its servo fine-tuning on 900, the attention on 1000 sets of 64),
G = 1 and a group of G = 4 vmapped, compiled as the command line compiles it
(``training.accelerated_epochs``, ``epoch_compiler_options``) at each ``--unroll``; compile
seconds and milliseconds per epoch, ratios against ``u = 1`` measured in the same run.

    python experiments/scan_unroll.py [--epochs 20] [--unroll 1 2 4 8]

Random inputs of the folds' shapes: what is timed does not depend on the values.
"""

from __future__ import annotations

import argparse
import contextlib
import functools

import jax

jax.config.update("jax_enable_x64", True)

import epoch_compile  # noqa: E402 - the sibling's inputs
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from attention_group_speed import training_inputs  # noqa: E402

from jaxinertia import training  # noqa: E402
from jaxinertia.networks import AttentionModel  # noqa: E402

K, G = epoch_compile.K, epoch_compile.G


@contextlib.contextmanager
def unrolled(u: int):
    """``lax.scan`` unrolled by ``u`` while the epochs are traced (the epoch caches emptied)."""
    scan = jax.lax.scan
    jax.lax.scan = functools.partial(scan, unroll=u)
    training._torque_epoch.cache_clear()
    training._attention_epoch.cache_clear()
    try:
        yield
    finally:
        jax.lax.scan = scan


def _torque(rng, S: int, trainable: str, epochs: int):
    batch = min(256, S)
    return epoch_compile._torque(
        rng, S, trainable, **training.accelerated_epochs(),
        compiler_options=training.epoch_compiler_options(epochs * (S // batch)))


def _attention(rng):
    model = AttentionModel(n_joints=4)
    ep = training._attention_epoch(model, 1e-4, "all", 32, 1.0, 0.3,
                                   training.epoch_compiler_options(30 * 1000 // 32),
                                   **training.accelerated_epochs())
    return ep, [training_inputs(rng, ep, model, g, jnp.float64) for g in range(G)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--epochs", type=int, default=20)
    ap.add_argument("--unroll", type=int, nargs="+", default=[1, 2, 4, 8])
    args = ap.parse_args()
    print(f"device: {jax.devices()[0].device_kind}, K = {K} models per training")
    base: dict = {}
    for u in args.unroll:
        with unrolled(u):
            rng = np.random.default_rng(0)
            kinds = {"physical torque from scratch (74k samples)":
                     _torque(rng, 74000, "all", 300),
                     "physical torque, servo fine-tuning (900 samples)":
                     _torque(rng, 900, "servo", 200),
                     "attention (1000 sets, float64)": _attention(rng)}
            for name, (ep, parts) in kinds.items():
                for g in (1, G):
                    fn, args_g = epoch_compile.group_inputs(ep, parts, g)
                    c, e = epoch_compile.compile_and_time(
                        fn, dict(ep.compiler_options) or None, args_g, args.epochs)
                    b = base.setdefault((name, g), (c, e))
                    print(f"unroll {u}: {name}, G = {g}: compile {c:.2f} s ({c / b[0]:.2f} x), "
                          f"epoch {e * 1e3:.1f} ms ({e / b[1]:.2f} x)", flush=True)

if __name__ == "__main__":
    main()
