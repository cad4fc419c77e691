"""Servo models as data (jaxinertia.servos): the XM430 record reproduces the simulator's
and the servo boundary's numbers exactly, the others carry their datasheet values, a chain
may mix models, and a servo without a current sensor says so."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from jaxinertia import xm430
from jaxinertia.servos import (
    KG_CM,
    SERVO_MODELS,
    STS3215_7V4,
    STS3215_12V,
    XL330_M288,
    XL430_W250,
    XM430_W350,
    SensorUnavailableError,
    servo_model,
)
from jaxinertia.sim.servo import ServoParams


def test_xm430_record_is_todays_numbers_exactly():
    # The literals the project used before the servo became data (xm430.py, sim/servo.py).
    assert xm430.TICKS_PER_REV == 4096 and xm430.PWM_FULL_SCALE == 885.0
    assert xm430.RAD_PER_TICK == 2.0 * np.pi / 4096
    assert xm430.CURRENT_LSB_A == 2.69e-3
    assert xm430.NOMINAL_TORQUE_CONSTANT == 4.1 / 2.3
    v, no_load = 12.0, 46.0 * 2.0 * np.pi / 60.0
    expected = dict(p_gain=800.0, i_gain=0.0, d_gain=0.0, pwm_limit=885.0, supply_voltage=v,
                    torque_constant=4.1 / 2.3, resistance=v / 2.3, back_emf=v / no_load,
                    current_limit=3.2, current_noise=2 * 2.69e-3, current_dead_band=0.0)
    for params in (ServoParams.xm430_w350(4), ServoParams.from_model(XM430_W350, 4)):
        assert set(params.__dict__) == set(expected)
        for k, val in expected.items():
            np.testing.assert_array_equal(np.asarray(params.__dict__[k]), np.full(4, val),
                                          err_msg=k)
    over = ServoParams.xm430_w350(2, p_gain=[700.0, 710.0], i_gain=3.0)
    np.testing.assert_array_equal(np.asarray(over.p_gain), [700.0, 710.0])
    np.testing.assert_array_equal(np.asarray(over.i_gain), [3.0, 3.0])


def test_datasheet_values():
    assert (XL430_W250.stall_torque, XL430_W250.stall_current, XL430_W250.no_load_rpm,
            XL430_W250.supply_voltage) == (1.5, 1.4, 61.0, 12.0)
    assert (XL330_M288.stall_torque, XL330_M288.stall_current, XL330_M288.no_load_rpm,
            XL330_M288.supply_voltage, XL330_M288.sensed_lsb) == (0.52, 1.47, 103.0, 5.0, 1e-3)
    assert STS3215_7V4.stall_torque == pytest.approx(1.912, abs=1e-3)  # 19.5 kg cm
    assert STS3215_12V.stall_torque == 30.0 * KG_CM and STS3215_12V.supply_voltage == 12.0
    for m in SERVO_MODELS.values():
        assert m.ticks_per_rev == 4096 and m.gains[1] == 0.0  # the method needs I = 0
        assert m.torque_constant == m.stall_torque / m.stall_current
        assert set(m.estimates) <= {f.name for f in dataclasses.fields(m)}
    assert {STS3215_7V4.protocol, XM430_W350.protocol} == {"feetech_sts", "dynamixel2"}
    assert servo_model("XL330-M288") is XL330_M288 and servo_model(XM430_W350) is XM430_W350
    with pytest.raises(KeyError, match="unknown servo model"):
        servo_model("mg996r")


def test_load_only_servo_has_no_sensor_baseline():
    assert not XL430_W250.has_current_sensor and XL330_M288.has_current_sensor
    with pytest.raises(SensorUnavailableError, match="XL430-W250-T.*Present Load only"):
        XL430_W250.require_current_sensor()
    with pytest.raises(SensorUnavailableError, match="Sensor baseline is unavailable"):
        XL430_W250.require_current_sensor()
    with pytest.raises(SensorUnavailableError):
        XL430_W250.current_lsb  # noqa: B018
    assert XL330_M288.current_lsb == 1e-3 and STS3215_12V.current_lsb == 6.5e-3


def test_a_chain_may_mix_models():
    koch = [XL430_W250] * 2 + [XL330_M288] * 3
    params = ServoParams.from_model(koch, 5)
    one = {m.name: ServoParams.from_model(m, 1) for m in (XL430_W250, XL330_M288)}
    for k, v in params.__dict__.items():
        np.testing.assert_array_equal(
            np.asarray(v), [float(one[m.name].__dict__[k][0]) for m in koch], err_msg=k)
    with pytest.raises(ValueError, match="3 servo models for 5 joints"):
        ServoParams.from_model(koch[:3], 5)
    # Another loop's gains give the same duty per tick of error in the XM430's scales.
    sts = ServoParams.from_model(STS3215_12V, 1)
    duty_per_tick = float(sts.p_gain[0]) / 128.0 / 885.0
    assert duty_per_tick == pytest.approx(16.0 / 1000.0, rel=1e-12)


def test_a_load_only_joint_has_no_current_torque_in_the_simulator_as_on_the_bus():
    import jax
    import jax.numpy as jnp

    from jaxinertia.arms import KOCH_V1_1
    from jaxinertia.hardware.arm_config import arm_config
    from jaxinertia.hardware.driver import DynamixelArm
    from jaxinertia.objects import resolve
    from jaxinertia.sim.params import arm_sim_params
    from jaxinertia.sim.sampling import record
    from jaxinertia.sim.simulator import SimState

    params = arm_sim_params(KOCH_V1_1)
    q = jnp.zeros(5)
    state = SimState.at_rest(q)
    current = jnp.array([0.1, -0.2, 0.3, -0.05, 0.01])  # [A]
    state = state.replace(servo=state.servo.replace(current=current))
    rec = record(params.replace(servo=params.servo.replace(current_noise=jnp.zeros(5))),
                 params.robot, resolve("none", tag_in_ee=KOCH_V1_1.tag_in_ee), q,
                 jnp.ones(5), state, jax.random.key(0), at_rest=True, settle_time=0.0)
    tau = np.asarray(rec.current_tau)
    # XL430-W250 joints (1-2): Present Load only, no current-based torque; XL330-M288
    # joints: k_t times the current in its 1 mA steps.
    assert np.isnan(tau[:2]).all() and np.isfinite(tau[2:]).all(), tau
    np.testing.assert_allclose(tau[2:], XL330_M288.torque_constant * np.asarray(current[2:]),
                               rtol=1e-12, err_msg="current_tau of the XL330 joints")
    # The driver reads the same joints as the simulator records them (NaN where no sensor).
    driver = DynamixelArm(arm_config(KOCH_V1_1, "/dev/null"))
    np.testing.assert_array_equal(np.isnan(driver.torque_constants), np.isnan(tau))
    np.testing.assert_array_equal(driver.torque_constants[2:], XL330_M288.torque_constant)
