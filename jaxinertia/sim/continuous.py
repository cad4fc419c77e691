"""The continuous switching-load run (paper Sec. IV-D): consecutive nearby configurations,
measured without waiting for rest, while the held object switches at given samples.

One arm, one long trajectory: a ``lax.scan`` over samples, each a fixed-length ``lax.scan``
over servo periods (the profiled move to the next goal, then a short dwell before the
reading). Unlike the discrete samples, the arm is not required to be at rest: ``at_rest``
records whether it happened to be, for diagnostics only.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from jaxinertia.objects import HeldObject, resolve
from jaxinertia.plans import continuous_plan, switching_schedule
from jaxinertia.sim.sampling import Record, jitter_friction, loaded_params, record
from jaxinertia.sim.servo import goal_ticks
from jaxinertia.sim.simulator import SimParams, SimState, step, trapezoid

__all__ = ["simulate_continuous", "simulate_continuous_run"]


def simulate_continuous(
    params: SimParams,
    objects: HeldObject,
    schedule: np.ndarray,
    q_d: np.ndarray,
    direction: np.ndarray,
    key: jax.Array,
    *,
    dwell: float = 0.1,
    chunk: int = 128,
    progress: bool = True,
    desc: str = "continuous",
) -> Record:
    """Simulates the trajectory; ``objects`` is a stacked HeldObject (leading axis O; a
    zero mass is the empty gripper) and ``schedule`` (S,) picks the one held per sample."""
    q_d = np.asarray(q_d, np.float64)
    prev = np.concatenate([q_d[:1], q_d[:-1]])
    _, t_total = trapezoid(prev, q_d, 0.0, params.profile_velocity,
                           params.profile_acceleration)
    n_steps = int(math.ceil((float(np.max(t_total)) + dwell) / params.dt))

    def per_sample(state, inp):
        q0, q1, o, d, k = inp
        obj = jax.tree_util.tree_map(lambda a: a[o], objects)
        k_f, k_r = jax.random.split(k)
        p = jitter_friction(loaded_params(params, obj), k_f, q1.shape[0])

        def body(s, i):
            goal, _ = trapezoid(q0, q1, i * p.dt, p.profile_velocity, p.profile_acceleration)
            return step(p, s, goal_ticks(goal)), None

        state, _ = jax.lax.scan(body, state, jnp.arange(n_steps))
        rest = jnp.all(jnp.abs(state.qd) < p.rest_velocity)
        return state, record(p, bare, obj, q1, d, state, k_r, at_rest=rest,
                             settle_time=jnp.asarray(n_steps * p.dt))

    keys = jax.random.split(key, len(q_d))
    xs = (jnp.asarray(prev), jnp.asarray(q_d), jnp.asarray(schedule), jnp.asarray(direction),
          keys)
    state = SimState.at_rest(jnp.asarray(q_d[0]))
    # One arm stepped sequentially is latency-bound: a GPU launches kernels every servo
    # period (the full run's 4,096 samples took 67 s on an H100), so the scan runs on the
    # host CPU whatever the default backend.
    cpu = jax.devices("cpu")[0]
    params, objects, xs, state = jax.device_put((params, objects, xs, state), cpu)
    bare = params.robot
    run = jax.jit(lambda state, xs: jax.lax.scan(per_sample, state, xs))
    out = []
    S = len(q_d)
    with tqdm(total=S, desc=desc, unit="sample", disable=not progress) as bar:
        for start in range(0, S, chunk):  # chunks of one compiled size (the last padded)
            n = min(chunk, S - start)
            state, rec = run(state, tuple(_chunk(a, start, chunk) for a in xs))
            out.append([np.asarray(a)[:n] for a in rec])
            bar.update(n)
    return Record(*(np.concatenate(f) for f in zip(*out)))


def _chunk(a: jnp.ndarray, start: int, size: int) -> jnp.ndarray:
    """``a[start:start + size]``, padded with its last row to ``size`` rows."""
    part = a[start:start + size]
    pad = size - part.shape[0]
    return jnp.concatenate([part, jnp.repeat(part[-1:], pad, 0)]) if pad else part


def simulate_continuous_run(params: SimParams, *, n: int, objects: list[str],
                            switch_every: int, seed: int = 0,
                            progress: bool = True) -> tuple[dict, dict]:
    """The switching-load run as native-format fields and metadata (``object_id`` is the
    object held at each sample, ``x`` per object; ``objects``: names as
    :func:`jaxinertia.objects.resolve` takes them, ``empty`` for the empty gripper)."""
    objs = [resolve(o) for o in objects]
    stacked = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *objs)
    q, d = continuous_plan(n, seed)
    schedule = switching_schedule(n, len(objs), switch_every)
    rec = simulate_continuous(params, stacked, schedule, q, d, jax.random.key(seed + 99),
                              progress=progress)
    fields = dict(rec._asdict())
    fields["object_id"] = schedule
    fields["x"] = np.stack([np.asarray(o.x) for o in objs])
    meta = {"scenario": "continuous", "seed": seed, "source": "simulator", "objects": objects,
            "switch_every": switch_every, "robot": params.robot.name,
            "simulator": {"precision": str(jnp.dtype(jnp.result_type(float)))},
            "request": {"scenario": "continuous", "seed": seed, "n": n,
                        "objects": objects, "switch_every": switch_every}}
    return fields, meta
