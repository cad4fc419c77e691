"""The continuous switching-load run (paper Sec. IV-D): consecutive nearby configurations,
measured without waiting for rest, while the held object switches at given samples.

One arm, one long trajectory: each sample is a fixed-length ``lax.scan`` over servo
periods (the profiled move to the next goal, then a short dwell before the reading), the
arm's state carried from sample to sample. Unlike the discrete samples, the arm is not
required to be at rest: ``at_rest`` records whether it happened to be, for diagnostics
only.

**Lanes.** Stepped as one sequence the walk is latency-bound (4,096 samples of ~1,500
servo periods each, one after the other). :func:`simulate_continuous` cuts it into
``lanes`` consecutive segments stepped side by side (``vmap``: one batched program, on
whatever device is the default), each its own arm. A segment starts ``warmup`` samples
early, at rest at the goal before its first warm-up sample, and drops the warm-up
samples' readings: the warm-up walks the same goals with the same per-sample random
draws as the single sequence, so by the segment's first sample the arm is where the
single sequence has it (the servo's memory is a few periods long; ``tests/test_sim.py``
measures the difference). ``lanes=1`` is the single sequence exactly.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from jaxinertia.arm import Arm
from jaxinertia.compile_options import stepping_jit
from jaxinertia.objects import HeldObject, resolve
from jaxinertia.open_manipulator_x import ARM as OMX_ARM
from jaxinertia.plans import continuous_plan, switching_schedule
from jaxinertia.sim.sampling import Record, jitter_friction, record
from jaxinertia.sim.servo import goal_ticks
from jaxinertia.sim.simulator import SimParams, SimState, physical_params, step, trapezoid

__all__ = ["MAX_LANES", "lane_indices", "simulate_continuous", "simulate_continuous_run",
           "walk_lanes"]


#: The most lanes :func:`walk_lanes` gives: the 4,096-sample walk of ``reproduce --full`` as
#: 128 segments of 32 samples (+2 warm-up samples each).
MAX_LANES = 128


def walk_lanes(n: int) -> int:
    """Segments of an ``n``-sample walk to step side by side: up to :data:`MAX_LANES`, each
    of at least 16 samples (the 2 warm-up samples a segment steps again stay a small part
    of it). On an accelerator one arm stepped alone is latency-bound (kernel launches every
    servo period); on a CPU the lanes are vectorised: 2,048 samples in 64 or 128 lanes took
    12-13 s against 24-26 s for the single sequence (2-core machine, session 37; while a
    short lane was padded to a whole call of 128 samples, the single sequence was the
    faster)."""
    return max(1, min(MAX_LANES, n // 16))


def lane_indices(n: int, lanes: int, warmup: int) -> tuple[np.ndarray, np.ndarray, int]:
    """The samples each lane walks: ``(idx, live, seg)`` with ``idx`` (lanes, warmup + seg)
    sample indices (clipped into ``[0, n)``), ``live`` where a step is a real sample of the
    walk (False: lane 0's warm-up, which does not exist, and the padding past ``n``), and
    ``seg`` samples kept per lane (lane l keeps samples ``l * seg`` to ``(l + 1) * seg``)."""
    if n < 1 or lanes < 1 or warmup < 0:
        raise ValueError(f"n={n}, lanes={lanes}, warmup={warmup}")
    seg = -(-n // lanes)
    raw = np.arange(lanes)[:, None] * seg - warmup + np.arange(warmup + seg)[None, :]
    return np.clip(raw, 0, n - 1), (raw >= 0) & (raw < n), seg


def simulate_continuous(
    params: SimParams,
    objects: HeldObject,
    schedule: np.ndarray,
    q_d: np.ndarray,
    direction: np.ndarray,
    key: jax.Array,
    *,
    dwell: float = 0.1,
    lanes: int = 1,
    warmup: int = 2,
    chunk: int = 128,
    progress: bool = True,
    desc: str = "continuous",
) -> Record:
    """Simulates the trajectory; ``objects`` is a stacked HeldObject (leading axis O; a
    zero mass is the empty gripper) and ``schedule`` (S,) picks the one held per sample.
    ``lanes`` segments side by side, each starting ``warmup`` samples early (see the
    module docstring); at most ``chunk`` samples per lane per compiled call (the progress
    bar's step), the calls as even as their count allows. Runs on the default device."""
    q_d = np.asarray(q_d, np.float64)
    S = len(q_d)
    prev = np.concatenate([q_d[:1], q_d[:-1]])
    _, t_total = trapezoid(prev, q_d, 0.0, params.profile_velocity,
                           params.profile_acceleration)
    n_steps = int(math.ceil((float(np.max(t_total)) + dwell) / params.dt))
    bare = params.robot

    def per_sample(state, inp):
        q0, q1, o, d, k, live = inp
        obj = jax.tree_util.tree_map(lambda a: a[o], objects)
        k_f, k_r = jax.random.split(k)
        p = jitter_friction(physical_params(params, obj), k_f, q1.shape[0])

        def body(s, i):
            goal, _ = trapezoid(q0, q1, i * p.dt, p.profile_velocity, p.profile_acceleration)
            return step(p, s, goal_ticks(goal)), None

        moved, _ = jax.lax.scan(body, state, jnp.arange(n_steps))
        # A step that is no sample of the walk leaves the arm as it was.
        state = jax.tree_util.tree_map(lambda a, b: jnp.where(live, a, b), moved, state)
        rest = jnp.all(jnp.abs(state.qd) < p.rest_velocity)
        return state, record(p, bare, obj, q1, d, state, k_r, at_rest=rest,
                             settle_time=jnp.asarray(n_steps * p.dt))

    idx, live, seg = lane_indices(S, lanes, warmup)
    W = idx.shape[1]
    n_chunks = -(-W // chunk)
    # The calls' steps as even as their count allows: padding a lane of 34 steps (4,096
    # samples in 128 lanes) to a whole chunk of 128 stepped the arm 3.8 times over.
    chunk = -(-W // n_chunks)
    pad = n_chunks * chunk - W  # steps that are no sample: not live (fewer than n_chunks)
    idx = np.pad(idx, ((0, 0), (0, pad)), mode="edge")
    live = np.pad(live, ((0, 0), (0, pad)))
    keys = jax.random.split(key, S)[idx]
    xs = (prev[idx], q_d[idx], np.asarray(schedule)[idx], np.asarray(direction)[idx], keys,
          live)
    state = jax.vmap(SimState.at_rest)(jnp.asarray(prev[idx[:, 0]]))
    run = stepping_jit(jax.vmap(lambda state, xs: jax.lax.scan(per_sample, state, xs)))
    out = []
    # The bar counts the samples stepped, warm-ups included (their work is the same).
    with tqdm(total=int(live.sum()), desc=desc, unit="sample", disable=not progress) as bar:
        for c in range(n_chunks):
            part = slice(c * chunk, (c + 1) * chunk)
            state, rec = run(state, tuple(jnp.asarray(a[:, part]) for a in xs))
            out.append(rec)
            bar.update(int(live[:, part].sum()))
    # (lanes, steps, ...) -> the kept samples in walk order
    return Record(*(np.concatenate([np.asarray(a) for a in f], axis=1)[:, warmup:warmup + seg]
                    .reshape(lanes * seg, *np.shape(f[0])[2:])[:S] for f in zip(*out)))


def simulate_continuous_run(params: SimParams, *, n: int, objects: list[str],
                            switch_every: int, seed: int = 0, lanes: int = 1,
                            progress: bool = True, arm: Arm | None = None
                            ) -> tuple[dict, dict]:
    """The switching-load run as native-format fields and metadata (``object_id`` is the
    object held at each sample, ``x`` per object; ``objects``: names as
    :func:`jaxinertia.objects.resolve` takes them, ``empty`` for the empty gripper;
    ``arm``: the record whose workspace and tag mount the walk uses, default the
    OpenMANIPULATOR-X's; ``params`` must be that arm's)."""
    arm = OMX_ARM if arm is None else arm
    objs = [resolve(o, tag_in_ee=arm.tag_in_ee) for o in objects]
    stacked = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *objs)
    q, d = continuous_plan(n, seed, workspace=arm.workspace_deg)
    schedule = switching_schedule(n, len(objs), switch_every)
    rec = simulate_continuous(params, stacked, schedule, q, d, jax.random.key(seed + 99),
                              lanes=lanes, progress=progress)
    fields = dict(rec._asdict())
    fields["object_id"] = schedule
    fields["x"] = np.stack([np.asarray(o.x) for o in objs])
    meta = {"scenario": "continuous", "seed": seed, "source": "simulator", "objects": objects,
            "switch_every": switch_every, "robot": params.robot.name, "arm": arm.name,
            "simulator": {"precision": str(jnp.dtype(jnp.result_type(float))),
                          "lanes": lanes},
            "request": {"scenario": "continuous", "seed": seed, "n": n,
                        "objects": objects, "switch_every": switch_every}}
    return fields, meta
