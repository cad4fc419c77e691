"""The virtual Koch v1.1 on its real servos: dynamixel-sdk and the driver against
:class:`jaxinertia.virtual.robot.VirtualServoBus` with the arm's servo models (joints 1-2
XL430-W250, joints 3-5 and the gripper XL330-M288), in this process, the simulated Koch
behind it.

* A clean bus: every servo pings with its own model number (1060, 1200), reads and writes
  at the X series' addresses, each table with its model's items (Present Load on the
  XL430, Present Current in 1 mA and a Current Limit on the XL330), sync read and sync
  write, a goal reached; what address 126 reports at rest is the position loop's output
  in that model's unit: **no failed transaction**.
* A faulty bus (status packets dropped, corrupted and late): ``jaxinertia collect --arm
  koch_v1_1``, interrupted and resumed, loses nothing, records nothing twice and raises
  **no false alarm**; the XL430 joints' current-based torque is absent (NaN), the XL330
  joints' present.

No wall-clock assertions: the SDK's port waits generously on the clean bus, and waits are
for conditions with generous deadlines.
"""

from __future__ import annotations

import sys
import time

import numpy as np
import pytest
from dynamixel_sdk import COMM_SUCCESS, GroupSyncRead, GroupSyncWrite, PacketHandler
from support.hardware import Client, collect_interrupted_and_resumed
from test_hardware_protocol import PatientPort

from jaxinertia.arms import KOCH_V1_1 as KOCH
from jaxinertia.hardware import control_table as ct
from jaxinertia.objects import resolve
from jaxinertia.samples import load_native
from jaxinertia.servos import servo_model
from jaxinertia.sim.params import arm_sim_params
from jaxinertia.virtual.bus import Faults
from jaxinertia.virtual.robot import VirtualServoBus

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"),
                                reason="the virtual servo bus needs a Linux pseudo-terminal")

JOINTS = KOCH.bus_ids
IDS = (*JOINTS, KOCH.gripper_id)
MODELS = [servo_model(m) for m in (*KOCH.servos, KOCH.gripper_servo)]
DEADLINE_S = 120.0  # for a condition on a busy host
FAULTS = Faults(drop_rate=0.01, corrupt_rate=0.01, delay_rate=0.01, delay_s=0.05, seed=3)


@pytest.fixture(scope="module")
def bus():
    b = VirtualServoBus(arm_sim_params(KOCH), resolve("none", tag_in_ee=KOCH.tag_in_ee),
                        ids=JOINTS, extra_ids=(KOCH.gripper_id,), speed=10.0,
                        q0=np.radians([np.mean(w) for w in KOCH.workspace_deg]),
                        servo_models=MODELS, gain_registers=[g[0] for g in KOCH.joint_gains])
    with b:
        yield b


