"""The SO-101 end to end as a user runs it: ``jaxinertia plan-poses --arm so101``,
``jaxinertia virtual-robot --arm so101 --object cube`` (a subprocess: six STS3215 servos
whose joints are the simulated SO-101 holding the cube, faults injected), ``jaxinertia
collect --arm so101`` through the Feetech driver (interrupted, then resumed), and
``jaxinertia estimate`` on the collected file.

What is asserted, each able to fail:

* the vendor SDK (scservo_sdk) pings all six servos as STS3215s (model 777);
* the collection, interrupted after two samples and resumed, holds every planned goal
  and direction once, in plan order, at rest; the injected faults were met and retried,
  with no false alarm;
* **physics through the STS registers**: each joint's Present Current is the position
  loop's output for the tick error it rests at (the servo law of the simulated STS3215 at
  rest: ``k_tick * (q_d - q)``, within the reading's noise), so the sign-magnitude
  registers arrive with the right sign; and the collected rest is a rest of the simulated
  arm holding the cube: the servo's torque balances the statics' load ``tau = tau_g + A x``
  (gravity of the links and of the cube at the measured q) within the simulator's
  sticking friction, ``|k e - tau| <= f_s + mu |k e|``;
* the estimate runs on the collected file with a model folder of the SO-101 (untrained
  networks, baselines fitted to this file: no SO-101 models exist cheaply; the numbers it
  gives are not checked against the truth, the plumbing is), answers the cube with finite
  mass and COM, and a model folder of another arm is refused in one line.

Limits are generous (a busy host): waits are for conditions, never sleeps of a set length.

Its cost is kept down (the suite's time is mostly compiling): the commands run in this
process (``main()``), and a plan of 4 poses shares its programs with the suite's other
5-joint tests, in the session's compilation cache (``tests/conftest.py`` runs them first):
plan-poses with ``test_arms``, and the physics of the virtual robot's subprocess (the
Koch's and the SO-101's are one program) and the collected file's statics with
``test_hardware_koch``. The untrained networks are drawn in numpy, not initialised by
Flax (whose one-by-one operations compile ~2 s).

The protocol and driver on the bus model (no simulator) are ``test_feetech_bus`` and
``test_feetech_driver``.
"""

from __future__ import annotations

import json
import sys

import jax
import numpy as np
import pytest
from scservo_sdk import COMM_SUCCESS
from support.hardware import RETRIES, interrupting_tag_pose, journal_indices

from jaxinertia.app.cli import main
from jaxinertia.arms import SO101
from jaxinertia.baselines import fit_baselines
from jaxinertia.checkpoints import save_models
from jaxinertia.design import load_plan
from jaxinertia.estimation import ModelPair
from jaxinertia.features import FeatureConfig
from jaxinertia.hardware import collect
from jaxinertia.hardware.feetech import FeetechArm, feetech_config
from jaxinertia.networks import AttentionModel, TorqueModel, parameter_shapes
from jaxinertia.samples import load_native
from jaxinertia.servos import STS3215_7V4
from jaxinertia.session import SessionReference
from jaxinertia.sim.params import arm_sim_params
from jaxinertia.virtual.testing import VirtualRobotProcess

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"),
                                reason="the virtual servo bus needs a Linux pseudo-terminal")

#: The plan's poses: as many as test_arms plans for the SO-101 (one set of plan-poses
#: programs), and as many samples as test_hardware_koch collects on the Koch, another
#: 5-joint arm (one statics program for the collected file).
N_POSES = 4
AFTER = 2  # samples before the interrupt
#: Faults on the bus (each costs the collection ~70 ms of a quiet bus and a retry): about
#: 15 are met, all retried.
FAULTS = ["--drop-rate", "0.003", "--corrupt-rate", "0.003", "--delay-rate", "0.003",
          "--delay-ms", "50", "--fault-seed", "4"]
TICK = 2 * np.pi / 4096


