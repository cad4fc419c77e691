"""The command line's compiled stream programs: one
:class:`jaxinertia.sim.stream.StreamPrograms` per process, made at its first use (not at
import), so that the commands run in one process (``main()`` called again, the tests)
compile each stream program once."""

from __future__ import annotations

import functools

from jaxinertia.sim.stream import StreamPrograms

__all__ = ["stream_programs"]


@functools.cache
def stream_programs() -> StreamPrograms:
    """This process's stream programs (made on the first call)."""
    return StreamPrograms()
