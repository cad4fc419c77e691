"""Training throughput: torque model (batch 256) and attention model (32 sets of 64).

Measures epochs per second after compilation (from per-epoch timestamps) for K = 1 and K
model pairs trained together (vmap), on the paper's training-set size (82,144 samples) or a
sample file, and reports samples/s and the extrapolated wall time of the paper's 300 + 30
epochs. When PyTorch is importable, the same torque-model training (same architecture, batch
256, Adam, a shuffled minibatch loop as in the authors' code base) is timed in the same run as
the reference.

    python experiments/bench_train.py [--data FILE] [--models 10] [--epochs 5]
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import jax

from jaxinertia import apply_xla_workarounds

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from jaxinertia.features import featurize  # noqa: E402
from jaxinertia.samples import Samples, load_samples  # noqa: E402
from jaxinertia.training import (  # noqa: E402
    TrainConfig,
    feature_config_from,
    split_validation,
    train_attention_models,
    train_torque_models,
)

PAPER_SAMPLES = 82144


def synthetic(n: int, seed: int = 0) -> Samples:
    """Arrays of the right shapes and plausible ranges (throughput does not depend on the
    values); four objects as the paper's training loads."""
    rng = np.random.default_rng(seed)
    q = rng.uniform(-0.8, 0.8, (n, 4))
    s = rng.choice([-1.0, 1.0], (n, 4))
    A = rng.normal(size=(n, 4, 4)) * [1.0, 0.1, 0.1, 0.1]
    x = np.array([[0.0, 0, 0, 0], [0.05, 0, 0, -1e-3], [0.1, 0, 0, -2e-3], [0.15, 0, 0, -3e-3]])
    oid = np.arange(n) % 4
    tau_g = rng.normal(size=(n, 4)) * 0.3
    tau = tau_g + np.einsum("snp,sp->sn", A, x[oid])
    return Samples(q_d=q + tau / 17.0, q=q, direction=s, current_tau=tau, tau=tau,
                   tau_g=tau_g, A=A, object_id=oid, x=x, names=("0g", "50g", "100g", "150g"))


def time_epochs(fn, n_epochs: int) -> float:
    """Seconds per epoch after compilation, from one run of n + 1 epochs: ``fn(epochs,
    on_epoch)`` calls ``on_epoch`` after each epoch (its losses on the host), and the time from
    the end of the first epoch (compilation and first-use costs) to the end of the last,
    divided by n, is the steady epoch time (no subtraction of separate runs)."""
    stamps = []
    fn(n_epochs + 1, lambda e, losses: stamps.append(time.perf_counter()))
    return (stamps[-1] - stamps[0]) / n_epochs


def torch_reference(train: Samples, fc, n_epochs: int) -> tuple[float, str] | None:
    """Seconds per torque-model epoch in PyTorch (on CUDA when it has a GPU, as the authors
    would train), or None without PyTorch."""
    try:  # PyTorch is optional (the reference only)
        import torch
        from torch import nn
    except ImportError:
        return None
    torch.set_num_threads(len(os.sched_getaffinity(0)))
    dev = "cuda" if torch.cuda.is_available() else "cpu"
    X = torch.tensor(np.asarray(featurize(fc, train.q, train.q_d, train.direction)),
                     dtype=torch.float32, device=dev)
    Y = torch.tensor(train.tau / np.asarray(fc.tau_scale), dtype=torch.float32, device=dev)

    class Torque(nn.Module):  # the paper's architecture, written as the authors' modules
        def __init__(self):
            super().__init__()
            self.j = nn.ModuleList([nn.Sequential(nn.Linear(4, 12), nn.ReLU(), nn.Linear(12, 12))
                                    for _ in range(4)])
            self.tau = nn.Sequential(nn.Linear(48, 64), nn.ReLU(), nn.Linear(64, 64), nn.ReLU(),
                                     nn.Linear(64, 4))

        def forward(self, x):
            return self.tau(torch.cat([m(x[:, j]) for j, m in enumerate(self.j)], dim=-1))

    model = Torque().to(dev)
    opt = torch.optim.Adam(model.parameters(), lr=3e-4)
    loader = torch.utils.data.DataLoader(torch.utils.data.TensorDataset(X, Y), batch_size=256,
                                         shuffle=True)

    def run(epochs):
        for _ in range(epochs):
            for xb, yb in loader:
                opt.zero_grad()
                loss = ((model(xb) - yb) ** 2).mean()
                loss.backward()
                opt.step()

    def sync():
        if dev == "cuda":
            torch.cuda.synchronize()

    run(1)
    sync()
    t = time.perf_counter()
    run(n_epochs)
    sync()
    return (time.perf_counter() - t) / n_epochs, dev


def torch_version() -> str:
    import torch

    return torch.__version__


def main() -> None:
    apply_xla_workarounds()  # XLA:CPU settings, before JAX starts its backend
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", help="a native sample file (default: synthetic, paper size)")
    ap.add_argument("--models", type=int, default=10)
    ap.add_argument("--epochs", type=int, default=5, help="timed epochs per measurement")
    args = ap.parse_args()
    if args.data:
        data = load_samples(args.data)[0]
    else:
        data = synthetic(PAPER_SAMPLES)
    train, val = split_validation(data, 0.1, 0)
    fc = feature_config_from(train)
    dev = jax.devices()[0]
    cores = len(os.sched_getaffinity(0))
    print(f"# {platform.machine()}, {cores} CPU cores, JAX {jax.__version__} on "
          f"{dev.platform} ({getattr(dev, 'device_kind', '')}); {train.n_samples} training "
          f"samples")
    key = jax.random.key(0)
    rows = []
    torque = None
    for K in sorted({1, args.models}):
        cfg = TrainConfig(n_models=K)

        def run_t(e, on_epoch, cfg=cfg):
            nonlocal torque
            torque = train_torque_models(cfg.replace(torque_epochs=e), fc, train, val, key,
                                         progress=False, on_epoch=on_epoch)

        s_t = time_epochs(run_t, args.epochs)

        def run_a(e, on_epoch, cfg=cfg):
            train_attention_models(cfg.replace(attention_epochs=e), fc, torque, train, val, key,
                                   progress=False, on_epoch=on_epoch)

        s_a = time_epochs(run_a, max(1, args.epochs // 2))
        total = 300 * s_t + 30 * s_a
        rows.append((K, s_t, K * train.n_samples / s_t, s_a, total))
        print(f"K={K:<3} torque {s_t * 1e3:8.1f} ms/epoch ({K * train.n_samples / s_t:,.0f} "
              f"samples/s)  attention {s_a * 1e3:8.1f} ms/epoch  300+30 epochs: {total:6.1f} s "
              f"({total / K:.1f} s per model pair)")
    ref = torch_reference(train, fc, args.epochs)
    if ref is None:
        print("PyTorch not importable: no reference in this run")
    else:
        ref, where = ref
        K1 = rows[0][1]
        print(f"PyTorch {torch_version()} reference (same architecture and loop, {where}): "
              f"{ref * 1e3:.1f} ms/epoch "
              f"-> jaxinertia K=1 is {ref / K1:.1f}x faster; K={rows[-1][0]} per model pair "
              f"{ref / (rows[-1][1] / rows[-1][0]):.1f}x")


if __name__ == "__main__":
    main()
