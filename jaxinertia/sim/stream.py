"""Many samples on a fixed set of lanes that refill as they finish: one compiled program.

``simulate_samples`` vmaps the protocol of one sample over a batch, and a ``vmap`` of a
``while_loop`` runs every lane until the *slowest* sample of the batch has settled (a
sample takes 0.7-1.9 s of simulated time, with a tail), and a small batch (a 1,000-sample
test object) leaves a GPU mostly idle. Here a sample is a small state machine run by a
lane::

    phase 0: rest at the pre-position q_d - s delta (hold until at rest, or time out)
    phase 1: profiled move to q_d, hold until at rest (or time out)
    phase 2: done -> recorded into the output at the sample's index; the lane takes the
             next sample of the table (objects mixed freely) or idles when none is left

Lanes step together in blocks of ``refill_every`` servo periods; a lane that finishes
inside a block waits (frozen) for the block's end. The step-by-step arithmetic is that of
:func:`jaxinertia.sim.sampling.simulate_samples`, with the same per-sample keys, so both
give the same samples (tests/test_sim.py checks it); only the scheduling differs. The
table is padded to a power of two and the objects to a multiple of four, so plans of
different sizes share the stepping program per lane count (only the small preparation,
:func:`_prepare`, is compiled per set of plan sizes).

The host loop advances ``blocks_per_call`` blocks per jitted call (buffers donated) and
updates the progress bar from the count of recorded samples.
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from tqdm.auto import tqdm

from jaxinertia.sim.sampling import HeldObject, Samples, jitter_friction, loaded_params, record
from jaxinertia.sim.servo import goal_ticks
from jaxinertia.sim.simulator import SimParams, SimState, step, trapezoid

__all__ = ["Plan", "default_lanes", "stream_plans"]

#: Pre-position offset of the protocol [rad] (``simulate_samples``' default ``delta``).
DELTA = 3.0 * np.pi / 180.0


class Plan(NamedTuple):
    """One object's samples: goals and directions (S, N) and the key split per sample."""

    obj: HeldObject
    q_d: np.ndarray
    direction: np.ndarray
    key: jax.Array


def default_lanes() -> int:
    """Lanes: a few hundred on a CPU (its throughput is flat beyond that, and fewer lanes
    shorten the tail); tens of thousands on an accelerator."""
    return 256 if jax.default_backend() == "cpu" else 16384


@struct.dataclass
class _Table:
    """The samples to run (leading axis S_pad) and the objects (leading axis O_pad)."""

    q_d: jnp.ndarray  # (S_pad, N)
    direction: jnp.ndarray  # (S_pad, N)
    key: jax.Array  # (S_pad,) typed keys
    obj_id: jnp.ndarray  # (S_pad,) int
    objects: HeldObject  # leading O_pad
    loaded: SimParams  # physical arm per object (robot leaves with leading O_pad)
    count: jnp.ndarray  # () the real S


@struct.dataclass
class _Lanes:
    """Per-lane state (leading axis L)."""

    state: SimState
    robot: object  # the loaded robot of the lane's object
    friction: object  # the lane's jittered friction
    pre: jnp.ndarray  # (L, N)
    q_d: jnp.ndarray
    direction: jnp.ndarray
    key: jax.Array  # record key
    obj_id: jnp.ndarray
    idx: jnp.ndarray  # sample index, S_pad when idle
    phase: jnp.ndarray  # 0, 1, 2 (done / idle)
    k: jnp.ndarray  # steps in the phase
    still: jnp.ndarray  # consecutive steps at rest
    ok_pre: jnp.ndarray  # phase 0 ended at rest
    ok: jnp.ndarray  # phase 1 ended at rest
    t_settle: jnp.ndarray  # duration of phase 1 [s]


@struct.dataclass
class _Carry:
    lanes: _Lanes
    out: Samples  # leading S_pad
    next: jnp.ndarray  # () next sample of the table to hand out
    done: jnp.ndarray  # () samples recorded


def _lane_step(base: SimParams, lane: _Lanes) -> _Lanes:
    """One servo period of one lane (``move_and_settle``'s loop body and condition)."""
    params = base.replace(robot=lane.robot, friction=lane.friction)
    dt = base.dt
    hold_steps = int(round(base.hold_time / dt))
    max_steps = int(round(base.timeout / dt))
    active = lane.phase < 2
    end = jnp.where(lane.phase == 0, lane.pre, lane.q_d)
    t = lane.k * dt
    q_goal, t_total = trapezoid(lane.pre, end, t, base.profile_velocity,
                                base.profile_acceleration)
    s = step(params, lane.state, goal_ticks(q_goal))
    resting = (t >= jnp.max(t_total)) & jnp.all(jnp.abs(s.qd) < base.rest_velocity)
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


