"""The host runner of the lane program (:mod:`jaxinertia.sim.lanes`): many samples on a
fixed set of lanes, one compiled program for any plans.

The sample table is padded to a power of two and the objects to a multiple of four, so
plans of different sizes share the stepping program per lane count (only the small
preparation, :func:`jaxinertia.sim.lanes.prepare`, is compiled per set of plan sizes).
Sample keys are split on the host CPU (:func:`_sample_keys`).

The host loop dispatches ``blocks_per_call`` blocks (a refill program, then a steps
program of ``refill_every`` servo periods; buffers donated) before it reads the count of
finished samples for the progress bar; the records are computed once after the stream
(:func:`jaxinertia.sim.lanes.finish`). The programs are compiled ahead of time in
background threads (:class:`Compiler`), overlapping the preparation and each other, and
kept by a :class:`StreamPrograms` that the caller owns (the command line keeps one for its
process; without one a stream compiles for itself alone);
:meth:`StreamPrograms.precompile` starts the stepping program before the plans exist. On
an accelerator
the last samples move to a program of fewer lanes (:func:`default_tail_lanes`). By default
the lanes step batch-last (:func:`batch_last_default`).

One module: the host loop, the compiler that prepares its programs ahead of time and the
registry that keeps them share the programs' signatures and lane counts.
"""

from __future__ import annotations

import logging
import time
from concurrent.futures import Future, ThreadPoolExecutor
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from jaxinertia.compile_options import stepping_options
from jaxinertia.objects import HeldObject
from jaxinertia.sim import lanes as lane_program
from jaxinertia.sim.sampling import Record
from jaxinertia.sim.simulator import SimParams

__all__ = ["Compiler", "LanePlan", "StreamPrograms", "batch_last_default", "default_lanes",
           "default_tail_lanes", "stream_jobs", "stream_lanes", "stream_plans"]

_log = logging.getLogger(__name__)


class LanePlan(NamedTuple):
    """One object's samples: goals and directions (S, N) and the key split per sample."""

    obj: HeldObject
    q_d: np.ndarray
    direction: np.ndarray
    key: jax.Array


def default_lanes() -> int:
    """Lanes: a few hundred on a CPU (its throughput is flat beyond that, and fewer lanes
    shorten the tail); tens of thousands on an accelerator."""
    return 256 if jax.default_backend() == "cpu" else 16384


def batch_last_default() -> bool:
    """Whether the stream steps its lanes batch-last by default: yes, on every backend.

    Measured (docs/benchmarks.md): on a 2-core CPU the batch-last step is 3-9x faster than
    ``vmap`` (no tiny batched ``dot``s); on an H100 it steps 1.9x (float32) and 5.5x
    (float64) faster, and the paper-scale set simulates cold in 6.7-9.3 s in float64
    (vmapped: 9.3-11.7 s). (In float32 the vmapped step's shorter compile makes a cold
    paper-scale run 1.5-3 s shorter; the stepping itself is slower.)
    """
    return True


# The lane program's functions as compiled here. Refill and steps are two programs, not
# one: they compile in parallel (compilation is most of a cold run's time on an
# accelerator) and the host loop dispatches them asynchronously. The preparation is one
# compiled call (op by op, an accelerator would compile each small kernel separately).
_refill_jit = jax.jit(lane_program.refill, donate_argnums=(2,))
_steps_jit = jax.jit(lane_program.steps, static_argnames=("n", "batch_last"),
                     donate_argnums=(1,))
_finish = jax.jit(lane_program.finish)


def _steps_many(params, lanes, *, n: int, batch_last: bool):
    return jax.vmap(partial(lane_program.steps, n=n, batch_last=batch_last))(params, lanes)


# The same programs over several independent streams (:func:`stream_jobs`), vmapped.
_refill_many_jit = jax.jit(jax.vmap(lane_program.refill), donate_argnums=(2,))
_steps_many_jit = jax.jit(_steps_many, static_argnames=("n", "batch_last"), donate_argnums=(1,))
_finish_many = jax.jit(jax.vmap(lane_program.finish))
_prepare = jax.jit(lane_program.prepare, static_argnames=("sizes", "lanes"))
_compact = jax.jit(lane_program.compact, static_argnames=("size",))