def test_every_servo_answers_as_its_model_and_a_goal_is_reached(bus):
    c = Client(PatientPort(bus.path), PacketHandler(2.0))
    for i, m in zip(IDS, MODELS):
        assert c.call(c.ph.ping, i) == (m.model_number, COMM_SUCCESS, 0), f"ping ID {i}"
        table = ct.items_of(m.model_number)
        got = c.call(c.ph.read2ByteTxRx, i, 84)[0]
        assert got == table["position_p_gain"].default == m.default_gains[0], f"P of ID {i}"
        # Address 126 is read-only on both: Present Load (XL430), Present Current (XL330).
        assert c.call(c.ph.write2ByteTxRx, i, 126, 5) == (COMM_SUCCESS, 7), f"126 of ID {i}"
    assert "present_load" in bus.servos[1].items and "current_limit" not in bus.servos[1].items
    assert c.call(c.ph.read2ByteTxRx, 3, 38) == (1750, COMM_SUCCESS, 0), "Current Limit ID 3"
    assert c.call(c.ph.write4ByteTxRx, 2, 112, 40) == (COMM_SUCCESS, 0)  # Profile Velocity
    assert c.call(c.ph.read4ByteTxRx, 2, 112) == (40, COMM_SUCCESS, 0)
    assert c.call(c.ph.write4ByteTxRx, 2, 112, 0) == (COMM_SUCCESS, 0)
    start, length = ct.STATE_BLOCK
    state = GroupSyncRead(c.port, c.ph, start, length)
    for i in JOINTS:
        assert state.addParam(i)
    assert c.call(lambda _port: state.txRxPacket()) == COMM_SUCCESS

    for i, m in zip(JOINTS, MODELS):  # each at its own supply: 12 V (XL430), 5 V (XL330)
        assert state.getData(i, 144, 2) == round(m.supply_voltage * 10), f"voltage ID {i}"

    def position(i: int) -> int:
        return ct.to_signed(state.getData(i, 132, 4), 4)

    goals = {i: position(i) + 60 * (-1) ** k for k, i in enumerate(JOINTS)}
    for i in JOINTS:
        assert c.call(c.ph.write1ByteTxRx, i, 64, 1) == (COMM_SUCCESS, 0), f"torque ID {i}"
    write = GroupSyncWrite(c.port, c.ph, 116, 4)
    for i, g in goals.items():
        assert write.addParam(i, g.to_bytes(4, "little"))
    assert c.call(lambda _port: write.txPacket()) == COMM_SUCCESS
    # At rest (Moving 0, no tick changed between two readings) near every goal.
    deadline, last = time.monotonic() + DEADLINE_S, None
    while True:
        assert c.call(lambda _port: state.txRxPacket()) == COMM_SUCCESS
        ticks = {i: position(i) for i in JOINTS}
        moving = [state.getData(i, 122, 1) for i in JOINTS]
        if not any(moving) and ticks == last:
            break
        assert time.monotonic() < deadline, (ticks, goals, moving)
        last = ticks
        time.sleep(0.05)
    for k, i in enumerate(JOINTS):
        e = goals[i] - ticks[i]
        assert abs(e) < 150, f"ID {i} rests {e} ticks from its goal"
        # At rest the loop's output is P/128 * e (PWM, 885 = 100 %); 126 reports it as the
        # motor current in 1 mA (XL330) or as a share of the maximum torque in 0.1 %
        # (XL430: the duty, since the stall current is V/R). Noise: 2 LSB std.
        m = MODELS[k]
        duty = m.default_gains[0] / 128 * e / 885
        sensed = ct.to_signed(state.getData(i, 126, 2), 2)
        want = duty * (1000 if not m.has_current_sensor else m.stall_current / m.sensed_lsb)
        assert abs(sensed - want) <= 12, f"ID {i}: 126 reads {sensed}, loop output {want:.1f}"
    assert c.failed == 0, f"{c.failed} of {c.attempted} transactions failed on a clean bus"
    c.close()


@pytest.fixture
def faulty(bus):
    bus.faults, bus._fault_rng = FAULTS, np.random.default_rng(FAULTS.seed)
    yield bus
    bus.faults = Faults()


def test_collect_interrupted_and_resumed_loses_nothing_on_a_faulty_bus(faulty, tmp_path,
                                                                       monkeypatch, capsys):
    out = tmp_path / "koch.npz"
    err = collect_interrupted_and_resumed(faulty.path, KOCH, out, monkeypatch, capsys)
    retried = int(err.split("bus: ")[1].split()[0])
    assert retried > 0, "the injected faults must have been met and retried"
    samples, meta = load_native(out, only_at_rest=False)
    assert meta["servo"]["p_gain"] == [640, 640, 1500, 400, 400]
    # No current sensor on the XL430s (joints 1-2): no current-based torque there.
    assert np.isnan(samples.current_tau[:, :2]).all()
    assert np.isfinite(samples.current_tau[:, 2:]).all() and not samples.has_current
