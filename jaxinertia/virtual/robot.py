"""The virtual robot: a :class:`jaxinertia.virtual.bus.ServoBus` whose joint servos are the
simulated arm (:mod:`jaxinertia.virtual.physics`), the simulator running in a **process of
its own**.

:class:`VirtualServoBus` keeps the servos' control tables in a shared buffer and shares
their lock with the physics process (``spawn``: JAX does not survive a fork); goals and
holds go to it through a pipe, in order. The bus thread never waits on the physics:

* every program the physics runs is compiled before the bus opens
  (:meth:`VirtualServoBus.compile` returns when the physics process has compiled both
  paths, torque on and off, with the argument types it will use);
* the physics holds the shared lock only to copy registers and to publish a finished
  chunk, never while computing, and between publications the bus answers from the last
  published state;
* being another process, the physics never holds the bus's interpreter: a physics
  thread that a busy host preempts while it holds the GIL would stall every reply for a
  scheduler period, past the master's ~35 ms timeout.

The physics process ends with the bus (:meth:`VirtualServoBus.close`), and by itself when
the bus's process is gone.
"""

from __future__ import annotations

import ctypes
import multiprocessing as mp
import os
import time
from collections.abc import Sequence

import jax
import numpy as np

from jaxinertia.errors import SimulationError, UsageError
from jaxinertia.objects import HeldObject
from jaxinertia.open_manipulator_x import GRIPPER_ID, JOINT_IDS
from jaxinertia.servos import ServoModel
from jaxinertia.sim.servo import ServoParams
from jaxinertia.sim.simulator import SimParams, physical_params
from jaxinertia.virtual.bus import TABLE_SIZE, Faults, ServoBus
from jaxinertia.virtual.physics import (
    DxlRegisterMap,
    PhysicsSpec,
    gain_scale,
    loop_ratios,
    physics_main,
    servo_from_registers,
)

__all__ = ["STARTUP_TIMEOUT_S", "VirtualServoBus"]

#: How long the bus waits for the physics process to start and compile [s] (generous: an
#: interpreter starts and the physics compiles, on a host that may be busy).
STARTUP_TIMEOUT_S = 900.0


def _reading_lsb(model: ServoModel) -> float:
    """The motor current [A] of one LSB of address 126: Present Current's unit, or for a
    servo without a current sensor Present Load's (0.1 % of the maximum torque, the stall
    current's share)."""
    return model.sensed_lsb if model.has_current_sensor else (model.sensed_lsb
                                                               * model.stall_current)


