"""Counting traces and XLA compilations of jitted functions, to catch recompilation.

The equivalent of ``chex.assert_max_traces`` (chex is not a dependency) that needs no change
to the function under test: JAX reports every trace and every backend compilation through
:mod:`jax.monitoring` with the function's name, and :func:`compile_counter` counts those
events for the names asked for while its block runs. A persistent-cache hit still counts as a
compilation (the program was needed again); a call served by the jitted function's own cache
counts nothing.
"""

from __future__ import annotations

import contextlib
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field

import jax

__all__ = ["Compiles", "compile_counter"]

# jax._src.dispatch.JAXPR_TRACE_EVENT and BACKEND_COMPILE_EVENT; their fun_name is the
# function's name for the trace and "jit(<name>)" for the compilation.
TRACE_EVENT = "/jax/core/compile/jaxpr_trace_duration"
COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"


@dataclass
class Compiles:
    """Traces and compilations seen, by function name."""

    traces: Counter = field(default_factory=Counter)
    compiles: Counter = field(default_factory=Counter)


@contextlib.contextmanager
def compile_counter(*names: str) -> Iterator[Compiles]:
    """Counts the traces and compilations of the jitted functions ``names`` in the block."""
    seen = Compiles()
    wanted = {n: n for n in names} | {f"jit({n})": n for n in names}

    def listener(event: str, duration: float, **kwargs) -> None:
        name = wanted.get(kwargs.get("fun_name", ""))
        if name is None:
            return
        if event == TRACE_EVENT:
            seen.traces[name] += 1
        elif event == COMPILE_EVENT:
            seen.compiles[name] += 1

    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        yield seen
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)