def _sample_keys(plans: list[LanePlan]) -> jax.Array:
    """``jax.random.split(plan.key, S)`` of every plan, concatenated, from one program on
    the host CPU (on a GPU each threefry program takes ~0.3 s to compile).

    With partitionable threefry (JAX's default) key j of a split does not depend on how
    many keys are split, so every plan is split to the same power-of-two count and cut:
    one compiled program for any set of plan sizes. Otherwise one split per plan size.
    """
    cpu = jax.devices("cpu")[0]
    sizes = [len(p.q_d) for p in plans]
    keys = jax.device_put(jnp.stack([p.key for p in plans]), cpu)
    if jax.config.jax_threefry_partitionable:
        n = 1 << (max(sizes) - 1).bit_length()
        data = np.asarray(_split_all(keys, n))
        data = np.concatenate([d[:s] for d, s in zip(data, sizes)])
    else:
        data = np.concatenate([np.asarray(jax.random.key_data(jax.random.split(k, s)))
                               for k, s in zip(keys, sizes)])
    return jax.random.wrap_key_data(jnp.asarray(data), impl=jax.random.key_impl(keys))


@partial(jax.jit, static_argnums=1)
def _split_all(keys: jax.Array, n: int) -> jax.Array:
    return jax.vmap(lambda k: jax.random.key_data(jax.random.split(k, n)))(keys)


def _pad(a: np.ndarray, size: int) -> np.ndarray:
    return np.concatenate([a, np.repeat(a[-1:], size - len(a), 0)]) if len(a) < size else a


def stream_lanes(samples: int) -> int:
    """:func:`default_lanes`, or for a stream of at most a sixteenth of them as many as it
    has samples (a power of two, >= 256): a real file's plan, which a fold's calibration
    simulates a dozen times, steps 1,024 lanes on an accelerator, not 16,384."""
    lanes = default_lanes()
    if samples > lanes // 16:
        return lanes
    return min(lanes, max(256, 1 << max(samples - 1, 0).bit_length()))


