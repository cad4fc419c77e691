"""Training side by side with the authors' own scripts: same data, same work per epoch,
per-epoch timestamps on both sides.

    python experiments/bench_authors_train.py [--torque-epochs 3] [--attention-epochs 1]
        [--train-dir runs/bench_authors] [--json OUT]

Theirs: ``shared/lbipe/authors/torque_train.py`` and ``attn_train.py``, run unchanged as
subprocesses in ``--train-dir`` (they read ``data/data_train_*.npz`` there and write
``dicts/``; the paper-scale simulated set is made there in their names when absent). Each
prints ``Epoch N`` as epoch N starts; the time between successive lines is one epoch
(training loop and validation loop), and the run is stopped once the epochs asked for are
timed. Ours: :func:`jaxinertia.training.train_torque_models` and
:func:`~jaxinertia.training.train_attention_models` for one model pair on the same samples
(torque: their 82,144 training and 4,000 validation samples, batch 256; attention: 61,608
sets of 64 per epoch drawn from the same six files, batch 32, and 3,000 validation sets, as
theirs), timed from the ``on_epoch`` callback; the first epoch (compilation) is reported
apart. Theirs and ours alternate (theirs' torque, ours' torque, theirs' attention, ours'
attention), so a busy machine slows both alike. Needs PyTorch (a throwaway venv on the CPU).
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np

from jaxinertia import apply_xla_workarounds

jax.config.update("jax_enable_x64", True)

from bench_authors import _training_files, machine  # noqa: E402

from jaxinertia.lbipe import default_lbipe_dir  # noqa: E402
from jaxinertia.samples import Samples, load_lbipe  # noqa: E402
from jaxinertia.training import (  # noqa: E402
    TrainConfig,
    feature_config_from,
    train_attention_models,
    train_torque_models,
)

LOADS = ("0g", "50g", "100g", "150g")


def theirs(script: Path, train_dir: Path, n_epochs: int) -> dict:
    """Runs one of their training scripts until ``n_epochs`` epochs are timed; returns the
    seconds to the first epoch (loading, datasets) and each epoch's seconds."""
    (train_dir / "dicts").mkdir(exist_ok=True)
    t0 = time.perf_counter()
    stamps = []
    proc = subprocess.Popen([sys.executable, "-u", str(script)], cwd=train_dir,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        for line in proc.stdout:
            if line.startswith("Epoch "):
                stamps.append(time.perf_counter())
                print(f"  theirs {script.name}: {line.strip()} at "
                      f"{stamps[-1] - t0:.1f} s", flush=True)
                if len(stamps) > n_epochs:
                    break
            elif "Error" in line or "Traceback" in line:
                print("  theirs:", line.rstrip(), flush=True)
    finally:
        proc.kill()
        out = proc.communicate()[0]
    if len(stamps) <= n_epochs:
        sys.exit(f"{script.name} ended before {n_epochs} epochs were timed:\n{out[-2000:]}")
    return {"setup_s": stamps[0] - t0, "epoch_s": np.diff(stamps).tolist()}


def ours(fn, n_epochs: int) -> dict:
    """``fn(epochs, on_epoch)``; the first epoch (with compilation) and the others apart."""
    stamps = [time.perf_counter()]
    fn(n_epochs + 1, lambda e, losses: stamps.append(time.perf_counter()))
    d = np.diff(stamps)
    return {"first_epoch_s": float(d[0]), "epoch_s": d[1:].tolist()}


def load_theirs(data: Path) -> dict[str, Samples]:
    """Their training and validation selections (torque_train.py / attn_train.py): every
    planning sample, the random samples 0-8999 for training and 9000-9999 for validation."""
    out = {}
    for load in LOADS:
        rand = load_lbipe(data / f"data_train_random_{load}.npz", f"random_{load}")
        if rand.n_samples < 10_000:
            sys.exit(f"{data} holds {rand.n_samples} random samples of {load}; their scripts "
                     "need 10,000 (delete the folder to make it again)")
        out[f"plan_{load}"] = load_lbipe(data / f"data_train_{load}.npz", f"plan_{load}")
        out[f"rand_{load}"] = rand.take(np.arange(9000))
        out[f"val_{load}"] = rand.take(np.arange(9000, 10_000))
    return out


def main() -> None:
    apply_xla_workarounds()  # XLA:CPU settings, before JAX starts its backend
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lbipe-dir", type=Path, default=None)
    ap.add_argument("--train-dir", type=Path, default=Path("runs/bench_authors"))
    ap.add_argument("--torque-epochs", type=int, default=3)
    ap.add_argument("--attention-epochs", type=int, default=1)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    authors = (args.lbipe_dir or default_lbipe_dir()) / "authors"
    try:
        import torch  # noqa: PLC0415
    except ImportError as e:
        sys.exit(f"the authors' scripts need PyTorch ({e}); install it in a throwaway venv")

    data = args.train_dir / "data"
    _training_files(data)
    d = load_theirs(data)
    torque_train = Samples.concatenate([d[f"{k}_{load}"] for k in ("plan", "rand")
                                        for load in LOADS])
    torque_val = Samples.concatenate([d[f"val_{load}"] for load in LOADS])
    # Their attention sets: 11,536 per planning file and 9,000 per random file of the three
    # loaded objects (61,608); ours the same number, 10,268 from each of the six.
    att = Samples.concatenate([d[f"{k}_{load}"] for k in ("plan", "rand")
                               for load in LOADS[1:]])
    att_val = Samples.concatenate([d[f"val_{load}"] for load in LOADS[1:]])
    cfg = TrainConfig(n_models=1, attention_sets=61_608 // 6, attention_val_sets=1000)
    fc = feature_config_from(torque_train)
    print(f"torque: {torque_train.n_samples} training, {torque_val.n_samples} validation "
          f"samples; attention: {cfg.attention_sets * att.n_objects} training and "
          f"{cfg.attention_val_sets * att_val.n_objects} validation sets per epoch", flush=True)
    key = jax.random.key(0)
    rows = {}

    print("torque model, theirs", flush=True)
    rows["torque_theirs"] = theirs(authors / "torque_train.py", args.train_dir,
                                   args.torque_epochs)
    print("torque model, ours", flush=True)
    trained = {}

    def torque(n, on_epoch):
        trained["torque"] = train_torque_models(cfg.replace(torque_epochs=n), fc, torque_train,
                                                torque_val, key, progress=False,
                                                on_epoch=on_epoch)
    rows["torque_ours"] = ours(torque, args.torque_epochs)

    print("attention model, theirs", flush=True)
    rows["attention_theirs"] = theirs(authors / "attn_train.py", args.train_dir,
                                      args.attention_epochs)
    print("attention model, ours", flush=True)
    rows["attention_ours"] = ours(
        lambda n, on_epoch: train_attention_models(
            cfg.replace(attention_epochs=n), fc, trained["torque"], att, att_val, key,
            progress=False, on_epoch=on_epoch), args.attention_epochs)

    summary = {}
    for part, paper_epochs in (("torque", 300), ("attention", 30)):
        t = statistics.median(rows[f"{part}_theirs"]["epoch_s"])
        o = statistics.median(rows[f"{part}_ours"]["epoch_s"])
        summary[part] = {"theirs_epoch_s": t, "ours_epoch_s": o, "ratio": t / o,
                         "paper_epochs": paper_epochs}
        print(f"{part}: theirs {t:.2f} s/epoch, ours {o:.3f} s/epoch after compilation "
              f"(first epoch {rows[f'{part}_ours']['first_epoch_s']:.1f} s): {t / o:.1f}x",
              flush=True)
    t_all = sum(s["theirs_epoch_s"] * s["paper_epochs"] for s in summary.values())
    o_all = sum(s["ours_epoch_s"] * s["paper_epochs"] for s in summary.values()) + sum(
        rows[f"{p}_ours"]["first_epoch_s"] - summary[p]["ours_epoch_s"] for p in summary)
    summary["pair_300_30"] = {"theirs_s": t_all, "ours_s": o_all, "ratio": t_all / o_all}
    print(f"one model pair, 300 + 30 epochs: theirs {t_all:.0f} s, ours {o_all:.0f} s "
          f"(compilation included): {t_all / o_all:.1f}x", flush=True)
    out = {"machine": machine(torch), "runs": rows, "summary": summary}
    print(out["machine"])
    if args.json:
        args.json.write_text(json.dumps(out, indent=2) + "\n")


if __name__ == "__main__":
    main()
