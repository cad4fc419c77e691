"""Does a training repeat bit for bit on this GPU? The folds' grouped physical torque epoch
(G = 4 trainings of K = 10 models, 74k samples, batch 256, as a GPU builds it), five
epochs, in fresh processes: XLA compiles (and on a GPU autotunes: times candidate kernels
and keeps the fastest) anew in each. Runs with the GPU idle and beside a process that
loads it (as the folds' other programs do), with XLA's defaults, with
``--xla_gpu_deterministic_ops``, and with a per-fusion autotune cache (the first run
autotunes and writes it, the later ones read it); per run a digest of the parameters and
the epoch time.

    python experiments/gpu_repeat.py [--runs 2] [--configs NAME ...] [--idle-only]

docs/benchmarks.md ("A GPU run does not repeat") records what it printed.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import subprocess
import sys
import tempfile
import time

#: XLA flags per configuration ({autotune_dir}: one new folder for all runs of the run).
CONFIGS = {"XLA's defaults": "", "deterministic ops": "--xla_gpu_deterministic_ops=true",
           "autotune cache": "--xla_gpu_per_fusion_autotune_cache_dir={autotune_dir}"}


def child() -> None:
    import jax
    import jax.numpy as jnp
    import numpy as np
    from epoch_step import _stack, _torque_parts

    from jaxinertia import training
    from jaxinertia.networks import PhysicalTorqueModel

    parts = _torque_parts(np.random.default_rng(0), PhysicalTorqueModel(), 74000, 4)
    ep = training._torque_epoch(PhysicalTorqueModel(), 3e-4, "all", 256, (),
                                **training.accelerated_epochs())
    st = _stack([ep.init(p, jnp.float32) for p, *_ in parts])
    data, val = _stack([d for _, d, _ in parts]), _stack([v for *_, v in parts])
    keys = jax.random.split(jax.random.key(0), 4)
    update = jax.jit(jax.vmap(ep.update_fn))
    st, loss, _ = update(st, keys, data, val)
    np.asarray(loss)
    t = time.perf_counter()
    for _ in range(4):
        st, loss, _ = update(st, keys, data, val)
        np.asarray(loss)
    ms = (time.perf_counter() - t) / 4 * 1e3
    h = hashlib.sha256()
    for leaf in jax.tree_util.tree_leaves(jax.device_get(st.params)):
        h.update(np.ascontiguousarray(leaf).tobytes())
    print(f"{h.hexdigest()[:16]} {ms:.1f}", flush=True)


def load() -> None:
    """Keeps the GPU busy with products of many sizes until killed."""
    import jax
    import jax.numpy as jnp
    f = jax.jit(lambda a: jnp.tanh(a @ a) * 0.5)
    xs = [jnp.ones((n, n), jnp.float32) * 0.01 for n in (64, 512, 2048)]
    while True:
        for x in xs:
            f(x).block_until_ready()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=2)
    ap.add_argument("--configs", nargs="+", choices=list(CONFIGS), default=list(CONFIGS))
    ap.add_argument("--idle-only", action="store_true", help="no runs beside a GPU load")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--load", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        return child()
    if args.load:
        return load()
    here = os.path.dirname(os.path.abspath(__file__))
    base_env = {**os.environ, "XLA_PYTHON_CLIENT_PREALLOCATE": "false"}
    first = None
    tmp = tempfile.mkdtemp(prefix="gpu_repeat_")
    for name in args.configs:
        flags = CONFIGS[name].format(autotune_dir=os.path.join(tmp, "autotune"))
        env = {**base_env, "XLA_FLAGS": (base_env.get("XLA_FLAGS", "") + " " + flags).strip()}
        for loaded in (False,) if args.idle_only else (False, True):
            loader = (subprocess.Popen([sys.executable, __file__, "--load"], env=base_env,
                                       cwd=here) if loaded else None)
            try:
                time.sleep(5 if loaded else 0)
                for r in range(args.runs):
                    out = subprocess.run([sys.executable, __file__, "--child"], env=env,
                                         cwd=here, capture_output=True, text=True, check=True)
                    digest, ms = out.stdout.split()[-2:]
                    first = first or digest
                    print(f"{name}, GPU {'loaded' if loaded else 'idle'}, run {r + 1}: "
                          f"parameters {digest} ({'the same as' if digest == first else 'not'}"
                          f" the first run's), epoch {ms} ms", flush=True)
            finally:
                if loader is not None:
                    loader.kill()
                    loader.wait()


if __name__ == "__main__":
    main()
