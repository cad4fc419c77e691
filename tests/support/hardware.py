"""Helpers of the hardware tests: journals, collections running in a subprocess, one-line
errors. Waits are for conditions with a deadline, never sleeps of a set length."""

from __future__ import annotations

import contextlib
import json
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

__all__ = ["journal_indices", "one_line", "running", "wait_for_samples"]


def journal_path(out: Path) -> Path:
    return out.parent / (out.name + ".journal.jsonl")


def journal_indices(out: Path) -> list[int]:
    """The plan indices recorded in ``out``'s journal, in journal order."""
    lines = journal_path(out).read_text().splitlines()
    assert json.loads(lines[0])["kind"] == "header"
    return [json.loads(line)["index"] for line in lines[1:]]


def one_line(stderr: str) -> str:
    """The one line of ``stderr`` (fails if there are more)."""
    lines = stderr.strip().splitlines()
    assert len(lines) == 1, f"one line expected: {lines}"
    return lines[0]


def wait_for_samples(out: Path, n: int, deadline_s: float,
                     proc: subprocess.Popen | None = None) -> None:
    """Waits until ``out``'s journal holds ``n`` samples (or ``proc`` ended, or the
    deadline passed: the caller's assertions then say what went wrong)."""
    journal = journal_path(out)
    deadline = time.monotonic() + deadline_s
    while time.monotonic() < deadline and (proc is None or proc.poll() is None):
        if journal.exists() and len(journal.read_text().splitlines()) > n:
            return
        time.sleep(0.05)


@contextlib.contextmanager
def running(cmd: list[str]) -> Iterator[subprocess.Popen]:
    """``cmd`` in a subprocess (text pipes); killed on the way out if still running."""
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=60)