def _refill(base: SimParams, bare, table: _Table, carry: _Carry) -> _Carry:
    """Records the lanes that finished and hands them the next samples."""
    lanes, S_pad = carry.lanes, table.q_d.shape[0]
    finished = (lanes.phase == 2) & (lanes.idx < S_pad)

    def rec(lane):
        params = base.replace(robot=lane.robot, friction=lane.friction)
        obj = jax.tree.map(lambda a: a[lane.obj_id], table.objects)
        return record(params, bare, obj, lane.q_d, lane.direction, lane.state, lane.key,
                      at_rest=lane.ok_pre & lane.ok, settle_time=lane.t_settle)

    r = jax.vmap(rec)(lanes)
    where = jnp.where(finished, lanes.idx, S_pad)  # S_pad: dropped
    out = jax.tree.map(lambda buf, v: buf.at[where].set(v, mode="drop"), carry.out, r)

    free = lanes.phase == 2
    new_idx = carry.next + jnp.cumsum(free, dtype=jnp.int32) - 1
    take = free & (new_idx < table.count)
    n_taken = jnp.sum(take, dtype=jnp.int32)
    i = jnp.where(take, new_idx, 0)
    q_d, direction, obj_id = table.q_d[i], table.direction[i], table.obj_id[i]
    key_f, key_r = jax.vmap(jax.random.split, out_axes=1)(table.key[i])
    n = q_d.shape[1]
    friction = jax.vmap(lambda kf: jitter_friction(base, kf, n).friction)(key_f)
    robot = jax.tree.map(lambda a: a[obj_id], table.loaded.robot)
    pre = q_d - direction * DELTA
    fresh = _Lanes(
        state=jax.vmap(SimState.at_rest)(pre), robot=robot, friction=friction, pre=pre,
        q_d=q_d, direction=direction, key=key_r, obj_id=obj_id,
        idx=i, phase=jnp.zeros_like(lanes.phase), k=jnp.zeros_like(lanes.k),
        still=jnp.zeros_like(lanes.still), ok_pre=jnp.zeros_like(lanes.ok_pre),
        ok=jnp.zeros_like(lanes.ok), t_settle=jnp.zeros_like(lanes.t_settle))

    def pick(new, old):
        m = take.reshape(take.shape + (1,) * (new.ndim - 1))
        return jnp.where(m, new, old)

    lanes = jax.tree.map(pick, fresh, lanes)
    lanes = lanes.replace(idx=jnp.where(take, i, jnp.where(free, S_pad, lanes.idx)))
    return _Carry(lanes, out, carry.next + n_taken, carry.done + jnp.sum(finished, dtype=jnp.int32))


def _advance(base: SimParams, bare, table: _Table, carry: _Carry, *, refill_every: int,
             blocks: int) -> _Carry:
    """Up to ``blocks`` blocks, each a refill (record the lanes that finished, hand out new
    samples) and ``refill_every`` steps; stops early once every sample is recorded."""

    def block(c: _Carry) -> _Carry:
        c = _refill(base, bare, table, c)
        lanes = jax.lax.fori_loop(
            0, refill_every, lambda _, ln: jax.vmap(_lane_step, (None, 0))(base, ln), c.lanes)
        return c.replace(lanes=lanes)

    def cond(state):
        b, c = state
        return (b < blocks) & (c.done < table.count)

    def body(state):
        b, c = state
        return b + 1, block(c)

    return jax.lax.while_loop(cond, body, (0, carry))[1]


_advance_jit = jax.jit(_advance, static_argnames=("refill_every", "blocks"),
                       donate_argnums=(3,))


