"""The physics side of the virtual robot: the simulated OpenMANIPULATOR-X behind the
joint servos of a :class:`jaxinertia.virtual.bus.ServoBus`.

:class:`ArmPhysics` advances :func:`jaxinertia.sim.simulator.step` (1 ms servo periods,
``chunk`` steps per jitted ``lax.scan``), with each joint's goal fed through the servo's
velocity-based trapezoidal profile (Profile Velocity/Acceleration registers); both of its
programs (torque on, torque off) are compiled by :meth:`ArmPhysics.compile`.
:class:`PhysicsLoop` couples it to the servos' control tables: it applies the bus's news
(goal writes, holds, in order), copies the registers a chunk needs under the tables' lock,
computes the chunk without it and publishes Present Position/Velocity/Current/PWM, Moving,
Moving Status and Realtime Tick under it, paced at ``speed`` x real time. Address 126 is
published per servo model: Present Current in the model's unit, or, on a servo without a
current sensor (XL430-W250), Present Load in 0.1 % of the maximum torque (the motor
current as a share of the stall current: the simulated motor's torque is ``k_t I``, its
maximum ``k_t`` times the stall current).
:func:`physics_main` runs that loop in the process of its own that
:class:`jaxinertia.virtual.robot.VirtualServoBus` starts; when that bus's process is gone
(killed, even while it held the tables' lock, which it then never releases) the loop
ends: it waits for the lock in slices and checks its parent between them. One module: the
arm, the loop and the process entry share the tables' conventions and are read together.

Answers follow simulated time whatever the host's speed: Realtime Tick is the simulated
clock, and a joint whose Goal Position was written reports Moving (and the profile bit of
Moving Status) from that write until a published chunk has simulated the new goal
(``pending`` in :func:`publish`), so a slow host shows a moving arm as moving, never at its
old position at rest. The random draws are reproducible: each joint's friction draws come
from its own stream, one per Goal Position write, whatever the number of chunks computed
in between.

Physics as in :func:`jaxinertia.sim.sampling.simulate_samples`: the arm feels
``-robot.gravity`` (the recorded convention is the opposite of the physical gravity),
the object is fused into the end-effector body, the friction bound of each joint is
scaled by a fresh log-normal draw (``friction.jitter``) whenever its goal changes (the
simulator draws one per sample), and Present Current carries ``servo.current_noise``.

Registers map onto the simulator's parameters (:class:`DxlRegisterMap` for a DYNAMIXEL X
servo, as below; :class:`jaxinertia.virtual.sts_robot.StsRegisterMap` for the STS3215,
whose I and D registers weigh :func:`loop_ratios` against its P): Position P/I/D Gain and
PWM Limit onto
``ServoParams`` (the gains through the ratio ``sim p_gain / P register`` per joint, the P
register the simulator's gain belongs to: the OpenMANIPULATOR-X's factory 800, whose
ratio carries the calibrated PWM-to-torque scale; 1 for a servo simulated from its
datasheet); Profile Velocity/Acceleration onto
the goal profile (0 = no profile). Approximations, stated: while any joint's torque is
off the arm is held still (the simulator has no end stops for a limp arm to fall
against); temperature and input voltage are constant (``ambient_temperature``, the
servo supply voltage); Return Delay Time is not modelled.
"""

from __future__ import annotations

import contextlib
import gc
import os
import sys
import time
import traceback
from collections.abc import Iterator
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from jaxinertia import _xla_workarounds, compilation_cache
from jaxinertia.hardware import control_table as ct
from jaxinertia.sim.servo import ServoParams, current_reading_share, goal_ticks
from jaxinertia.sim.simulator import SimParams, SimState, step, trapezoid
from jaxinertia.virtual.bus import ServoMemory, table_views
from jaxinertia.xm430 import PWM_FULL_SCALE

__all__ = ["REGISTERS", "ArmPhysics", "DxlRegisterMap", "PhysicsLoop", "PhysicsSpec", "Present",
           "gain_scale", "loop_ratios", "physics_main", "publish", "servo_from_registers"]

#: Profile register 0 means "no profile": a step goal. Stand-ins that the trapezoid takes.
_UNLIMITED_VELOCITY = 1e6  # [rad/s]
_UNLIMITED_ACCELERATION = 1e9  # [rad/s^2]
#: The registers each chunk reads from a DYNAMIXEL X servo, in this order (the rows of the
#: register array: :meth:`DxlRegisterMap.registers`).
REGISTERS = ("position_p_gain", "position_i_gain", "position_d_gain", "pwm_limit",
              "profile_velocity", "profile_acceleration")


