"""Compilations per stage of a command (issue 30 item 4): how many programs XLA compiled
and how long compiling, lowering and tracing took, per stage of ``reproduce`` and per part
of the held-out folds.

    JAXINERTIA_CACHE_DIR=off python experiments/compile_profile.py reproduce --out runs/q \\
        --lbipe-dir ../shared/lbipe [--json runs/q_compiles.json]

A ``jax.monitoring`` listener counts ``/jax/core/compile/*`` events under the stage that
is running (``reproduce``'s stage timer and the folds' parts, wrapped here). The labels
assume one stage at a time: on an accelerator, where stages run side by side
(``jaxinertia.app.programs.side_by_side``), the counts of overlapping stages mix.
"""

from __future__ import annotations

import collections
import contextlib
import functools
import json
import os
import sys
import time

os.environ.setdefault("JAXINERTIA_CACHE_DIR", "off")

from jax._src import monitoring  # noqa: E402 - the listener API (jax.monitoring's private home)

from jaxinertia.app import folds as F  # noqa: E402
from jaxinertia.app import reproduce as R  # noqa: E402
from jaxinertia.app.cli import main  # noqa: E402

label = ["setup"]
stats: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
by_name: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)


def _on_duration(event: str, secs: float, **kw) -> None:
    if not event.startswith("/jax/core/compile/"):
        return
    key, short = "/".join(label), event.rsplit("/", 1)[-1].removesuffix("_duration")
    stats[key][short + "_s"] += secs
    stats[key][short + "_n"] += 1
    if short == "backend_compile":
        by_name[key][kw.get("fun_name", "?")] += secs


def _labelled(mod, attr: str, name: str) -> None:
    f = getattr(mod, attr)

    @functools.wraps(f)
    def g(*a, **k):
        old = list(label)
        label.append(name)
        t = time.perf_counter()
        try:
            return f(*a, **k)
        finally:
            stats["/".join(label)]["wall_s"] += time.perf_counter() - t
            label[:] = old

    setattr(mod, attr, g)


def _install() -> None:
    monitoring.register_event_duration_secs_listener(_on_duration)
    timer = R._Stages.__call__

    @contextlib.contextmanager
    def stage(self, name):
        label[:] = [name]
        t = time.perf_counter()
        with timer(self, name):
            yield
        stats[name]["wall_s"] += time.perf_counter() - t

    R._Stages.__call__ = stage
    for attr, name in (("fit_simulators", "calibrate"), ("simulate_files", "simulate"),
                       ("train", "train"), ("_finetuned", "finetune")):
        _labelled(F, attr, name)
    _labelled(F.Fold, "judge", "judge")


def run(argv: list[str]) -> int:
    out = None
    if "--json" in argv:
        i = argv.index("--json")
        out, argv = argv[i + 1], argv[:i] + argv[i + 2:]
    _install()
    rc = main(argv)
    print(f"\n{'stage':45s} {'compiles':>8s} {'compile s':>9s} {'lower s':>8s} "
          f"{'trace s':>8s} {'wall s':>8s}")
    for k, v in stats.items():
        print(f"{k:45s} {v['backend_compile_n']:8d} {v['backend_compile_s']:9.1f} "
              f"{v['jaxpr_to_mlir_module_s']:8.1f} {v['jaxpr_trace_s']:8.1f} {v['wall_s']:8.1f}")
    print(f"{'all':45s} {sum(v['backend_compile_n'] for v in stats.values()):8d}")
    if out:
        with open(out, "w") as fh:
            json.dump({"stages": {k: dict(v) for k, v in stats.items()},
                       "compile_s_by_program": {k: dict(v) for k, v in by_name.items()}},
                      fh, indent=1)
    return rc


if __name__ == "__main__":
    sys.exit(run(sys.argv[1:]))