@partial(jax.jit, static_argnames=("sizes", "lanes"))
def _prepare(params: SimParams, q_d, direction, obj_id, objects: HeldObject, keys,
             *, sizes: tuple[int, ...], lanes: int) -> tuple[_Table, _Carry]:
    """The sample table (per-sample keys, the loaded arm of every object) and the starting
    carry (every lane idle: phase 2, index S_pad; empty outputs), in one compiled call (op
    by op, an accelerator would compile each small kernel separately)."""
    S_pad, n = q_d.shape
    pad = S_pad - keys.shape[0]
    keys = jnp.concatenate([keys, jnp.repeat(keys[-1:], pad, 0)])
    loaded = jax.vmap(loaded_params, (None, 0))(params, objects)
    count = jnp.asarray(sum(sizes), jnp.int32)
    table = _Table(q_d, direction, keys, obj_id, objects, loaded, count)
    dtype = q_d.dtype
    zeros = jnp.zeros((lanes, n), dtype)
    lane0 = _Lanes(
        state=jax.vmap(SimState.at_rest)(zeros),
        robot=jax.tree.map(lambda a: jnp.broadcast_to(a[0], (lanes,) + a.shape[1:]),
                           loaded.robot),
        friction=jax.tree.map(lambda a: jnp.broadcast_to(a, (lanes,) + a.shape),
                              params.friction),
        pre=zeros, q_d=zeros, direction=zeros, key=keys[:lanes],
        obj_id=jnp.zeros(lanes, jnp.int32), idx=jnp.full(lanes, S_pad, jnp.int32),
        phase=jnp.full(lanes, 2, jnp.int32), k=jnp.zeros(lanes, jnp.int32),
        still=jnp.zeros(lanes, jnp.int32), ok_pre=jnp.zeros(lanes, bool),
        ok=jnp.zeros(lanes, bool), t_settle=jnp.zeros(lanes, dtype))
    obj = jax.tree.map(lambda a: a[0], objects)
    template = jax.eval_shape(
        lambda: record(params, params.robot, obj, zeros[0], zeros[0],
                       SimState.at_rest(zeros[0]), keys[0], at_rest=jnp.bool_(True),
                       settle_time=jnp.zeros((), dtype)))
    out = jax.tree.map(lambda s: jnp.zeros((S_pad,) + s.shape, s.dtype), template)
    return table, _Carry(lane0, out, jnp.asarray(0, jnp.int32), jnp.asarray(0, jnp.int32))


def _sample_keys(plans: list[Plan]) -> jax.Array:
    """``jax.random.split(plan.key, S)`` of every plan, concatenated. Split on the host
    CPU: each distinct S is a separate threefry program, ~0.3 s to compile on a GPU (12
    plans: ~4 s) and a few milliseconds on the CPU; the keys are the same bits anywhere."""
    cpu = jax.devices("cpu")[0]
    data = [jax.random.key_data(jax.random.split(jax.device_put(p.key, cpu), len(p.q_d)))
            for p in plans]
    impl = jax.random.key_impl(plans[0].key)
    return jax.random.wrap_key_data(jnp.asarray(np.concatenate([np.asarray(d) for d in data])),
                                    impl=impl)


def _pad(a: np.ndarray, size: int) -> np.ndarray:
    return np.concatenate([a, np.repeat(a[-1:], size - len(a), 0)]) if len(a) < size else a


def stream_plans(params: SimParams, plans: list[Plan], *, lanes: int | None = None,
                 refill_every: int = 32, blocks_per_call: int = 16, desc: str = "simulating",
                 progress: bool = True) -> list[Samples]:
    """Simulates every plan's samples (``params.robot``: the bare arm, lbipe convention);
    returns one :class:`Samples` (numpy) per plan, in plan order.

    Sample j of a plan gets ``jax.random.split(plan.key, S)[j]``, as in
    :func:`jaxinertia.sim.run.run_plan`'s reference path, so results depend neither on the
    lane count nor on the other plans.
    """
    lanes = int(lanes or default_lanes())
    sizes = tuple(len(p.q_d) for p in plans)
    S = sum(sizes)
    S_pad = max(lanes, 1 << (S - 1).bit_length())
    O_pad = -(-len(plans) // 4) * 4
    dtype = jnp.result_type(float)
    # Host-side assembly (numpy), one transfer, then one compiled preparation.
    q_d = _pad(np.concatenate([np.asarray(p.q_d, np.float64) for p in plans]), S_pad)
    direction = _pad(np.concatenate([np.asarray(p.direction, np.float64) for p in plans]),
                     S_pad)
    obj_id = _pad(np.concatenate([np.full(n, i, np.int32) for i, n in enumerate(sizes)]),
                  S_pad)
    objs = [p.obj for p in plans] + [plans[-1].obj] * (O_pad - len(plans))
    objects = jax.tree.map(lambda *a: np.stack([np.asarray(x, dtype) for x in a]), *objs)
    table, carry = _prepare(params, q_d.astype(dtype), direction.astype(dtype), obj_id,
                            objects, _sample_keys(plans), sizes=sizes, lanes=lanes)

    bare = params.robot
    with tqdm(total=S, desc=desc, unit="sample", disable=not progress) as bar:
        while int(carry.done) < S:
            carry = _advance_jit(params, bare, table, carry, refill_every=refill_every,
                                 blocks=blocks_per_call)
            bar.update(int(carry.done) - bar.n)
    out = jax.tree.map(lambda a: np.asarray(a)[:S], carry.out)
    bounds = np.cumsum((0,) + sizes)
    return [jax.tree.map(lambda a, lo=lo, hi=hi: a[lo:hi], out)
            for lo, hi in zip(bounds[:-1], bounds[1:])]
