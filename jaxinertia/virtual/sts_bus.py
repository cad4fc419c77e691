"""A virtual SO-101 bus: Feetech STS3215 servos answering the SCS/STS protocol on a
pseudo-terminal, as scservo_sdk (LeRobot's client) talks to them.

:class:`StsBus` is a :class:`jaxinertia.virtual.bus.ServoBus` (the pty, the threads,
the fault injection: dropped, checksum-corrupted and delayed status packets, an overload
after a number of Goal Position writes) that speaks the STS protocol
(:mod:`jaxinertia.hardware.feetech_protocol`) over the STS3215 memory table
(:mod:`jaxinertia.hardware.feetech_table`): PING, READ, WRITE, REG_WRITE + ACTION,
SYNC_READ, SYNC_WRITE; a packet with a bad checksum gets no answer, a broadcast none,
and with Response Status Level 0 only PING and READ are answered.

The servos' rules, as modelled (what a driver must cope with):

* an EEPROM item (addresses below 40) written while Lock (55) is 1 keeps its old value
  (the status packet reports nothing: the driver must unlock and read back); read-only
  items ignore writes;
* a goal beyond Min/Max Position Limit is clamped to it;
* an overload sets Status bit 5 and the same bit in every status packet, and turns the
  torque off; writing Torque Enable = 1 clears it (the STS resumes when its torque is
  enabled again);
* a servo whose torque is turned on holds where it is (Goal Position = Present Position).

Its joints are told of every goal and hold (``ServoBus._goal_changed``, ``_held``) and
moved by a subclass: :class:`jaxinertia.virtual.sts_robot.VirtualStsBus` is the simulated
SO-101 behind these servos (``virtual-robot --arm so101``); :class:`StsServoBus` here is
the **first-order bus model**, in a thread of its own (no simulator, no JAX: a fast bus
for protocol and driver tests): each joint approaches its goal with time
constant ``tau`` at no more than Goal Velocity (0: ``max_speed``), settling
``load * 1000 / P`` ticks short of it under a constant external load (a fraction of the
maximum torque, per joint: the rest discrepancy the method measures), Present Load the
position loop's output ``P * error`` (0.1 %), Present Current its share of the stall
current. Time is the host's, times ``speed``. The gripper answers but does not move.
Not modelled: the homing offset (stored, not applied), Goal Time and Acceleration,
temperature and voltage (held at ``temperature`` and ``input_voltage``).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import numpy as np

from jaxinertia.hardware import feetech_table as ft
from jaxinertia.hardware.feetech_protocol import (
    BROADCAST_ID,
    Instruction,
    Packet,
    StsPacketParser,
    encode_packet,
)
from jaxinertia.servos import STS3215_7V4
from jaxinertia.virtual.bus import Faults, ServoBus

__all__ = ["SO101_IDS", "StsBus", "StsMemory", "StsServoBus"]

#: The SO-101's bus IDs: five joints, then the gripper (LeRobot's defaults).
SO101_IDS = ((1, 2, 3, 4, 5), (6,))


class StsMemory:
    """One STS3215's memory table (bytes) with its access rules (module docstring): its
    own, or the first ``ft.TABLE_SIZE`` bytes of ``table``, a writable view into a shared
    buffer (``reset``: filled with the factory defaults; False: attached as it is)."""

    default_model = ft.STS3215_MODEL

    def __init__(self, scs_id: int, table=None, *, reset: bool = True,
                 model: int = default_model) -> None:
        if model != ft.STS3215_MODEL:
            raise ValueError(f"model number {model}: the virtual STS servo is an STS3215 "
                             f"({ft.STS3215_MODEL})")
        self.table = (bytearray(ft.TABLE_SIZE) if table is None
                      else memoryview(table)[:ft.TABLE_SIZE])
        if reset:
            for item in ft.ITEMS.values():
                self._put(item, item.default)
            self.set("id", scs_id)
        self.pending: tuple[int, bytes] | None = None  # REG_WRITE until ACTION

    def _put(self, item: ft.Item, value: int) -> None:
        raw = ft.encode(item, value)
        self.table[item.address:item.address + item.size] = raw.to_bytes(item.size, "little")

    def set(self, name: str, value: int) -> None:
        self._put(ft.ITEMS[name], value)

    def get(self, name: str) -> int:
        return ft.field(ft.ITEMS[name], self.table, 0)

    def read(self, address: int, length: int) -> bytes | None:
        if length < 1 or address + length > ft.TABLE_SIZE:
            return None
        return bytes(self.table[address:address + length])

    def write(self, address: int, data: bytes) -> set[str]:
        """Writes what the rules allow; returns the names of the items written."""
        locked = self.get("lock") == 1
        written = set()
        for name, item in ft.ITEMS.items():
            lo, hi = max(address, item.address), min(address + len(data),
                                                      item.address + item.size)
            if lo >= hi or not item.writable or (item.eeprom and locked):
                continue
            self.table[lo:hi] = data[lo - address:hi - address]
            written.add(name)
        return written


class StsBus(ServoBus):
    """Servos ``joint_ids`` then ``extra_ids`` answering the STS protocol (module
    docstring); the joints' motion is a subclass's."""

    memory_class = StsMemory
    parser_class = StsPacketParser

    @staticmethod
    def _set_supply(mem: StsMemory, volts: float) -> None:
        mem.set("present_voltage", round(volts / ft.VOLTAGE_LSB))

    @staticmethod
    def _mark_moving(mem: StsMemory) -> None:
        mem.set("moving", 1)

    # ---- the protocol --------------------------------------------------------------------

    def _status(self, scs_id: int, params: bytes = b"") -> bytes:
        return encode_packet(scs_id, self.servos[scs_id].get("status"), params)

    def handle(self, packet: Packet) -> list[bytes]:
        if not packet.checksum_ok:
            return []  # a servo ignores a corrupted packet (the master times out)
        with self._lock:
            return self._handle(packet)

    def _handle(self, p: Packet) -> list[bytes]:
        inst, prm = p.instruction, p.params
        if inst == Instruction.SYNC_READ:
            if len(prm) < 2:
                return []
            out = []
            for scs_id in prm[2:]:
                data = self.servos[scs_id].read(prm[0], prm[1]) if scs_id in self.servos \
                    else None
                if data is not None:
                    out.append(self._status(scs_id, data))
            return out
        if inst == Instruction.SYNC_WRITE:
            if len(prm) < 2:
                return []
            address, length = prm[0], prm[1]
            for k in range(2, len(prm) - length, 1 + length):
                if prm[k] in self.servos:
                    self._write(prm[k], address, prm[k + 1:k + 1 + length])
            return []
        ids = sorted(self.servos) if p.id == BROADCAST_ID else (
            [p.id] if p.id in self.servos else [])
        replies = [(i, self._unicast(i, inst, prm)) for i in ids]
        if p.id == BROADCAST_ID:
            return []
        quiet = inst not in (Instruction.PING, Instruction.READ)
        return [r for i, r in replies if r is not None
                and not (quiet and self.servos[i].get("response_status_level") == 0)]

    def _unicast(self, scs_id: int, inst: int, prm: bytes) -> bytes | None:
        mem = self.servos[scs_id]
        if inst == Instruction.PING:
            return self._status(scs_id)
        if inst == Instruction.READ:
            data = mem.read(prm[0], prm[1]) if len(prm) == 2 else None
            return None if data is None else self._status(scs_id, data)
        if inst in (Instruction.WRITE, Instruction.REG_WRITE):
            if len(prm) < 2:
                return None
            if inst == Instruction.WRITE:
                self._write(scs_id, prm[0], prm[1:])
            else:
                mem.pending = (prm[0], bytes(prm[1:]))
            return self._status(scs_id)
        if inst == Instruction.ACTION:
            if mem.pending is not None:
                self._write(scs_id, *mem.pending)
                mem.pending = None
            return self._status(scs_id)
        return None  # an unknown instruction gets no answer

    def _write(self, scs_id: int, address: int, data: bytes) -> None:
        mem = self.servos[scs_id]
        was_on = mem.get("torque_enable") == 1
        written = mem.write(address, data)
        j = self.joint_ids.index(scs_id) if scs_id in self.joint_ids else None
        if "torque_enable" in written and mem.get("torque_enable") == 1:
            mem.set("status", 0)  # re-enabling the torque clears a protection stop
            if not was_on:
                here = mem.get("present_position")
                if "goal_position" not in written:
                    mem.set("goal_position", here)  # holds where it is
                if j is not None:
                    self._held(j, float(ft.ticks_to_rad(here)))
        if "goal_position" in written:
            self.goal_position_writes += 1
            self._goal_writes[scs_id] += 1
            if j is not None:  # clamped to the position limits
                goal = min(max(mem.get("goal_position"), mem.get("min_position_limit")),
                           mem.get("max_position_limit"))
                self._goal_changed(j, float(ft.ticks_to_rad(goal)))
            f = self.faults
            if f.overload_id == scs_id and self._goal_writes[scs_id] == f.overload_after + 1:
                mem.set("status", ft.STATUS_OVERLOAD)
                mem.set("torque_enable", 0)


class StsServoBus(StsBus):
    """Servos ``joint_ids`` (moving by the first-order model) then ``extra_ids`` (answering
    only) on a pty."""

    def __init__(
        self,
        joint_ids: tuple[int, ...] = SO101_IDS[0],
        extra_ids: tuple[int, ...] = SO101_IDS[1],
        *,
        faults: Faults = Faults(),  # noqa: B008  (frozen dataclass)
        temperature: int = 30,
        input_voltage: float = STS3215_7V4.supply_voltage,
        q0_ticks=None,
        loads=None,
        tau: float = 0.05,
        max_speed: float = STS3215_7V4.no_load_speed,
        speed: float = 1.0,
        period: float = 0.002,
    ) -> None:
        super().__init__(joint_ids, extra_ids, faults=faults, temperature=temperature,
                         input_voltage=input_voltage)
        n = len(self.joint_ids)
        self._pos = np.full(n, float(ft.ZERO_TICKS)) if q0_ticks is None else np.array(
            q0_ticks, np.float64)
        self._vel = np.zeros(n)
        self._loads = np.zeros(n) if loads is None else np.asarray(loads, np.float64)
        self.tau, self.speed, self.period = float(tau), float(speed), float(period)
        self._max_speed = max_speed / ft.RAD_PER_TICK  # [ticks/s]
        self._stall_ticks = STS3215_7V4.stall_current / ft.CURRENT_LSB_A
        with self._lock:
            for j in range(n):
                self._publish(j)
                self.servos[self.joint_ids[j]].set("goal_position", int(round(self._pos[j])))

    def _loops(self) -> list[tuple[Callable[[], None], str]]:
        return [(self._bus_loop, "sts-bus"), (self._motion_loop, "sts-motion")]

    # ---- the joints ----------------------------------------------------------------------

    def _motion_loop(self) -> None:
        last = time.monotonic()
        while not self._stop.wait(self.period):
            now = time.monotonic()
            dt = min(now - last, 0.05) * self.speed  # a stalled host is not a leap
            last = now
            with self._lock:
                for j in range(len(self.joint_ids)):
                    self._step(j, dt)

    def _step(self, j: int, dt: float) -> None:
        mem = self.servos[self.joint_ids[j]]
        if mem.get("torque_enable") != 1:
            self._vel[j] = 0.0
        else:
            p_gain = max(mem.get("p_coefficient"), 1)
            lo, hi = mem.get("min_position_limit"), mem.get("max_position_limit")
            goal = min(max(mem.get("goal_position"), lo), hi)
            rest = goal - self._loads[j] * 1000.0 / p_gain
            step = (rest - self._pos[j]) * -math.expm1(-dt / self.tau)
            v_max = mem.get("goal_velocity") or self._max_speed  # 0: full speed
            step = float(np.clip(step, -v_max * dt, v_max * dt))
            self._pos[j] += step
            self._vel[j] = step / dt if dt > 0 else 0.0
        self._publish(j)

    def _publish(self, j: int) -> None:
        mem = self.servos[self.joint_ids[j]]
        ticks = int(round(self._pos[j]))
        on = mem.get("torque_enable") == 1
        error = (max(mem.get("goal_position"), 0) - self._pos[j]) if on else 0.0
        pwm = float(np.clip(mem.get("p_coefficient") * error, -1000, 1000))
        mem.set("present_position", int(np.clip(ticks, 0, 4095)))
        mem.set("present_velocity", int(round(self._vel[j])))
        mem.set("present_load", int(round(pwm)))
        mem.set("present_current", int(round(pwm / 1000.0 * self._stall_ticks)))
        mem.set("moving", int(abs(self._vel[j]) >= 1.0))
