"""``jaxinertia virtual-robot --arm so101`` (a subprocess, the STS bus model, faults
injected) answers as six STS3215 servos, and the collection protocol
(:func:`jaxinertia.hardware.collect.collect`: pre-position, goal, record at rest, the
journal) runs on it through :class:`jaxinertia.hardware.feetech.FeetechArm`: interrupted
after two samples and resumed, it loses nothing and records nothing twice.

The tag pose is a fixed stand-in (the kinematic source would compile the SO-101's forward
kinematics; the journal and the driver are what is tested here). Then the command itself:
``jaxinertia collect --arm so101`` (the arm record's bus picks the Feetech driver) on the
virtual STS bus with faults injected, interrupted and resumed
(``support.hardware.collect_interrupted_and_resumed``, as the Koch's in
``test_hardware_koch``), loses nothing and raises no false alarm. Limits are generous (a
busy host): waits are for conditions, never sleeps of a set length.
"""

from __future__ import annotations

import sys

import numpy as np
import pytest
from scservo_sdk import COMM_SUCCESS
from support.hardware import collect_interrupted_and_resumed

from jaxinertia.arms import SO101
from jaxinertia.hardware.collect import Journal, collect, journal_path, plan_digest
from jaxinertia.hardware.feetech import FeetechArm, feetech_config
from jaxinertia.plans import random_plan
from jaxinertia.samples import load_native
from jaxinertia.virtual.bus import Faults
from jaxinertia.virtual.sts_bus import StsServoBus
from jaxinertia.virtual.testing import VirtualRobotProcess

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"),
                                reason="the virtual servo bus needs a Linux pseudo-terminal")

N = 4
FAULTS = ["--drop-rate", "0.003", "--corrupt-rate", "0.003", "--delay-rate", "0.003",
          "--delay-ms", "50", "--fault-seed", "2"]


class Interrupt:
    """The tag-pose source, which presses Ctrl-C after ``after`` samples."""

    def __init__(self, after: int | None):
        self.after, self.calls = after, 0

    def __call__(self, q):
        if self.after is not None and self.calls == self.after:
            raise KeyboardInterrupt
        self.calls += 1
        return np.eye(3), np.zeros(3)


def header(q_d, direction) -> dict:
    return {"kind": "header", "n_samples": len(q_d), "object": "none",
            "plan_digest": plan_digest(q_d, direction)}


def run(path: str, out, q_d, direction, *, resume: bool, after: int | None) -> FeetechArm:
    config = feetech_config(path, SO101, retries=400, move_timeout=120.0,
                            profile_velocity=3.0)
    journal = Journal.open(journal_path(out), header(q_d, direction), resume=resume)
    arm = FeetechArm(config)
    try:
        with arm:
            collect(arm, q_d, direction, journal, tag_pose=Interrupt(after),
                    delta=SO101.pre_position, progress=False)
    finally:
        journal.close()
    return arm


def test_virtual_so101_collect_interrupted_and_resumed_loses_nothing(tmp_path):
    workspace = tuple((lo / 4, hi / 4) for lo, hi in SO101.workspace_deg)  # short moves
    q_d, direction = random_plan(N, 1, workspace=workspace)
    out = tmp_path / "so101.npz"
    with VirtualRobotProcess(["--arm", "so101", *FAULTS],
                             stderr=tmp_path / "virtual.log") as robot:
        # The vendor SDK sees six STS3215s.
        probe = FeetechArm(feetech_config(robot.path, SO101))
        probe.open()
        for i in (*SO101.bus_ids, SO101.gripper_id):
            for _ in range(400):
                model, result, _ = probe.packet.ping(probe.port, i)
                if result == COMM_SUCCESS:
                    break
            assert model == 777, i
        probe.close()
        with pytest.raises(KeyboardInterrupt):
            run(robot.path, out, q_d, direction, resume=False, after=2)
        first = Journal.open(journal_path(out), header(q_d, direction), resume=True)
        assert sorted(first.records) == [0, 1]
        arm = run(robot.path, out, q_d, direction, resume=True, after=None)
    print(f"resumed collection, bus: {arm.bus_report()}")
    assert arm.unconfirmed_alarms == 0
    lines = journal_path(out).read_text().splitlines()
    records = Journal.open(journal_path(out), header(q_d, direction), resume=True).records
    assert len(lines) == 1 + N and sorted(records) == list(range(N)), "each sample once"
    for i, rec in records.items():
        np.testing.assert_array_equal(rec["q_d"], q_d[i])
        np.testing.assert_array_equal(rec["direction"], direction[i])
        assert rec["at_rest"], i
        # At rest at the goal (no load in the bus model): within a tick.
        assert np.all(np.abs(np.asarray(rec["q"]) - q_d[i]) <= 2 * np.pi / 4096), i


def test_collect_command_on_the_so101_interrupted_and_resumed_loses_nothing(
        tmp_path, monkeypatch, capsys):
    faults = Faults(drop_rate=0.01, corrupt_rate=0.01, delay_rate=0.01, delay_s=0.05, seed=4)
    out = tmp_path / "so101-cli.npz"
    with StsServoBus(tuple(SO101.bus_ids), (SO101.gripper_id,), faults=faults,
                     speed=10.0) as bus:
        err = collect_interrupted_and_resumed(bus.path, SO101, out, monkeypatch, capsys)
    assert int(err.split("bus: ")[1].split()[0]) > 0, "the injected faults were met"
    samples, meta = load_native(out, only_at_rest=False)
    assert meta["source"] == "feetech" and samples.has_current  # STS3215: current sensed
