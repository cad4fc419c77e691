"""An arm on DYNAMIXEL X servos (the OpenMANIPULATOR-X's XM430-W350-T; the Koch v1.1's
XL430-W250-T and XL330-M288-T), through dynamixel-sdk (Protocol 2.0).

Everything this class returns is SI (rad, A, N m, V, degC, s); ticks and register LSBs
exist only inside it (``control_table``). Each servo is read per its model
(``ArmConfig.servo_models``): it must ping with that model number, and address 126 is
Present Current in its unit (2.69 mA on the XM430, 1 mA on the XL330) or, on the XL430,
Present Load (0.1 %): that joint's ``ArmState.current`` is then NaN (no current sensor;
``load`` holds the reading) and so is its current-based torque (:attr:`torque_constants`).

A move follows the paper's protocol one goal at a time:
:meth:`DynamixelArm.move_and_settle` commands the goal (GroupSyncWrite), then polls
(GroupSyncRead) until no servo reports Moving and no Present Position tick changed for
``settle_time``. Every goal is checked against joint limits and a workspace box first, and
the servos' own Min/Max Position Limit registers are set to the same joint limits.

A hardware error (Hardware Error Status or the alert bit), a bus failure that outlasts
``retries``, a timeout or Ctrl-C leaves the arm in the state ``on_stop`` names: ``hold``
(goal = present position, torque on) or ``torque_off``.

The bus is :mod:`jaxinertia.hardware.transport`: the port is locked while open, every
status packet is matched to its request (late ones are discarded), and the bus is drained
before a failed transaction is retried. A Hardware Error Status reading, or an alert bit,
is confirmed by reading register 70 of each servo concerned on its own before
:class:`ServoHardwareError` tells the user to power-cycle; an unconfirmed one is counted
(``unconfirmed_alarms``) and the collection goes on. A device that cannot be opened, is
locked by another program or disappears (``OSError``, pyserial's ``SerialException``,
``termios.error``) is a :class:`CommError` (:class:`PortError` when opening).

One module, one class, whose bus primitives, lifecycle and motion share the port, the
retry policy and the bus diagnostics; its configuration, readings and errors are
:mod:`jaxinertia.hardware.driver_config` (re-exported here).
"""

from __future__ import annotations

import itertools
import os
import time

import numpy as np
from dynamixel_sdk import COMM_SUCCESS, GroupSyncRead, GroupSyncWrite

from jaxinertia import errors
from jaxinertia.hardware import control_table as ct
from jaxinertia.hardware.driver_config import (
    BUS_ERRORS,
    ArmConfig,
    ArmState,
    CommError,
    PortError,
    ServoHardwareError,
)
from jaxinertia.hardware.safety import SafetyLimits
from jaxinertia.hardware.transport import (
    LockedPortHandler,
    MatchingPacketHandler,
    PortInUse,
    drain,
)
from jaxinertia.robot import Robot
from jaxinertia.servos import ServoModel, servo_model

__all__ = ["ArmConfig", "ArmState", "CommError", "DynamixelArm", "PortError",
           "ServoHardwareError"]


