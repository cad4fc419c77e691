"""Writing outputs so that nothing is lost: checked before the work, locked, written
atomically, with the user's permissions.

Every file the library and the command line write goes through :func:`replacing` (a
temporary file beside the target, renamed over it only when complete) or, for a folder,
:func:`replacing_dir`; a crash leaves the old output or none, never half of one.
:func:`check_output` runs before any work: an existing output is kept unless the caller
passes ``overwrite`` (a folder where a file is expected, or the reverse, is refused even
then), and a folder that cannot be created is reported then, not after minutes of
computing.

**Locks.** :func:`check_output` takes a lock file beside the output (``.<name>.lock``) and
this process holds it until the output is renamed into place (or the command ends:
:func:`command_locks`; the operating system drops it when the process ends). A second
writer of the same output, in this process or another, is refused at once with one line
instead of both writing and one result being lost. A write without a prior check takes
the lock for its own duration. The lock file is removed when the lock is released.

**Permissions.** Outputs honour the umask like any file the user creates: files
``0o666 & ~umask``, folders ``0o777 & ~umask`` (the temporary files they are written as
would otherwise keep ``0600``/``0700``).
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

from jaxinertia.errors import JaxinertiaError, UsageError

__all__ = ["OutputError", "OutputLockedError", "check_output", "command_locks",
           "nan_to_null", "null_to_nan", "release_locks", "replacing", "replacing_dir",
           "write_json", "write_text"]

#: Locks this process holds, by the output's absolute path (see the module's docstring).
_HELD: dict[Path, object] = {}
#: Those of them that belong to the caller of the running command (:func:`command_locks`).
_OTHERS: frozenset[Path] = frozenset()

#: Errors of a write that the user fixes (space, quota, a read-only disk): one line.
_USER_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EFBIG, errno.EACCES}


class OutputLockedError(UsageError):
    """Another writer (process or command) holds the output's lock."""


class OutputError(JaxinertiaError, OSError):
    """An output that could not be written (disk full, quota, read-only); nothing of it
    is left (the old output, if any, is kept)."""


def _umask() -> int:
    """The process's umask, read without changing it (Linux); else set and restored."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _lock_path(path: Path) -> Path:
    return path.with_name(f".{path.name}.lock")


def _acquire(path: Path, option: str) -> None:
    """Takes the lock of ``path`` (absolute) for this command, or refuses at once
    (``option``: how the message names the output)."""
    if path in _HELD and path not in _OTHERS:
        return
    from filelock import FileLock, Timeout  # light, but only writers need it

    lock = FileLock(str(_lock_path(path)), timeout=0)
    try:
        if path in _OTHERS:
            raise Timeout(str(_lock_path(path)))
        lock.acquire()
    except Timeout:
        raise OutputLockedError(f"{option} {path} is being written by another command (lock "
                                f"{_lock_path(path)}); wait for it to finish or choose "
                                "another output") from None
    except OSError as e:
        raise UsageError(f"{option} {path}: cannot lock it ({e.strerror or e})") from None
    _HELD[path] = lock


def _release(path: Path) -> None:
    lock = _HELD.pop(path, None)
    if lock is not None:
        with contextlib.suppress(OSError):  # removed while held: no other writer has it
            Path(lock.lock_file).unlink(missing_ok=True)
        lock.release()


def release_locks(keep: frozenset[Path] = frozenset()) -> None:
    """Releases the output locks this process holds, but ``keep``."""
    for path in list(_HELD):
        if path not in keep:
            _release(path)


@contextlib.contextmanager
def command_locks() -> Iterator[None]:
    """One command's outputs (the command line runs each command in one): the locks this
    process held before it (an in-process caller's, another command's) refuse the command
    as another process's would, and those it takes are released when it ends."""
    global _OTHERS
    before, outer = frozenset(_HELD), _OTHERS
    _OTHERS = before
    try:
        yield
    finally:
        _OTHERS = outer
        release_locks(keep=before)