def servo_from_registers(base: ServoParams, gain_scale, registers) -> ServoParams:
    """ServoParams of the register rows (P, I, D gains through the calibrated ratios
    ``gain_scale``, (3, N) or (N,) shared by the three; PWM limit on the simulator's scale)."""
    scale = jnp.broadcast_to(gain_scale, (3, jnp.shape(registers)[1]))
    return base.replace(p_gain=registers[0] * scale[0], i_gain=registers[1] * scale[1],
                        d_gain=registers[2] * scale[2], pwm_limit=registers[3])


def gain_scale(servo: ServoParams, gain_registers=None, loop_ratios=None) -> np.ndarray:
    """(3, N) simulated P, I and D gain per unit of their registers: ``servo.p_gain /
    gain_registers`` (default: the XM430's factory P = 800, which the calibrated gains
    belong to), times ``loop_ratios`` ((2, N): the I and D register's weight in the
    simulator's loop against the P register's, :func:`loop_ratios`; default 1, as on the X
    series, whose loop the simulator's is)."""
    p = np.asarray(servo.p_gain, np.float64)
    registers = (ct.ITEMS["position_p_gain"].default if gain_registers is None
                 else np.asarray(gain_registers, np.float64))
    ratios = np.ones((2, len(p))) if loop_ratios is None else np.asarray(loop_ratios,
                                                                          np.float64)
    return (p / registers) * np.vstack([np.ones((1, len(p))), ratios])


def loop_ratios(models) -> np.ndarray:
    """(2, N) the I and D register's weight in the simulator's loop (the XM430's, KP = P/128,
    KI = I/65536, KD = D/16) against the P register's, for servos of ``models`` (one
    :class:`jaxinertia.servos.ServoModel` per joint): 1 on the X series; on the STS3215
    (PWM = P e + D de + I sum(e)/65536) 1/128 for I, 1/8 for D."""
    kp, ki, kd = (np.array([m.gain_scale[k] for m in models], np.float64) for k in range(3))
    return np.vstack([ki * 65536.0 / (kp * 128.0), kd * 16.0 / (kp * 128.0)])


class DxlRegisterMap:
    """How the physics reads and writes a DYNAMIXEL X servo's control table: the servo's
    memory (``memory``), the registers a chunk needs on the simulator's scales
    (:meth:`registers`) and the published Present values (:meth:`publish`). One per physics
    loop (a register map may keep state between chunks)."""

    memory = ServoMemory
    reading_lsb = ct.CURRENT_LSB_A  # [A] per LSB of the current reading (XM430)

    def __init__(self, n_joints: int) -> None:
        self.n_joints = n_joints

    @staticmethod
    def registers(servos: list) -> np.ndarray:
        """(len(REGISTERS), N) float64: P, I, D registers, PWM limit (885 = 100 %), profile
        velocity [rad/s] and acceleration [rad/s^2] (0: none)."""
        r = np.array([[m.get(name) for m in servos] for name in REGISTERS], np.float64)
        r[4] *= ct.VELOCITY_LSB
        r[5] *= ct.ACCELERATION_LSB
        return r

    def publish(self, servos: list, p: Present, pending: np.ndarray,
                reading_lsb=ct.CURRENT_LSB_A) -> None:
        publish(servos, p, pending, reading_lsb)


@jax.jit
def _advance(params: SimParams, gain_scale, registers, friction_scale, state: SimState,
             start, end, t_rel, v_max, a_max):
    """``len(t_rel)`` servo periods with the gains of ``registers`` and the friction bounds
    scaled by ``friction_scale``; returns the new state and the last profile goal [rad]."""
    fr = params.friction
    params = params.replace(
        servo=servo_from_registers(params.servo, gain_scale, registers),
        friction=fr.replace(coulomb=fr.coulomb * friction_scale,
                            static=fr.static * friction_scale))

    def body(s, t):
        q_goal, _ = trapezoid(start, end, t, v_max, a_max)
        return step(params, s, goal_ticks(q_goal)), q_goal

    state, goals = jax.lax.scan(body, state, t_rel)
    _, t_total = trapezoid(start, end, 0.0, v_max, a_max)
    return state, goals[-1], t_total


