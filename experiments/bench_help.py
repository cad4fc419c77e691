"""How long ``jaxinertia --help`` and each ``jaxinertia <command> --help`` take, as a user
starts them: the installed entry point in a fresh process, best of ``--repeat`` runs (the
fastest is the least disturbed by other load on the machine). The issue 32 target is
0.5 s each; the tests check that no heavy module is imported, never the time.

    python experiments/bench_help.py [--repeat 5]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

from jaxinertia.app.cli import COMMANDS


def best_of(argv: list[str], repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        subprocess.run(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True)
        times.append(time.perf_counter() - t)
    return min(times)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeat", type=int, default=5)
    args = p.parse_args()
    exe = str(Path(sys.executable).with_name("jaxinertia"))
    rows = [("--help", best_of([exe, "--help"], args.repeat))]
    rows += [(f"{c} --help", best_of([exe, c, "--help"], args.repeat)) for c in COMMANDS]
    for name, t in rows:
        print(f"{name:<28} {t:6.2f} s" + ("" if t < 0.5 else "   (over 0.5 s)"))


if __name__ == "__main__":
    main()
