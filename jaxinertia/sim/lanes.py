"""The lane program: many samples on a fixed set of lanes that refill as they finish, as
pure functions on pytrees (no threads, no compilation, no host loop).

``simulate_samples`` vmaps the protocol of one sample over a batch, and a ``vmap`` of a
``while_loop`` runs every lane until the *slowest* sample of the batch has settled (a
sample takes 0.7-1.9 s of simulated time, with a tail). Here a sample is a small state
machine run by a lane::

    phase 0: rest at the pre-position q_d - s delta (hold until at rest, or time out)
    phase 1: profiled move to q_d, hold until at rest (or time out)
    phase 2: done -> its final state is stored at the sample's index; the lane takes the
             next sample of the table (objects mixed freely) or idles when none is left

The program, given the sample :class:`Table` and a :class:`Carry` (lanes, outputs,
counters):

* :func:`prepare` builds the table and the starting carry (every lane idle);
* :func:`refill` stores the lanes that finished and hands them the next samples;
* :func:`steps` advances every lane ``n`` servo periods (:func:`lane_step`; a lane that
  finishes inside the block waits, frozen, for the block's end);
* :func:`compact` moves the carry to fewer lanes (the stream's tail);
* :func:`finish` records every sample (:func:`jaxinertia.sim.sampling.record`) from the
  final states, once after the stream, so that the stepping program carries no statics.

The step-by-step arithmetic is that of :func:`jaxinertia.sim.sampling.simulate_samples`,
with the same per-sample keys, so both give the same samples (tests/test_sim.py checks
it); only the scheduling differs. ``batch_last`` steps the lanes with
:func:`jaxinertia.sim.batched.step_batched` (the same physics, rounded differently; the
same ticks). :mod:`jaxinertia.sim.stream` compiles these functions and runs them.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxinertia.objects import HeldObject
from jaxinertia.sim import batched
from jaxinertia.sim.sampling import Record, jitter_friction, record
from jaxinertia.sim.servo import goal_ticks
from jaxinertia.sim.simulator import SimParams, SimState, physical_params, step, trapezoid

__all__ = ["DELTA", "Carry", "Ended", "Lanes", "Table", "compact", "finish", "lane_step",
           "prepare", "refill", "steps"]

#: Pre-position offset of the protocol [rad]: the OpenMANIPULATOR-X's (the lanes read
#: ``SimParams.pre_position``, which an arm record sets).
DELTA = 3.0 * np.pi / 180.0


@struct.dataclass
class Table:
    """The samples to run (leading axis S_pad) and the objects (leading axis O_pad)."""

    q_d: jnp.ndarray  # (S_pad, N)
    direction: jnp.ndarray  # (S_pad, N)
    key: jax.Array  # (S_pad,) typed keys
    obj_id: jnp.ndarray  # (S_pad,) int
    objects: HeldObject  # leading O_pad
    loaded: SimParams  # physical arm per object (robot leaves with leading O_pad)
    count: jnp.ndarray  # () the real S


@struct.dataclass
class Lanes:
    """Per-lane state (leading axis L)."""

    state: SimState
    robot: object  # the loaded robot of the lane's object
    friction: object  # the lane's jittered friction
    pre: jnp.ndarray  # (L, N)
    q_d: jnp.ndarray
    direction: jnp.ndarray
    obj_id: jnp.ndarray
    idx: jnp.ndarray  # sample index, S_pad when idle
    phase: jnp.ndarray  # 0, 1, 2 (done / idle)
    k: jnp.ndarray  # steps in the phase
    still: jnp.ndarray  # consecutive steps at rest
    ok_pre: jnp.ndarray  # phase 0 ended at rest
    ok: jnp.ndarray  # phase 1 ended at rest
    t_settle: jnp.ndarray  # duration of phase 1 [s]


@struct.dataclass
class Ended:
    """What a finished lane leaves behind (leading axis S_pad); :func:`finish` turns it
    into the recorded :class:`~jaxinertia.sim.sampling.Record` after the stream."""

    state: SimState
    at_rest: jnp.ndarray
    settle_time: jnp.ndarray


@struct.dataclass
class Carry:
    lanes: Lanes
    out: Ended  # leading S_pad
    next: jnp.ndarray  # () next sample of the table to hand out
    done: jnp.ndarray  # () samples recorded


def lane_step(base: SimParams, lane: Lanes, *, batch_last: bool = False) -> Lanes:
    """One servo period (``move_and_settle``'s loop body and condition) of one lane, or of
    all lanes at once when ``batch_last`` (every leaf with the lanes as its last axis,
    stepped by :func:`jaxinertia.sim.batched.step_batched`)."""
    params = base.replace(robot=lane.robot, friction=lane.friction)
    joints = 0 if batch_last else -1  # the joint axis of (N,) or (N, L) arrays
    dt = base.dt
    hold_steps = int(round(base.hold_time / dt))
    max_steps = int(round(base.timeout / dt))
    active = lane.phase < 2
    end = jnp.where(lane.phase == 0, lane.pre, lane.q_d)
    t = lane.k * dt
    q_goal, t_total = trapezoid(lane.pre, end, t, base.profile_velocity,
                                base.profile_acceleration)
    s = (batched.step_batched if batch_last else step)(params, lane.state, goal_ticks(q_goal))
    resting = ((t >= jnp.max(t_total, axis=joints))
               & jnp.all(jnp.abs(s.qd) < base.rest_velocity, axis=joints))
    still = jnp.where(resting, lane.still + 1, 0)
    k = lane.k + 1
    ended = active & ((still >= hold_steps) | (k >= max_steps))
    at_rest = still >= hold_steps
    first = ended & (lane.phase == 0)
    second = ended & (lane.phase == 1)
    keep = lambda new, old: jnp.where(active, new, old)  # noqa: E731
    return lane.replace(
        state=jax.tree.map(keep, s, lane.state),
        phase=lane.phase + ended.astype(lane.phase.dtype),
        k=jnp.where(first, 0, keep(k, lane.k)),
        still=jnp.where(first, 0, keep(still, lane.still)),
        ok_pre=jnp.where(first, at_rest, lane.ok_pre),
        ok=jnp.where(second, at_rest, lane.ok),
        t_settle=jnp.where(second, k * dt, lane.t_settle),
    )


def refill(base: SimParams, table: Table, carry: Carry) -> Carry:
    """Stores the lanes that finished and hands them the next samples."""
    lanes, S_pad = carry.lanes, table.q_d.shape[0]
    finished = (lanes.phase == 2) & (lanes.idx < S_pad)
    ended = Ended(lanes.state, lanes.ok_pre & lanes.ok, lanes.t_settle)
    where = jnp.where(finished, lanes.idx, S_pad)  # S_pad: dropped
    out = jax.tree.map(lambda buf, v: buf.at[where].set(v, mode="drop"), carry.out, ended)

    free = lanes.phase == 2
    new_idx = carry.next + jnp.cumsum(free, dtype=jnp.int32) - 1
    take = free & (new_idx < table.count)
    n_taken = jnp.sum(take, dtype=jnp.int32)
    i = jnp.where(take, new_idx, 0)
    q_d, direction, obj_id = table.q_d[i], table.direction[i], table.obj_id[i]
    key_f = jax.vmap(lambda k: jax.random.split(k)[0])(table.key[i])
    n = q_d.shape[1]
    friction = jax.vmap(lambda kf: jitter_friction(base, kf, n).friction)(key_f)
    robot = jax.tree.map(lambda a: a[obj_id], table.loaded.robot)
    pre = q_d - direction * base.pre_position
    fresh = Lanes(
        state=jax.vmap(SimState.at_rest)(pre), robot=robot, friction=friction, pre=pre,
        q_d=q_d, direction=direction, obj_id=obj_id,
        idx=i, phase=jnp.zeros_like(lanes.phase), k=jnp.zeros_like(lanes.k),
        still=jnp.zeros_like(lanes.still), ok_pre=jnp.zeros_like(lanes.ok_pre),
        ok=jnp.zeros_like(lanes.ok), t_settle=jnp.zeros_like(lanes.t_settle))

    def pick(new, old):
        m = take.reshape(take.shape + (1,) * (new.ndim - 1))
        return jnp.where(m, new, old)

    lanes = jax.tree.map(pick, fresh, lanes)
    lanes = lanes.replace(idx=jnp.where(take, i, jnp.where(free, S_pad, lanes.idx)))
    return Carry(lanes, out, carry.next + n_taken, carry.done + jnp.sum(finished, dtype=jnp.int32))


def steps(base: SimParams, lanes: Lanes, *, n: int, batch_last: bool) -> Lanes:
    """``n`` servo periods of every lane (none when no lane is running), batch-last
    (:mod:`jaxinertia.sim.batched`) or by ``vmap`` of the one-arm step."""
    if batch_last:
        def run(ln):
            return batched.batch_first(jax.lax.fori_loop(
                0, n, lambda _, x: lane_step(base, x, batch_last=True),
                batched.batch_last(ln)))
    else:
        def run(ln):
            return jax.lax.fori_loop(
                0, n, lambda _, x: jax.vmap(lane_step, (None, 0))(base, x), ln)
    return jax.lax.cond(jnp.any(lanes.phase < 2), run, lambda ln: ln, lanes)


def finish(params: SimParams, table: Table, ended: Ended) -> Record:
    """The records of every sample (:func:`record`: what the servos and the statics
    report) from the final states; the current noise uses the second half of the
    sample's key, as :func:`jaxinertia.sim.sampling.simulate_samples` does."""

    def one(q_d, direction, key, obj_id, state, at_rest, settle_time):
        obj = jax.tree.map(lambda a: a[obj_id], table.objects)
        return record(params, params.robot, obj, q_d, direction, state,
                      jax.random.split(key)[1], at_rest=at_rest, settle_time=settle_time)

    return jax.vmap(one)(table.q_d, table.direction, table.key, table.obj_id, ended.state,
                         ended.at_rest, ended.settle_time)


def prepare(params: SimParams, q_d, direction, obj_id, objects: HeldObject, keys,
            *, sizes: tuple[int, ...], lanes: int) -> tuple[Table, Carry]:
    """The sample table (per-sample keys, the loaded arm of every object) and the starting
    carry (every lane idle: phase 2, index S_pad; empty outputs).

    ``q_d``, ``direction`` (S_pad, N) and ``obj_id`` (S_pad,) are padded; ``keys`` (S,)
    holds one key per real sample (padded here with the last); ``sizes`` are the plans'
    sample counts (their sum is S)."""
    S_pad, n = q_d.shape
    pad = S_pad - keys.shape[0]
    keys = jnp.concatenate([keys, jnp.repeat(keys[-1:], pad, 0)])
    loaded = jax.vmap(physical_params, (None, 0))(params, objects)
    count = jnp.asarray(sum(sizes), jnp.int32)
    table = Table(q_d, direction, keys, obj_id, objects, loaded, count)
    dtype = q_d.dtype
    zeros = jnp.zeros((lanes, n), dtype)
    lane0 = Lanes(
        state=jax.vmap(SimState.at_rest)(zeros),
        robot=jax.tree.map(lambda a: jnp.broadcast_to(a[0], (lanes,) + a.shape[1:]),
                           loaded.robot),
        friction=jax.tree.map(lambda a: jnp.broadcast_to(a, (lanes,) + a.shape),
                              params.friction),
        pre=zeros, q_d=zeros, direction=zeros,
        obj_id=jnp.zeros(lanes, jnp.int32), idx=jnp.full(lanes, S_pad, jnp.int32),
        phase=jnp.full(lanes, 2, jnp.int32), k=jnp.zeros(lanes, jnp.int32),
        still=jnp.zeros(lanes, jnp.int32), ok_pre=jnp.zeros(lanes, bool),
        ok=jnp.zeros(lanes, bool), t_settle=jnp.zeros(lanes, dtype))
    out = Ended(jax.vmap(SimState.at_rest)(jnp.zeros((S_pad, n), dtype)),
                jnp.zeros(S_pad, bool), jnp.zeros(S_pad, dtype))
    return table, Carry(lane0, out, jnp.asarray(0, jnp.int32), jnp.asarray(0, jnp.int32))


def compact(carry: Carry, *, size: int) -> Carry:
    """The carry on ``size`` lanes: the occupied ones first (every occupied lane is kept
    when at most ``size`` are occupied), then idle ones."""
    S_pad = carry.out.at_rest.shape[0]
    order = jnp.argsort(carry.lanes.idx >= S_pad, stable=True)[:size]
    return carry.replace(lanes=jax.tree.map(lambda a: a[order], carry.lanes))
