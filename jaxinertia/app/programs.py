"""The command line's compiled programs and how its independent stages share the device.

One :class:`jaxinertia.sim.stream.StreamPrograms` per process, made at its first use (not at
import), so that the commands run in one process (``main()`` called again, the tests)
compile each stream program once. :func:`side_by_side` runs independent stages (the
held-out folds, a fold's fine-tunings) in threads on an accelerator, one after the other
on a CPU."""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

import jax

from jaxinertia.sim.stream import StreamPrograms

__all__ = ["side_by_side", "side_by_side_workers", "stream_programs"]

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
