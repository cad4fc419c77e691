"""Trainings as one program (jaxinertia.training_group): the device time of one torque
epoch of G trainings (K = 10 models each, 40k samples, batch 256) vmapped over the group,
against one training alone measured in the same run; and whether the group's parameters
after three epochs are each training's own bit for bit.

    python experiments/group_speed.py        # on the device to measure (CPU or GPU)

docs/benchmarks.md, "Trainings as one program", records what it printed.
"""

import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxinertia import training
from jaxinertia.networks import PhysicalTorqueModel, TorqueModel

S, K, E = 40000, 10, 20


def _stack(trees):
    return jax.tree_util.tree_map(lambda *a: jnp.stack(a), *trees)


def time_epochs(update, state, keys, data, val, n: int):
    """The first call's seconds (compiling), then the seconds per epoch over ``n`` more
    (each waited for), and the state after them."""
    t = time.perf_counter()
    state, loss, _ = update(state, keys, data, val)
    np.asarray(loss)
    first = time.perf_counter() - t
    t = time.perf_counter()
    for _ in range(n):
        state, loss, _ = update(state, keys, data, val)
        np.asarray(loss)
    return first, (time.perf_counter() - t) / n, state


def main() -> None:
    rng = np.random.default_rng(0)
    print(f"device: {jax.devices()[0].device_kind}")
    for name, model in (("paper", TorqueModel()), ("physical", PhysicalTorqueModel())):
        ep = training._torque_epoch(model, 3e-4, "all", 256)
        grouped = jax.jit(jax.vmap(ep.update))
        base = None
        for G in (1, 2, 4, 6):
            X = jnp.asarray(rng.normal(size=(G, S, 4, 4)), jnp.float32)
            Y = jnp.asarray(rng.normal(size=(G, S, 4)), jnp.float32)
            starts = [ep.init(training._start(model, jax.random.key(g), K, X[g][:1], None),
                              jnp.float32) for g in range(G)]
            data, val = ((X, Y), None), ((X[:, :4000], Y[:, :4000]), None)
            keys = jax.random.split(jax.random.key(0), G)
            _, w, _ = time_epochs(grouped, _stack(starts), keys, data, val, E)
            base = base or w
            # The group after three epochs against each training alone.
            same = True
            st = _stack(starts)
            alone = list(starts)
            for _ in range(3):
                st, _, _ = grouped(st, keys, data, val)
                for g in range(G):
                    alone[g], _, _ = ep.update(alone[g], keys[g], ((X[g], Y[g]), None),
                                               ((X[g, :4000], Y[g, :4000]), None))
            for g in range(G):
                same &= all(np.array_equal(np.asarray(a), np.asarray(b[g])) for a, b in zip(
                    jax.tree_util.tree_leaves(alone[g].params),
                    jax.tree_util.tree_leaves(st.params)))
            print(f"{name} G={G}: epoch {w * 1e3:.1f} ms ({w / base:.2f} x one training's), "
                  f"per training {w / G * 1e3:.1f} ms ({w / G / base:.2f} x); "
                  f"{'bit for bit' if same else 'NOT bit for bit'} each training alone",
                  flush=True)


if __name__ == "__main__":
    main()
