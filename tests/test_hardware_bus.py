"""Acceptance (issue 18): a bad bus never raises a false alarm or loses a run.

* ``collect`` of a 20-sample plan on a virtual robot whose status packets are 10 % late by
  50 ms (longer than dynamixel-sdk's ~35 ms wait, so a late packet arrives while the
  master waits for the answer to its next request), and on one that drops and corrupts
  5 % each: both complete without a hardware error, every sample at rest, with the goal
  positions and directions of the plan (those a fault-free collection records,
  ``test_hardware_collect``), each sample once.
* The port is locked for one collection: a second ``collect`` on it gets one line and exit
  code 3 and writes nothing; a port that disappears mid-collection (the virtual robot
  killed) gives one line and exit code 3, and the journal keeps every finished sample.

Limits are generous (a busy host): ``--retries`` ``support.hardware.RETRIES`` (the bus may
stay silent for seconds), wall-clock limits far beyond the collections' simulated time;
waits are for conditions, never sleeps of a set length.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from support.hardware import RETRIES, journal_indices, one_line, running, wait_for_samples

from jaxinertia.open_manipulator_x import ARM as OMX
from jaxinertia.plans import random_plan
from jaxinertia.samples import load_native
from jaxinertia.virtual.testing import VirtualRobotProcess

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"),
                                reason="the virtual servo bus needs a Linux pseudo-terminal")

N = 20
SEED = 0
SPEED = 15
#: A collection: 10 minutes to start beside 20 x its simulated time (2 moves of at most
#: 6 s per sample).
WALL_LIMIT_S = 600 + 20 * N * 2 * 6.0 / SPEED


def collect_cmd(port: str, out, *extra: str, n: int = N) -> list[str]:
    return [sys.executable, "-m", "jaxinertia", "collect", "--port", port, "--plan", "random",
            "--n", str(n), "--seed", str(SEED), "--object", "cube", "--out", str(out),
            "--no-progress", "--retries", str(RETRIES), *extra]


@pytest.mark.parametrize("faults", [
    ["--delay-rate", "0.1", "--delay-ms", "50"],
    ["--drop-rate", "0.05", "--corrupt-rate", "0.05"],
], ids=["late", "dropped-and-corrupt"])
def test_a_faulty_bus_completes_the_plan_without_a_false_alarm(tmp_path, faults):
    out = tmp_path / "faulty.npz"
    with VirtualRobotProcess(["--object", "cube", "--speed", str(SPEED), "--seed", "3",
                              "--fault-seed", "11", *faults],
                             stderr=tmp_path / "virtual.log") as robot:
        run = subprocess.run(collect_cmd(robot.path, out), capture_output=True, text=True,
                             timeout=WALL_LIMIT_S)
    assert "hardware error" not in run.stderr, run.stderr
    assert run.returncode == 0, run.stderr
    retried = int(run.stderr.split("bus: ")[1].split()[0])
    assert retried > 0, "the injected faults must have been met and retried"
    samples, _ = load_native(out, only_at_rest=False)
    fields = samples.fields()
    # what the fault-free collection records
    q_d, d = random_plan(N, SEED, workspace=OMX.workspace_deg)
    np.testing.assert_array_equal(fields["q_d"], q_d, err_msg="q_d")
    np.testing.assert_array_equal(fields["direction"], d, err_msg="direction")
    np.testing.assert_array_equal(fields["plan_index"], np.arange(N), err_msg="plan_index")
    assert fields["at_rest"].all(), "at_rest"
    assert sorted(journal_indices(out)) == list(range(N)), "each sample exactly once"


def _children(pid: int) -> list[int]:
    """The processes whose parent is ``pid`` (Linux /proc)."""
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:  # gone meanwhile
            continue
        if int(fields[1]) == pid:
            out.append(int(stat.parent.name))
    return out


def _alive(pid: int) -> bool:
    """Running (not gone, not a zombie that nobody reaped)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def test_one_collect_per_port_and_a_vanishing_port_stops_cleanly(tmp_path):
    first, second = tmp_path / "first.npz", tmp_path / "second.npz"
    # Slow enough that the first collection is still running when the second starts.
    robot = VirtualRobotProcess(["--object", "cube", "--speed", "1"],
                                stderr=tmp_path / "virtual.log")
    with robot, running(collect_cmd(robot.path, first, n=1000)) as proc:
        wait_for_samples(first, 1, WALL_LIMIT_S, proc)
        assert proc.poll() is None, "the first collection stopped early"
        refused = subprocess.run(collect_cmd(robot.path, second), capture_output=True,
                                 text=True, timeout=WALL_LIMIT_S)
        assert refused.returncode == 3, refused.stderr
        assert "in use" in one_line(refused.stderr)
        assert not (tmp_path / "second.npz.journal.jsonl").exists(), "second journal"
        assert proc.poll() is None, "the first collection goes on"
        # The device disappears under the first collection, its physics process with it
        # (even when the robot died holding the tables' lock: the physics waits for it in
        # slices and ends when its parent is gone).
        physics = _children(robot.proc.pid)
        assert physics, "the virtual robot runs its physics in a process of its own"
        robot.proc.send_signal(signal.SIGKILL)
        _, err = proc.communicate(timeout=WALL_LIMIT_S)
    deadline = time.monotonic() + WALL_LIMIT_S
    while (alive := [p for p in physics if _alive(p)]) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not alive, f"processes of the killed robot left running: {alive}"
    assert proc.returncode == 3, err
    line = one_line(err)
    assert "samples are in" in line and "--resume" in line, line
    got = journal_indices(first)
    assert len(got) >= 1 and got == list(range(len(got))), "finished samples, in order"
    assert not first.exists(), "no sample file from an unfinished collection"
