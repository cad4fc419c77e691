"""Where each thread of a run spends its time, from a py-spy profile of every thread.

    py-spy record -r 20 --idle --threads -f speedscope -o tl.json -- \\
        python -m jaxinertia reproduce --full --out DIR --lbipe-dir DIR
    python experiments/profile_threads.py tl.json[.gz] [--min-seconds 60] [--top 8]

Each sample of a thread is one of: ``compile`` (XLA compiling: the GIL is free),
``group-wait`` (a training group's member waiting for the others), ``idle`` (waiting on a
lock, a future, a queue, a sleep), ``device`` (reading a result back: waiting for the
device), ``trace/lower`` (JAX tracing or lowering a program: Python), or ``python`` (any
other Python, which needs the GIL: time here is slowed by the threads beside it). Per
thread of at least ``--min-seconds``: the seconds in each, then the ``--top`` places (the
innermost jaxinertia frame) outside ``idle``. Session 28 read the held-out folds' threads
this way (docs/benchmarks.md, "Session 28").
"""

from __future__ import annotations

import argparse
import collections
import gzip
import json
from pathlib import Path

#: Innermost frames of a thread that waits (py-spy's names).
IDLE = ("wait (threading", "_wait_for_tstate_lock", "acquire", "select", "sleep",
        "_worker (concurrent", "get (queue", "Condition.wait")


def _names(profile: dict) -> list[str]:
    def short(f: dict) -> str:
        path = f.get("file", "").split("site-packages/")[-1].split("/work/")[-1]
        return f"{f['name']} ({path}:{f.get('line', '')})"
    return [short(f) for f in profile["shared"]["frames"]]


def classify(stack: list[str]) -> tuple[str, str]:
    """A sample's category and its innermost jaxinertia frame (else its innermost frame)."""
    joined, leaf = ";".join(stack), (stack[-1] if stack else "")
    ours = [x.split(" (")[0] for x in stack if "jaxinertia/" in x]
    where = ours[-1] if ours else leaf.split(" (")[0]
    if "backend_compile" in joined or "compile_or_get_cached" in joined:
        return "compile", where
    waiting = any(k in leaf for k in IDLE)
    if waiting and "_submit (jaxinertia/training_group" in joined:
        return "group-wait", where
    if waiting:
        return "idle", where
    if any(k in joined for k in ("_value (", "__array__", "block_until_ready")):
        return "device", where
    if any(k in joined for k in ("trace_to_jaxpr", "lower_sharding", "jaxpr_to_mlir",
                                 "_pjit_lower")):
        return "trace/lower", where
    return "python", where


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("profile", help="py-spy's speedscope output (.json or .json.gz)")
    p.add_argument("--min-seconds", type=float, default=60.0)
    p.add_argument("--top", type=int, default=8)
    a = p.parse_args()
    path = Path(a.profile)
    opener = gzip.open if path.suffix == ".gz" else open
    with opener(path, "rt") as f:
        data = json.load(f)
    names = _names(data)
    for prof in data["profiles"]:
        total = sum(prof["weights"])
        if total < a.min_seconds:
            continue
        cats, places = collections.Counter(), collections.Counter()
        for stack, w in zip(prof["samples"], prof["weights"]):
            cat, where = classify([names[i] for i in stack])
            cats[cat] += w
            if cat != "idle":
                places[(cat, where)] += w
        print(f"== {prof['name']} {total:.0f} s: "
              + ", ".join(f"{k} {v:.0f}" for k, v in cats.most_common()))
        for (cat, where), v in places.most_common(a.top):
            print(f"   {v:6.1f} {cat:11s} {where}")


if __name__ == "__main__":
    main()