#: The arm held still with the torque off (the servo's memory cleared).
_at_rest = jax.jit(SimState.at_rest)


@dataclass(frozen=True)
class Present:
    """One published chunk: the joints' present values (N,) each, at ``sim_time`` [s]."""

    q: np.ndarray  # [rad]
    qd: np.ndarray  # [rad/s]
    current: np.ndarray  # the reading, with its noise [A]
    pwm: np.ndarray  # [PWM register units]
    traj_pos: np.ndarray  # profile goal [rad]
    profile_on: np.ndarray  # bool
    sim_time: float


class ArmPhysics:
    """The simulated arm behind the joint servos, one chunk at a time (no threads, no bus):
    :meth:`goal` and :meth:`hold` tell it what the servos were told, :meth:`advance` runs
    a chunk with the registers given and returns what the servos present."""

    def __init__(self, params: SimParams, *, q0: np.ndarray, chunk: int = 20,
                 seed: int = 0, gain_registers=None, loop_ratios=None) -> None:
        """``params``: :func:`jaxinertia.sim.simulator.physical_params` (leaves may be numpy
        arrays); ``gain_registers``: the P register each joint's simulated gain belongs to
        (default the XM430's factory 800); ``loop_ratios``: :func:`gain_scale`'s."""
        n = len(q0)
        self.params = params
        # Register -> simulator gain: the calibrated effective gains belong to the factory
        # P = 800 (the calibration absorbs the PWM-to-torque scale of the real servos).
        self.gain_scale = gain_scale(params.servo, gain_registers, loop_ratios)
        self._jitter = np.asarray(params.friction.jitter, np.float64)
        self.chunk = int(chunk)
        self.dt = float(params.dt)
        # One friction stream per joint (its k-th goal write always gets the same draw)
        # and one for the current-reading noise.
        streams = np.random.SeedSequence(seed).spawn(n + 1)
        self._friction_rngs = [np.random.default_rng(s) for s in streams[:n]]
        self._noise_rng = np.random.default_rng(streams[n])
        q0 = np.asarray(q0, np.float64)
        self.state = _at_rest(q0)
        self._resting: SimState | None = None  # cached state while the torque is off
        self.sim_time = 0.0
        self._start, self._end, self._traj_pos = q0.copy(), q0.copy(), q0.copy()
        self._t0 = np.zeros(n)
        self._total = np.zeros(n)
        self._friction_scale = np.ones(n)
        self.goals_applied = np.zeros(n, np.int64)

    def compile(self) -> None:
        """Compiles both paths (torque on, torque off) with the types :meth:`advance`
        uses; the state is left as it was."""
        state, resting = self.state, self._resting
        registers = np.zeros((len(REGISTERS), len(self._t0)))
        jax.block_until_ready(self._compute(registers, torque=True))
        jax.block_until_ready(self._compute(registers, torque=False))
        self.state, self._resting = state, resting

    def goal(self, j: int, q_goal: float) -> None:
        """Joint j got a new Goal Position [rad]: its profile starts now from where the
        profile goal is."""
        self._start[j] = self._traj_pos[j]
        self._end[j] = q_goal
        self._t0[j] = self.sim_time
        # Friction varies from move to move (the simulator: sample to sample).
        self._friction_scale[j] = np.exp(self._jitter[j]
                                         * self._friction_rngs[j].standard_normal())
        self.goals_applied[j] += 1

    def hold(self, j: int, q: float) -> None:
        """Joint j holds at ``q`` [rad] (torque enabled, reboot)."""
        self._start[j] = self._end[j] = self._traj_pos[j] = q
        self._t0[j] = self.sim_time

    def _compute(self, registers: np.ndarray, *, torque: bool):
        if not torque:  # held still; the servo memory (integral, previous error) is cleared
            if self._resting is None:
                self._resting = _at_rest(self.state.q)
            return self._resting, self._end.copy(), np.zeros_like(self._end)
        self._resting = None
        v = np.where(registers[4] > 0, registers[4], _UNLIMITED_VELOCITY)
        a = np.where(registers[5] > 0, registers[5], _UNLIMITED_ACCELERATION)
        times = self.sim_time + self.dt * np.arange(self.chunk)
        t_rel = times[:, None] - self._t0[None, :]
        return _advance(self.params, self.gain_scale, registers, self._friction_scale.copy(),
                        self.state, self._start.copy(), self._end.copy(), t_rel, v, a)

    def advance(self, registers: np.ndarray, torque: bool) -> Present:
        """Runs ``chunk`` servo periods with ``registers`` ((len(REGISTERS), N) float64, on
        the simulator's scales: :meth:`DxlRegisterMap.registers`)."""
        state, q_goal, t_total = self._compute(registers, torque=torque)
        self.state = state = jax.block_until_ready(state)
        q = np.asarray(state.q)
        qd = np.asarray(state.qd)
        current = np.asarray(state.servo.current)
        s = self.params.servo
        share = np.asarray(current_reading_share(np.asarray(state.servo.prev_error),
                                                 np.asarray(s.current_dead_band)))
        reading = np.where(share > 0, current * share + np.asarray(s.current_noise)
                           * self._noise_rng.standard_normal(current.shape), 0.0)
        # Present PWM from the motor equation V = R I + k_e qd (before the reading noise).
        volts = np.asarray(s.resistance) * current + np.asarray(s.back_emf) * qd
        if torque:
            pwm = volts / np.asarray(s.supply_voltage) * PWM_FULL_SCALE
        else:
            pwm, reading = np.zeros_like(q), np.zeros_like(q)
        self.sim_time += self.chunk * self.dt
        self._traj_pos = np.array(q_goal)
        self._total = np.array(t_total)
        profile_on = (self.sim_time - self._t0) < self._total
        return Present(q, qd, reading, pwm, self._traj_pos.copy(), profile_on, self.sim_time)