class VirtualServoBus(ServoBus):
    """Servos ``ids`` (one per joint of ``params.robot``, then optional extra servos such as
    a gripper, which answer but do not move) on a pty, driven by the simulator in a
    process of its own (started by :meth:`compile`, or on entry).

    ``servo_models``: the :class:`jaxinertia.servos.ServoModel` of each servo, joints then
    extras (default: XM430-W350s): each answers with its model number and control table,
    and its joint's motor current is published in its unit (Present Current, or Present
    Load where it has no current sensor). ``gain_registers``: the P register each joint's
    simulated gain belongs to (default: the XM430's 800, the calibrated arm's).

    The servos' protocol is the bus class's (this one: DYNAMIXEL Protocol 2.0; a subclass
    that also derives from another protocol's bus, such as
    :class:`jaxinertia.virtual.sts_robot.VirtualStsBus`, speaks that one), their tables
    as the physics reads and writes them ``register_map``'s."""

    register_map = DxlRegisterMap

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
        servo_models: Sequence[ServoModel] | None = None,
        gain_registers: Sequence[float] | None = None,
    ) -> None:
        n = len(ids)
        if n != params.robot.n_joints:
            raise UsageError(f"{n} servo ids for {params.robot.n_joints} joints")
        models = None if servo_models is None else tuple(servo_models)
        if models is not None and len(models) != n + len(extra_ids):
            raise UsageError(f"{len(models)} servo models for {n + len(extra_ids)} servos")
        ctx = mp.get_context("spawn")  # JAX does not survive a fork
        n_servos = n + len(extra_ids)
        self._shared_tables = ctx.RawArray(ctypes.c_uint8, n_servos * TABLE_SIZE)
        self._shared_goal_writes = ctx.RawArray(ctypes.c_int64, n)
        super().__init__(ids, extra_ids, faults=faults, temperature=ambient_temperature,
                         input_voltage=float(params.servo.supply_voltage[0]),
                         tables=self._shared_tables, lock=ctx.Lock(),
                         models=None if models is None else tuple(m.model_number
                                                                  for m in models))
        if models is not None:  # each servo at its own model's supply (XL330: 5 V)
            for i, m in zip(self.servos, models):
                self._set_supply(self.servos[i], m.supply_voltage)
        self._ctx = ctx
        self._base_servo = params.servo
        joints = models[:n] if models is not None else None
        ratios = None if joints is None else tuple(map(tuple, loop_ratios(joints)))
        self._gain_scale = gain_scale(params.servo, gain_registers, ratios)
        q0 = np.zeros(n) if q0 is None else np.asarray(q0, np.float64)
        self._spec = PhysicsSpec(jax.tree.map(np.asarray, physical_params(params, obj)),
                                 tuple(ids), q0, int(chunk), int(seed), float(speed),
                                 jax.config.jax_compilation_cache_dir,
                                 jax.config.jax_compilation_cache_max_size,
                                 models=None if joints is None else tuple(
                                     m.model_number for m in joints),
                                 reading_lsb=None if joints is None else tuple(
                                     _reading_lsb(m) for m in joints),
                                 gain_registers=None if gain_registers is None else tuple(
                                     float(g) for g in gain_registers),
                                 loop_ratios=ratios, register_map=self.register_map)
        self.speed = float(speed)
        self._events_in, self._events_out = ctx.Pipe(duplex=False)
        self._ready, self._physics_stop = ctx.Event(), ctx.Event()
        self._process = None

    # ---- lifecycle -------------------------------------------------------------------

    def compile(self) -> None:
        """Starts the physics process and returns once it has compiled every path (so no
        reply ever waits on a compilation)."""
        if self._process is not None:
            return
        self._process = self._ctx.Process(
            target=physics_main, name="dxl-physics", daemon=True,
            args=(self._spec, self._shared_tables, self._shared_goal_writes, self._lock,
                  self._events_in, self._ready, self._physics_stop, os.getpid()))
        self._process.start()
        deadline = time.monotonic() + STARTUP_TIMEOUT_S
        while not self._ready.wait(0.2):
            if not self._process.is_alive() or time.monotonic() > deadline:
                code = self._process.exitcode
                self.close()
                raise SimulationError(f"the virtual robot's physics did not start (exit code "
                                      f"{code}; see its messages above)")

    def start(self) -> None:
        self.compile()
        super().start()

    def stop(self) -> None:
        super().stop()
        self._physics_stop.set()

    def close(self) -> None:
        self.stop()
        super().close()
        if self._process is not None:
            self._process.join(timeout=10)
            if self._process.is_alive():
                self._process.kill()
                self._process.join(timeout=10)
        self._events_out.close()
        self._events_in.close()

    def wait(self) -> None:
        """Blocks until closed, or the bus thread or the physics process failed."""
        while not self._stop.wait(0.2):
            if self._process is not None and not self._process.is_alive():
                self.error = SimulationError(f"the virtual robot's physics exited (code "
                                             f"{self._process.exitcode})")
                self.stop()
        if self.error is not None:
            raise self.error

    def __enter__(self) -> VirtualServoBus:
        self.start()
        return self

    # ---- the bus's news about the joints (under the lock) ------------------------------

    def _goal_changed(self, j: int, q_goal: float) -> None:
        self._events_out.send(("goal", j, q_goal))
        self._shared_goal_writes[j] += 1
        # Moving from now on, until a chunk that simulates this goal is published.
        self._mark_moving(self.servos[self.joint_ids[j]])

    def _held(self, j: int, q: float) -> None:
        self._events_out.send(("hold", j, q))

    def _servo_params(self) -> ServoParams:
        """ServoParams from the registers of the joint servos (under the lock)."""
        registers = self.register_map.registers([self.servos[i] for i in self.joint_ids])
        return servo_from_registers(self._base_servo, self._gain_scale, registers)
