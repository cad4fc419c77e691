"""Trainings side by side in threads on one device: the wall time of T torque trainings'
epochs run at once (each its own program, its own thread), against one alone measured in
the same run. On a GPU a minibatch scan is a while loop whose every iteration may wait
for the host, and the host waits behind the other threads' work: run under different
XLA_FLAGS (e.g. ``--xla_gpu_enable_command_buffer=...,WHILE``) to compare.

    XLA_FLAGS=... python experiments/side_by_side_epochs.py
"""

import os
import threading
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxinertia import training
from jaxinertia.networks import TorqueModel

S, K, E = 40000, 10, 10


def main() -> None:
    rng = np.random.default_rng(0)
    model = TorqueModel()
    ep = training._torque_epoch(model, 3e-4, "all", 256)

    def job(g):
        X = jnp.asarray(rng.normal(size=(S, 4, 4)), jnp.float32)
        Y = jnp.asarray(rng.normal(size=(S, 4)), jnp.float32)
        st = ep.init(training._start(model, jax.random.key(g), K, X[:1], None), jnp.float32)
        return st, ((X, Y), None), ((X[:4000], Y[:4000]), None)

    jobs = [job(g) for g in range(4)]
    st, d, v = jobs[0]
    np.asarray(ep.update(st, jax.random.key(0), d, v)[1])  # compiled

    def run(j):
        st, d, v = jobs[j]
        for e in range(E):
            st, tl, _ = ep.update(st, jax.random.key(e), d, v)
            np.asarray(tl)

    print(f"device: {jax.devices()[0].device_kind}; XLA_FLAGS={os.environ.get('XLA_FLAGS', '')}")
    base = None
    for T in (1, 2, 4):
        threads = [threading.Thread(target=run, args=(j,)) for j in range(T)]
        t = time.perf_counter()
        for th in threads:
            th.start()
        for th in threads:
            th.join()
        w = (time.perf_counter() - t) / E
        base = base or w
        print(f"{T} trainings side by side: {w * 1e3:.1f} ms an epoch of each "
              f"({w / base:.2f} x one alone; {w / T / base:.2f} x per training)", flush=True)


if __name__ == "__main__":
    main()
