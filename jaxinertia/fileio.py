"""Writing outputs so that nothing is lost: checked before the work, written atomically.

Every file the library and the command line write goes through :func:`replacing` (a
temporary file beside the target, renamed over it only when complete) or, for a folder,
:func:`replacing_dir`; a crash leaves the old output or none, never half of one.
:func:`check_output` runs before any work: an existing output is kept unless the caller
passes ``overwrite``, and a folder that cannot be created is reported then, not after
minutes of computing.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from jaxinertia.errors import UsageError

__all__ = ["check_output", "replacing", "replacing_dir", "write_json", "write_text"]


def check_output(path: str | os.PathLike, *, overwrite: bool = False, option: str = "--out",
                 ) -> Path:
    """``path`` if it may be written: it does not exist (or ``overwrite``) and its folder
    exists or can be created and is writable. Raises :class:`UsageError` naming the option."""
    path = Path(path)
    if path.exists() and not overwrite:
        raise UsageError(f"{option} {path} exists; pass --overwrite to replace it")
    parent = path.parent if str(path.parent) else Path(".")
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise UsageError(f"{option} {path}: cannot create the folder {parent} "
                         f"({e.strerror or e})") from None
    if not os.access(parent, os.W_OK | os.X_OK):
        raise UsageError(f"{option} {path}: the folder {parent} is not writable")
    return path


@contextlib.contextmanager
def replacing(path: str | os.PathLike, *, suffix: str = "") -> Iterator[Path]:
    """A temporary path beside ``path`` (ending in ``suffix``, e.g. ``.npz`` for numpy's
    writers); renamed over ``path`` when the block completes, removed when it fails."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=f".tmp{suffix}", dir=path.parent)
    os.close(fd)
    tmp = Path(tmp)
    try:
        yield tmp
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


def _json_default(o):
    if isinstance(o, np.ndarray | np.generic):
        return o.tolist()
    raise TypeError(type(o).__name__)


@contextlib.contextmanager
def replacing_dir(path: str | os.PathLike) -> Iterator[Path]:
    """A temporary folder beside ``path``; when the block completes it takes the place of
    ``path`` (an old folder there is removed only after the new one is complete)."""
    path = Path(path).absolute()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent))
    try:
        yield tmp
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
