"""JAX's persistent compilation cache as the command line and its helper processes use it.

The command line keeps compiled programs in one folder, capped in size (JAX evicts the
least recently used entries beyond it). With a cap, JAX keeps an access-time file beside
every entry and reads all of them before each write; an entry without one (written by a
process without the cap, or by one stopped between the two writes) makes every later write
to the folder fail with a warning. So every process that writes the folder applies the same
cap (:func:`enable`; the virtual robot's physics process takes its parent's settings), and
:func:`repair` gives such entries an access time when the command line starts.
"""

from __future__ import annotations

import os
from pathlib import Path

import jax

__all__ = ["MAX_BYTES", "enable", "repair"]

#: The cache's size cap [bytes].
MAX_BYTES = 512 * 2**20

# JAX's file names (jax._src.lru_cache): "<key>-cache" and its "<key>-atime".
_CACHE, _ATIME = "-cache", "-atime"


def repair(where: str | os.PathLike) -> int:
    """Gives every entry of the cache folder ``where`` that lacks its access-time file one
    (its modification time); returns how many were repaired."""
    fixed = 0
    folder = Path(where)
    if not folder.is_dir():
        return 0
    for entry in folder.glob(f"*{_CACHE}"):
        atime = entry.with_name(entry.name[: -len(_CACHE)] + _ATIME)
        if atime.exists():
            continue
        try:
            atime.write_bytes(entry.stat().st_mtime_ns.to_bytes(8, "little"))
            fixed += 1
        except OSError:  # removed meanwhile by another process's eviction, or read-only
            pass
    return fixed


#: JAX's own setting of the threshold below (its environment variable, when a user set it).
_MIN_COMPILE_TIME_ENV = "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"


def enable(where: str | os.PathLike, max_bytes: int = MAX_BYTES, *,
           keep_small: bool = False) -> None:
    """This process keeps compiled programs in ``where``, at most ``max_bytes`` (-1: no
    cap, JAX's default), after repairing the folder (:func:`repair`).

    JAX keeps only programs that took a second or more to compile. ``keep_small`` keeps
    every program (unless the user set ``JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS``):
    for commands made of many small programs, run again and again on new files
    (``estimate``: with an ensemble folder of 28 members, 76 programs of 60 ms each;
    kept, a second ``estimate`` took 7.8-8.2 s instead of 14.0 s on the 2-core CPU). Not
    for every command: with the cap, each write reads every entry's access time, so the
    hundreds of small programs of a ``reproduce`` would slow the writes down as the
    folder grows."""
    if max_bytes >= 0:
        repair(where)
    jax.config.update("jax_compilation_cache_dir", str(where))
    jax.config.update("jax_compilation_cache_max_size", int(max_bytes))
    if keep_small and _MIN_COMPILE_TIME_ENV not in os.environ:
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