def check_output(path: str | os.PathLike, *, overwrite: bool = False, option: str = "out",
                 folder: bool = False) -> Path:
    """``path`` if it may be written: it does not exist (or ``overwrite``, and it is a
    folder exactly when ``folder``), its folder exists or can be created and is writable,
    and no other writer holds it. Takes the output's lock (held until the output is
    renamed into place). Raises :class:`UsageError` naming the argument ``option``."""
    path = Path(path)
    if path.exists() and not overwrite:
        raise UsageError(f"`{option}` {path} exists; pass `overwrite` to replace it")
    if path.exists() and path.is_dir() != folder:
        raise UsageError(f"`{option}` {path} is a {'file' if folder else 'folder'}; "
                         f"{'a model folder' if folder else 'a file'} is written there: "
                         "remove it or choose another name")
    parent = path.parent if str(path.parent) else Path(".")
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise UsageError(f"`{option}` {path}: cannot create the folder {parent} "
                         f"({e.strerror or e})") from None
    if not os.access(parent, os.W_OK | os.X_OK):
        raise UsageError(f"`{option}` {path}: the folder {parent} is not writable")
    _acquire(path.absolute(), f"`{option}`")
    return path


@contextlib.contextmanager
def _locked_write(path: Path) -> Iterator[None]:
    """The output's lock held for the write (taken here unless already held), released
    after the rename; a write that fails for want of space is an :class:`OutputError`."""
    taken = path not in _HELD
    _acquire(path, "output")
    try:
        yield
    except OSError as e:
        if e.errno in _USER_ERRNOS and not isinstance(e, JaxinertiaError):
            raise OutputError(f"{path}: cannot write ({e.strerror or e}); nothing was "
                              "written") from e
        raise
    finally:
        if taken or path in _HELD:
            _release(path)


@contextlib.contextmanager
def replacing(path: str | os.PathLike, *, suffix: str = "") -> Iterator[Path]:
    """A temporary path beside ``path`` (ending in ``suffix``, e.g. ``.npz`` for numpy's
    writers); renamed over ``path`` when the block completes, removed when it fails."""
    path = Path(path).absolute()
    path.parent.mkdir(parents=True, exist_ok=True)
    with _locked_write(path):
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=f".tmp{suffix}",
                                   dir=path.parent)
        os.close(fd)
        tmp = Path(tmp)
        try:
            yield tmp
            if tmp.exists():
                os.chmod(tmp, 0o666 & ~_umask())
            os.replace(tmp, path)
        finally:
            tmp.unlink(missing_ok=True)


def write_text(path: str | os.PathLike, text: str) -> Path:
    """Writes ``text`` to ``path`` atomically."""
    with replacing(path) as tmp:
        tmp.write_text(text)
    return Path(path)


def write_json(path: str | os.PathLike, obj) -> Path:
    """``obj`` as indented JSON (numpy arrays as lists), written atomically."""
    return write_text(path, json.dumps(obj, indent=2, default=_json_default) + "\n")


def nan_to_null(a) -> list:
    """``a`` (1-D) as a JSON list, a NaN (a value that does not exist: the current-based
    torque of a servo without a current sensor) as null; strict JSON has no NaN."""
    import numpy as np  # (as in _json_default)

    return [None if v != v else float(v) for v in np.asarray(a, np.float64).ravel()]


def null_to_nan(values):
    """The float64 array of a JSON list, null as NaN (:func:`nan_to_null` read back)."""
    import numpy as np  # (as in _json_default)

    return np.asarray([np.nan if v is None else v for v in values], np.float64)


def _json_default(o):
    import numpy as np  # numpy values in results (numpy is loaded wherever they exist)

    if isinstance(o, np.ndarray | np.generic):
        return o.tolist()
    raise TypeError(type(o).__name__)


@contextlib.contextmanager
def replacing_dir(path: str | os.PathLike) -> Iterator[Path]:
    """A temporary folder beside ``path``; when the block completes it takes the place of
    ``path`` (an old folder there is removed only after the new one is complete)."""
    path = Path(path).absolute()
    path.parent.mkdir(parents=True, exist_ok=True)
    with _locked_write(path):
        tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent))
        try:
            yield tmp
            os.chmod(tmp, 0o777 & ~_umask())
            old = None
            if path.exists():
                old = path.with_name(f".{path.name}.old-{os.getpid()}")
                os.replace(path, old)
            os.replace(tmp, path)
            if old is not None:
                shutil.rmtree(old, ignore_errors=True)
        finally:
            if tmp.exists():
                shutil.rmtree(tmp, ignore_errors=True)