def untrained_folder(samples):
    """What a model folder for 5-joint ``samples`` holds: one untrained network pair
    (weights drawn as Flax initialises them, kernels N(0, 1/fan_in) and zero biases, in
    numpy: nothing compiled for a network that is never trained), the baselines fitted to
    ``samples`` (with their truth) and a feature configuration around them."""
    n, rng = samples.n_joints, np.random.default_rng(0)

    def weights(model):
        return jax.tree.map(lambda a: (rng.normal(size=a.shape) / np.sqrt(a.shape[-2])
                                       if a.ndim > 2 else np.zeros(a.shape)).astype(a.dtype),
                            parameter_shapes(model, n, n_models=1))

    tm, am = TorqueModel(n_joints=n), AttentionModel(n_joints=n)
    pair = ModelPair(torque_vars=weights(tm), attention_vars=weights(am),
                     tau_scale=np.ones(n, np.float32), torque_model=tm, attention_model=am)
    fc = FeatureConfig.create(samples.q.min(0) - 0.1, samples.q.max(0) + 0.1,
                              np.full(n, 0.05), np.ones(n))
    b = fit_baselines(samples.q_d, samples.q, samples.direction, samples.current_tau,
                      samples.tau)
    return pair, b, fc


def test_so101_plan_virtual_robot_collect_and_estimate(tmp_path, monkeypatch, capsys):
    plan, out = tmp_path / "plan.json", tmp_path / "cube.npz"
    assert main(["plan-poses", "--arm", "so101", "--n", str(N_POSES), "--out", str(plan)]) == 0
    q_plan, d_plan = load_plan(plan, arm="so101")
    with VirtualRobotProcess(["--arm", "so101", "--object", "cube", "--speed", "10", *FAULTS],
                             stderr=tmp_path / "virtual.log") as robot:
        probe = FeetechArm(feetech_config(robot.path, SO101))  # the vendor SDK: six STS3215s
        probe.open()
        for i in (*SO101.bus_ids, SO101.gripper_id):
            for _ in range(RETRIES):
                model, result, _ = probe.packet.ping(probe.port, i)
                if result == COMM_SUCCESS:
                    break
            assert model == 777, f"ID {i}"
        probe.close()

        base = collect.KinematicTagPose

        Interrupting = interrupting_tag_pose(base, AFTER)  # Ctrl-C after AFTER samples
        argv = ["collect", "--arm", "so101", "--port", robot.path, "--plan", str(plan),
                "--object", "cube", "--out", str(out), "--no-progress",
                "--retries", str(RETRIES), "--timeout", "120"]
        capsys.readouterr()
        monkeypatch.setattr(collect, "KinematicTagPose", Interrupting)
        assert main(argv) == 130, capsys.readouterr().err
        assert journal_indices(out) == list(range(AFTER)) and not out.exists()
        monkeypatch.setattr(collect, "KinematicTagPose", base)
        assert main([*argv, "--resume"]) == 0, capsys.readouterr().err
        err = capsys.readouterr().err
    assert "hardware error" not in err and " 0 unconfirmed hardware-error readings" in err, err
    assert int(err.split("bus: ")[1].split()[0]) > 0, "the injected faults met and retried"
    print(err)
    assert journal_indices(out) == list(range(N_POSES)), "each sample exactly once"
    s, meta = load_native(out, only_at_rest=False)
    assert meta["arm"] == meta["robot"] == "so101" and meta["source"] == "feetech"
    np.testing.assert_array_equal(s.q_d, q_plan)
    np.testing.assert_array_equal(s.direction, d_plan)
    assert s.at_rest.all() and s.names == ("cube",)

    # Physics through the STS registers. At rest the simulated STS3215's torque is
    # k_tick * e for its tick error e (PWM = P e, V = PWM/885 * V_s, I = V/R, tau = k_t I).
    sv, fr = (arm_sim_params(SO101).servo, arm_sim_params(SO101).friction)
    k_tick = np.asarray(sv.p_gain / 128 / 885 * sv.supply_voltage / sv.resistance
                        * sv.torque_constant)  # [N m per tick]
    ticks = s.q / TICK  # Present Position: whole ticks
    np.testing.assert_allclose(ticks, np.round(ticks), atol=1e-9)
    e = np.round(s.q_d / TICK) - np.round(ticks)  # the servo's error: Goal - Present [ticks]
    # Present Current, 6.5 mA sign-magnitude, is the loop's output within its noise
    # (2 LSB std: 5 sigma, and half an LSB of rounding).
    noise = (5 * np.asarray(sv.current_noise) + 0.5 * 6.5e-3) * np.asarray(sv.torque_constant)
    print("e [ticks]\n", e, "\ncurrent torque / k_tick\n", np.round(s.current_tau / k_tick, 2),
          "\ntau / k_tick\n", np.round(s.tau / k_tick, 2))
    off = np.abs(s.current_tau - k_tick * e)
    assert (off < noise).all(), f"current torque {off.max():.4f} N m off the loop's output"
    loaded = np.abs(e) >= 3
    assert loaded[:, 1].all() and loaded[:, 2].all(), "shoulder and elbow carry the arm"
    assert (np.sign(s.current_tau[loaded]) == np.sign(e[loaded])).all()
    assert (np.sign(s.tau[loaded]) == np.sign(e[loaded])).all(), "pushing against the load"
    # The rest balances the statics' load (links and cube at the measured q) within the
    # sticking friction (static f_s + load-dependent mu |servo torque|, at rest).
    servo = k_tick * e
    bound = np.asarray(fr.static) + np.asarray(fr.load_coefficient) * np.abs(servo)
    slack = np.abs(servo - s.tau) - bound
    assert (slack <= 2e-3).all(), f"off the sticking band by {slack.max():.4f} N m"

    # estimate on the collected file, with a model folder of the SO-101 whose training
    # files recorded a 7.8 V supply at 25 deg C (no adaptation) ...
    folder = untrained_folder(s)
    ref = SessionReference(np.full(5, 10.0), 0.0, np.full(5, 7.8), np.full(5, 25.0))
    models = save_models(tmp_path / "models", *folder, robot="so101", arm="so101",
                         extra={"session": ref.to_dict()})
    capsys.readouterr()
    result = tmp_path / "estimate.json"
    assert main(["estimate", "--models", str(models), "--samples", str(out),
                 "--set-size", str(N_POSES), "--json", str(result)]) == 0, capsys.readouterr()
    printed = capsys.readouterr().out
    print(printed)
    answer = json.loads(result.read_text())["objects"]["cube"]
    assert answer["n_samples"] == N_POSES
    # ... which reports the servos' state as they recorded it (the virtual STS3215s: their
    # model's supply, 0.1 V a register step, at the virtual robot's 30 deg C), against the
    # folder's.
    state = answer["servo_state"]
    np.testing.assert_allclose(state["supply_voltage"], STS3215_7V4.supply_voltage, atol=0.05)
    assert state["temperature"] == [30.0] * 5
    np.testing.assert_allclose(state["supply_ratio"], np.asarray(state["supply_voltage"]) / 7.8)
    assert state["temperature_change"] == [5.0] * 5
    assert "cube: servo state recorded: 7.40 V, 30 deg C; the models' session: 7.80 V, " \
           "25 deg C (supply x 0.949; temperature +5 K" in printed
    ok = {m: r for m, r in answer["methods"].items() if r["ok"]}
    assert ok, answer["methods"]
    for r in ok.values():
        assert 0 < r["mass_kg"] <= 5 and np.isfinite(r["com_tag_m"]).all() and len(
            r["com_tag_m"]) == 3
    # ... and not with another arm's.
    other = save_models(tmp_path / "koch", *folder, robot="koch_v1_1", arm="koch_v1_1")
    assert main(["estimate", "--models", str(other), "--samples", str(out)]) == 2
    assert "koch_v1_1" in capsys.readouterr().err
