"""Acceptance: faults on the bus, a servo overload, Ctrl-C, and ``--resume``.

One virtual robot (subprocess, 15x real time) drops, corrupts and delays 1 % of its
status packets each (a 4-servo sync read then fails about 8 % of the time), and servo 13
raises an overload error on its 6th Goal Position write (one-shot, as a real overload
that the operator then clears). The driver must retry
through the bus faults, stop cleanly on the overload with every finished sample in the
journal, and ``--resume --clear-errors`` must complete the plan with exactly the planned
samples: none lost, none duplicated.

Then what is refused before anything moves (exit code 2, one line): ``--n`` that is not
positive, ``--ids`` of the wrong count, a journal damaged before its last line; and a port
that cannot be opened (exit code 3, one line, no journal left behind).

Limits are generous (a busy host): ``--retries`` ``support.hardware.RETRIES`` (the bus may
stay silent for seconds), and wall-clock limits far beyond the collections' simulated time.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys

import numpy as np
import pytest
from support.hardware import RETRIES, journal_indices, one_line, running, wait_for_samples

from jaxinertia.app.cli import main
from jaxinertia.design import PLAN_FORMAT, PLAN_FORMAT_VERSION
from jaxinertia.hardware.collect import DELTA, RECORD_FIELDS, plan_digest
from jaxinertia.open_manipulator_x import ARM as OMX
from jaxinertia.plans import random_plan
from jaxinertia.samples import load_native
from jaxinertia.virtual.testing import VirtualRobotProcess

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"),
                                reason="the virtual servo bus needs a Linux pseudo-terminal")

N = 6
#: The interrupted collection's plan (see its test).
N_INTERRUPTED = 60
SPEED = 15
#: Each collection: 10 minutes to start beside 20 x its simulated time (2 moves of at most
#: 6 s per sample).
WALL_LIMIT_S = 600 + 20 * N * 2 * 6.0 / SPEED
FAULTS = ["--drop-rate", "0.01", "--corrupt-rate", "0.01", "--delay-rate", "0.01",
          "--delay-ms", "10", "--overload-id", "13", "--overload-after", "5",
          "--fault-seed", "7"]


@pytest.fixture(scope="module")
def robot(tmp_path_factory):
    log = tmp_path_factory.mktemp("faults") / "virtual.log"
    with VirtualRobotProcess(["--object", "50g", "--speed", str(SPEED), *FAULTS],
                             stderr=log) as r:
        yield r


def collect_cmd(port: str, out, *extra: str, n: int = N) -> list[str]:
    return [sys.executable, "-m", "jaxinertia", "collect", "--port", port,
            "--plan", "random", "--n", str(n), "--seed", "4", "--object", "50g",
            "--out", str(out), "--no-progress", "--retries", str(RETRIES), *extra]


def check_complete(out, n: int = N) -> None:
    samples, _ = load_native(out, only_at_rest=False)
    fields = samples.fields()
    q_d, d = random_plan(n, 4, workspace=OMX.workspace_deg)
    np.testing.assert_array_equal(fields["plan_index"], np.arange(n), err_msg="plan_index")
    np.testing.assert_array_equal(fields["q_d"], q_d, err_msg="q_d")
    np.testing.assert_array_equal(fields["direction"], d, err_msg="direction")
    assert sorted(journal_indices(out)) == list(range(n)), "each sample exactly once"


def test_overload_stops_cleanly_and_resume_completes_the_plan(robot, tmp_path):
    out = tmp_path / "load.npz"
    first = subprocess.run(collect_cmd(robot.path, out), capture_output=True, text=True,
                           timeout=WALL_LIMIT_S)
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
                             text=True, timeout=WALL_LIMIT_S)
    assert refused.returncode == 3 and "overload" in refused.stderr
    assert journal_indices(out) == [0, 1]
    done = subprocess.run(collect_cmd(robot.path, out, "--resume", "--clear-errors"),
                          capture_output=True, text=True, timeout=WALL_LIMIT_S)
    assert done.returncode == 0, done.stderr
    retried = int(done.stderr.split("bus: ")[1].split()[0])
    assert retried > 0, "the injected faults must have been met and retried"
    check_complete(out)


def test_refuses_to_overwrite_a_journal_without_resume(robot, tmp_path):
    out = tmp_path / "x.npz"
    (tmp_path / "x.npz.journal.jsonl").write_text('{"kind": "header"}\n')
    r = subprocess.run(collect_cmd(robot.path, out), capture_output=True, text=True,
                       timeout=WALL_LIMIT_S)
    assert r.returncode == 2 and "--resume" in r.stderr


def test_ctrl_c_leaves_the_journal_consistent_and_resume_completes(robot, tmp_path):
    # A plan long enough that the interrupt, sent as soon as the first sample is on disk,
    # lands mid-plan however busy the host is (6 samples took ~1 s at 15x real time and
    # could all finish between two polls of a descheduled test process).
    n = N_INTERRUPTED
    out = tmp_path / "int.npz"
    with running(collect_cmd(robot.path, out, n=n)) as proc:
        wait_for_samples(out, 1, WALL_LIMIT_S, proc)  # the first sample on disk
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=WALL_LIMIT_S)
    assert proc.returncode == 130, err
    assert "interrupted (hold)" in err
    got = journal_indices(out)
    assert 1 <= len(got) < n and got == list(range(len(got)))
    # The shared robot injects an overload on servo 13 (FAULTS), which a plan this long can
    # meet: that stop is the overload test's subject; here resume until the plan is done.
    resumes = []
    for _ in range(3):
        resumes.append(subprocess.run(
            collect_cmd(robot.path, out, "--resume", "--clear-errors", n=n),
            capture_output=True, text=True, timeout=WALL_LIMIT_S * n / N))
        if resumes[-1].returncode != 3 or "overload" not in resumes[-1].stderr:
            break
    assert resumes[-1].returncode == 0, resumes[-1].stderr
    assert f"{len(got)} of {n} samples already" in resumes[0].stderr
    check_complete(out, n)


# ---- refused before anything moves (in this process; the port does not exist) ------------

NO_PORT = "/dev/jaxinertia-no-such-port"


def collect_args(out, *extra: str) -> list[str]:
    return ["collect", "--port", NO_PORT, "--plan", "random", "--n", str(N), "--seed", "4",
            "--object", "50g", "--out", str(out), "--no-progress", *extra]


def run(argv: list[str]) -> int:
    """``jaxinertia ARGV`` in this process: its exit code (argparse's errors included)."""
    try:
        return main(argv)
    except SystemExit as e:
        return e.code


def one_line_error(capsys, *words: str) -> str:
    line = one_line(capsys.readouterr().err)
    for w in words:
        assert w in line, (w, line)
    return line


@pytest.mark.parametrize(("args", "words"), [
    (["--n", "0"], ["--n", "positive"]),
    (["--n", "-2"], ["--n", "positive"]),
    (["--ids", "11,12,13"], ["--ids", "4 joint servo IDs", "got 3"]),
    (["--ids", "11,12,12,14"], ["--ids", "distinct"]),
    (["--retries", "-1"], ["--retries"]),
    (["--settle-time", "nan"], ["--settle-time"]),
])
def test_bad_options_are_refused_before_the_port_is_opened(tmp_path, capsys, args, words):
    out = tmp_path / "x.npz"
    argv = collect_args(out)
    for k in range(0, len(args), 2):  # replace or add the option
        if args[k] in argv:
            argv[argv.index(args[k]) + 1] = args[k + 1]
        else:
            argv += args[k:k + 2]
    assert run(argv) == 2, "exit code"  # 3 would mean it went on to the port
    one_line_error(capsys, *words)
    assert not out.exists() and not (tmp_path / "x.npz.journal.jsonl").exists()


def test_a_plan_file_with_an_unsafe_pose_is_refused_before_the_port_is_opened(tmp_path, capsys):
    q_d, d = random_plan(3, 4, workspace=OMX.workspace_deg)
    q_d[1, 1] = np.radians(170.0)  # joint 2 far outside the workspace
    plan = tmp_path / "plan.json"
    plan.write_text(json.dumps({"format": PLAN_FORMAT, "format_version": PLAN_FORMAT_VERSION,
                                "q_d": q_d.tolist(), "direction": d.tolist()}))
    out = tmp_path / "x.npz"
    argv = collect_args(out)
    argv[argv.index("--plan") + 1] = str(plan)
    assert run(argv) == 2
    one_line_error(capsys, "--plan", "pose 1")
    argv[argv.index("--plan") + 1] = str(tmp_path / "missing.json")
    assert run(argv) == 2
    one_line_error(capsys, "missing.json")
    assert not out.exists() and not (tmp_path / "x.npz.journal.jsonl").exists()


def header_for(out) -> dict:
    q_d, d = random_plan(N, 4, workspace=OMX.workspace_deg)
    return {"kind": "header", "plan": "random", "seed": 4, "n_samples": N, "object": "50g",
            "plan_digest": plan_digest(q_d, d), "port": NO_PORT,
            "servo_ids": [11, 12, 13, 14], "delta": DELTA}


def record(index: int) -> dict:
    rec = {k: [0.0] * 4 for k in RECORD_FIELDS}
    rec.update(index=index, R_base_tag=np.eye(3).tolist(), p_base_tag=[0.0] * 3,
               at_rest=True, settle_time=0.5, timestamp=float(index))
    return rec


def planned(index: int, **change) -> dict:
    """A record at the plan's goal and direction, with ``change``."""
    q_d, d = random_plan(N, 4, workspace=OMX.workspace_deg)
    return {**record(index), "q_d": q_d[index].tolist(), "direction": d[index].tolist(),
            **change}


@pytest.mark.parametrize(("content", "words"), [
    (lambda h: "\n".join([json.dumps(h), json.dumps(record(0)), '{"index": 1, "q_d": [0.',
                          json.dumps(record(2))]) + "\n", ["[line 3]", "corrupt record"]),
    (lambda h: json.dumps(h)[:20], ["[line 1]", "torn header"]),
    (lambda h: "\n".join([json.dumps(h), json.dumps({"index": 0})]) + "\n",
     ["[line 2]", "record without"]),
    (lambda h: "\n".join([json.dumps(h), json.dumps(record(N + 3))]) + "\n",
     ["[line 2]", "not a sample of the plan"]),
    # Records checked as sample files are, before the arm moves (issue 32).
    (lambda h: "\n".join([json.dumps(h), json.dumps({**record(0), "direction": [1.0] * 4})])
     + "\n", ["[line 2 q_d]", "not the plan's"]),
    (lambda h: "\n".join([json.dumps(h), json.dumps(planned(0, q=[100.0, 0, 0, 0]))]) + "\n",
     ["[line 2 q]", "beyond one turn"]),
    (lambda h: "\n".join([json.dumps(h), json.dumps(planned(0, R_base_tag=[[0.0] * 3] * 3))])
     + "\n", ["[line 2 R_base_tag]", "not a rotation"]),
])
def test_a_damaged_journal_is_one_line_and_exit_2(tmp_path, capsys, content, words):
    out = tmp_path / "j.npz"
    journal = tmp_path / "j.npz.journal.jsonl"
    journal.write_text(content(header_for(out)))
    before = journal.read_bytes()
    assert run(collect_args(out, "--resume")) == 2
    one_line_error(capsys, str(journal), *words)
    assert journal.read_bytes() == before, "the journal is left as it was"


def test_a_port_that_cannot_be_opened_leaves_no_journal(tmp_path, capsys):
    out = tmp_path / "p.npz"
    assert run(collect_args(out)) == 3
    one_line_error(capsys, f"cannot open {NO_PORT}", "No such file")
    assert not (tmp_path / "p.npz.journal.jsonl").exists(), "no journal of nothing"
    assert not out.exists()
