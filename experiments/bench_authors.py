"""Side by side with the authors' own evaluation code, same work, same process.

    python experiments/bench_authors.py [--lbipe-dir DIR] [--rounds 3] [--json OUT]

The authors' ``estimate_object`` (``shared/lbipe/authors/attn_test.py``, imported unchanged;
it needs PyTorch) evaluates one real object: the ten released model pairs, 1000 random
sets of 64 samples, Sensor / PE / T / T-A by their pseudo-inverse per set. Ours is
:func:`jaxinertia.evaluation.evaluate` on the same object, pairs and number of sets (T and
T-A; their two baselines are 2 of the 22 solves per set they do). Rounds interleave the two
so that a busy machine slows both alike; the first of ours includes compilation. Prints the
medians and the ratio; the results go in docs/benchmarks.md with the machine.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np

from jaxinertia import apply_xla_workarounds

jax.config.update("jax_enable_x64", True)

from jaxinertia.app.pipeline import load_real  # noqa: E402
from jaxinertia.evaluation import evaluate  # noqa: E402
from jaxinertia.features import LBIPE_FEATURES  # noqa: E402
from jaxinertia.lbipe import default_lbipe_dir, load_released_models  # noqa: E402


def _authors(lbipe_dir: Path):
    """The authors' estimate_object and model classes, imported from their folder."""
    sys.path.insert(0, str(lbipe_dir / "authors"))
    import attn_test  # noqa: PLC0415  (theirs, only here: it needs torch)
    from lbipe.models import AttnModel, TorqueModel  # noqa: PLC0415
    return attn_test.estimate_object, TorqueModel, AttnModel


def machine(torch) -> str:
    """The host, torch's build and threads, and JAX's device: the line a result is filed
    under."""
    dev = jax.devices()[0]
    return (f"{platform.machine()} {os.cpu_count()} CPU cores, torch {torch.__version__} "
            f"({torch.get_num_threads()} threads), JAX {jax.__version__} on {dev.platform} "
            f"({getattr(dev, 'device_kind', dev.platform)})")


def _training_files(data: Path) -> None:
    """The paper-scale simulated training set in the names their baselines load:
    ``data_train_<load>.npz`` (planning grid) and ``data_train_random_<load>.npz``."""
    last = data / "data_train_random_150g.npz"
    if last.exists() and len(np.load(last)["joint_data"]) >= 10_000:
        return
    # their training cuts random samples 0-8999 of each load for training and 9000-9999
    # for validation: a few more, as some time out
    for scenario, extra in (("planning", []), ("random", ["--n", "10100"])):
        tmp = data.parent / scenario
        subprocess.run([sys.executable, "-m", "jaxinertia", "simulate", "--scenario", scenario,
                        *extra, "--format", "lbipe", "--out", str(tmp), "--overwrite"],
                       check=True, stdout=subprocess.DEVNULL)
        data.mkdir(parents=True, exist_ok=True)
        for f in tmp.glob("data_train_*.npz"):
            name = f.name if scenario == "planning" else f.name.replace("train_", "train_random_")
            f.replace(data / name)


def main() -> None:
    apply_xla_workarounds()  # XLA:CPU settings, before JAX starts its backend
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lbipe-dir", type=Path, default=None)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--train-dir", type=Path, default=Path("runs/bench_authors"),
                    help="where their baselines find data/data_train_*.npz (their code fits "
                    "the Sensor and PE baselines on the training files at every call); made "
                    "here from the simulator at paper scale when absent")
    args = ap.parse_args()
    lbipe_dir = args.lbipe_dir or default_lbipe_dir()
    try:
        estimate_object, TorqueModel, AttnModel = _authors(lbipe_dir)
    except ImportError as e:
        sys.exit(f"the authors' code needs PyTorch ({e}); install it in a throwaway venv")
    import torch  # noqa: PLC0415

    _training_files(args.train_dir / "data")
    weights = (lbipe_dir / "weights").resolve()
    torque_files = [str(weights / f"dict_torque_{i}.pt") for i in range(1, 11)]
    attn_files = [str(weights / f"dict_attn_{i}.pt") for i in range(1, 11)]
    real = load_real(lbipe_dir)
    pair = load_released_models(real.layout.weights_dir, prefer=real.layout.prefer)
    rows = {}
    for obj, sets, l_max, path in zip(real.objects, real.sets, real.l_max,
                                      real.layout.test_files.values()):
        pack = dict(np.load(path))
        theirs, ours = [], []
        for _ in range(args.rounds):
            t = time.perf_counter()
            with contextlib.redirect_stdout(io.StringIO()), contextlib.chdir(args.train_dir):
                estimate_object(TorqueModel, AttnModel, torque_files, attn_files, pack, l_max)
            theirs.append(time.perf_counter() - t)
            t = time.perf_counter()
            res = evaluate([obj], [sets], pair=pair, fc=LBIPE_FEATURES, l_max=[l_max])
            jax.block_until_ready(res["model_estimates"])
            ours.append(time.perf_counter() - t)
        rows[obj.name] = {"theirs_s": theirs, "ours_s": ours,
                          "ratio_after_compile": statistics.median(theirs)
                          / statistics.median(ours[1:] or ours),
                          "ratio_incl_compile": statistics.median(theirs) / ours[0]}
        r = rows[obj.name]
        print(f"{obj.name}: theirs {statistics.median(theirs):.2f} s, ours "
              f"{1e3 * statistics.median(ours[1:] or ours):.1f} ms after compilation "
              f"({ours[0]:.2f} s the first call): {r['ratio_after_compile']:.0f}x, "
              f"{r['ratio_incl_compile']:.1f}x including compilation", flush=True)
    out = {"machine": machine(torch), "objects": rows}
    print(out["machine"])
    if args.json:
        args.json.write_text(json.dumps(out, indent=2) + "\n")


if __name__ == "__main__":
    main()
