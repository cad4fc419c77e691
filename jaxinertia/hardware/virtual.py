"""A virtual chain of XM430-W350-T servos on a pseudo-terminal, driven by the simulator.

Two threads share the servos' control tables under one lock:

* the **bus** thread reads instruction packets from the pty master and answers with
  status packets as a servo does (Protocol 2.0: PING, READ, WRITE, SYNC_READ, SYNC_WRITE,
  BULK_READ, REBOOT; a packet with a bad CRC gets no reply; broadcast writes get none);
* the **physics** thread advances :func:`jaxinertia.sim.simulator.step` (1 ms servo
  periods, ``chunk`` steps per jitted ``lax.scan``) paced at ``speed`` x real time, with
  the goal fed through the servo's velocity-based trapezoidal profile (Profile
  Velocity/Acceleration registers), and publishes Present Position/Velocity/Current/PWM,
  Moving and Moving Status.

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

Fault injection (:class:`Faults`): dropped, CRC-corrupted or delayed status packets, and
an overload (Hardware Error Status bit 5, alert bit in every status packet, torque off)
after a number of Goal Position writes to one servo.
"""

from __future__ import annotations

import os
import select
import sys
import threading
import time
import tty
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from jaxinertia.hardware import control_table as ct
from jaxinertia.hardware.protocol import (
    BROADCAST_ID,
    ERROR_ALERT,
    Error,
    Instruction,
    Packet,
    PacketParser,
    status_packet,
)
from jaxinertia.sim.sampling import HeldObject
from jaxinertia.sim.servo import RAD_PER_TICK, goal_ticks
from jaxinertia.sim.simulator import SimParams, SimState, attach_payload, step, trapezoid

__all__ = ["Faults", "VirtualServoBus", "open_pty"]

TABLE_SIZE = 256
#: Profile register 0 means "no profile": a step goal. Stand-ins that the trapezoid takes.
_UNLIMITED_VELOCITY = 1e6  # [rad/s]
_UNLIMITED_ACCELERATION = 1e9  # [rad/s^2]


@dataclass(frozen=True)
class Faults:
    """Faults injected into the bus (probabilities per status packet)."""

    drop_rate: float = 0.0
    corrupt_rate: float = 0.0
    delay_rate: float = 0.0
    delay_s: float = 0.01
    #: Servo that raises an overload error after ``overload_after`` Goal Position writes.
    overload_id: int | None = None
    overload_after: int = 0
    seed: int = 0


class ServoMemory:
    """One servo's control table (bytes) with the e-manual's access rules."""

    def __init__(self, dxl_id: int) -> None:
        self.table = bytearray(TABLE_SIZE)
        self.reset_all(dxl_id)

    def reset_all(self, dxl_id: int) -> None:
        for item in ct.ITEMS.values():
            self._put(item, item.default)
        self._put(ct.ITEMS["id"], dxl_id)

    def reset_ram(self) -> None:
        """REBOOT: RAM back to defaults, EEPROM kept."""
        for item in ct.ITEMS.values():
            if item.address >= ct.EEPROM_END:
                self._put(item, item.default)

    def _put(self, item: ct.Item, value: int) -> None:
        raw = ct.to_unsigned(value, item.size)
        self.table[item.address:item.address + item.size] = raw.to_bytes(item.size, "little")

    def set(self, name: str, value: int) -> None:
        self._put(ct.ITEMS[name], value)

    def get(self, name: str) -> int:
        item = ct.ITEMS[name]
        raw = int.from_bytes(self.table[item.address:item.address + item.size], "little")
        return ct.to_signed(raw, item.size) if item.signed else raw

    def read(self, address: int, length: int) -> tuple[int, bytes]:
        if length < 1 or address + length > TABLE_SIZE:
            return Error.ACCESS, b""
        return Error.NONE, bytes(self.table[address:address + length])

    def check_write(self, address: int, data: bytes) -> int:
        """The error a WRITE of ``data`` at ``address`` gets (0: allowed)."""
        end = address + len(data)
        if not data or end > TABLE_SIZE:
            return Error.ACCESS
        torque_on = self.get("torque_enable") == 1
        for name, item in ct.ITEMS.items():
            if item.address < end and address < item.address + item.size:
                if not item.writable:
                    return Error.ACCESS
                if item.address < ct.EEPROM_END and torque_on:
                    return Error.ACCESS  # EEPROM is locked while the torque is on
                if name == "goal_position" and address == item.address and len(data) >= 4:
                    goal = ct.to_signed(int.from_bytes(data[:4], "little"), 4)
                    lo, hi = self.get("min_position_limit"), self.get("max_position_limit")
                    if not lo <= goal <= hi:
                        return Error.DATA_LIMIT
        return Error.NONE


def open_pty() -> tuple[int, int, str]:
    """A raw pseudo-terminal: (master fd, slave fd, slave path)."""
    master, slave = os.openpty()
    tty.setraw(slave)
    os.set_blocking(master, False)
    return master, slave, os.ttyname(slave)


