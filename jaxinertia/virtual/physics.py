"""The physics side of the virtual robot: the simulated OpenMANIPULATOR-X behind the
joint servos of a :class:`jaxinertia.virtual.bus.ServoBus`.

:class:`VirtualServoBus` adds a **physics** thread to the bus: it advances
:func:`jaxinertia.sim.simulator.step` (1 ms servo periods, ``chunk`` steps per jitted
``lax.scan``) paced at ``speed`` x real time, with the goal fed through the servo's
velocity-based trapezoidal profile (Profile Velocity/Acceleration registers), and
publishes Present Position/Velocity/Current/PWM, Moving and Moving Status. The two
threads share the control tables under the bus's lock.

Physics as in :func:`jaxinertia.sim.sampling.simulate_samples`: the arm feels
``-robot.gravity`` (the recorded convention is the opposite of the physical gravity),
the object is fused into the end-effector body, the friction bound of each joint is
scaled by a fresh log-normal draw (``friction.jitter``) whenever its goal changes (the
simulator draws one per sample), and Present Current carries ``servo.current_noise``.

Registers map onto the simulator's parameters: Position P/I/D Gain and PWM Limit onto
``ServoParams`` (the gains through the calibrated ratio ``sim p_gain / 800`` per joint,
which carries the calibrated PWM-to-torque scale); Profile Velocity/Acceleration onto
the goal profile (0 = no profile). Approximations, stated: while any joint's torque is
off the arm is held still (the simulator has no end stops for a limp arm to fall
against); temperature and input voltage are constant (``ambient_temperature``, the
servo supply voltage); Return Delay Time is not modelled.
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxinertia.hardware import control_table as ct
from jaxinertia.objects import HeldObject
from jaxinertia.open_manipulator_x import GRIPPER_ID, JOINT_IDS
from jaxinertia.sim.servo import goal_ticks
from jaxinertia.sim.simulator import SimParams, SimState, attach_payload, step, trapezoid
from jaxinertia.virtual.bus import Faults, ServoBus
from jaxinertia.xm430 import PWM_FULL_SCALE

__all__ = ["VirtualServoBus"]

#: Profile register 0 means "no profile": a step goal. Stand-ins that the trapezoid takes.
_UNLIMITED_VELOCITY = 1e6  # [rad/s]
_UNLIMITED_ACCELERATION = 1e9  # [rad/s^2]


@jax.jit
def _advance(params: SimParams, state: SimState, start, end, t_rel, v_max, a_max):
    """``len(t_rel)`` servo periods; returns the new state and the last profile goal [rad]."""

    def body(s, t):
        q_goal, _ = trapezoid(start, end, t, v_max, a_max)
        return step(params, s, goal_ticks(q_goal)), q_goal

    state, goals = jax.lax.scan(body, state, t_rel)
    _, t_total = trapezoid(start, end, 0.0, v_max, a_max)
    return state, goals[-1], t_total


class VirtualServoBus(ServoBus):
    """Servos ``ids`` (one per joint of ``params.robot``, then optional extra servos such as
    a gripper, which answer but do not move) on a pty, driven by the simulator."""

    def __init__(
        self,
        params: SimParams,
        obj: HeldObject | None,
        *,
        ids: tuple[int, ...] = JOINT_IDS,
        extra_ids: tuple[int, ...] = (GRIPPER_ID,),
        q0: np.ndarray | None = None,
        speed: float = 1.0,
        chunk: int = 20,
        faults: Faults = Faults(),  # noqa: B008  (frozen dataclass)
        seed: int = 0,
        ambient_temperature: int = 30,
    ) -> None:
        n = len(ids)
        if n != params.robot.n_joints:
            raise ValueError(f"{n} servo ids for {params.robot.n_joints} joints")
        super().__init__(ids, extra_ids, faults=faults, temperature=ambient_temperature,
                         input_voltage=float(params.servo.supply_voltage[0]))
        physical = params.robot.with_gravity(-params.robot.gravity)
        if obj is not None:
            R = obj.R_ee_tag
            physical = attach_payload(physical, obj.mass, obj.com_ee(),
                                      R @ obj.inertia @ R.T)
        self._base_params = params.replace(robot=physical)
        # Register -> simulator gain: the calibrated effective gains belong to the factory
        # P = 800 (the calibration absorbs the PWM-to-torque scale of the real servos).
        self._gain_scale = np.asarray(params.servo.p_gain) / ct.ITEMS["position_p_gain"].default
        self._friction = params.friction
        self.speed = float(speed)
        self.chunk = int(chunk)
        self.dt = float(params.dt)
        self._rng = np.random.default_rng(seed)
        q0 = np.zeros(n) if q0 is None else np.asarray(q0, np.float64)
        self._state = SimState.at_rest(jnp.asarray(q0))
        self._resting: SimState | None = None  # cached state while the torque is off
        self._sim_time = 0.0
        self._traj_start = q0.copy()
        self._traj_end = q0.copy()
        self._traj_t0 = np.zeros(n)
        self._traj_pos = q0.copy()  # profile goal now [rad]
        self._traj_total = np.zeros(n)
        self._friction_scale = np.ones(n)
        self._jitter_pending = np.zeros(n, bool)
        self._publish(q0, np.zeros(n), np.zeros(n), np.zeros(n))

    # ---- lifecycle -------------------------------------------------------------------

    def compile(self) -> None:
        """Compiles the physics step before the bus opens (so the first reply is prompt)."""
        q = jnp.asarray(self._traj_pos)
        t = jnp.zeros((self.chunk, len(q)))
        with self._lock:
            servo = self._servo_params()
        params = self._base_params.replace(servo=servo)
        jax.block_until_ready(_advance(params, self._state, q, q, t, q + 1.0, q + 1.0))

    def _loops(self):
        return [*super()._loops(), (self._physics_loop, "dxl-physics")]

    def __enter__(self) -> VirtualServoBus:
        self.compile()
        self.start()
        return self

    # ---- the bus's news about the joints (under the lock) ------------------------------

    def _goal_changed(self, j: int, q_goal: float) -> None:
        # The profile starts from where the profile goal is now.
        self._traj_start[j] = self._traj_pos[j]
        self._traj_end[j] = q_goal
        self._traj_t0[j] = self._sim_time
        self._jitter_pending[j] = True

    def _held(self, j: int, q: float) -> None:
        self._traj_start[j] = self._traj_end[j] = self._traj_pos[j] = q
        self._traj_t0[j] = self._sim_time

    # ---- physics ---------------------------------------------------------------------

    def _servo_params(self):
        """ServoParams from the registers of the joint servos (under the lock)."""
        mem = [self.servos[i] for i in self.joint_ids]
        reg = lambda name: np.array([m.get(name) for m in mem], np.float64)  # noqa: E731
        s = self._base_params.servo
        return s.replace(p_gain=jnp.asarray(reg("position_p_gain") * self._gain_scale),
                         i_gain=jnp.asarray(reg("position_i_gain") * self._gain_scale),
                         d_gain=jnp.asarray(reg("position_d_gain") * self._gain_scale),
                         pwm_limit=jnp.asarray(reg("pwm_limit")))

    def _profile_limits(self):
        mem = [self.servos[i] for i in self.joint_ids]
        v = np.array([m.get("profile_velocity") for m in mem]) * ct.VELOCITY_LSB
        a = np.array([m.get("profile_acceleration") for m in mem]) * ct.ACCELERATION_LSB
        return (np.where(v > 0, v, _UNLIMITED_VELOCITY),
                np.where(a > 0, a, _UNLIMITED_ACCELERATION))

    def _advance(self) -> None:
        """Runs ``chunk`` servo periods from the present sim time (the lock is held while
        reading the registers and publishing, not while computing)."""
        with self._lock:
            torque = all(self.servos[i].get("torque_enable") == 1 for i in self.joint_ids)
            servo = self._servo_params()
            v, a = self._profile_limits()
            pending = self._jitter_pending.copy()
            self._jitter_pending[:] = False
            start, end = self._traj_start.copy(), self._traj_end.copy()
            t0 = self._traj_t0.copy()
            t_now = self._sim_time
        n_new = int(pending.sum())
        if n_new:  # friction varies from move to move (the simulator: sample to sample)
            draw = np.exp(np.asarray(self._friction.jitter)[pending]
                          * self._rng.standard_normal(n_new))
            self._friction_scale[pending] = draw
        fr = self._friction
        scale = jnp.asarray(self._friction_scale)
        params = self._base_params.replace(
            servo=servo, friction=fr.replace(coulomb=fr.coulomb * scale, static=fr.static * scale))
        times = t_now + self.dt * np.arange(self.chunk)
        t_rel = jnp.asarray(times[:, None] - t0[None, :])
        if torque:
            state, q_goal, t_total = _advance(params, self._state, jnp.asarray(start),
                                              jnp.asarray(end), t_rel, jnp.asarray(v),
                                              jnp.asarray(a))
            state = jax.block_until_ready(state)
            self._resting = None
        else:  # held still; the servo memory (integral, previous error) is cleared
            if self._resting is None:
                self._resting = SimState.at_rest(self._state.q)
            state, q_goal, t_total = self._resting, end, np.zeros_like(end)
        q = np.asarray(state.q)
        qd = np.asarray(state.qd)
        current = np.asarray(state.servo.current)
        noise = np.asarray(self._base_params.servo.current_noise)
        current = current + noise * self._rng.standard_normal(current.shape)
        # Present PWM from the motor equation V = R I + k_e qd (before the reading noise).
        s = self._base_params.servo
        volts = np.asarray(s.resistance) * np.asarray(state.servo.current) + np.asarray(
            s.back_emf) * qd
        pwm = volts / np.asarray(s.supply_voltage) * PWM_FULL_SCALE if torque else np.zeros_like(q)
        with self._lock:
            self._state = state
            self._sim_time = t_now + self.chunk * self.dt
            self._traj_pos = np.array(q_goal)  # a writable copy (goal writes edit it)
            self._traj_total = np.array(t_total)
            profile_on = (self._sim_time - self._traj_t0) < self._traj_total
            self._publish(q, qd, current if torque else np.zeros_like(q), pwm, profile_on)

    def _publish(self, q, qd, current, pwm, profile_on=None) -> None:
        profile_on = np.zeros(len(q), bool) if profile_on is None else profile_on
        ticks = ct.rad_to_ticks(q)  # Present Position: the encoder's integer ticks
        traj_ticks = ct.rad_to_ticks(self._traj_pos)
        for j, dxl_id in enumerate(self.joint_ids):
            m = self.servos[dxl_id]
            vel = int(round(qd[j] / ct.VELOCITY_LSB))
            threshold = m.get("moving_threshold")
            moving = abs(vel) > threshold or bool(profile_on[j])
            in_position = abs(m.get("goal_position") - int(ticks[j])) <= threshold
            m.set("present_position", int(ticks[j]))
            m.set("present_velocity", vel)
            m.set("present_current", int(ct.current_to_register(current[j])))
            m.set("present_pwm", int(round(pwm[j])))
            m.set("position_trajectory", int(traj_ticks[j]))
            m.set("moving", int(moving))
            m.set("moving_status", int(in_position) | (int(bool(profile_on[j])) << 1))
            m.set("realtime_tick", round(self._sim_time * 1000) % ct.REALTIME_TICK_WRAP)

    def _physics_loop(self) -> None:
        wall0, sim0 = time.monotonic(), self._sim_time
        while not self._stop.is_set():
            ahead = (self._sim_time - sim0) / self.speed - (time.monotonic() - wall0)
            if ahead > 0:
                time.sleep(ahead)
            self._advance()
