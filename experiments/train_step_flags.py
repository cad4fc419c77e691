"""The cost of one training step on this device (torque and attention epochs, K = 10
models), with the minibatch scan unrolled U times (env UNROLL) and whatever XLA_FLAGS
say: does a step of small MLPs get cheaper by unrolling or by CUDA graphs?

    UNROLL=4 XLA_FLAGS=... python experiments/train_step_flags.py [results.jsonl]

docs/benchmarks.md, "Trainings as one program", records the H200 numbers (no flag helped).
"""
import functools
import json
import os
import sys
import time

import jax

U = int(os.environ.get("UNROLL", "1"))
if U > 1:
    _scan = jax.lax.scan
    jax.lax.scan = functools.partial(_scan, unroll=U)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from jaxinertia import training  # noqa: E402
from jaxinertia.networks import AttentionModel, PhysicalTorqueModel, TorqueModel  # noqa: E402

S, SV, K, E = int(os.environ.get("S", 40000)), 4000, 10, int(os.environ.get("E", 30))
rng = np.random.default_rng(0)
out = {"unroll": U, "xla_flags": os.environ.get("XLA_FLAGS", ""), "device": str(jax.devices()[0])}
for name, model in (("paper", TorqueModel()), ("physical", PhysicalTorqueModel())):
    X = jnp.asarray(rng.normal(size=(S, 4, 4)), jnp.float32)
    Y = jnp.asarray(rng.normal(size=(S, 4)), jnp.float32)
    Xv, Yv = X[:SV], Y[:SV]
    ep = training._torque_epoch(model, 3e-4, "all", 256)
    p0 = training._start(model, jax.random.key(0), K, X[:1], None)
    st = ep.init(p0, jnp.float32)
    t = time.perf_counter()
    st, tl, vl = ep.update(st, jax.random.key(1), ((X, Y), None), ((Xv, Yv), None))
    np.asarray(tl)
    first = time.perf_counter() - t
    t = time.perf_counter()
    for e in range(E):
        st, tl, vl = ep.update(st, jax.random.key(e), ((X, Y), None), ((Xv, Yv), None))
        np.asarray(tl)
    warm = (time.perf_counter() - t) / E
    out[name] = {"first_epoch_s": first, "epoch_s": warm,
                 "step_us": warm / (S // 256) * 1e6, "loss": float(np.asarray(vl).mean())}
    print(name, out[name], flush=True)

# attention: 1000 sets of 64 from 40 objects' worth of samples, batch 32
am = AttentionModel(n_joints=4)
N = 16000
feats = jnp.asarray(rng.normal(size=(N, 4, 4)), jnp.float32)
A = jnp.asarray(rng.normal(size=(N, 4, 4)), jnp.float32)
x_obj = jnp.asarray(rng.normal(size=(N, 4)), jnp.float32)
sets = jnp.asarray(rng.integers(0, N, size=(1000, 64)), jnp.int32)
vsets = sets[:200]
y = jnp.asarray(rng.normal(size=(K, N, 4)), jnp.float32)
ep = training._attention_epoch(am, 1e-4, "all", 32, 1.0, 0.3)
p0 = training._start(am, jax.random.key(0), K, feats[:1], None)
st = ep.init(p0, jnp.float32)
data, vdata = ((feats, A, x_obj, sets), y), ((feats, A, x_obj, vsets), y)
t = time.perf_counter()
st, tl, vl = ep.update(st, jax.random.key(1), data, vdata)
np.asarray(tl)
first = time.perf_counter() - t
t = time.perf_counter()
for e in range(E):
    st, tl, vl = ep.update(st, jax.random.key(e), data, vdata)
    np.asarray(tl)
warm = (time.perf_counter() - t) / E
out["attention"] = {"first_epoch_s": first, "epoch_s": warm, "step_us": warm / (1000 // 32) * 1e6,
                    "loss": float(np.asarray(vl).mean())}
print("attention", out["attention"], flush=True)
if len(sys.argv) > 1:
    with open(sys.argv[1], "a") as f:
        f.write(json.dumps(out) + "\n")
