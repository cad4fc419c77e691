"""Shared fixtures. Identification is tested in float64 (the library's choice)."""

from __future__ import annotations

import os
import resource
import shutil
import tempfile
from pathlib import Path

import jax
import numpy as np
import pytest

# XLA:CPU's older loop emitters instead of its fusion emitters: the same programs compile
# in about 2/3 of the time (tests/test_uncertainty.py: 25 s -> 17 s of compiling on the
# 2-core CI machine; test_sim + test_identify 144 s -> 112 s) and run as fast, and the
# suite's time is mostly compiling. Set before JAX starts, so that the command-line and
# virtual-robot subprocesses the tests start inherit it; what the tests check (numbers
# against MuJoCo, the real data, golden files, within their tolerances) does not depend
# on which emitter wrote the machine code.
# Likewise LLVM without its expensive passes and at optimisation level 0 (of 0-3): most of
# the suite's programs are compiled for a few calls, and at level 0 they compile in about
# half the time (session 36, 2-core VM: the whole suite 9:13 -> 6:49, XLA compiling 533 ->
# 243 s summed over the tests). The programs that loop for long, the simulator's stepping,
# keep level 1 whatever this says (jaxinertia.compile_options.stepping_options): at level 0
# the calibration's and identification's tests ran twice as long (test_real_fit 49 -> 99 s).
# And one thread per process for XLA's compiler (the LLVM module compiled in one piece, not
# split over threads) and for its Eigen kernels: the two workers already keep both cores
# busy, and the threads only contended (session 16, 2-core VM: test_sim + test_learning +
# test_identify 225 -> 210 CPU seconds; the whole suite 364 -> 358 s).
for _flag in ("--xla_cpu_use_fusion_emitters=false", "--xla_llvm_disable_expensive_passes=true",
              "--xla_backend_optimization_level=0", "--xla_cpu_multi_thread_eigen=false",
              "--xla_cpu_parallel_codegen_split_count=1"):
    if _flag.split("=")[0] not in os.environ.get("XLA_FLAGS", ""):
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " " + _flag).strip()

from jaxinertia import apply_xla_workarounds  # noqa: E402

apply_xla_workarounds()  # the library's XLA:CPU settings, before JAX starts (and inherited)

jax.config.update("jax_enable_x64", True)

# The command line keeps compiled programs in a persistent cache; tests point it at one
# folder per session (never the user's ~/.cache), shared with the CLI and virtual-robot
# subprocesses they start, so each program compiles once per session.
if "JAXINERTIA_CACHE_DIR" not in os.environ:
    _CACHE = tempfile.mkdtemp(prefix="jaxinertia-test-xla-")
    os.environ["JAXINERTIA_CACHE_DIR"] = _CACHE

    def pytest_sessionfinish(session, exitstatus):  # noqa: ARG001
        shutil.rmtree(_CACHE, ignore_errors=True)