def publish(servos: list[ServoMemory], p: Present, pending: np.ndarray,
            reading_lsb=ct.CURRENT_LSB_A) -> None:
    """Writes a chunk into the joint servos' tables (under the lock); ``pending``: joints
    with a goal written that the chunk did not simulate yet (reported as moving);
    ``reading_lsb``: per joint (or shared), the motor current [A] of one LSB of address
    126 (Present Current, or Present Load where the servo has no current sensor)."""
    lsb = np.broadcast_to(np.asarray(reading_lsb, np.float64), (len(servos),))
    ticks = ct.rad_to_ticks(p.q)  # Present Position: the encoder's integer ticks
    traj_ticks = ct.rad_to_ticks(p.traj_pos)
    clock = round(p.sim_time * 1000) % ct.REALTIME_TICK_WRAP
    for j, m in enumerate(servos):
        vel = int(round(p.qd[j] / ct.VELOCITY_LSB))
        threshold = m.get("moving_threshold")
        profile_on = bool(p.profile_on[j] or pending[j])
        moving = abs(vel) > threshold or profile_on
        in_position = abs(m.get("goal_position") - int(ticks[j])) <= threshold
        m.set("present_position", int(ticks[j]))
        m.set("present_velocity", vel)
        sensed = "present_current" if "present_current" in m.items else "present_load"
        m.set(sensed, int(ct.current_to_register(p.current[j], lsb[j])))
        m.set("present_pwm", int(round(p.pwm[j])))
        m.set("position_trajectory", int(traj_ticks[j]))
        m.set("moving", int(moving))
        m.set("moving_status", int(in_position) | (int(profile_on) << 1))
        m.set("realtime_tick", clock)