class DynamixelArm:
    """The joint servos of one arm. Use as a context manager: ``connect`` and ``configure``
    on entry; on exit (also on an exception or Ctrl-C) :meth:`stop`, then the port closes."""

    #: What another servo family's driver (hardware.feetech) changes.
    sync_read_class = GroupSyncRead
    refused_bits = 0x7F
    error_register = "hardware_error_status"
    hardware_error = ServoHardwareError

    def __init__(self, config: ArmConfig, *, robot: Robot | None = None,
                 safety: SafetyLimits | None = None) -> None:
        self.config = config
        self.robot = robot
        if safety is None and config.joint_limits is None:
            raise errors.UsageError("ArmConfig without joint_limits needs SafetyLimits "
                                    "(hardware.arm_config gives an arm's)")
        self.safety = safety or SafetyLimits(np.asarray(config.joint_limits, np.float64))
        #: What the servos' own Min/Max Position Limit registers are set to.
        self.joint_limits = np.asarray(self.safety.joint_limits if config.joint_limits is None
                                       else config.joint_limits, np.float64)
        self.port = LockedPortHandler(config.port)
        self.packet = MatchingPacketHandler()
        self.servo_of = self._servo_models(config)
        self._connected = False
        # Diagnostics: bus transactions that were retried, hardware-error readings that
        # register 70 did not confirm, state readings older than the last one (discarded).
        self.failed_transactions = 0
        self.most_attempts = 0  # of one successful transaction
        self.unconfirmed_alarms = 0
        self.stale_readings = 0

    @staticmethod
    def _servo_models(c: ArmConfig) -> dict[int, ServoModel]:
        """The servo model of each bus ID (joints, then the gripper)."""
        names = tuple(c.servo_models)
        if len(names) != len(c.joint_ids):
            if len(set(names)) != 1:
                raise errors.UsageError(f"{len(names)} servo models for {len(c.joint_ids)} "
                                        "joints")
            names = names[:1] * len(c.joint_ids)
        out = {i: servo_model(n) for i, n in zip(c.joint_ids, names)}
        if c.gripper_id is not None:
            out[c.gripper_id] = servo_model(c.gripper_model or names[0])
        return out

    @property
    def torque_constants(self) -> np.ndarray:
        """(N,) output torque per motor current of each joint's servo [N m/A] (the
        datasheet's stall point; NaN where the servo senses no current)."""
        return np.array([m.torque_constant if m.has_current_sensor else np.nan
                         for m in (self.servo_of[i] for i in self.config.joint_ids)])

    def _items(self, dxl_id: int) -> dict[str, ct.Item]:
        """The control table of servo ``dxl_id``'s model."""
        return ct.items_of(self.servo_of[dxl_id].model_number)

    def bus_report(self) -> str:
        """One line of bus diagnostics (starts with the number of retried transactions)."""
        return (f"{self.failed_transactions} failed transactions retried (at most "
                f"{self.most_attempts} attempts of `retries` + 1 = {self.config.retries + 1} "
                f"for one), {self.packet.stale_packets} late status packets discarded, "
                f"{self.unconfirmed_alarms} unconfirmed hardware-error readings, "
                f"{self.stale_readings} late readings skipped")

    def _drain(self) -> None:
        try:
            drain(self.port)
        except BUS_ERRORS as e:
            raise CommError(f"{self.config.port}: {e}") from e

    def _failed(self) -> None:
        """A transaction failed: count it and let late answers to it arrive and go."""
        self.failed_transactions += 1
        self._drain()

    # ---- bus primitives (with retries) -----------------------------------------------

    def _retry(self, what: str, call):
        """Runs ``call() -> (value, comm_result, status_error)`` until the bus succeeds."""
        result = None
        for attempt in range(1, self.config.retries + 2):
            try:
                value, result, error = call()
            except BUS_ERRORS as e:  # the device went away
                raise CommError(f"{what}: {e}") from e
            if result != COMM_SUCCESS:
                self._failed()
            else:
                self.most_attempts = max(self.most_attempts, attempt)
                if attempt > 1:
                    # What answered may have been the late answer to a failed attempt: the
                    # retry's own answer can still be on its way. Let it arrive and go, so
                    # that no later request of this servo and length takes it for its own.
                    self._drain()
                if error & self.refused_bits:
                    raise CommError(f"{what}: {self.packet.getRxPacketError(error)}")
                return value, error
        raise CommError(f"{what}: {self.packet.getTxRxResult(result)} "
                        f"({self.config.retries + 1} attempts)")

    def _write(self, dxl_id: int, name: str, value: int) -> None:
        item = self._items(dxl_id)[name]
        fn = {1: self.packet.write1ByteTxRx, 2: self.packet.write2ByteTxRx,
              4: self.packet.write4ByteTxRx}[item.size]
        raw = ct.to_unsigned(value, item.size)
        _, error = self._retry(f"write {name} = {value} to ID {dxl_id}",
                               lambda: (None, *fn(self.port, dxl_id, item.address, raw)))
        if error & 0x80:  # the alert bit: confirmed (or not) by register 70
            self._confirm_hardware_errors({*self.config.joint_ids, dxl_id})

    def _read(self, dxl_id: int, name: str) -> int:
        item = self._items(dxl_id)[name]
        fn = {1: self.packet.read1ByteTxRx, 2: self.packet.read2ByteTxRx,
              4: self.packet.read4ByteTxRx}[item.size]
        raw, _ = self._retry(f"read {name} of ID {dxl_id}",
                             lambda: fn(self.port, dxl_id, item.address))
        return ct.to_signed(raw, item.size) if item.signed else raw

    def _write_all(self, name: str, values) -> None:
        for dxl_id, v in zip(self.config.joint_ids, np.broadcast_to(values, (self.n_joints,))):
            self._write(dxl_id, name, int(v))

    def _sync_read(self, address: int, length: int) -> dict[int, bytes]:
        group = self.sync_read_class(self.port, self.packet, address, length)
        for dxl_id in self.config.joint_ids:
            group.addParam(dxl_id)
        self._retry(f"sync read {address}+{length}", lambda: (None, group.txRxPacket(), 0))
        return {i: bytes(group.data_dict[i]) for i in self.config.joint_ids}

    @property
    def n_joints(self) -> int:
        return len(self.config.joint_ids)

    # ---- lifecycle ---------------------------------------------------------------------

    def open(self) -> None:
        """Opens and locks the port (:class:`PortError` when it cannot be had)."""
        if self._connected:
            return
        c = self.config
        try:
            ok = self.port.setBaudRate(c.baudrate)  # opens the device
        except PortInUse as e:
            raise PortError(e.strerror) from None
        except BUS_ERRORS as e:
            why = os.strerror(e.errno) if getattr(e, "errno", None) else str(e)
            raise PortError(f"cannot open {c.port}: {why}") from None
        if not ok:
            raise PortError(f"cannot open {c.port}: {c.baudrate} bit/s is not a supported "
                            "baud rate")
        self._connected = True

    def connect(self) -> None:
        """Opens the port, pings every servo and checks its model number."""
        self.open()
        ids = list(self.config.joint_ids)
        if self.config.gripper_id is not None:
            ids.append(self.config.gripper_id)
        for dxl_id in ids:
            model, _ = self._retry(f"ping ID {dxl_id}",
                                   lambda i=dxl_id: self.packet.ping(self.port, i))
            want = self.servo_of[dxl_id]
            if model != want.model_number:
                raise CommError(f"ID {dxl_id} is model {model}, expected {want.name} "
                                f"({want.model_number})")
        try:
            self.check_hardware_errors()
        except ServoHardwareError as e:
            if not self.config.reboot_on_error:
                raise
            for dxl_id in e.errors:
                self.reboot(dxl_id)
            self.check_hardware_errors()

    def reboot(self, dxl_id: int, wait: float = 2.0) -> None:
        """REBOOT one servo (clears Hardware Error Status; torque off) and wait until it
        answers a ping again (``wait`` seconds, and at least ``retries + 1`` pings)."""
        self._retry(f"reboot ID {dxl_id}",
                    lambda: (None, *self.packet.reboot(self.port, dxl_id)))
        deadline = time.monotonic() + wait
        for attempt in itertools.count():
            if time.monotonic() >= deadline and attempt > self.config.retries:
                break
            try:
                if self.packet.ping(self.port, dxl_id)[1] == COMM_SUCCESS:
                    return
            except BUS_ERRORS as e:
                raise CommError(f"ping ID {dxl_id}: {e}") from e
            time.sleep(0.05)
        raise CommError(f"ID {dxl_id} did not answer {attempt} pings within {wait} s of its "
                        "reboot")

    def configure(self) -> None:
        """Position mode, velocity-based profile, position limits, PD gains, torque on."""
        c = self.config
        self._write_all("torque_enable", 0)  # EEPROM is writable only with the torque off
        self._write_all("operating_mode", 3)  # position control
        self._write_all("drive_mode", 0)  # velocity-based profile, normal direction
        limits = ct.rad_to_ticks(self.joint_limits)
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
            self._connected = False
            try:
                self.port.closePort()
            except BUS_ERRORS:
                pass  # the device is gone already

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
        """Raises :class:`ServoHardwareError` if any joint servo has Hardware Error Status set
        (a nonzero reading is confirmed first: :meth:`_confirm_hardware_errors`)."""
        item = ct.ITEMS["hardware_error_status"]
        data = self._sync_read(item.address, item.size)
        suspects = [i for i, d in data.items() if d[0]]
        if suspects:
            self._confirm_hardware_errors(suspects)

    def _confirm_hardware_errors(self, ids) -> None:
        """Reads Hardware Error Status (70) of each servo in ``ids`` on its own, on a
        drained bus: raises :class:`ServoHardwareError` for those where it is set (the register
        latches until a reboot, so a real error reads the same again); otherwise the
        reading or alert bit was not the servos' and is counted in ``unconfirmed_alarms``."""
        self._drain()
        confirmed = {}
        for dxl_id in sorted(ids):
            value = self._read(dxl_id, self.error_register)
            if value:
                confirmed[dxl_id] = value
        if confirmed:
            raise self.hardware_error(confirmed)
        self.unconfirmed_alarms += 1

    def read_state(self) -> ArmState:
        address, length = ct.STATE_BLOCK
        data = self._sync_read(address, length)
        t = time.time()

        def field_of(name: str) -> np.ndarray:
            item = ct.ITEMS[name]  # (the same address on every X servo)
            k = item.address - address
            raw = [int.from_bytes(data[i][k:k + item.size], "little")
                   for i in self.config.joint_ids]
            return np.array([ct.to_signed(r, item.size) if item.signed else r for r in raw])

        # Address 126: Present Current in the servo's unit, or Present Load (XL430).
        models = [self.servo_of[i] for i in self.config.joint_ids]
        sensed = field_of("present_current").astype(np.float64)
        has_current = np.array([m.has_current_sensor for m in models])
        lsb = np.array([m.sensed_lsb for m in models])
        ticks = field_of("present_position")
        return ArmState(
            q=ct.ticks_to_rad(ticks),
            velocity=field_of("present_velocity") * ct.VELOCITY_LSB,
            current=np.where(has_current, ct.register_to_current(sensed, lsb), np.nan),
            moving=field_of("moving").astype(bool),
            temperature=field_of("present_temperature").astype(np.float64),
            voltage=field_of("present_input_voltage") * ct.VOLTAGE_LSB,
            ticks=ticks, servo_clock=int(field_of("realtime_tick")[0]), timestamp=t,
            load=np.where(has_current, np.nan, sensed * lsb))

    def check_goal(self, q_goal: np.ndarray) -> None:
        """Joint limits and workspace (raises :class:`SafetyError`; nothing is sent)."""
        self.safety.check(np.asarray(q_goal, np.float64), self.robot)

    def command(self, q_goal: np.ndarray) -> None:
        """Checks, then writes Goal Position of every joint in one GroupSyncWrite."""
        self.check_goal(q_goal)
        self._write_goals(ct.rad_to_ticks(q_goal))

    def _goal_group(self, ticks) -> GroupSyncWrite:
        item = ct.ITEMS["goal_position"]
        group = GroupSyncWrite(self.port, self.packet, item.address, item.size)
        for dxl_id, t in zip(self.config.joint_ids, ticks):
            group.addParam(dxl_id, ct.to_unsigned(int(t), 4).to_bytes(4, "little"))
        return group

    def _write_goals(self, ticks) -> None:
        """Goal Position ``ticks`` (N,): one sync write (no reply; only a tx failure shows)."""
        try:
            result = self._goal_group(ticks).txPacket()
        except BUS_ERRORS as e:
            raise CommError(f"sync write goal: {e}") from e
        if result != COMM_SUCCESS:
            raise CommError(f"sync write goal: {self.packet.getTxRxResult(result)}")

    def wait_until_settled(self) -> tuple[ArmState, bool, float]:
        """Polls until no joint moves and no tick changed for ``settle_time``.

        Times are kept on the servo's own clock (Realtime Tick), so a virtual robot that
        runs faster or slower than real time sees the same protocol; ``elapsed`` is the
        time the arm was watched: a gap between two readings (a bus that did not answer
        for a while) counts at most ``max_reading_gap``, so a stretch of bus retries never
        times a move out by itself. Returns ``(state, at_rest, elapsed [s])``;
        ``at_rest`` is False on ``move_timeout``. Checks Hardware Error Status on every
        poll."""
        c = self.config
        elapsed, still_since = 0.0, 0.0
        last = None
        while True:
            state = self.read_state()
            self.check_hardware_errors()
            moved = last is None or np.any(state.ticks != last.ticks)
            if last is not None:
                dt_ms = (state.servo_clock - last.servo_clock) % ct.REALTIME_TICK_WRAP
                if dt_ms > ct.REALTIME_TICK_WRAP // 2:  # the clock went back: a late reading
                    self.stale_readings += 1
                    dt_ms, moved = 0, True  # no time watched; stillness starts again
                elapsed += min(dt_ms * ct.REALTIME_TICK_S, c.max_reading_gap)
            if state.moving.any() or moved:
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
        self._write_goals(state.ticks)  # (a failure: stop() turns the torque off)
