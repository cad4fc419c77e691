"""The command line's compilation cache stays writable (jaxinertia.compilation_cache).

With a size cap JAX keeps an access-time file beside every entry and reads all of them
before each write; one entry without it (written by a process without the cap, as the
virtual robot's physics process was) made every later write of the command line fail.
Each step runs in a fresh interpreter: JAX sets its cache up once per process."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest

WRITE_FAILED = "Error writing persistent compilation cache entry"


def _python(code: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0"}
    env.pop("JAXINERTIA_CACHE_DIR", None)
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], env=env,
                          capture_output=True, text=True, timeout=300, check=True)


def _uncapped_entry(folder) -> None:
    """One cache entry written without a cap: no access-time file beside it."""
    _python(f"""
        import jax
        jax.config.update("jax_compilation_cache_dir", {str(folder)!r})
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
        jax.jit(lambda x: x + 1.0)(1.0).block_until_ready()
        """)
    names = sorted(p.name for p in folder.iterdir())
    assert len(names) == 1 and names[0].endswith("-cache"), names


def _capped_write(folder, setup: str) -> subprocess.CompletedProcess:
    return _python(f"""
        import jax
        {setup}
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
        jax.jit(lambda x: x * 3.0 - 2.0)(2.0).block_until_ready()
        """)


@pytest.mark.parametrize("repaired", [False, True], ids=["jax-alone", "enable"])
def test_a_capped_cache_stays_writable_beside_an_uncapped_entry(tmp_path, repaired):
    folder = tmp_path / "xla"
    folder.mkdir()
    _uncapped_entry(folder)
    if repaired:  # what the command line and the virtual robot's physics do
        setup = ("from jaxinertia import compilation_cache; "
                 f"compilation_cache.enable({str(folder)!r})")
    else:  # the cap set directly: the write fails on the entry without an access time
        setup = (f"jax.config.update('jax_compilation_cache_dir', {str(folder)!r}); "
                 "jax.config.update('jax_compilation_cache_max_size', 2**29)")
    run = _capped_write(folder, setup)
    entries = sorted(p.name for p in folder.glob("*-cache"))
    if not repaired:
        assert WRITE_FAILED in run.stderr and len(entries) == 1, (run.stderr, entries)
        return
    assert WRITE_FAILED not in run.stderr, run.stderr
    assert len(entries) == 2, entries
    for name in entries:  # every entry has its access time now
        assert (folder / name.replace("-cache", "-atime")).is_file(), name


@pytest.mark.parametrize("command", ["estimate", "train"])
def test_the_commands_run_on_new_files_keep_their_small_programs(tmp_path, command):
    """``estimate`` (and ``evaluate``) keep every compiled program, however quick: a second
    run on another file finds its many small programs; other commands keep JAX's threshold
    (a second of compilation), and a threshold the user set is kept as set."""
    folder = tmp_path / "xla"
    env = {k: v for k, v in os.environ.items()
           if k not in ("JAXINERTIA_CACHE_DIR", "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS")}
    code = textwrap.dedent(f"""
        import os, jax
        from jaxinertia.app import cli
        cli._compilation_cache({command!r})
        print(jax.config.jax_persistent_cache_min_compile_time_secs)
        jax.jit(lambda x: x * 3.0 - 2.0)(2.0).block_until_ready()
        """)

    def run(**extra):
        if folder.exists():
            for p in folder.iterdir():
                p.unlink()
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                             timeout=300, check=True,
                             env={**env, "JAX_PLATFORMS": "cpu",
                                  "JAXINERTIA_CACHE_DIR": str(folder), **extra})
        entries = list(folder.glob("*-cache")) if folder.exists() else []
        return float(out.stdout.split()[-1]), len(entries)

    threshold, entries = run()
    if command == "estimate":
        assert (threshold, entries) == (0.0, 1)
    else:
        assert threshold >= 1.0 and entries == 0
    # The user's own setting wins.
    threshold, entries = run(JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="30")
    assert (threshold, entries) == (30.0, 0)