class PhysicsLoop:
    """An :class:`ArmPhysics` behind the joint servos' tables: :meth:`step` applies the
    bus's news (``events``: a pipe of ``("goal" | "hold", joint, rad)``, in order), copies
    the registers under ``lock``, computes a chunk without it and publishes the chunk
    under it. ``goal_writes`` (shared, per joint) counts the goals the bus accepted;
    ``register_map``: how the servos' tables are read and written (a
    :class:`DxlRegisterMap`, or the STS3215's)."""

    def __init__(self, arm: ArmPhysics, servos: list, lock, events, goal_writes,
                 reading_lsb=ct.CURRENT_LSB_A, register_map=None) -> None:
        self.arm, self.servos, self.lock = arm, servos, lock
        self.events, self.goal_writes = events, goal_writes
        self.reading_lsb = reading_lsb
        self.map = DxlRegisterMap(len(servos)) if register_map is None else register_map
        self.parent_pid: int | None = None  # set by run(): the bus's process

    @contextlib.contextmanager
    def _locked(self) -> Iterator[None]:
        """The tables' lock, waited for in slices: a bus process killed while holding it
        never releases it, and its physics must then end, not wait for ever."""
        while not self.lock.acquire(timeout=_LOCK_POLL_S):
            if self._orphaned():
                raise _Orphaned
        try:
            yield
        finally:
            self.lock.release()

    def _orphaned(self) -> bool:
        return self.parent_pid is not None and os.getppid() != self.parent_pid

    def step(self) -> Present:
        while self.events.poll():
            kind, j, value = self.events.recv()
            (self.arm.goal if kind == "goal" else self.arm.hold)(j, value)
        with self._locked():
            torque = all(m.get("torque_enable") == 1 for m in self.servos)
            registers = self.map.registers(self.servos)
        present = self.arm.advance(registers, torque)
        with self._locked():
            pending = np.asarray(self.goal_writes[:len(self.servos)]) != self.arm.goals_applied
            self.map.publish(self.servos, present, pending, self.reading_lsb)
        return present

    def run(self, speed: float, stop, parent_pid: int | None = None) -> None:
        """Steps paced at ``speed`` x real time until ``stop`` is set (or the parent
        process is gone, even while it held the tables' lock)."""
        self.parent_pid = parent_pid
        wall0, sim0 = time.monotonic(), self.arm.sim_time
        try:
            while not stop.is_set():
                if self._orphaned():
                    return  # the bus's process died: nobody is listening
                ahead = (self.arm.sim_time - sim0) / speed - (time.monotonic() - wall0)
                if ahead > 0:
                    time.sleep(ahead)
                self.step()
        except _Orphaned:
            return


#: How long the physics waits for the tables' lock before it checks that its bus lives.
_LOCK_POLL_S = 0.5


class _Orphaned(Exception):
    """The bus's process is gone (while the physics waited for the lock)."""


@dataclass(frozen=True)
class PhysicsSpec:
    """What the physics process is built from (picklable: numpy leaves)."""

    params: SimParams
    joint_ids: tuple[int, ...]
    q0: np.ndarray
    chunk: int
    seed: int
    speed: float
    cache_dir: str | None
    cache_max_size: int  # the parent's cap: every writer of a cache folder needs the same
    models: tuple[int, ...] | None = None  # joint servos' model numbers (None: XM430s)
    reading_lsb: tuple[float, ...] | None = None  # [A] per LSB of the reading (None: 2.69 mA)
    gain_registers: tuple[float, ...] | None = None  # P registers (None: 800)
    loop_ratios: tuple[tuple[float, ...], ...] | None = None  # gain_scale's (None: 1)
    register_map: type = DxlRegisterMap  # the servos' tables, read and written


def physics_main(spec: PhysicsSpec, tables, goal_writes, lock, events, ready, stop,
                 parent_pid: int) -> None:
    """Entry of the physics process."""
    try:
        _xla_workarounds.apply()  # a spawned process: before its JAX backend starts
        jax.config.update("jax_enable_x64", True)
        if spec.cache_dir:
            compilation_cache.enable(spec.cache_dir, spec.cache_max_size)
        arm = ArmPhysics(spec.params, q0=spec.q0, chunk=spec.chunk, seed=spec.seed,
                         gain_registers=spec.gain_registers, loop_ratios=spec.loop_ratios)
        arm.compile()
        n = len(spec.joint_ids)
        register_map = spec.register_map(n)
        models = spec.models or (register_map.memory.default_model,) * n
        lsb = register_map.reading_lsb if spec.reading_lsb is None else spec.reading_lsb
        servos = [register_map.memory(i, v, reset=False, model=m)
                  for i, v, m in zip(spec.joint_ids, table_views(tables, n), models,
                                     strict=True)]
        loop = PhysicsLoop(arm, servos, lock, events, goal_writes, lsb, register_map)
        with lock:
            register_map.publish(servos, _initial(arm), np.zeros(n, bool), lsb)
        gc.freeze()  # no full collection over the imported modules while holding the lock
        ready.set()
        loop.run(spec.speed, stop, parent_pid)
    except KeyboardInterrupt:  # Ctrl-C reaches the whole process group: the bus stops us
        pass
    except BaseException:
        traceback.print_exc(file=sys.stderr)
        sys.exit(1)


def _initial(arm: ArmPhysics) -> Present:
    """The arm at rest where it starts (before any chunk)."""
    q = np.asarray(arm.state.q)
    zeros = np.zeros_like(q)
    return Present(q, zeros, zeros, zeros, q.copy(), np.zeros(len(q), bool), arm.sim_time)
