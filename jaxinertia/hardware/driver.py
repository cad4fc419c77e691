"""The OpenMANIPULATOR-X on DYNAMIXEL XM430-W350-T servos, through dynamixel-sdk (Protocol 2.0).

Everything this class returns is SI (rad, A, N m, V, degC, s); ticks and register LSBs
exist only inside it (``control_table``). A move follows the paper's protocol one goal at a
time: :meth:`DynamixelArm.move_and_settle` commands the goal (GroupSyncWrite), then polls
(GroupSyncRead) until no servo reports Moving and no Present Position tick changed for
``settle_time``. Every goal is checked against joint limits and a workspace box first, and
the servos' own Min/Max Position Limit registers are set to the same joint limits.

A hardware error (Hardware Error Status or the alert bit), a bus failure that outlasts
``retries``, a timeout or Ctrl-C leaves the arm in the state ``on_stop`` names: ``hold``
(goal = present position, torque on) or ``torque_off``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from dynamixel_sdk import (
    COMM_SUCCESS,
    GroupSyncRead,
    GroupSyncWrite,
    PacketHandler,
    PortHandler,
)

from jaxinertia import errors
from jaxinertia.hardware import control_table as ct
from jaxinertia.hardware.safety import SafetyLimits, default_joint_limits
from jaxinertia.robot import Robot

__all__ = ["ArmConfig", "ArmState", "CommError", "DynamixelArm", "HardwareError"]


class CommError(errors.HardwareError):
    """The bus failed (no or corrupt status packet) after all retries (exit code 3)."""


class HardwareError(errors.HardwareError):
    """A servo reported a hardware error (Hardware Error Status, alert bit; exit code 3)."""

    def __init__(self, errors: dict[int, int]) -> None:
        self.errors = errors
        names = {ct.HW_ERROR_VOLTAGE: "input voltage", ct.HW_ERROR_OVERHEATING: "overheating",
                 ct.HW_ERROR_ENCODER: "encoder", ct.HW_ERROR_ELECTRICAL_SHOCK: "electrical shock",
                 ct.HW_ERROR_OVERLOAD: "overload"}
        text = "; ".join(f"ID {i}: " + ", ".join(n for b, n in names.items() if e & b)
                         for i, e in errors.items())
        super().__init__(f"hardware error: {text} (power-cycle or reboot the servo)")


@dataclass(frozen=True)
class ArmConfig:
    """Bus, servo registers and the motion protocol. Defaults: OpenMANIPULATOR-X, as the
    paper ran it (PD position loop: I = 0; ROBOTIS' own configuration sets I = 100, which
    would integrate the very discrepancy the method measures)."""

    port: str
    baudrate: int = 1_000_000
    joint_ids: tuple[int, ...] = (11, 12, 13, 14)
    gripper_id: int | None = 15
    p_gain: int = 800
    i_gain: int = 0
    d_gain: int = 0
    pwm_limit: int = 885
    profile_velocity: float = 0.5  # [rad/s], the simulator's profile
    profile_acceleration: float = 2.0  # [rad/s^2]
    joint_limits: np.ndarray = field(default_factory=default_joint_limits)  # (N, 2) [rad]
    settle_time: float = 0.2  # no tick may change for this long [s]
    move_timeout: float = 6.0  # per move [s]
    poll_period: float = 0.002  # [s]
    retries: int = 3
    on_stop: Literal["hold", "torque_off"] = "hold"
    #: On connect, REBOOT servos that report a hardware error (after its cause is fixed).
    reboot_on_error: bool = False


@dataclass(frozen=True)
class ArmState:
    """One synchronous reading of the joint servos (N,) each, SI."""

    q: np.ndarray  # Present Position [rad] (integer ticks)
    velocity: np.ndarray  # [rad/s]
    current: np.ndarray  # Present Current [A] (2.69 mA steps)
    moving: np.ndarray  # Moving flag (bool)
    temperature: np.ndarray  # [degC]
    voltage: np.ndarray  # [V]
    ticks: np.ndarray  # Present Position register (int)
    servo_clock: int  # Realtime Tick of the first joint servo [ms, mod 32768]
    timestamp: float  # time.time() of the reading [s]


class DynamixelArm:
    """The joint servos of one arm. Use as a context manager: ``connect`` and ``configure``
    on entry; on exit (also on an exception or Ctrl-C) :meth:`stop`, then the port closes."""

    def __init__(self, config: ArmConfig, *, robot: Robot | None = None,
                 safety: SafetyLimits | None = None) -> None:
        self.config = config
        self.robot = robot
        self.safety = safety or SafetyLimits(np.asarray(config.joint_limits, np.float64))
        self.port = PortHandler(config.port)
        self.packet = PacketHandler(2.0)
        self._connected = False
        self.failed_transactions = 0  # bus transactions that were retried (diagnostics)

    # ---- bus primitives (with retries) -----------------------------------------------

    def _retry(self, what: str, call):
        """Runs ``call() -> (value, comm_result, status_error)`` until the bus succeeds."""
        result = None
        for _ in range(self.config.retries + 1):
            try:
                value, result, error = call()
            except OSError as e:  # serial.SerialException: the device went away
                raise CommError(f"{what}: {e}") from e
            if result != COMM_SUCCESS:
                self.failed_transactions += 1
            else:
                if error & 0x7F:
                    raise CommError(f"{what}: {self.packet.getRxPacketError(error)}")
                return value, error
        raise CommError(f"{what}: {self.packet.getTxRxResult(result)} "
                        f"({self.config.retries + 1} attempts)")

    def _write(self, dxl_id: int, name: str, value: int) -> None:
        item = ct.ITEMS[name]
        fn = {1: self.packet.write1ByteTxRx, 2: self.packet.write2ByteTxRx,
              4: self.packet.write4ByteTxRx}[item.size]
        raw = ct.to_unsigned(value, item.size)
        _, error = self._retry(f"write {name} = {value} to ID {dxl_id}",
                               lambda: (None, *fn(self.port, dxl_id, item.address, raw)))
        if error & 0x80:
            self._raise_hardware_error()

    def _read(self, dxl_id: int, name: str) -> int:
        item = ct.ITEMS[name]
        fn = {1: self.packet.read1ByteTxRx, 2: self.packet.read2ByteTxRx,
              4: self.packet.read4ByteTxRx}[item.size]
        raw, _ = self._retry(f"read {name} of ID {dxl_id}",
                             lambda: fn(self.port, dxl_id, item.address))
        return ct.to_signed(raw, item.size) if item.signed else raw

    def _write_all(self, name: str, values) -> None:
        for dxl_id, v in zip(self.config.joint_ids, np.broadcast_to(values, (self.n_joints,))):
            self._write(dxl_id, name, int(v))

    def _sync_read(self, address: int, length: int) -> dict[int, bytes]:
        group = GroupSyncRead(self.port, self.packet, address, length)
        for dxl_id in self.config.joint_ids:
            group.addParam(dxl_id)
        result = None
        for _ in range(self.config.retries + 1):
            try:
                result = group.txRxPacket()
            except OSError as e:
                raise CommError(f"sync read {address}+{length}: {e}") from e
            self.failed_transactions += result != COMM_SUCCESS
            if result == COMM_SUCCESS:
                return {i: bytes(group.data_dict[i]) for i in self.config.joint_ids}
        raise CommError(f"sync read {address}+{length}: {self.packet.getTxRxResult(result)} "
                        f"({self.config.retries + 1} attempts)")

    @property
    def n_joints(self) -> int:
        return len(self.config.joint_ids)

    # ---- lifecycle ---------------------------------------------------------------------

    def connect(self) -> None:
        """Opens the port, pings every servo and checks its model number."""
        if not self.port.openPort() or not self.port.setBaudRate(self.config.baudrate):
            raise CommError(f"cannot open {self.config.port} at {self.config.baudrate} bit/s")
        self._connected = True
        ids = list(self.config.joint_ids)
        if self.config.gripper_id is not None:
            ids.append(self.config.gripper_id)
        for dxl_id in ids:
            model, _ = self._retry(f"ping ID {dxl_id}",
                                   lambda i=dxl_id: self.packet.ping(self.port, i))
            if model != ct.XM430_W350_MODEL:
                raise CommError(f"ID {dxl_id} is model {model}, expected XM430-W350 "
                                f"({ct.XM430_W350_MODEL})")
        try:
            self.check_hardware_errors()
        except HardwareError as e:
            if not self.config.reboot_on_error:
                raise
            for dxl_id in e.errors:
                self.reboot(dxl_id)
            self.check_hardware_errors()

    def reboot(self, dxl_id: int, wait: float = 2.0) -> None:
        """REBOOT one servo (clears Hardware Error Status; torque off) and wait until it
        answers a ping again."""
        self._retry(f"reboot ID {dxl_id}",
                    lambda: (None, *self.packet.reboot(self.port, dxl_id)))
        deadline = time.monotonic() + wait
        while time.monotonic() < deadline:
            if self.packet.ping(self.port, dxl_id)[1] == COMM_SUCCESS:
                return
            time.sleep(0.05)
        raise CommError(f"ID {dxl_id} did not answer within {wait} s of its reboot")

    def configure(self) -> None:
        """Position mode, velocity-based profile, position limits, PD gains, torque on."""
        c = self.config
        self._write_all("torque_enable", 0)  # EEPROM is writable only with the torque off
        self._write_all("operating_mode", 3)  # position control
        self._write_all("drive_mode", 0)  # velocity-based profile, normal direction
        limits = ct.rad_to_ticks(np.asarray(c.joint_limits))
        self._write_all("min_position_limit", limits[:, 0])
        self._write_all("max_position_limit", limits[:, 1])
        self._write_all("pwm_limit", c.pwm_limit)
        self._write_all("position_p_gain", c.p_gain)
        self._write_all("position_i_gain", c.i_gain)
        self._write_all("position_d_gain", c.d_gain)
        self._write_all("profile_velocity",
                        max(1, round(c.profile_velocity / ct.VELOCITY_LSB)))
        self._write_all("profile_acceleration",
                        max(1, round(c.profile_acceleration / ct.ACCELERATION_LSB)))
        self._write_all("torque_enable", 1)

    def close(self) -> None:
        if self._connected:
            self.port.closePort()
            self._connected = False

    def __enter__(self) -> DynamixelArm:
        try:
            self.connect()
            self.configure()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            if exc_type is not None:
                self.stop()
        finally:
            self.close()

    # ---- state and motion --------------------------------------------------------------

    def check_hardware_errors(self) -> None:
        """Raises :class:`HardwareError` if any joint servo has Hardware Error Status set."""
        item = ct.ITEMS["hardware_error_status"]
        data = self._sync_read(item.address, item.size)
        errors = {i: d[0] for i, d in data.items() if d[0]}
        if errors:
            raise HardwareError(errors)

    def _raise_hardware_error(self) -> None:
        self.check_hardware_errors()
        raise HardwareError({})  # alert bit without a readable status

    def read_state(self) -> ArmState:
        address, length = ct.STATE_BLOCK
        data = self._sync_read(address, length)
        t = time.time()

        def field_of(name: str) -> np.ndarray:
            item = ct.ITEMS[name]
            k = item.address - address
            raw = [int.from_bytes(data[i][k:k + item.size], "little")
                   for i in self.config.joint_ids]
            return np.array([ct.to_signed(r, item.size) if item.signed else r for r in raw])

        ticks = field_of("present_position")
        return ArmState(
            q=ct.ticks_to_rad(ticks),
            velocity=field_of("present_velocity") * ct.VELOCITY_LSB,
            current=ct.register_to_current(field_of("present_current")),
            moving=field_of("moving").astype(bool),
            temperature=field_of("present_temperature").astype(np.float64),
            voltage=field_of("present_input_voltage") * ct.VOLTAGE_LSB,
            ticks=ticks, servo_clock=int(field_of("realtime_tick")[0]), timestamp=t)

    def check_goal(self, q_goal: np.ndarray) -> None:
        """Joint limits and workspace (raises :class:`SafetyError`; nothing is sent)."""
        self.safety.check(np.asarray(q_goal, np.float64), self.robot)

    def command(self, q_goal: np.ndarray) -> None:
        """Checks, then writes Goal Position of every joint in one GroupSyncWrite."""
        self.check_goal(q_goal)
        item = ct.ITEMS["goal_position"]
        group = GroupSyncWrite(self.port, self.packet, item.address, item.size)
        for dxl_id, t in zip(self.config.joint_ids, ct.rad_to_ticks(q_goal)):
            group.addParam(dxl_id, ct.to_unsigned(int(t), 4).to_bytes(4, "little"))
        try:
            result = group.txPacket()
        except OSError as e:
            raise CommError(f"sync write goal: {e}") from e
        if result != COMM_SUCCESS:  # a sync write has no reply: only a tx failure shows
            raise CommError(f"sync write goal: {self.packet.getTxRxResult(result)}")

    def wait_until_settled(self) -> tuple[ArmState, bool, float]:
        """Polls until no joint moves and no tick changed for ``settle_time``.

        Times are kept on the servo's own clock (Realtime Tick), so a virtual robot that
        runs faster or slower than real time sees the same protocol. Returns ``(state,
        at_rest, elapsed [s])``; ``at_rest`` is False on ``move_timeout``. Checks Hardware
        Error Status on every poll."""
        c = self.config
        elapsed, still_since = 0.0, 0.0
        last = None
        while True:
            state = self.read_state()
            self.check_hardware_errors()
            if last is not None:
                dt_ms = (state.servo_clock - last.servo_clock) % ct.REALTIME_TICK_WRAP
                elapsed += dt_ms * ct.REALTIME_TICK_S
            if state.moving.any() or last is None or np.any(state.ticks != last.ticks):
                still_since = elapsed
            elif elapsed - still_since >= c.settle_time:
                return state, True, elapsed
            if elapsed > c.move_timeout:
                return state, False, elapsed
            last = state
            time.sleep(c.poll_period)

    def move_and_settle(self, q_goal: np.ndarray) -> tuple[ArmState, bool, float]:
        self.command(q_goal)
        return self.wait_until_settled()

    def stop(self) -> None:
        """Leaves the arm in the configured state; best effort (the bus may be the problem)."""
        # An interrupted transaction (Ctrl-C inside the SDK) leaves the port marked busy.
        self.port.is_using = False
        try:
            if self.config.on_stop == "torque_off":
                self._write_all("torque_enable", 0)
            else:
                state = self.read_state()
                self._hold(state)
        except Exception:  # noqa: BLE001  (keep going: try the stronger measure)
            try:
                self._write_all("torque_enable", 0)
            except Exception:  # noqa: BLE001
                pass

    def _hold(self, state: ArmState) -> None:
        item = ct.ITEMS["goal_position"]
        group = GroupSyncWrite(self.port, self.packet, item.address, item.size)
        for dxl_id, t in zip(self.config.joint_ids, state.ticks):
            group.addParam(dxl_id, ct.to_unsigned(int(t), 4).to_bytes(4, "little"))
        group.txPacket()
