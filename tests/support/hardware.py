"""Helpers of the hardware tests: journals, collections running in a subprocess, one-line
errors. Waits are for conditions with a deadline, never sleeps of a set length."""

from __future__ import annotations

import contextlib
import json
import re
import signal
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

__all__ = ["RETRIES", "Client", "collect_interrupted_and_resumed", "interrupting_tag_pose",
           "journal_indices", "one_line", "running", "wait_for_samples"]

#: ``collect --retries`` of the hardware tests: how long the bus may stay silent before a
#: collection gives up (each failed attempt costs ~70 ms: the SDK's ~35 ms wait, then as
#: long a quiet bus), here ~28 s. Why that long (docs/hardware.md, "A busy host"): every
#: byte on a pseudo-terminal (and on a USB serial adapter) passes through the kernel's
#: tty worker (``flush_to_ldisc`` on the unbound workqueue), and beside busy loops on both
#: cores of the 2-core test machine that worker was measured runnable but unscheduled for
#: up to 3.7 s (the virtual robot's bus thread meanwhile in ``__flush_work``, state D).
#: No code of ours runs in that time; what the tests check is that the collection then
#: carries on with every sample right, not how fast the host's kernel moves bytes.
RETRIES = 400


def journal_path(out: Path) -> Path:
    return out.parent / (out.name + ".journal.jsonl")


def journal_indices(out: Path) -> list[int]:
    """The plan indices recorded in ``out``'s journal, in journal order."""
    lines = journal_path(out).read_text().splitlines()
    assert json.loads(lines[0])["kind"] == "header"
    return [json.loads(line)["index"] for line in lines[1:]]


#: A Python warning as ``warnings`` prints it: "path:line: SomeWarning: text", then the
#: source line, indented.
_WARNING = re.compile(r"^\S+:\d+: \w*Warning: ")


def one_line(stderr: str) -> str:
    """The one line of ``stderr`` (fails if there are more, or a traceback). Python
    warnings of the libraries underneath (JAX's compilation cache, shared by the test
    session's processes, warns when another process evicts an entry it reads) are not
    the command's output and are left out."""
    assert "Traceback" not in stderr, stderr
    lines, skip = [], False
    for line in stderr.strip().splitlines():
        if _WARNING.match(line):
            skip = True
        elif not (skip and line.startswith(" ")):
            lines.append(line)
            skip = False
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


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@contextlib.contextmanager
def running(cmd: list[str]) -> Iterator[subprocess.Popen]:
    """``cmd`` in a subprocess (text pipes); killed on the way out if still running.

    SIGINT is reset to its default in the child: a test runner started in the background
    by a non-interactive shell inherits SIGINT ignored, and Python then never turns Ctrl-C
    into KeyboardInterrupt (the interrupt tests would see a collect that cannot be
    interrupted)."""
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=_default_sigint)
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=60)


def collect_interrupted_and_resumed(port: str, arm, out: Path, monkeypatch, capsys, *,
                                    n: int = 4, after: int = 2, seed: int = 1) -> str:
    """``jaxinertia collect --arm ARM`` of an ``n``-sample random plan in this process on
    ``port``, interrupted (Ctrl-C: a KeyboardInterrupt from the tag-pose source, once
    ``after`` samples are in the journal: deterministic whatever the host's speed), then
    ``--resume``d to the end. Checks that the first run stops with exit code 130 and the
    journal holds samples ``0..after-1``, and that the resumed one completes the plan:
    every planned goal and direction once, in plan order, at rest, with no hardware
    error (a faulty bus raises no false alarm). Returns the resumed run's stderr."""
    import numpy as np  # (the test modules import JAX; these helpers stay light)

    from jaxinertia.app.cli import main
    from jaxinertia.hardware import collect
    from jaxinertia.plans import random_plan
    from jaxinertia.samples import load_native

    base = collect.KinematicTagPose
    Interrupting = interrupting_tag_pose(base, after)

    argv = ["collect", "--arm", arm.name, "--port", port, "--plan", "random", "--n", str(n),
            "--seed", str(seed), "--object", "50g", "--out", str(out), "--no-progress",
            "--retries", str(RETRIES)]
    capsys.readouterr()
    monkeypatch.setattr(collect, "KinematicTagPose", Interrupting)
    assert main(argv) == 130, capsys.readouterr().err
    err = capsys.readouterr().err
    assert "interrupted (hold)" in err and "hardware error" not in err, err
    assert journal_indices(out) == list(range(after)), "the samples before the interrupt"
    assert not out.exists(), "no sample file from an unfinished collection"
    monkeypatch.setattr(collect, "KinematicTagPose", base)
    assert main([*argv, "--resume"]) == 0, capsys.readouterr().err
    err = capsys.readouterr().err
    assert f"{after} of {n} samples already" in err and "hardware error" not in err, err
    assert " 0 unconfirmed hardware-error readings" in err, err
    samples, meta = load_native(out, only_at_rest=False)
    fields = samples.fields()
    q_d, d = random_plan(n, seed, workspace=arm.workspace_deg)
    assert meta["arm"] == arm.name
    np.testing.assert_array_equal(fields["plan_index"], np.arange(n), err_msg="plan_index")
    np.testing.assert_array_equal(fields["q_d"], q_d, err_msg="q_d")
    np.testing.assert_array_equal(fields["direction"], d, err_msg="direction")
    assert fields["at_rest"].all(), "at_rest"
    assert journal_indices(out) == list(range(n)), "each sample exactly once"
    return err


class Client:
    """A vendor SDK's ``port`` (opened here) and packet handler ``ph`` (dynamixel-sdk's or
    scservo_sdk's: the same calls), counting transactions (``attempted``, ``failed``)."""

    SUCCESS = 0  # COMM_SUCCESS in both SDKs

    def __init__(self, port, ph):
        self.port, self.ph = port, ph
        assert self.port.openPort()
        self.attempted = self.failed = 0

    def call(self, fn, *args):
        """One transaction: (value, result, error) of the SDK (its comm result counted)."""
        self.attempted += 1
        out = fn(self.port, *args)
        result = out if isinstance(out, int) else out[1] if len(out) == 3 else out[0]
        if result != self.SUCCESS:
            self.failed += 1
        return out

    def close(self):
        self.port.closePort()


def interrupting_tag_pose(base, after: int):
    """``base`` (the collect's tag-pose source) raising Ctrl-C once ``after`` samples were
    taken, whatever the host's speed."""
    class Interrupting(base):
        calls = 0

        def __call__(self, q):
            if Interrupting.calls == after:
                raise KeyboardInterrupt
            Interrupting.calls += 1
            return super().__call__(q)

    return Interrupting
