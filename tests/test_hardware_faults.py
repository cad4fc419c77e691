"""Acceptance: faults on the bus, a servo overload, Ctrl-C, and ``--resume``.

One virtual robot (subprocess, 15x real time) drops, corrupts and delays 1 % of its
status packets each (a 4-servo sync read then fails about 8 % of the time), and servo 13
raises an overload error on its 6th Goal Position write (one-shot, as a real overload
that the operator then clears). The driver must retry
through the bus faults, stop cleanly on the overload with every finished sample in the
journal, and ``--resume --clear-errors`` must complete the plan with exactly the planned
samples: none lost, none duplicated.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from jaxinertia.plans import random_plan
from jaxinertia.samples import load_native
from jaxinertia.virtual.testing import VirtualRobotProcess

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"),
                                reason="the virtual servo bus needs a Linux pseudo-terminal")

N = 6
FAULTS = ["--drop-rate", "0.01", "--corrupt-rate", "0.01", "--delay-rate", "0.01",
          "--delay-ms", "10", "--overload-id", "13", "--overload-after", "5",
          "--fault-seed", "7"]


@pytest.fixture(scope="module")
def robot(tmp_path_factory):
    log = tmp_path_factory.mktemp("faults") / "virtual.log"
    with VirtualRobotProcess(["--object", "50g", "--speed", "15", *FAULTS],
                             stderr=log) as r:
        yield r


def collect_cmd(port: str, out, *extra: str) -> list[str]:
    return [sys.executable, "-m", "jaxinertia", "collect", "--port", port,
            "--plan", "random", "--n", str(N), "--seed", "4", "--object", "50g",
            "--out", str(out), "--no-progress", "--retries", "5", *extra]


def journal_indices(out) -> list[int]:
    lines = (out.parent / (out.name + ".journal.jsonl")).read_text().splitlines()
    assert json.loads(lines[0])["kind"] == "header"
    return [json.loads(line)["index"] for line in lines[1:]]


def check_complete(out) -> None:
    samples, _ = load_native(out, only_at_rest=False)
    fields = samples.fields()
    q_d, d = random_plan(N, 4)
    np.testing.assert_array_equal(fields["plan_index"], np.arange(N), err_msg="plan_index")
    np.testing.assert_array_equal(fields["q_d"], q_d, err_msg="q_d")
    np.testing.assert_array_equal(fields["direction"], d, err_msg="direction")
    assert sorted(journal_indices(out)) == list(range(N)), "each sample exactly once"


def test_overload_stops_cleanly_and_resume_completes_the_plan(robot, tmp_path):
    out = tmp_path / "load.npz"
    first = subprocess.run(collect_cmd(robot.path, out), capture_output=True, text=True,
                           timeout=180)
    # Goal writes 1-4 are samples 0 and 1 (pre-position, goal); the 6th, sample 2's goal.
    assert first.returncode == 3, first.stderr
    assert "overload" in first.stderr and "ID 13" in first.stderr
    assert journal_indices(out) == [0, 1]
    assert not out.exists(), "no sample file from an unfinished collection"
    # A torn last line (power cut mid-write) must be discarded, not crash the resume.
    journal = out.parent / (out.name + ".journal.jsonl")
    with open(journal, "a") as f:
        f.write('{"index": 2, "q_d": [0.1')
    # Without clearing the error the arm refuses to start.
    refused = subprocess.run(collect_cmd(robot.path, out, "--resume"), capture_output=True,
                             text=True, timeout=180)
    assert refused.returncode == 3 and "overload" in refused.stderr
    assert journal_indices(out) == [0, 1]
    done = subprocess.run(collect_cmd(robot.path, out, "--resume", "--clear-errors"),
                          capture_output=True, text=True, timeout=180)
    assert done.returncode == 0, done.stderr
    retried = int(done.stderr.split("bus: ")[1].split()[0])
    assert retried > 0, "the injected faults must have been met and retried"
    check_complete(out)


def test_refuses_to_overwrite_a_journal_without_resume(robot, tmp_path):
    out = tmp_path / "x.npz"
    (tmp_path / "x.npz.journal.jsonl").write_text('{"kind": "header"}\n')
    r = subprocess.run(collect_cmd(robot.path, out), capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 2 and "--resume" in r.stderr


def test_ctrl_c_leaves_the_journal_consistent_and_resume_completes(robot, tmp_path):
    out = tmp_path / "int.npz"
    journal = tmp_path / "int.npz.journal.jsonl"
    proc = subprocess.Popen(collect_cmd(robot.path, out), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:  # wait for the first sample on disk
            if journal.exists() and len(journal.read_text().splitlines()) >= 2:
                break
            time.sleep(0.05)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)
    assert proc.returncode == 130, err
    assert "interrupted (hold)" in err
    got = journal_indices(out)
    assert 1 <= len(got) < N and got == list(range(len(got)))
    done = subprocess.run(collect_cmd(robot.path, out, "--resume"), capture_output=True,
                          text=True, timeout=180)
    assert done.returncode == 0, done.stderr
    assert f"{len(got)} of {N} samples already" in done.stderr
    check_complete(out)
