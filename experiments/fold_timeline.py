"""``jaxinertia reproduce`` with a timeline: when each thread starts and ends the folds'
stages (calibration, simulation, each training and its epoch programs, each judge),
``reproduce``'s own stages (what runs beside the folds) and every XLA compile (its thread,
program and seconds), into ``--timeline`` (text, one event a line, seconds since start).
How sessions 30 and 31 found what a GPU fold waits for (docs/benchmarks.md, "Session 30",
"Session 31"):

    python experiments/fold_timeline.py --timeline tl.txt -- --full --out DIR --lbipe-dir DIR

Everything after ``--`` is ``reproduce``'s. Cold on a GPU: ``JAXINERTIA_CACHE_DIR=off``.
``--sample-stacks 0.5`` also writes where the folds' threads are every half second (a wait
that no event shows: docs/benchmarks.md, "Session 44"); ``--side-by-side 4`` runs the
stages side by side and groups the folds' trainings as a GPU does, on a CPU too.
``experiments/timeline_stages.py`` sums a timeline up, stage by stage.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import logging
import os
import sys
import threading
import time

import jax

from jaxinertia import training, training_group
from jaxinertia.app import cli, fit, fold, fold_groups, folds, programs, reproduce


class Timeline:
    def __init__(self, path: str):
        self.t0, self.out, self.lock = time.time(), open(path, "w", buffering=1), threading.Lock()

    def emit(self, kind: str, what: str, seconds: float | None = None) -> None:
        with self.lock:
            self.out.write(f"{time.time() - self.t0:8.2f} {threading.current_thread().name:30s} "
                           f"{kind:6s} {what}" + ("" if seconds is None else f" {seconds:.2f}")
                           + "\n")

    def wrap(self, owner, attr: str) -> None:
        """``owner.attr`` logs its start and end (with the first path among its arguments)."""
        fn = getattr(owner, attr)

        @functools.wraps(fn)
        def timed(*args, **kwargs):
            path = next((os.path.basename(str(a)) for a in args[:3]
                         if isinstance(a, (str, os.PathLike))), "")
            what = f"{attr} {path}".strip()
            self.emit("start", what)
            t = time.time()
            try:
                return fn(*args, **kwargs)
            finally:
                self.emit("end", what, time.time() - t)

        setattr(owner, attr, timed)


def _programs(timeline: Timeline) -> None:
    """Each group program (``training_group._run_stacked``) with what it trains and how
    many members: ``_run_stacked torque model x6``."""
    fn = training_group._run_stacked

    @functools.wraps(fn)
    def timed(trainings):
        what = f"_run_stacked {trainings[0].desc} x{len(trainings)}"
        timeline.emit("start", what)
        t = time.time()
        try:
            return fn(trainings)
        finally:
            timeline.emit("end", what, time.time() - t)

    training_group._run_stacked = timed


def _stages(timeline: Timeline) -> None:
    """``reproduce``'s own stages (simulate, train, ..., the held-out folds) on the timeline
    too: what runs beside the folds."""
    call = reproduce._Stages.__call__

    @contextlib.contextmanager
    def timed(self, name: str):
        timeline.emit("start", f"stage {name}")
        t = time.time()
        try:
            with call(self, name):
                yield
        finally:
            timeline.emit("end", f"stage {name}", time.time() - t)

    reproduce._Stages.__call__ = timed


class _Compiles(logging.Handler):
    def __init__(self, timeline: Timeline):
        super().__init__(logging.DEBUG)
        self.timeline = timeline

    #: JAX's messages under ``jax_log_compiles``: a compile's start, its tracing, its
    #: lowering (to MLIR) and its XLA compilation (``comp``, the only kind before session
    #: 44). Tracing and lowering are Python under the GIL: the threads of the folds wait for
    #: each other's there, which the compiles' seconds alone do not show.
    _KINDS = (("Finished XLA compilation of ", "comp"), ("Finished tracing ", "trace"),
              ("Finished jaxpr to MLIR module conversion ", "lower"))
    #: Tracing and lowering shorter than this are left out (every eager op is traced).
    MIN_S = 0.05

    def emit(self, record: logging.LogRecord) -> None:
        message = record.getMessage()
        if message.startswith("Compiling ") and " with global shapes" in message:
            self.timeline.emit("cstart", message.split()[1])
            return
        for prefix, kind in self._KINDS:
            if message.startswith(prefix):
                what = message.removeprefix(prefix)
                if kind != "comp":
                    try:
                        if float(what.split(" in ")[-1].split()[0]) < self.MIN_S:
                            return
                    except ValueError:
                        pass
                self.timeline.emit(kind, what)
                return


def _sample_stacks(timeline: Timeline, every: float) -> None:
    """Every ``every`` seconds, where the folds' threads are (session 44: a training's
    threads waited 18-21 s at a place no event showed): each thread's innermost frame in
    jaxinertia, with the innermost frame below it (the call it waits in), one ``stack``
    line per place and its count of threads, written when the places changed."""
    package = os.path.dirname(os.path.abspath(training.__file__))
    root = os.path.dirname(package)

    def place(frame) -> str:
        inner = frame
        while frame is not None and not frame.f_code.co_filename.startswith(package):
            frame = frame.f_back
        if frame is None:
            return ""
        own = f"{os.path.relpath(frame.f_code.co_filename, root)}:{frame.f_lineno}"
        return f"{own} {frame.f_code.co_name} <- {os.path.basename(inner.f_code.co_filename)}:" \
               f"{inner.f_lineno} {inner.f_code.co_name}"

    def run() -> None:
        last = None
        while True:
            time.sleep(every)
            names = {t.ident: t.name for t in threading.enumerate()}
            counts: dict[str, int] = {}
            for ident, frame in sys._current_frames().items():
                if names.get(ident, "").startswith(("jaxinertia-", "rehearse-")):
                    where = place(frame)
                    if where:
                        counts[where] = counts.get(where, 0) + 1
            if counts != last:
                for where, n in sorted(counts.items(), key=lambda kv: -kv[1]):
                    timeline.emit("stack", f"x{n} {where}")
                last = counts

    threading.Thread(target=run, name="stack-sampler", daemon=True).start()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--timeline", required=True, help="the text file to write")
    p.add_argument("--sample-stacks", type=float, default=0.0, metavar="SECONDS",
                   help="also where the folds' threads are, every SECONDS (0: never)")
    p.add_argument("--side-by-side", type=int, default=0, metavar="N",
                   help="N stages side by side and the folds' trainings grouped, as on a GPU, "
                        "whatever the device (0: the device's own way)")
    p.add_argument("--switch-interval", type=float, default=0.0, metavar="SECONDS",
                   help="the interpreter's GIL switch interval (sys.setswitchinterval; 0: "
                        "Python's own, 5 ms): how long a thread that gave the GIL up for C "
                        "work may wait to get it back from a busy one (session 45)")
    p.add_argument("reproduce", nargs=argparse.REMAINDER, help="-- then reproduce's arguments")
    a = p.parse_args()
    timeline = Timeline(a.timeline)
    jax.config.update("jax_log_compiles", True)
    logger = logging.getLogger("jax")  # every compile, into the timeline, not onto stderr
    logger.addHandler(_Compiles(timeline))
    logger.setLevel(logging.WARNING)
    logger.propagate = False
    for owner, attr in ((folds, "fit_simulators"), (folds, "simulate_files"), (folds, "train"),
                        (fold, "evaluate"), (folds.Fold, "judge"),
                        (fit, "train_torque_models"), (fit, "train_attention_models"),
                        # inside a training, before its epochs (session 44): the attention's
                        # inputs, its epoch object, and when the member hands its epochs in
                        (training, "torque_predictions"), (training, "_features"),
                        (training, "_attention_epoch"), (training, "_torque_epoch"),
                        (training, "run_epochs")):
        timeline.wrap(owner, attr)
    _programs(timeline)
    _stages(timeline)
    if a.side_by_side > 0:  # a GPU's threads and groups on a CPU (session 44)
        programs.side_by_side_workers = fold_groups.side_by_side_workers = \
            lambda: a.side_by_side
    if a.sample_stacks > 0:
        _sample_stacks(timeline, a.sample_stacks)
    if a.switch_interval > 0:
        sys.setswitchinterval(a.switch_interval)
    args = [x for x in a.reproduce if x != "--"]
    t = time.time()
    try:
        cli.main(["reproduce", *args])
    finally:
        timeline.emit("end", "reproduce", time.time() - t)


if __name__ == "__main__":
    main()
