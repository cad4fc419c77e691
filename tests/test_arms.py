"""The arm as data (jaxinertia.arm, jaxinertia.arms): the OpenMANIPULATOR-X record holds
today's constants exactly, the SO-101 and Koch v1.1 records load their published
descriptions, and a user's own arm comes from a JSON or TOML file."""

from __future__ import annotations

import importlib
import inspect
import json
import shutil

import jax
import numpy as np
import pytest

from jaxinertia.arm import Arm, MotionTiming, arm_from_dict, arm_to_dict
from jaxinertia.arms import ARMS, DEFAULT_ARM, KOCH_V1_1, SO101, get_arm
from jaxinertia.errors import ConfigError
from jaxinertia.hardware import collect
from jaxinertia.hardware.arm_config import arm_config
from jaxinertia.hardware.driver import ArmConfig
from jaxinertia.robot import data_path, open_manipulator_x
from jaxinertia.servos import STS3215_7V4, XL330_M288, XL430_W250, XM430_W350
from jaxinertia.sim import lanes, sampling
from jaxinertia.sim.simulator import SimParams

omx = importlib.import_module("jaxinertia.open_manipulator_x")


def _default(fn, name):
    return inspect.signature(fn).parameters[name].default


def test_open_manipulator_x_record_is_todays_constants():
    arm = get_arm()
    assert arm is ARMS["open_manipulator_x"] is omx.ARM and DEFAULT_ARM == omx.NAME
    assert arm.bus_ids == omx.JOINT_IDS == (11, 12, 13, 14) and arm.gripper_id == omx.GRIPPER_ID
    assert arm.workspace_deg == omx.WORKSPACE_DEG
    R, p = arm.tag_in_ee
    np.testing.assert_array_equal(R, omx.TAG_IN_EE[0])
    np.testing.assert_array_equal(p, omx.TAG_IN_EE[1])
    assert arm.mount_clearance_m == omx.MOUNT_CLEARANCE_M == 0.10
    assert arm.armature == omx.DEFAULT_ARMATURE and arm.sim_fit_file == omx.SIM_FIT_FILE
    assert arm.servo_models == (XM430_W350,) * 4 and arm.has_current_sensors
    # Motion timing and pre-position: the values spread over the simulator, the driver and
    # the collection until now.
    t = arm.timing
    fields = {f.name: f.default for f in SimParams.__dataclass_fields__.values()}
    assert (t.profile_velocity, t.profile_acceleration, t.settle_time, t.move_timeout) == (
        fields["profile_velocity"], fields["profile_acceleration"], fields["hold_time"],
        fields["timeout"]) == (0.5, 2.0, 0.2, 6.0)
    cfg, bare = arm_config(arm, "x"), ArmConfig(port="x")
    assert (cfg.profile_velocity, cfg.profile_acceleration, cfg.settle_time,
            cfg.move_timeout, cfg.joint_ids, cfg.gripper_id, cfg.baudrate) == (
        0.5, 2.0, 0.2, 6.0, arm.bus_ids, arm.gripper_id, arm.baudrate)
    assert (cfg.p_gain, cfg.i_gain, cfg.d_gain) == XM430_W350.gains
    for f in ArmConfig.__dataclass_fields__:  # the bare defaults are the same arm's
        if f != "joint_limits":
            assert getattr(bare, f) == getattr(cfg, f), f
    # The servos' limit registers: the paper's workspace widened by 8 deg, as before.
    np.testing.assert_array_equal(cfg.joint_limits, (np.asarray(omx.WORKSPACE_DEG)
                                                     + [-8.0, 8.0]) * (np.pi / 180.0))
    assert arm.pre_position == lanes.DELTA == collect.DELTA
    assert _default(sampling.simulate_samples, "delta") is None  # -> SimParams.pre_position
    assert arm.pre_position == fields["pre_position"]
    assert arm.planning_step_deg == 10.0
    # The robot: the embedded description, bit for bit, mounted as in the paper.
    robot, ref = arm.robot(), open_manipulator_x()
    assert robot.name == ref.name == "open_manipulator_x"
    assert jax.tree.structure(robot) == jax.tree.structure(ref)
    for a, b in zip(jax.tree.leaves(robot), jax.tree.leaves(ref), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.parametrize("arm", [SO101, KOCH_V1_1], ids=lambda a: a.name)
def test_published_arms_load(arm):
    robot = arm.robot()
    assert robot.name == arm.name and robot.joint_names == arm.arm_joints
    assert robot.n_joints == 5 and arm.gripper_joint not in robot.joint_names
    np.testing.assert_array_equal(np.asarray(robot.gravity), [0.0, 0.0, -9.81])
    assert len(arm.servo_models) == 5 and arm.gripper_id == 6
    assert "workspace_deg" in arm.estimates  # what the files do not state says so
    assert arm.description_path().exists()
    assert str(arm.description_path()).startswith(str(data_path("arms")))


def test_servos_per_arm():
    assert SO101.servo_models == (STS3215_7V4,) * 5 and SO101.has_current_sensors
    assert KOCH_V1_1.servo_models == (XL430_W250,) * 2 + (XL330_M288,) * 3
    assert not KOCH_V1_1.has_current_sensors  # XL430-W250: Present Load only


@pytest.mark.parametrize("suffix", [".json", ".toml"])
def test_a_users_arm_from_a_file(tmp_path, suffix):
    shutil.copy(data_path("arms/koch_v1_1/follower.urdf"), tmp_path / "my_arm.urdf")
    d = arm_to_dict(KOCH_V1_1)
    d.update(name="my_koch", description="my_arm.urdf", bus_ids=[11, 12, 13, 14, 15],
             gripper_id=16, pre_position_deg=2.0, timing={"settle_time": 0.3})
    path = tmp_path / f"arm{suffix}"
    if suffix == ".json":
        path.write_text(json.dumps(d))
    else:  # TOML has no null: leave the optional fields out
        lines = []
        for k, v in d.items():
            if v is None or k in ("gains", "timing"):
                continue
            lines.append(f"{k} = {json.dumps(v)}")
        lines += ['gains = [[640.0, 0.0, 0.0], [640.0, 0.0, 0.0], [1500.0, 0.0, 600.0], '
                  '[400.0, 0.0, 0.0], [400.0, 0.0, 0.0]]', "[timing]", "settle_time = 0.3"]
        path.write_text("\n".join(lines) + "\n")
    arm = get_arm(path)
    assert isinstance(arm, Arm) and arm.name == "my_koch"
    assert arm.timing == MotionTiming(settle_time=0.3)
    assert arm.pre_position == 2.0 * np.pi / 180.0 and arm.bus_ids == (11, 12, 13, 14, 15)
    assert arm.description_path() == (tmp_path / "my_arm.urdf").resolve()
    robot = arm.robot()
    assert robot.name == "my_koch" and robot.joint_names == KOCH_V1_1.arm_joints


def test_an_arm_file_of_the_older_key_calibration_file_still_reads():
    """``sim_fit_file`` was ``calibration_file`` in arm files written before the rename."""
    d = arm_to_dict(omx.ARM)
    d["calibration_file"] = d.pop("sim_fit_file")
    assert arm_from_dict(d).sim_fit_file == omx.SIM_FIT_FILE == "open_manipulator_x_sim.json"


def test_bad_arms_say_what_is_wrong(tmp_path):
    with pytest.raises(ConfigError, match="not a known arm"):
        get_arm("so100")
    d = arm_to_dict(SO101)
    for change, match in [({"bus_ids": [1, 2, 3]}, "needs 5 entries"),
                          ({"servos": ["mg996r"] * 5}, "unknown servo model"),
                          ({"bus_ids": [1, 2, 3, 4, 6]}, "IDs repeat"),
                          ({"colour": "yellow"}, "unknown field"),
                          ({"workspace_deg": [[10, -10]] * 5}, "is empty")]:
        path = tmp_path / "arm.json"
        path.write_text(json.dumps({**d, **change}))
        with pytest.raises(ConfigError, match=match):
            get_arm(path)
    path.write_text("{not json")
    with pytest.raises(ConfigError, match="not a readable arm file"):
        get_arm(path)
    path.write_text(json.dumps({**d, "arm_joints": ["a", "b", "c", "d", "e"]}))
    with pytest.raises(Exception, match="no joints named"):
        get_arm(path).robot()


def test_arm_sim_params():
    from jaxinertia.sim.params import arm_sim_params, default_sim_params
    from jaxinertia.sim.run import _scenario_jobs

    # The OpenMANIPULATOR-X: exactly the calibrated simulator it always had.
    ours, ref = arm_sim_params(), default_sim_params()
    assert jax.tree.structure(ours) == jax.tree.structure(ref)
    for a, b in zip(jax.tree.leaves(ours), jax.tree.leaves(ref), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert ours.pre_position == ref.pre_position == lanes.DELTA
    # An arm without a calibration: its links, datasheet servos, its timing.
    koch = arm_sim_params(KOCH_V1_1)
    assert koch.robot.name == "koch_v1_1" and koch.robot.n_joints == 5
    np.testing.assert_array_equal(np.asarray(koch.servo.p_gain), [640.0, 640.0, 1500.0, 400.0,
                                                                  400.0])
    np.testing.assert_array_equal(np.asarray(koch.servo.supply_voltage), [12.0] * 2 + [5.0] * 3)
    np.testing.assert_array_equal(np.asarray(koch.robot.armature), [0.005] * 5)
    assert koch.hold_time == KOCH_V1_1.timing.settle_time
    with pytest.raises(ConfigError, match="not the arm 'so101'"):
        arm_sim_params(SO101, data_path(omx.SIM_FIT_FILE))
    # Scenario goals inside the arm's workspace, objects on the arm's tag mount.
    for scenario in ("random", "test"):
        for name, obj, (q_d, d) in _scenario_jobs(scenario, 32, None, 0, arm=SO101):
            lo, hi = np.radians(np.asarray(SO101.workspace_deg)).T
            assert q_d.shape == d.shape == (32, 5) and np.all((q_d >= lo) & (q_d <= hi)), name
            np.testing.assert_array_equal(np.asarray(obj.p_ee_tag), SO101.tag_position)


def test_files_of_one_arm_refuse_another(tmp_path):
    from jaxinertia.app.arm_options import samples_arm
    from jaxinertia.app.options import flag_wording
    from jaxinertia.checkpoints import load_models
    from jaxinertia.design import PLAN_FORMAT, load_plan
    from jaxinertia.errors import RobotMismatchError, UsageError

    # A model folder records its arm; the check comes before the checkpoint is read.
    folder = tmp_path / "models"
    folder.mkdir()
    (folder / "config.json").write_text(json.dumps({
        "format": "jaxinertia-models", "format_version": 1, "robot": "so101", "arm": "so101"}))
    with pytest.raises(RobotMismatchError, match="arm 'so101'.*the arm 'koch_v1_1'") as e:
        load_models(folder, robot="koch_v1_1", arm="koch_v1_1")
    assert "\n" not in str(e.value)
    with pytest.raises(RobotMismatchError, match="train with `arm` open_manipulator_x") as e:
        load_models(folder, arm="open_manipulator_x")
    assert "train with --arm open_manipulator_x" in flag_wording(str(e.value))  # the CLI's
    # Sample files: the recorded arm against --arm; a file that records none takes --arm's.
    with pytest.raises(RobotMismatchError, match="samples of the arm 'so101', not of --arm "
                       "'koch_v1_1'"):
        samples_arm("s.npz", {"robot": "so101", "arm": "so101"}, "koch_v1_1")
    assert samples_arm("s.npz", {"format": "lbipe"}, "so101") == "so101"
    assert samples_arm("s.npz", {"robot": "open_manipulator_x"}) == "open_manipulator_x"
    # Plans.
    plan = tmp_path / "plan.json"
    plan.write_text(json.dumps({"format": PLAN_FORMAT, "format_version": 1, "robot": "so101",
                                "arm": "so101", "q_d": [[0.0] * 5], "direction": [[1] * 5]}))
    assert load_plan(plan, arm="so101")[0].shape == (1, 5)
    with pytest.raises(UsageError, match="a plan for the arm 'so101', not for "
                       "'open_manipulator_x'"):
        load_plan(plan, arm="open_manipulator_x")


def test_arm_option_on_the_commands(tmp_path, capsys):
    from jaxinertia.app.cli import main

    out = tmp_path / "plan.json"
    # 4 poses, as test_feetech_collect's end to end plans them: one set of programs.
    assert main(["plan-poses", "--arm", "so101", "--n", "4", "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert doc["arm"] == doc["robot"] == "so101" and doc["grid_step_deg"] == 20.0
    q = np.degrees(np.asarray(doc["q_d"]))
    lo, hi = np.asarray(SO101.workspace_deg).T
    assert q.shape == (4, 5) and np.all((q >= lo) & (q <= hi))
    capsys.readouterr()
    # Refused in one line before anything is opened or read.
    for argv, said in [
            # The SO-101 collects through its own (Feetech) driver: its IDs are checked.
            (["collect", "--arm", "so101", "--port", "/dev/null", "--plan", "random",
              "--object", "cube", "--ids", "1,2,3,4", "--out", str(tmp_path / "c.npz")],
             "--ids needs 5"),
            (["virtual-robot", "--arm", "koch_v1_1", "--q0", "0", "0"], "--q0 needs 5"),
            (["calibrate", "--arm", "so101"], "lbipe files, which are the open_manipulator_x"),
            (["evaluate", "--arm", "koch_v1_1", "--models", str(tmp_path)], "lbipe files"),
            (["collect", "--arm", "open_manipulator_x", "--port", "/dev/null", "--plan",
              str(out), "--object", "cube", "--out", str(tmp_path / "c.npz")],
             "a plan for the arm 'so101'")]:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip()
        assert said in err and "\n" not in err, (argv, err)
