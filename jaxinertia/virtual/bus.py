"""The bus side of the virtual robot: a chain of DYNAMIXEL X servos (XM430-W350-T by
default; any model with a table in :data:`jaxinertia.hardware.control_table.TABLES`, one
per servo: the Koch v1.1 mixes XL430-W250 and XL330-M288) answering Protocol 2.0 on a
pseudo-terminal. Each servo pings with its own model number and keeps its own control
table (an XL430 has Present Load where the others have Present Current).

:class:`ServoBus` keeps each servo's control table (:class:`ServoMemory`, the e-manual's
access rules) and runs the **bus** thread: it reads instruction packets from the pty master
and answers with status packets as a servo does (PING, READ, WRITE, SYNC_READ, SYNC_WRITE,
BULK_READ, REBOOT; a packet with a bad CRC gets no reply; broadcast writes get none).
Servos on this bus answer but do not move: :class:`jaxinertia.virtual.robot.VirtualServoBus`
drives the joint servos' Present registers from the simulator, told of every new goal and
every hold through :meth:`ServoBus._goal_changed` and :meth:`ServoBus._held`. The control
tables may live in a shared buffer (``tables``) and be guarded by a lock shared with another
process (``lock``): the simulator then runs in a process of its own, and the bus thread
never waits for the interpreter while the physics computes.

Fault injection (:class:`Faults`): dropped, CRC-corrupted or delayed status packets, and
an overload (Hardware Error Status bit 5, alert bit in every status packet, torque off)
after a number of Goal Position writes to one servo.

One module: the servo's memory, its access rules and the bus that answers from it are one
protocol's (another protocol's bus, :mod:`jaxinertia.virtual.sts_bus`, derives from it).
"""

from __future__ import annotations

import os
import select
import sys
import threading
import time
import tty
from collections.abc import Callable
from dataclasses import dataclass

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

__all__ = ["TABLE_SIZE", "Faults", "ServoBus", "ServoMemory", "open_pty", "table_views"]

TABLE_SIZE = 256


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
    """One servo's control table (bytes) with the e-manual's access rules: its own, or
    ``table``, a writable ``TABLE_SIZE``-byte view into a shared buffer (``reset``: filled
    with the factory defaults; False: attached as it is). ``model``: its model number
    (the control table's layout and initial values, :func:`control_table.items_of`)."""

    default_model = ct.XM430_W350_MODEL

    def __init__(self, dxl_id: int, table=None, *, reset: bool = True,
                 model: int = default_model) -> None:
        self.items = ct.items_of(model)
        self.table = bytearray(TABLE_SIZE) if table is None else table
        if reset:
            self.reset_all(dxl_id)

    def reset_all(self, dxl_id: int) -> None:
        for item in self.items.values():
            self._put(item, item.default)
        self._put(self.items["id"], dxl_id)

    def reset_ram(self) -> None:
        """REBOOT: RAM back to defaults, EEPROM kept."""
        for item in self.items.values():
            if item.address >= ct.EEPROM_END:
                self._put(item, item.default)

    def _put(self, item: ct.Item, value: int) -> None:
        raw = ct.to_unsigned(value, item.size)
        self.table[item.address:item.address + item.size] = raw.to_bytes(item.size, "little")

    def set(self, name: str, value: int) -> None:
        self._put(self.items[name], value)

    def get(self, name: str) -> int:
        item = self.items[name]
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
        for name, item in self.items.items():
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


def table_views(tables, n: int) -> list[memoryview]:
    """The ``n`` servo tables of a shared byte buffer (``TABLE_SIZE`` bytes each)."""
    view = memoryview(tables).cast("B")
    return [view[k * TABLE_SIZE:(k + 1) * TABLE_SIZE] for k in range(n)]


def open_pty() -> tuple[int, int, str]:
    """A raw pseudo-terminal: (master fd, slave fd, slave path)."""
    master, slave = os.openpty()
    tty.setraw(slave)
    os.set_blocking(master, False)
    return master, slave, os.ttyname(slave)


