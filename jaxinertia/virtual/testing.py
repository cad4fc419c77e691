"""Starting ``jaxinertia virtual-robot`` as a subprocess (tests, scripts, CI)."""

from __future__ import annotations

import os
import select
import subprocess
import sys
import time
from pathlib import Path

__all__ = ["VirtualRobotProcess"]


class VirtualRobotProcess:
    """``jaxinertia virtual-robot ARGS`` in a subprocess; ``path`` is its pty.

    A context manager: waits (``startup_timeout``, generous: two interpreters start and
    the physics compiles, on a host that may be busy) for the device path on the first
    line of stdout, and on exit terminates the process (then kills it if it lingers)."""

    def __init__(self, args: list[str], *, stderr: Path | None = None,
                 startup_timeout: float = 900.0) -> None:
        self.args = [sys.executable, "-m", "jaxinertia", "virtual-robot", *args]
        self.stderr_path = stderr
        self.startup_timeout = startup_timeout
        self.proc: subprocess.Popen | None = None
        self.path = ""

    def __enter__(self) -> VirtualRobotProcess:
        err = open(self.stderr_path, "wb") if self.stderr_path else subprocess.DEVNULL  # noqa: SIM115
        self.proc = subprocess.Popen(self.args, stdout=subprocess.PIPE, stderr=err)
        if self.stderr_path:
            err.close()
        deadline = time.monotonic() + self.startup_timeout
        line = b""
        fd = self.proc.stdout.fileno()
        while not line.endswith(b"\n"):
            left = deadline - time.monotonic()
            if left <= 0 or self.proc.poll() is not None:
                self.close()
                raise RuntimeError(f"virtual robot did not start: {self.args}")
            ready, _, _ = select.select([fd], [], [], min(left, 0.5))
            if ready:
                chunk = os.read(fd, 1)
                if not chunk:
                    continue
                line += chunk
        self.path = line.decode().strip()
        return self

    def close(self) -> None:
        if self.proc is None:
            return
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=10)
        if self.proc.stdout:
            self.proc.stdout.close()

    def __exit__(self, *exc) -> None:
        self.close()