@jax.jit
def _advance(params: SimParams, state: SimState, start, end, t_rel, v_max, a_max):
    """``len(t_rel)`` servo periods; returns the new state and the last profile goal [rad]."""

    def body(s, t):
        q_goal, _ = trapezoid(start, end, t, v_max, a_max)
        return step(params, s, goal_ticks(q_goal)), q_goal

    state, goals = jax.lax.scan(body, state, t_rel)
    _, t_total = trapezoid(start, end, 0.0, v_max, a_max)
    return state, goals[-1], t_total


class VirtualServoBus:
    """Servos ``ids`` (one per joint of ``params.robot``, then optional extra servos such as
    a gripper, which answer but do not move) on a pty, driven by the simulator."""

    def __init__(
        self,
        params: SimParams,
        obj: HeldObject | None,
        *,
        ids: tuple[int, ...] = (11, 12, 13, 14),
        extra_ids: tuple[int, ...] = (15,),
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
        self.joint_ids = tuple(ids)
        self.servos = {i: ServoMemory(i) for i in (*ids, *extra_ids)}
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
        self.faults = faults
        self._rng = np.random.default_rng(seed)
        self._fault_rng = np.random.default_rng(faults.seed)
        self._goal_writes = {i: 0 for i in self.servos}
        self.goal_position_writes = 0  # for tests: Goal Position writes accepted, all servos
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
        for dxl_id in self.servos:
            self.servos[dxl_id].set("present_temperature", ambient_temperature)
            self.servos[dxl_id].set("present_input_voltage",
                                    round(float(params.servo.supply_voltage[0]) / ct.VOLTAGE_LSB))
        self._publish(q0, np.zeros(n), np.zeros(n), np.zeros(n))
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self.master, self._slave, self.path = open_pty()
        self.error: BaseException | None = None

    # ---- lifecycle -------------------------------------------------------------------

    def compile(self) -> None:
        """Compiles the physics step before the bus opens (so the first reply is prompt)."""
        q = jnp.asarray(self._traj_pos)
        t = jnp.zeros((self.chunk, len(q)))
        with self._lock:
            servo = self._servo_params()
        params = self._base_params.replace(servo=servo)
        jax.block_until_ready(_advance(params, self._state, q, q, t, q + 1.0, q + 1.0))

    def start(self) -> None:
        # The bus thread must get the GIL back quickly after each blocking call: the
        # master's status-packet timeout is ~35 ms (dynamixel-sdk), Python's default
        # switch interval 5 ms per hand-over.
        sys.setswitchinterval(5e-4)
        for target, name in ((self._bus_loop, "dxl-bus"), (self._physics_loop, "dxl-physics")):
            th = threading.Thread(target=self._guard(target), name=name, daemon=True)
            th.start()
            self._threads.append(th)

    def _guard(self, fn):
        def run():
            try:
                fn()
            except BaseException as e:  # surfaced by wait()/close() instead of dying silently
                self.error = e
                self._stop.set()
        return run

    def close(self) -> None:
        self._stop.set()
        for th in self._threads:
            th.join(timeout=2.0)
        for fd in (self.master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass

    def wait(self) -> None:
        """Blocks until closed or a thread failed (re-raises its error)."""
        while not self._stop.wait(0.2):
            pass
        if self.error is not None:
            raise self.error

    def __enter__(self) -> VirtualServoBus:
        self.compile()
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

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
        pwm = volts / np.asarray(s.supply_voltage) * 885.0 if torque else np.zeros_like(q)
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

    # ---- bus ---------------------------------------------------------------------------

    def _bus_loop(self) -> None:
        parser = PacketParser()
        while not self._stop.is_set():
            ready, _, _ = select.select([self.master], [], [], 0.1)
            if not ready:
                continue
            try:
                data = os.read(self.master, 4096)
            except (BlockingIOError, InterruptedError):
                continue
            except OSError:  # no client on the slave side right now
                time.sleep(0.01)
                continue
            for packet in parser.feed(data):
                self._send(self.handle(packet))

    def _send(self, replies: list[bytes]) -> None:
        """Sends status packets back to back (one write: servos answer in turn on the bus,
        and every GIL hand-over of a separate write would add latency)."""
        f, r = self.faults, self._fault_rng
        out = bytearray()
        for reply in replies:
            if f.drop_rate and r.random() < f.drop_rate:
                continue
            if f.corrupt_rate and r.random() < f.corrupt_rate:
                reply = reply[:-1] + bytes([reply[-1] ^ 0x5A])
            if f.delay_rate and r.random() < f.delay_rate:
                self._write_out(bytes(out))
                out.clear()
                time.sleep(f.delay_s)
            out.extend(reply)
        self._write_out(bytes(out))

    def _write_out(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            try:
                n = os.write(self.master, view)
            except BlockingIOError:
                select.select([], [self.master], [], 0.1)
                continue
            view = view[n:]

    def _status(self, dxl_id: int, error: int = 0, params: bytes = b"") -> bytes:
        if self.servos[dxl_id].get("hardware_error_status"):
            error |= ERROR_ALERT
        return status_packet(dxl_id, error, params)

    def handle(self, packet: Packet) -> list[bytes]:
        """The status packets a chain of servos sends for one instruction packet."""
        if not packet.crc_ok:
            return []  # a servo ignores a corrupted packet (the master times out)
        with self._lock:
            return self._handle(packet)

    def _handle(self, p: Packet) -> list[bytes]:
        inst, prm = p.instruction, p.params
        ids = sorted(self.servos) if p.id == BROADCAST_ID else (
            [p.id] if p.id in self.servos else [])
        if inst == Instruction.PING:
            info = ct.ITEMS["model_number"].default.to_bytes(2, "little") + bytes(
                [ct.ITEMS["firmware_version"].default])
            return [self._status(i, 0, info) for i in ids]
        if inst == Instruction.SYNC_READ or inst == Instruction.SYNC_WRITE:
            if len(prm) < 4:
                return []
            address = int.from_bytes(prm[0:2], "little")
            length = int.from_bytes(prm[2:4], "little")
            if inst == Instruction.SYNC_READ:
                out = []
                for dxl_id in prm[4:]:
                    if dxl_id in self.servos:
                        err, data = self.servos[dxl_id].read(address, length)
                        out.append(self._status(dxl_id, err, data))
                return out
            for k in range(4, len(prm) - length + 1, 1 + length):
                dxl_id, data = prm[k], prm[k + 1:k + 1 + length]
                if dxl_id in self.servos and len(data) == length:
                    self._write(dxl_id, address, data)
            return []
        if inst == Instruction.BULK_READ:
            out = []
            for k in range(0, len(prm) - 4, 5):
                dxl_id = prm[k]
                address = int.from_bytes(prm[k + 1:k + 3], "little")
                length = int.from_bytes(prm[k + 3:k + 5], "little")
                if dxl_id in self.servos:
                    err, data = self.servos[dxl_id].read(address, length)
                    out.append(self._status(dxl_id, err, data))
            return out
        replies = []
        for dxl_id in ids:
            reply = self._unicast(dxl_id, inst, prm)
            if p.id != BROADCAST_ID:
                replies.append(reply)
        return replies

    def _unicast(self, dxl_id: int, inst: int, prm: bytes) -> bytes:
        mem = self.servos[dxl_id]
        if inst == Instruction.READ:
            if len(prm) != 4:
                return self._status(dxl_id, Error.DATA_LENGTH)
            err, data = mem.read(int.from_bytes(prm[0:2], "little"),
                                 int.from_bytes(prm[2:4], "little"))
            return self._status(dxl_id, err, data)
        if inst == Instruction.WRITE:
            if len(prm) < 3:
                return self._status(dxl_id, Error.DATA_LENGTH)
            err = self._write(dxl_id, int.from_bytes(prm[0:2], "little"), prm[2:])
            return self._status(dxl_id, err)
        if inst == Instruction.REBOOT:
            self._reboot(dxl_id)
            return self._status(dxl_id)
        return self._status(dxl_id, Error.INSTRUCTION)

    def _reboot(self, dxl_id: int) -> None:
        mem = self.servos[dxl_id]
        mem.reset_ram()
        if dxl_id in self.joint_ids:
            j = self.joint_ids.index(dxl_id)
            self._hold_here(j)

    def _hold_here(self, j: int) -> None:
        """Goal and profile of joint j at its present position (torque enabled, reboot)."""
        mem = self.servos[self.joint_ids[j]]
        here = mem.get("present_position")
        mem.set("goal_position", here)
        q = (here - ct.ZERO_TICKS) * RAD_PER_TICK
        self._traj_start[j] = self._traj_end[j] = self._traj_pos[j] = q
        self._traj_t0[j] = self._sim_time

    def _write(self, dxl_id: int, address: int, data: bytes) -> int:
        mem = self.servos[dxl_id]
        err = mem.check_write(address, data)
        if err:
            return err
        was_on = mem.get("torque_enable")
        mem.table[address:address + len(data)] = data
        j = self.joint_ids.index(dxl_id) if dxl_id in self.joint_ids else None
        if mem.get("torque_enable") == 1 and not was_on and j is not None:
            self._hold_here(j)  # the servo starts holding where it is
        goal = ct.ITEMS["goal_position"]
        if address <= goal.address < address + len(data):
            self.goal_position_writes += 1
            self._goal_writes[dxl_id] += 1
            if j is not None:
                # The profile starts from where the profile goal is now.
                self._traj_start[j] = self._traj_pos[j]
                self._traj_end[j] = (mem.get("goal_position") - ct.ZERO_TICKS) * RAD_PER_TICK
                self._traj_t0[j] = self._sim_time
                self._jitter_pending[j] = True
            f = self.faults
            # One-shot: the (overload_after + 1)-th Goal Position write raises it.
            if f.overload_id == dxl_id and self._goal_writes[dxl_id] == f.overload_after + 1:
                mem.set("hardware_error_status", ct.HW_ERROR_OVERLOAD)
                mem.set("torque_enable", 0)  # Shutdown (address 63) includes overload
        return Error.NONE
