"""XLA:CPU settings applied before JAX creates its backend, by the programs that start JAX:
the command line's :func:`jaxinertia.app.cli.main`, the virtual robot's physics process,
the test session (``tests/conftest.py``) and the experiments' scripts; a program of one's
own calls ``jaxinertia.apply_xla_workarounds()`` first. Importing the library changes
nothing.

``--xla_cpu_enable_concurrency_optimized_scheduler=false``: with jax/jaxlib 0.10.2 the
batched evaluation (10 models x 1000 sets of a vmapped QR least-squares solve over a
gather) deadlocks on XLA:CPU: the process sleeps in a futex forever with no CPU use
(reproduced on the 2-core CI machine; 50 sets run, 1000 sets hang). The default
scheduler runs the same program in 2 s. Set ``JAXINERTIA_KEEP_XLA_FLAGS=1`` to leave
``XLA_FLAGS`` untouched. The flag only takes effect if JAX's CPU backend has not been
initialised yet, so apply it before running any JAX computation (importing the package
runs none). ``XLA_FLAGS`` is in the environment, so the processes started afterwards (the
virtual robot's, a command line in a subprocess) inherit it.
"""

from __future__ import annotations

import os

_CPU_FLAGS = ("--xla_cpu_enable_concurrency_optimized_scheduler=false",)


def apply() -> None:
    """Adds the settings to ``XLA_FLAGS`` (unless ``JAXINERTIA_KEEP_XLA_FLAGS`` is set)."""
    if os.environ.get("JAXINERTIA_KEEP_XLA_FLAGS"):
        return
    flags = os.environ.get("XLA_FLAGS", "")
    for flag in _CPU_FLAGS:
        name = flag.split("=")[0]
        if name not in flags:
            flags = f"{flags} {flag}".strip()
    os.environ["XLA_FLAGS"] = flags
