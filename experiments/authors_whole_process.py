"""The authors' evaluation as one whole process, to time beside ours (issue "Speed" item 4).

Imports their ``attn_test`` and model classes unchanged from ``LBIPE/authors`` (needs
PyTorch: run it with a throwaway venv's python) and runs ``estimate_object`` on the real
cube and white files with the ten released weight files, as their ``attn_model_test`` does
(without the red and black files, which are not released). Time the whole process::

    /usr/bin/time -f "%e s" TORCHVENV/bin/python experiments/authors_whole_process.py \\
        --lbipe-dir ../shared/lbipe --train-dir runs/bench_authors
    /usr/bin/time -f "%e s" .venv/bin/jaxinertia lbipe-benchmark --json OUT.json

``--train-dir`` holds the simulated training files their baselines refit on at every call
(``experiments/bench_authors.py`` writes them). Deliberately free of jaxinertia and JAX:
the process must pay only what theirs pays.
"""

import argparse
import contextlib
import io
import os
import sys
from pathlib import Path

import numpy as np

from jaxinertia import apply_xla_workarounds

#: Their ``attn_model_test``'s L_max per object [m].
L_MAX = {"cube": 69.2820e-3, "white": 75.5513e-3}


def main() -> None:
    apply_xla_workarounds()  # XLA:CPU settings, before JAX starts its backend
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lbipe-dir", type=Path, required=True)
    ap.add_argument("--train-dir", type=Path, default=Path("runs/bench_authors"))
    args = ap.parse_args()
    lbipe = args.lbipe_dir.resolve()
    sys.path[:0] = [str(lbipe / "authors"), str(lbipe)]
    import attn_test  # noqa: PLC0415  (theirs: needs torch and the path above)
    from lbipe.models import AttnModel, TorqueModel  # noqa: PLC0415  (theirs, likewise)

    weights = lbipe / "weights"
    torque = [str(weights / f"dict_torque_{i}.pt") for i in range(1, 11)]
    attn = [str(weights / f"dict_attn_{i}.pt") for i in range(1, 11)]
    packs = {n: dict(np.load(lbipe / "data" / f"data_test_{n}.npz")) for n in L_MAX}
    os.chdir(args.train_dir)
    for name, l_max in L_MAX.items():
        with contextlib.redirect_stdout(io.StringIO()):
            attn_test.estimate_object(TorqueModel, AttnModel, torque, attn, packs[name], l_max)
        print(f"{name}: done")


if __name__ == "__main__":
    main()