class ServoBus:
    """Servos ``joint_ids`` then ``extra_ids`` (such as a gripper) on a pty. Every servo
    answers; the joint servos' motion is a subclass's (:meth:`_goal_changed`,
    :meth:`_held`, :meth:`_loops`). Servo state is shared under ``_lock``; ``tables`` (a
    writable byte buffer of ``TABLE_SIZE`` per servo, in this order) and ``lock`` let
    another process share them. A subclass may speak another protocol: its servos'
    memory (``memory_class``), its receiver (``parser_class``) and :meth:`handle`."""

    memory_class = ServoMemory
    parser_class = PacketParser

    def __init__(
        self,
        joint_ids: tuple[int, ...],
        extra_ids: tuple[int, ...] = (),
        *,
        faults: Faults = Faults(),  # noqa: B008  (frozen dataclass)
        temperature: int = 30,
        input_voltage: float = 12.0,
        tables=None,
        lock=None,
        models: tuple[int, ...] | None = None,
    ) -> None:
        self.joint_ids = tuple(joint_ids)
        ids = (*joint_ids, *extra_ids)
        views = [None] * len(ids) if tables is None else table_views(tables, len(ids))
        kinds = [{}] * len(ids) if models is None else [{"model": m} for m in models]
        self.servos = {i: self.memory_class(i, v, **k)
                       for i, v, k in zip(ids, views, kinds, strict=True)}
        self.faults = faults
        self._fault_rng = np.random.default_rng(faults.seed)
        self._goal_writes = {i: 0 for i in self.servos}
        self.goal_position_writes = 0  # for tests: Goal Position writes accepted, all servos
        self._set_ambient(temperature, input_voltage)
        self._lock = threading.Lock() if lock is None else lock
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self.master, self._slave, self.path = open_pty()
        self.error: BaseException | None = None

    def _set_ambient(self, temperature: int, input_voltage: float) -> None:
        for mem in self.servos.values():
            mem.set("present_temperature", temperature)
            self._set_supply(mem, input_voltage)

    @staticmethod
    def _set_supply(mem: ServoMemory, volts: float) -> None:
        """A servo's Present Input Voltage [V]."""
        mem.set("present_input_voltage", round(volts / ct.VOLTAGE_LSB))

    @staticmethod
    def _mark_moving(mem: ServoMemory) -> None:
        """A servo whose goal was just written reports moving (Moving, and the profile bit
        of Moving Status) until its motion says otherwise."""
        mem.set("moving", 1)
        mem.set("moving_status", mem.get("moving_status") | 0x02)

    # ---- what the joints do (a subclass moves them) -----------------------------------

    def _goal_changed(self, j: int, q_goal: float) -> None:
        """Joint j got a new Goal Position ``q_goal`` [rad] (under the lock)."""

    def _held(self, j: int, q: float) -> None:
        """Joint j holds at ``q`` [rad], its present position (torque on, reboot)."""

    def _loops(self) -> list[tuple[Callable[[], None], str]]:
        """The threads to run: (target, name)."""
        return [(self._bus_loop, "dxl-bus")]

    # ---- lifecycle -------------------------------------------------------------------

    def start(self) -> None:
        # The bus thread must get the GIL back quickly after each blocking call: the
        # master's status-packet timeout is ~35 ms (dynamixel-sdk), Python's default
        # switch interval 5 ms per hand-over.
        sys.setswitchinterval(5e-4)
        for target, name in self._loops():
            th = threading.Thread(target=self._guard(target), name=name, daemon=True)
            th.start()
            self._threads.append(th)

    def stop(self) -> None:
        """Asks the threads to end (:meth:`wait` then returns; signal-handler safe)."""
        self._stop.set()

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

    def __enter__(self) -> ServoBus:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ---- bus ---------------------------------------------------------------------------

    def _bus_loop(self) -> None:
        parser = self.parser_class()
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
        if inst == Instruction.PING:  # each servo its own model number and firmware
            return [self._status(i, 0, self.servos[i].get("model_number").to_bytes(
                2, "little") + bytes([self.servos[i].get("firmware_version")])) for i in ids]
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
            self._hold_here(self.joint_ids.index(dxl_id))

    def _hold_here(self, j: int) -> None:
        """Goal of joint j at its present position (torque enabled, reboot)."""
        mem = self.servos[self.joint_ids[j]]
        here = mem.get("present_position")
        mem.set("goal_position", here)
        self._held(j, float(ct.ticks_to_rad(here)))

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
        goal = mem.items["goal_position"]
        if address <= goal.address < address + len(data):
            self.goal_position_writes += 1
            self._goal_writes[dxl_id] += 1
            if j is not None:
                self._goal_changed(j, float(ct.ticks_to_rad(mem.get("goal_position"))))
            f = self.faults
            # One-shot: the (overload_after + 1)-th Goal Position write raises it.
            if f.overload_id == dxl_id and self._goal_writes[dxl_id] == f.overload_after + 1:
                mem.set("hardware_error_status", ct.HW_ERROR_OVERLOAD)
                mem.set("torque_enable", 0)  # Shutdown (address 63) includes overload
        return Error.NONE
