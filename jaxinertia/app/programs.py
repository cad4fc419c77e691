"""The command line's compiled programs and how its independent stages share the device.

One :class:`jaxinertia.sim.stream.StreamPrograms` per process, made at its first use (not at
import), so that the commands run in one process (``main()`` called again, the tests)
compile each stream program once. :func:`side_by_side` runs independent stages (the
held-out folds, a fold's fine-tunings) in threads on an accelerator, one after the other
on a CPU."""

from __future__ import annotations

import functools
import os
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

import jax

from jaxinertia.sim.stream import StreamPrograms

__all__ = ["folds_side_by_side", "side_by_side", "side_by_side_workers", "stream_programs"]

T = TypeVar("T")


@functools.cache
def stream_programs() -> StreamPrograms:
    """This process's stream programs (made on the first call)."""
    return StreamPrograms()


def side_by_side_workers() -> int:
    """How many independent stages run at once: several on an accelerator, one on a CPU.

    On an accelerator a cold stage is mostly compilation (XLA releases the GIL: stages
    compile in parallel on the host's cores) and small programs that leave the device
    mostly idle (K small MLPs, a 1,000-sample simulation); side by side their compilations
    and their programs overlap. A CPU's cores already run each compilation and program.
    Each stage's results do not depend on what runs beside it (its programs and keys are
    its own)."""
    return 1 if jax.default_backend() == "cpu" else 4


def _cores() -> int:
    """The CPU cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def folds_side_by_side(n_folds: int) -> int:
    """How many held-out folds run at once: every fold on an accelerator
    (:func:`side_by_side_workers`; their trainings grouped, :mod:`jaxinertia.app.fold_groups`);
    on a CPU one per core, each fold's own stages in order.

    A fold's programs are small (a 1,000-sample simulation on 256 lanes, K small MLPs on
    3,200 samples): one fold leaves most of a second core idle. Measured on the 2-core CI
    machine (``make demo``'s folds alone, docs/benchmarks.md "Folds side by side on a
    CPU"): 169 s one after the other, 117 s side by side, the same numbers bit for bit
    (each fold's programs and keys are its own, and the CPU's programs are deterministic).
    The folds beside the simulated stages lost instead (session 19): those fill both
    cores."""
    if side_by_side_workers() > 1:
        return min(side_by_side_workers(), n_folds)
    return max(1, min(_cores(), n_folds))


def side_by_side(calls: Sequence[Callable[[], T]], workers: int | None = None) -> list[T]:
    """``[call() for call in calls]``, up to ``workers`` (default
    :func:`side_by_side_workers`) at once in threads; in order in this thread when one.
    The first exception is raised once every call has ended."""
    workers = side_by_side_workers() if workers is None else int(workers)
    if workers <= 1 or len(calls) <= 1:
        return [call() for call in calls]
    with ThreadPoolExecutor(min(workers, len(calls)),
                            thread_name_prefix="jaxinertia-stage") as pool:
        futures = [pool.submit(call) for call in calls]
    return [f.result() for f in futures]