def default_tail_lanes(lanes: int) -> int:
    """Lanes for the end of a stream on an accelerator (0: none, the CPU's lane count is
    small already). Once every sample is handed out, the last few hundred samples (a
    time-out runs 6 s of simulated time per move) would otherwise step all ``lanes``."""
    return 0 if jax.default_backend() == "cpu" else max(lanes // 16, 1)


class Compiler:
    """Compiles programs ahead of time in the background, for abstract arguments.

    Lowering (tracing to StableHLO) is Python and holds the GIL: one thread lowers the
    programs one at a time, in the order submitted, so that concurrent lowerings do not
    starve each other or the stream's host loop. Compilation (XLA, which releases the
    GIL) runs in a pool, programs in parallel.
    """

    def __init__(self, workers: int = 4):
        self._lowering = ThreadPoolExecutor(1, thread_name_prefix="jaxinertia-lower")
        self._compiling = ThreadPoolExecutor(workers, thread_name_prefix="jaxinertia-compile")
        self._t0 = time.perf_counter()

    def submit(self, fn, *args, untimed: bool = False, **static) -> Future:
        """A future of ``fn.lower(*args, **static).compile()``.

        ``untimed``: on a GPU, compile without XLA's autotuner, which times candidate
        kernels on the device: for programs compiled while the stream runs on it (timing
        against the stream slowed both ~2x on an H100) and that run little.
        """
        out: Future = Future()
        # Every program of the stream steps or serves the stepping: compiled as such.
        options = stepping_options() | ({"xla_gpu_autotune_level": 0} if untimed and _on_gpu()
                                        else {})
        name = getattr(fn, "__name__", str(fn))

        def compile_(lowered, t_lowered):
            try:
                t0 = time.perf_counter()
                out.set_result(lowered.compile(compiler_options=options or None))
                _log.debug("stream: %s lowered in %.2f s, compiled in %.2f s (done at %.2f s)",
                           name, t_lowered, time.perf_counter() - t0,
                           time.perf_counter() - self._t0)
            except BaseException as e:  # noqa: BLE001 - handed to the waiting thread
                out.set_exception(e)

        def lower():
            try:
                t0 = time.perf_counter()
                lowered = fn.lower(*args, **static)
            except BaseException as e:  # noqa: BLE001
                out.set_exception(e)
                return
            self._compiling.submit(compile_, lowered, time.perf_counter() - t0)

        self._lowering.submit(lower)
        return out

    def close(self) -> None:
        """Waits for the programs submitted and stops the threads."""
        self._lowering.shutdown(wait=True)
        self._compiling.shutdown(wait=True)


def _on_gpu() -> bool:
    return jax.default_backend() == "gpu"


class _Block(NamedTuple):
    """The compiled programs of one lane count."""

    refill: object
    steps: object


def _signature(tree) -> tuple:
    leaves, treedef = jax.tree.flatten(tree)
    return treedef, tuple((np.shape(x), str(x.dtype if hasattr(x, "dtype") else type(x)))
                          for x in leaves)


class StreamPrograms:
    """The stream's compiled programs, one per program and signature (shapes, dtypes,
    static settings), held for as long as their owner keeps this object: ahead-of-time
    compiled executables are not kept by ``jax.jit``'s own cache. Streams given the same
    object share its programs (and its :class:`Compiler`'s threads); a compilation that
    fails is forgotten alone (the next stream that needs it submits it again), the other
    programs stay.

    ``compiler``: what compiles (default: a new :class:`Compiler`; anything with its
    ``submit``).
    """

    def __init__(self, compiler: Compiler | None = None):
        self.compiler = compiler or Compiler()
        self._programs: dict[tuple, Future] = {}

    def __enter__(self) -> StreamPrograms:
        return self

    def __exit__(self, *exc) -> None:
        close = getattr(self.compiler, "close", None)
        if close is not None:
            close()

    def keys(self) -> frozenset:
        """The programs held (submitted, compiling or compiled): ``(name, signature,
        ...)``."""
        return frozenset(self._programs)

    def _program(self, key: tuple, fn, *args, untimed: bool = False, **static) -> Future:
        """The future of ``fn`` compiled for ``args``, submitted once per ``key``."""
        key = key + (untimed, jax.default_backend())
        if key not in self._programs:
            self._programs[key] = self.compiler.submit(fn, *args, untimed=untimed, **static)
        return self._programs[key]

    def steps(self, params: SimParams, lanes, n: int, batch_last: bool,
              untimed: bool = False) -> Future:
        """A future of the compiled :func:`jaxinertia.sim.lanes.steps` for the (abstract)
        ``lanes`` (:meth:`precompile` may have submitted it).

        Batch-last steps always compile ``untimed``: they have no ``dot`` for the GPU
        autotuner to choose kernels for, and skipping it saved 0.3-1 s of an H100's 4.3-5.7 s
        compile (three cold paper-scale runs each way) with the same stream time."""
        return self._program(("steps", _signature((params, lanes)), n, batch_last), _steps_jit,
                             params, lanes, n=n, batch_last=batch_last,
                             untimed=untimed or batch_last)

    def programs(self, params: SimParams, table, carry, tail: int, refill_every: int,
                 batch_last: bool) -> dict:
        """Futures of the stream's compiled programs for the (abstract) ``table`` and
        ``carry``, submitted in the order they are needed: ``main`` (refill, steps: the
        largest, submitted first unless :meth:`precompile` did already), ``finish`` and,
        when ``tail``, ``tail`` (compaction, refill and steps on ``tail`` lanes). The last
        two compile while the stream runs."""
        steps = self.steps(params, carry.lanes, refill_every, batch_last)
        refill = self._program(("refill", _signature((params, table, carry))), _refill_jit,
                               params, table, carry)
        programs = dict(main=(refill, steps), tail=None,
                        finish=self._program(("finish", _signature((params, table, carry.out))),
                                             _finish, params, table, carry.out, untimed=True))
        if tail:
            small = jax.eval_shape(partial(_compact, size=tail), carry)
            compact = self._program(("compact", _signature(carry), tail), _compact, carry,
                                    size=tail, untimed=True)
            steps = self.steps(params, small.lanes, refill_every, batch_last, untimed=True)
            refill = self._program(("refill", _signature((params, table, small))), _refill_jit,
                                   params, table, small, untimed=True)
            programs["tail"] = (compact, refill, steps)
        return programs

    def many(self, params: SimParams, table, carry, refill_every: int,
             batch_last: bool) -> tuple[Future, Future, Future]:
        """Futures of the programs of :func:`stream_jobs` for the (abstract, stacked over the
        streams) ``params``, ``table`` and ``carry``: refill, steps and finish, each the
        stream's own ``vmap``-ped over the streams."""
        sig = _signature((params, table, carry))
        return (self._program(("refill_many", sig), _refill_many_jit, params, table, carry),
                self._program(("steps_many", _signature((params, carry.lanes)), refill_every,
                               batch_last), _steps_many_jit, params, carry.lanes,
                              n=refill_every, batch_last=batch_last, untimed=batch_last),
                self._program(("finish_many", _signature((params, table, carry.out))),
                              _finish_many, params, table, carry.out, untimed=True))

    def result(self, futures) -> tuple:
        """The compiled programs of ``futures``, waited for; a failed compilation is
        forgotten (that program alone) and its error raised."""
        try:
            return tuple(f.result() for f in futures)
        except Exception:
            self._programs = {k: f for k, f in self._programs.items()
                              if not (f.done() and f.exception() is not None)}
            raise

    def precompile(self, params: SimParams, obj: HeldObject, *, lanes: int | None = None,
                   batch_last: bool | None = None, refill_every: int = 32) -> None:
        """Starts compiling the stream's stepping program for ``lanes`` lanes in the
        background and returns at once; a later :func:`stream_plans` with the same settings
        and this object uses it.

        The stepping program is the largest and depends on neither the plans nor the objects
        (``obj``: any held object, for the shapes), so a caller can start it before building
        its plans: on a GPU its compilation is most of a cold paper-scale run.
        """
        lanes = int(lanes or default_lanes())
        batch_last = batch_last_default() if batch_last is None else bool(batch_last)
        params = _one_signature(params)
        n = params.robot.n_joints
        dummy = LanePlan(obj, np.zeros((1, n)), np.ones((1, n)), jax.random.key(0))
        args, sizes = _assemble(params, [dummy], lanes, keys=False)
        _, carry = jax.eval_shape(partial(_prepare, sizes=sizes, lanes=lanes), *args)
        self.steps(params, carry.lanes, refill_every, batch_last)


def _one_signature(params: SimParams) -> SimParams:
    """``params`` with an absent constant joint torque (``torque_offset`` None) as zeros:
    the signature of the fitted simulators, whose compiled programs it then shares (a
    held-out fold's calibration starts without offsets and fits them after its first
    iterations; the shipped fit has them). The step adds the offset to the servo torque,
    and ``x + 0.0`` is ``x`` for every ``x`` but -0.0, which becomes +0.0 (equal to it in
    every comparison): the same samples (the quick ``reproduce``'s, bit for bit)."""
    if params.torque_offset is not None:
        return params
    return params.replace(torque_offset=jnp.zeros(params.robot.n_joints,
                                                  jnp.result_type(float)))


def _assemble(params: SimParams, plans: list[LanePlan], lanes: int, *, keys: bool = True):
    """The arguments of :func:`jaxinertia.sim.lanes.prepare` (host-side assembly in numpy,
    one transfer): samples padded to a power of two (at least ``lanes``), objects to a
    multiple of four. ``keys=False``: the sample keys only as a shape (for
    :func:`jax.eval_shape`)."""
    sizes = tuple(len(p.q_d) for p in plans)
    S_pad = max(lanes, 1 << (sum(sizes) - 1).bit_length())
    O_pad = -(-len(plans) // 4) * 4
    dtype = jnp.result_type(float)

    def column(field, dt=np.float64):
        return _pad(np.concatenate([np.asarray(getattr(p, field), dt) for p in plans]), S_pad)

    obj_id = _pad(np.concatenate([np.full(n, i, np.int32) for i, n in enumerate(sizes)]),
                  S_pad)
    objs = [p.obj for p in plans] + [plans[-1].obj] * (O_pad - len(plans))
    objects = jax.tree.map(lambda *a: np.stack([np.asarray(x, dtype) for x in a]), *objs)
    args = (params, column("q_d").astype(dtype), column("direction").astype(dtype), obj_id,
            objects, _sample_keys(plans) if keys else
            jax.ShapeDtypeStruct((sum(sizes),), jax.random.key(0).dtype))
    return args, sizes


def stream_plans(params: SimParams, plans: list[LanePlan], *, lanes: int | None = None,
                 tail_lanes: int | None = None, batch_last: bool | None = None,
                 refill_every: int = 32, blocks_per_call: int = 16,
                 programs: StreamPrograms | None = None, desc: str = "simulating",
                 progress: bool = True) -> list[Record]:
    """Simulates every plan's samples (``params.robot``: the bare arm, lbipe convention);
    returns one :class:`~jaxinertia.sim.sampling.Record` (numpy) per plan, in plan order.

    Sample j of a plan gets ``jax.random.split(plan.key, S)[j]``, as in
    :func:`jaxinertia.sim.run.run_plan`'s reference path, so results depend neither on the
    lane count nor on the other plans (stepped batch-last, the simulator's true state may
    differ in its last bits between lane counts; the recorded ticks do not).

    ``lanes``: default :func:`stream_lanes`. ``tail_lanes`` (default
    :func:`default_tail_lanes`; 0: off): once every sample is handed out and at most this
    many are still running, they move to a program of that many lanes (compiled in the
    background while the stream runs), so that the last slow samples do not step every
    lane. Streams shorter than four lane-fulls do not use it.

    ``batch_last`` (default :func:`batch_last_default`): step the lanes with
    :func:`jaxinertia.sim.batched.step_batched` rather than ``vmap`` of
    :func:`jaxinertia.sim.simulator.step`; the same physics, rounded differently.

    ``programs``: where the compiled programs are found and kept (None: compiled for this
    stream alone).
    """
    if programs is None:
        with StreamPrograms() as own:
            return stream_plans(params, plans, lanes=lanes, tail_lanes=tail_lanes,
                                batch_last=batch_last, refill_every=refill_every,
                                blocks_per_call=blocks_per_call, programs=own, desc=desc,
                                progress=progress)
    t_start = time.perf_counter()
    lanes = int(lanes or stream_lanes(sum(len(p.q_d) for p in plans)))
    params = _one_signature(params)
    args, sizes = _assemble(params, plans, lanes)
    S = sum(sizes)
    tail = default_tail_lanes(lanes) if tail_lanes is None else int(tail_lanes)
    tail = tail if 0 < tail < lanes and S >= 4 * lanes else 0
    prepare = partial(_prepare, sizes=sizes, lanes=lanes)
    batch_last = batch_last_default() if batch_last is None else bool(batch_last)
    futures = programs.programs(params, *jax.eval_shape(prepare, *args), tail, refill_every,
                                batch_last)
    table, carry = prepare(*args)
    block = _Block(*programs.result(futures["main"]))
    _log.debug("stream: programs ready after %.3f s", time.perf_counter() - t_start)
    t0 = time.perf_counter()
    with tqdm(total=S, desc=desc, unit="sample", disable=not progress) as bar:
        done, small = 0, futures["tail"]
        while done < S:
            for _ in range(blocks_per_call):  # dispatched asynchronously
                carry = block.refill(params, table, carry)
                carry = carry.replace(lanes=block.steps(params, carry.lanes))
            done, handed = int(carry.done), int(carry.next)
            bar.update(done - bar.n)
            _log.debug("stream: %.3f s, %d done, %d handed out, %d lanes",
                       time.perf_counter() - t0, done, handed, carry.lanes.idx.shape[0])
            if (small and handed >= S and handed - done <= tail
                    and all(f.done() for f in small)):
                compact, *programs_small = programs.result(small)
                carry, block, small = compact(carry), _Block(*programs_small), None
    finish, = programs.result([futures["finish"]])
    out = jax.tree.map(lambda a: np.asarray(a)[:S], finish(params, table, carry.out))
    _log.debug("stream: recorded after %.3f s", time.perf_counter() - t0)
    bounds = np.cumsum((0,) + sizes)
    return [jax.tree.map(lambda a, lo=lo, hi=hi: a[lo:hi], out)
            for lo, hi in zip(bounds[:-1], bounds[1:])]


def stream_jobs(jobs, *, lanes: int | None = None, batch_last: bool | None = None,
                refill_every: int = 32, blocks_per_call: int = 16,
                programs: StreamPrograms | None = None) -> list[list[Record]]:
    """Several independent streams as one program: ``jobs`` is ``[(params, plans)]``, each
    a simulator and its plans (as :func:`stream_plans` takes them); returns each job's
    records per plan, as :func:`stream_plans` would (the same keys; the same samples up to
    the last bits of the simulator's state).

    Every stream's lane program is ``vmap``-ped over the jobs: one refill and one steps
    program a block for all of them. For latency-bound streams, each no more than a round
    of lanes (a held-out fold's calibration replays a 1,000-sample real file a dozen
    times): alone, one such replay took 0.41 s on an H100; two folds' replays side by side
    in threads, each waiting behind the other's small programs, 1.2 s each
    (docs/benchmarks.md, session 26). The jobs must have the same shapes (sample table
    padded alike, as many objects, the same static settings); no tail program.
    """
    if programs is None:
        with StreamPrograms() as own:
            return stream_jobs(jobs, lanes=lanes, batch_last=batch_last,
                               refill_every=refill_every, blocks_per_call=blocks_per_call,
                               programs=own)
    if not jobs:
        return []
    lanes = int(lanes or max(stream_lanes(sum(len(p.q_d) for p in plans)) for _, plans in jobs))
    batch_last = batch_last_default() if batch_last is None else bool(batch_last)
    prepared = []
    for params, plans in jobs:
        params = _one_signature(params)
        args, sizes = _assemble(params, plans, lanes)
        prepared.append((params, *_prepare(*args, sizes=sizes, lanes=lanes), sizes))
    signatures = {_signature(p[:3]) for p in prepared}
    if len(signatures) > 1:
        raise ValueError("stream_jobs: the jobs differ in shape (plan sizes padded to "
                         "different tables, object counts or static settings)")

    def stacked(i):
        return jax.tree.map(lambda *a: jnp.stack(a), *(p[i] for p in prepared))

    params, table, carry = stacked(0), stacked(1), stacked(2)
    refill, steps, finish = programs.result(programs.many(params, table, carry, refill_every,
                                                          batch_last))
    total = sum(sum(p[3]) for p in prepared)
    done = 0
    while done < total:
        for _ in range(blocks_per_call):  # dispatched asynchronously
            carry = refill(params, table, carry)
            carry = carry.replace(lanes=steps(params, carry.lanes))
        done = int(jnp.sum(carry.done))
    out = jax.tree.map(np.asarray, finish(params, table, carry.out))
    results = []
    for j, (*_, sizes) in enumerate(prepared):
        bounds = np.cumsum((0,) + sizes)
        results.append([jax.tree.map(lambda a, lo=lo, hi=hi, j=j: a[j, lo:hi], out)
                        for lo, hi in zip(bounds[:-1], bounds[1:])])
    return results