# The test process uses the same cache from its start (the command line's main() would
# switch it on at its first in-process call), and keeps every program, however quick to
# compile (JAX's default: those of 1 s or more): an identical program then compiles once
# per session even when it is built anew (a jit created per call, a stream program keyed by
# its lane count, the same program in a subprocess). That includes the small programs of
# operations run one by one (20-40 ms each on the CI machine), which every worker and every
# command-line and virtual-robot subprocess would otherwise compile again: the hardware
# tests took 8 % less CPU with them cached. Compile counts (support.compiles) still count a
# cache hit as a compilation.
# The threshold goes through the environment too, so that the command-line and
# virtual-robot subprocesses (a collect, the virtual servos' physics) keep and find the
# same programs.
if os.environ["JAXINERTIA_CACHE_DIR"].lower() != "off":
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
    jax.config.update("jax_compilation_cache_dir", os.environ["JAXINERTIA_CACHE_DIR"])
    jax.config.update("jax_persistent_cache_min_compile_time_secs",
                      float(os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"]))

from support.layouts import small_layout  # noqa: E402

#: Test files, longest first (seconds on the 2-core CI machine, two workers, session 19),
#: so that the workers of `make test` (pytest-xdist, one file per worker at a time, in this
#: order: the Makefile passes --no-loadscope-reorder, without which xdist orders files by
#: their number of tests) finish together instead of one waiting on a long file started
#: last; files not named run after these. test_folds comes first: test_learning's tiny end
#: to end and test_identify's search find its programs in the session's cache (started
#: together on two workers, both would compile them). The two hardware files that run a
#: virtual robot the longest are spread over both workers.
LONGEST_FIRST = ("test_folds.py",  # 74 s
                 "test_sim.py",  # 79 s in many short tests (67 s of it compiling)
                 "test_hardware_bus.py",  # 56 s
                 "test_learning.py",  # 60 s, its tiny end to end 38 s
                 "test_hardware_faults.py",  # 43 s
                 "test_finetune.py",  # 43 s
                 "test_real_fit.py",  # 33 s
                 "test_dynamics.py",  # 32 s
                 # Well before test_feetech_collect: the SO-101's end to end finds the
                 # Koch's physics and statics programs (another 5-joint arm) and
                 # test_arms's plan-poses --arm so101 in the session's cache only once these
                 # have compiled them.
                 "test_hardware_koch.py",  # 11 s
                 "test_arms.py",  # 2 s
                 "test_sharding.py",  # 29 s
                 "test_identify.py",  # 27 s
                 # After test_folds and test_learning, whose training programs (same shapes)
                 # it finds in the session's cache.
                 "test_training_group.py",  # 17 s
                 "test_feetech_collect.py",  # 20 s
                 "test_kinematics.py",  # 25 s
                 "test_uncertainty.py",  # 22 s
                 "test_statics.py",  # 22 s
                 "test_hardware_collect.py",  # 20 s
                 "test_reliability.py",  # 20 s
                 "test_design.py",  # 16 s
                 "test_hardware_protocol.py",  # 12 s
                 "test_sim_batched.py",  # 12 s
                 "test_by_part.py",  # 10 s
                 "test_identification.py")  # 10 s


def pytest_collection_modifyitems(config, items):  # noqa: ARG001
    rank = {name: k for k, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable

#: Seconds XLA spent compiling programs in this process (JAX's tracing and lowering, whose
#: events nest, are left out): the part of the suite's time that shared shapes and the
#: persistent cache can save. Compilations on other threads of the process (an in-process
#: virtual robot's physics) count too, so a file's share can exceed its wall time. Each
#: test's share is recorded with its report, and the session ends with the files that
#: compile most (under xdist the reports carry it from the workers).
_COMPILE_EVENTS = ("/jax/core/compile/backend_compile_duration",)
_compile_s = [0.0]


def _on_duration(name, secs, **kwargs):  # noqa: ARG001
    if name in _COMPILE_EVENTS:
        _compile_s[0] += secs


jax.monitoring.register_event_duration_secs_listener(_on_duration)


def _cpu_s() -> float:
    """CPU seconds of this process and of its finished (waited-for) subprocesses."""
    own, kids = (resource.getrusage(w) for w in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN))
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def _timed_phase(item):
    start, cpu = _compile_s[0], _cpu_s()
    yield
    item.user_properties.append(("compile_s", _compile_s[0] - start))
    item.user_properties.append(("cpu_s", _cpu_s() - cpu))


pytest_runtest_setup = pytest.hookimpl(wrapper=True)(_timed_phase)
pytest_runtest_call = pytest.hookimpl(wrapper=True)(_timed_phase)


def pytest_terminal_summary(terminalreporter):
    per_file = {}
    for reports in terminalreporter.stats.values():
        for r in reports:
            if getattr(r, "when", None) not in ("setup", "call"):
                continue
            props = dict.fromkeys(("compile_s", "cpu_s"), 0.0)
            for k, v in getattr(r, "user_properties", ()):
                if k in props:
                    props[k] += v
            f = r.nodeid.split("::")[0]
            per_file[f] = per_file.get(f, np.zeros(3)) + (r.duration, props["compile_s"],
                                                             props["cpu_s"])
    if not per_file:
        return
    total, compiling, cpu = sum(per_file.values())
    terminalreporter.write_sep("=", f"time in tests {total:.0f} s, of it XLA compiling "
                               f"{compiling:.0f} s; CPU {cpu:.0f} s; the 10 longest files")
    for f, (t, c, u) in sorted(per_file.items(), key=lambda kv: -kv[1][0])[:10]:
        terminalreporter.write_line(f"{t:7.1f} s  compiling {c:6.1f} s  CPU {u:6.1f} s  {f}")


from jaxinertia.lbipe import default_lbipe_dir  # noqa: E402

ASSETS = Path(__file__).parent / "assets"

HOW_TO_GET_LBIPE = (
    "the real OpenMANIPULATOR-X data (lbipe) is not at {path}. Put the shared/lbipe folder "
    "beside the repository (../shared/lbipe) or point JAXINERTIA_LBIPE_DIR at it; the data, "
    "weights and golden files come from the project's shared/ folder (the authors' "
    "ChirikjianLab/lbipe repository plus golden outputs)."
)


@pytest.fixture(scope="session")
def lbipe_dir() -> Path:
    """The shared lbipe folder; skipped with instructions when absent, failing under CI."""
    path = default_lbipe_dir()
    if not (path / "data").is_dir():
        msg = HOW_TO_GET_LBIPE.format(path=path)
        if os.environ.get("CI"):
            pytest.fail("CI is set and " + msg)
        pytest.skip(msg)
    return path


@pytest.fixture(scope="session")
def small_lbipe_dir(lbipe_dir, tmp_path_factory) -> Path:
    """The real files cut to their first ``support.layouts.N_REAL`` samples beside the
    released weights, for the pipeline tests (test_folds, the tiny end to end): one layout
    for all of them, so that their programs on the real data compile once."""
    return small_layout(lbipe_dir, tmp_path_factory.mktemp("lbipe"))


@pytest.fixture(scope="session")
def stream_programs():
    """The simulator stream's compiled programs for the tests: the command line's own
    (``jaxinertia.app.programs``), so that a program compiled by a test that calls the
    library serves the in-process ``main()`` calls too, and the other way round."""
    from jaxinertia.app.programs import stream_programs as programs  # noqa: PLC0415 - the app's, at first use

    return programs()
