"""Programs that XLA compiles otherwise than its defaults, per backend.

Two kinds of program want other settings than the rest, and each gets them from its own
``jax.jit`` (JAX passes ``compiler_options`` to the top-level program alone):

* :func:`run_once_jit`: a program that runs once where it is called (an initialisation, the
  predictions over a validation split). On a GPU it compiles without XLA's autotuner, which
  times candidate kernels on the device for seconds of compile that one run never pays back
  (in ``reproduce --full`` such programs, compiled with it, waited on the folds' critical
  path: docs/benchmarks.md, "Session 27").
* :func:`stepping_jit` (and :func:`stepping_options` for programs compiled ahead of time):
  the simulator's stepping, loops of thousands of integration steps whose running time,
  not their compile, is what they cost. On a CPU they compile at LLVM's optimisation level
  :data:`CPU_STEPPING_LEVEL` whatever ``XLA_FLAGS`` set for the other programs: the test
  suite compiles everything else at level 0, where its many short programs compile in half
  the time, but the simulator's calibration and identification ran twice as long at that
  level (docs/benchmarks.md, "Session 36").
"""

from __future__ import annotations

from collections.abc import Callable
from functools import cache, wraps

import jax

__all__ = ["CPU_STEPPING_LEVEL", "jit_for_backend", "run_once_jit", "stepping_jit",
           "stepping_options"]

#: LLVM's optimisation level (0-3) of the simulator's stepping programs on a CPU. Against
#: XLA's default (3), ``jaxinertia simulate`` on the 2-core VM, compile included, took 24-26 s
#: instead of 27-28 s (2,000 random samples per load) and 20-22 s instead of 25-33 s (a
#: continuous run of 2,048), the samples the same (docs/benchmarks.md, "Session 36").
CPU_STEPPING_LEVEL = 1


def stepping_options(backend: str | None = None) -> dict:
    """The compiler options of a simulator stepping program on ``backend`` (default: JAX's):
    on a CPU, LLVM at :data:`CPU_STEPPING_LEVEL`; elsewhere none."""
    if (backend or jax.default_backend()) == "cpu":
        return {"xla_backend_optimization_level": CPU_STEPPING_LEVEL}
    return {}


def _run_once_options(backend: str) -> dict:
    return {"xla_gpu_autotune_level": 0} if backend == "gpu" else {}


def jit_for_backend(fn, options: Callable[[str], dict], **jit_kwargs):
    """``jax.jit(fn, **jit_kwargs)`` compiled with ``options(backend)`` for the backend it
    runs on (JAX's default backend at the call), built at its first call there. Called
    inside another program being traced, ``fn`` is part of that program and runs as
    written (compiler options belong to the top-level program; JAX refuses them on a
    nested jit)."""
    built = cache(lambda backend: jax.jit(fn, **jit_kwargs,
                                          compiler_options=options(backend) or None))

    @wraps(fn)
    def call(*args, **kwargs):
        if any(isinstance(a, jax.core.Tracer) for a in jax.tree_util.tree_leaves((args,
                                                                                  kwargs))):
            return fn(*args, **kwargs)
        return built(jax.default_backend())(*args, **kwargs)

    return call


def run_once_jit(fn, **jit_kwargs):
    """``jax.jit(fn)`` for a program that runs once where it is called: on a GPU without
    XLA's autotuner (module docstring); on a CPU the plain jit."""
    return jit_for_backend(fn, _run_once_options, **jit_kwargs)


def stepping_jit(fn, **jit_kwargs):
    """``jax.jit(fn)`` for a simulator stepping program: :func:`stepping_options`."""
    return jit_for_backend(fn, stepping_options, **jit_kwargs)
