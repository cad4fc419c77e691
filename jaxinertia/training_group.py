"""The epochs of a training, alone or with other trainings as one program.

:func:`run_epochs` runs a training's epochs (:func:`jaxinertia.training.make_epoch`): alone
in the calling thread, or, when the thread is a member of a :class:`TrainingGroup`, together
with the other members' trainings.

Why groups: on an accelerator the held-out folds train many model sets at once in threads
(both folds; in each the paper network, the physical model and its variants, then their
fine-tunings). One epoch of K small MLPs leaves a GPU mostly idle: a step costs about as
much for 60 models as for 10 (docs/benchmarks.md, "Trainings as one program"). The members
of a group hand their epochs to it; trainings of the same epoch program and the same shapes
run as one program, the epoch ``vmap``-ped over the group, each with its own state, data
and keys, at about the device time of one: the torque models' epochs (300 of minibatches,
the bulk) and the attention's (30, through the WLS solve). The numbers are each training's
own up to float rounding: ``vmap`` may vectorise a reduction (a bias gradient over the
minibatch, the WLS's sums) in another order, a last-bit difference that training then
carries (tests/test_training_group.py; at the folds' shapes on an H200 the torque epochs
of four or six trainings came out bit for bit, of two not). Which trainings share a
program is fixed by the members and their shapes, never by timing: a run's numbers do not
depend on which thread came first.

A group waits, at each training of its members, until every member has either reached that
training or left the group (its ``with group.member(...)`` ended, normally or by an
exception): members must run side by side, in threads of their own. A training whose
shapes no other member shares runs alone.
"""

from __future__ import annotations

import contextlib
import functools
import threading
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from jaxinertia.errors import TrainingError
from jaxinertia.sharding import replicate, shard

__all__ = ["TrainingGroup", "rehearse", "run_epochs", "shared_cache"]

_local = threading.local()


@dataclass(frozen=True)
class _Training:
    """One call of :func:`run_epochs`: what it runs, from where, how long."""

    epoch: Any  # jaxinertia.training.Epoch (init, update)
    state: Any  # TrainState, stacked (K, ...)
    data: Any  # (shared, own)
    val_data: Any
    n_epochs: int
    key: jax.Array
    desc: str
    progress: bool
    on_epoch: Callable | None
    per_call: int = 1  # epochs per program call (:func:`epochs_per_call`)
    compile_only: bool = False  # a rehearsal's (:func:`rehearse`): compiled, not run

    def signature(self) -> tuple:
        """Trainings with equal signatures run as one program."""
        trees = (self.state, self.data, self.val_data)
        return (self.epoch, self.n_epochs, self.per_call, self.compile_only,
                jax.tree_util.tree_structure(trees),
                tuple((tuple(np.shape(a)), str(a.dtype))
                      for a in jax.tree_util.tree_leaves(trees)))


#: A call of a training's program runs about this many minibatch steps at most
#: (:func:`epochs_per_call`).
STEPS_PER_CALL = 512

#: ... and at most this fraction of its epochs, so that a progress bar moves.
MOST_EPOCHS_PER_CALL = 1 / 8


def epochs_per_call(n_epochs: int, steps_per_epoch: int) -> int:
    """How many epochs of a training of ``n_epochs`` epochs of ``steps_per_epoch`` minibatch
    steps one program call runs: the most that divides ``n_epochs`` within
    :data:`STEPS_PER_CALL` steps and :data:`MOST_EPOCHS_PER_CALL` of the epochs; 1 for a
    training of long epochs (every training from scratch at the paper's scale).

    Why: each call is a few dispatches and a wait for its losses on the host, each a
    hand-over of the GIL. A fine-tuning's epoch (200 of them, a few minibatches each) is
    about 2 ms of GPU: alone on an H100 a compiled fine-tuning took 0.49-1.15 s one epoch a
    call against 0.12-0.21 s at 25, and beside busy Python threads (the folds run a dozen)
    the one-a-call loop was 25-50 times slower on a CPU (``experiments/finetune_calls.py``;
    docs/benchmarks.md, "Session 29")."""
    if steps_per_epoch <= 0 or n_epochs <= 1:
        return 1
    most = max(1, min(STEPS_PER_CALL // steps_per_epoch,
                      int(n_epochs * MOST_EPOCHS_PER_CALL)))
    return max(c for c in range(1, most + 1) if n_epochs % c == 0)


def run_epochs(epoch, state, data, val_data, n_epochs: int, key, desc: str, progress: bool,
               on_epoch: Callable | None = None, *, steps_per_epoch: int = 0
               ) -> tuple[Any, np.ndarray]:
    """Runs ``epoch.update`` ``n_epochs`` times with a progress bar, calling
    ``on_epoch(e, (train_loss, val_loss))`` after each if given; returns the state and the
    (n_epochs, 2, K) history of training and validation losses. In a thread that is a
    member of a :class:`TrainingGroup`, the group runs it (with the others of its shapes).

    ``steps_per_epoch`` (the minibatches of an epoch, 0: unknown) sets how many epochs one
    program call runs (:func:`epochs_per_call`): several as a ``lax.scan`` over the epochs,
    epoch ``e``'s key ``fold_in(key, e)`` either way, so the keys, and so the minibatches,
    are those of one call per epoch. ``on_epoch`` sees a call's epochs when the host has
    read its losses (several at once when a call runs several; timings from it are per
    call, and every training of 15 epochs or fewer runs one a call)."""
    training = _Training(epoch, state, data, val_data, int(n_epochs), key, desc, progress,
                         on_epoch, epochs_per_call(int(n_epochs), int(steps_per_epoch)),
                         getattr(_local, "compile_only", False))
    member = getattr(_local, "member", None)
    if member is None:
        return _raise_or_return(_run_together([training])[0])
    group, name = member
    return group._submit(name, training)


def _raise_or_return(result):
    if isinstance(result, BaseException):
        raise result
    return result


def rehearse(fn: Callable[[], Any]) -> threading.Thread | None:
    """Compiles a later training of this thread's group member ahead, beside what the
    thread runs now: ``fn`` (a trainer called as the member will call it later, inputs of
    the same shapes) runs in a thread as the member of the group's twin
    (``TrainingGroup.rehearsal``), where :func:`run_epochs` compiles the program(s) the
    group will run and runs no epoch (the state comes back as it went in, no history);
    the rest of ``fn`` runs as written, compiling its programs too. The training then
    finds them compiled (JAX keeps them per function and shapes): in a GPU fold the
    attention's compile (14 s) left its critical path. Returns the thread (a daemon), or
    None outside a group (nothing to overlap). It changes no number: the programs are the
    training's own and nothing computed is kept; a failed one is dropped."""
    member = getattr(_local, "member", None)
    if member is None or member[0].rehearsal is None:
        return None
    group, name = member

    def run() -> None:
        _local.compile_only = True
        with contextlib.suppress(Exception), group.rehearsal.member(name):
            fn()  # a rehearsal only saves time: a failed one is the training's to report

    thread = threading.Thread(target=run, name=f"rehearse-{name}", daemon=True)
    thread.start()
    return thread


class TrainingGroup:
    """Trainings of named members, run side by side in threads, whose epochs run as one
    program where their shapes agree (module docstring). Each member's thread runs its
    trainings inside ``with group.member(name):``; the i-th training of every member
    meets the i-th of the others. The stacking order (and so nothing but the program's
    layout) is ``members``' order."""

    def __init__(self, members: Iterable[str], *, _rehearsal: bool = False):
        self._members = tuple(members)
        if len(set(self._members)) != len(self._members):
            raise ValueError(f"training group members repeat: {self._members}")
        self._cond = threading.Condition()
        self._made = dict.fromkeys(self._members, 0)  # trainings handed in, per member
        self._left: set[str] = set()
        self._waiting: dict[int, dict[str, _Training]] = {}
        self._results: dict[int, dict[str, Any]] = {}
        # The rehearsals (:func:`rehearse`) meet in a twin: the trainings keep their count.
        self.rehearsal = None if _rehearsal else TrainingGroup(self._members, _rehearsal=True)

    @property
    def members(self) -> tuple[str, ...]:
        return self._members

    @contextlib.contextmanager
    def member(self, name: str) -> Iterator[None]:
        """This thread's trainings, until the block ends, are ``name``'s in the group."""
        if name not in self._made:
            raise ValueError(f"{name!r} is not a member of this training group "
                             f"({', '.join(self._members)})")
        outer = getattr(_local, "member", None)
        _local.member = (self, name)
        try:
            yield
        finally:
            _local.member = outer
            self.leave([name])

    def leave(self, names: Iterable[str]) -> None:
        """These members train no more (whether or not they ever joined): the others stop
        waiting for them. Leaving twice is leaving once."""
        names = list(names)
        with self._cond:
            self._left.update(names)
            self._cond.notify_all()
        if self.rehearsal is not None:  # one that trains no more rehearses no more either
            self.rehearsal.leave(names)

    def _submit(self, name: str, training: _Training):
        with self._cond:
            i = self._made[name]
            self._made[name] += 1
            self._waiting.setdefault(i, {})[name] = training
            self._cond.notify_all()
            while True:
                if name in self._results.get(i, {}):
                    return _raise_or_return(self._results[i].pop(name))
                if i in self._waiting and all(m in self._left or self._made[m] > i
                                              for m in self._members):
                    todo = self._waiting.pop(i)  # this thread runs the i-th trainings
                    break
                self._cond.wait()
        names = [m for m in self._members if m in todo]
        outs = _run_together([todo[m] for m in names])
        with self._cond:
            self._results[i] = dict(zip(names, outs))
            mine = self._results[i].pop(name)
            self._cond.notify_all()
        return _raise_or_return(mine)


def _run_together(trainings: list[_Training]) -> list:
    """Each training's (state, history), or its exception; trainings of equal signatures
    as one program, the programs side by side in threads (each one's host loop waits on
    its epochs while another's run)."""
    parts: dict[tuple, list[int]] = {}
    for i, t in enumerate(trainings):
        parts.setdefault(t.signature(), []).append(i)

    def run(idx: list[int]) -> list:
        try:
            return _run_stacked([trainings[i] for i in idx])
        except BaseException as exc:  # noqa: BLE001 - every training of the program gets it
            return [exc] * len(idx)

    if len(parts) == 1:
        done = [run(idx) for idx in parts.values()]
    else:
        with ThreadPoolExecutor(len(parts), thread_name_prefix="jaxinertia-group") as pool:
            done = list(pool.map(run, parts.values()))
    out: list = [None] * len(trainings)
    for idx, results in zip(parts.values(), done):
        for i, result in zip(idx, results):
            out[i] = result
    return out


def shared_cache(fn):
    """``functools.lru_cache`` (32 entries) whose misses are filled under a lock, for the
    epochs (``training._torque_epoch``, ``_attention_epoch``) and their group programs.
    Trainings share a program only if they run the same epoch object, and a plain
    ``lru_cache`` lets threads that miss at once each build their own (it calls the
    function outside its lock): then a group's members can split by timing, the one way
    found in which they could (most likely why, in a full run on an H100 in session 29,
    one of the folds' groups of four fine-tunings ran as three and one). Building an
    epoch or a ``jax.jit`` traces nothing: the lock is held briefly."""
    cached = functools.lru_cache(maxsize=32)(fn)
    lock = threading.Lock()

    @functools.wraps(fn)
    def get(*args, **kwargs):
        with lock:
            return cached(*args, **kwargs)

    get.cache_clear, get.cache_info = cached.cache_clear, cached.cache_info
    return get


@shared_cache
def _update_of_group(epoch):
    return jax.jit(jax.vmap(epoch.update_fn),
                   compiler_options=dict(epoch.compiler_options) or None)


@shared_cache
def _epochs_of(epoch, grouped: bool, n: int):
    """``n`` epochs of ``epoch`` (of a group's members: ``grouped``) as one program:
    ``(state, keys, e0, data, val_data) -> (state, (train_loss, val_loss))``, the losses with
    a leading axis of the ``n`` epochs ``e0, ..., e0 + n - 1``; ``keys`` the trainings'
    keys (stacked when ``grouped``), folded with the epoch inside."""
    update = jax.vmap(epoch.update_fn) if grouped else epoch.update_fn
    fold_in = jax.vmap(jax.random.fold_in, (0, None)) if grouped else jax.random.fold_in

    def run(state, keys, e0, data, val_data):
        def one(state, e):
            state, train_loss, val_loss = update(state, fold_in(keys, e), data, val_data)
            return state, (train_loss, val_loss)

        return jax.lax.scan(one, state, e0 + jnp.arange(n, dtype=jnp.int32))

    return jax.jit(run, compiler_options=dict(epoch.compiler_options) or None)


@jax.jit
def _stack(trees):
    # One program per group's structure and shapes (eager, each leaf's stack was a program
    # of its own: 130 of them in a full run, compiled on the folds' critical path).
    return jax.tree_util.tree_map(lambda *a: jnp.stack(a), *trees)


@functools.partial(jax.jit, static_argnums=1)
def _unstack(tree, G: int) -> list:
    # Likewise one program for the G states of a group (eager, a slice per leaf and member).
    return [jax.tree_util.tree_map(lambda a, g=g: a[g], tree) for g in range(G)]


def _run_stacked(trainings: list[_Training]) -> list:
    """G trainings of one signature: alone when G is 1, else the epoch vmapped over them.
    The K models of each (state, own data) are split over every local device
    (:mod:`jaxinertia.sharding`)."""
    G, first = len(trainings), trainings[0]
    if G == 1:
        update, axis = first.epoch.update, 0
        state, data, val_data = first.state, first.data, first.val_data
    else:
        update, axis = _update_of_group(first.epoch), 1
        state, data, val_data = (_stack([getattr(t, f) for t in trainings])
                                 for f in ("state", "data", "val_data"))
    # Placed alike whatever made them (a rehearsal's inputs): else another program compiles.
    state = shard(state, axis)
    data, val_data = ((replicate(shared), shard(own, axis)) for shared, own in (data, val_data))
    history: list[list] = [[] for _ in trainings]
    failed: list[BaseException | None] = [None] * G
    desc = first.desc if G == 1 else f"{first.desc} (x{G}, one program)"
    n = first.per_call
    if n > 1:
        several = _epochs_of(first.epoch, G > 1, n)
        keys = first.key if G == 1 else jnp.stack([t.key for t in trainings])
    if first.compile_only:  # a rehearsal: the first call's program(s), compiled only
        if n > 1:
            several.lower(state, keys, jnp.int32(0), data, val_data).compile()
        else:
            keys = [jax.random.fold_in(t.key, 0) for t in trainings]
            update.lower(state, keys[0] if G == 1 else jnp.stack(keys), data,
                         val_data).compile()
        K = jax.tree_util.tree_leaves(first.state)[0].shape[0]
        return [(t.state, np.zeros((0, 2, K), np.float32)) for t in trainings]
    with tqdm(total=first.n_epochs, desc=desc, unit="epoch",
              disable=not any(t.progress for t in trainings)) as bar:

        def read(e0, train_loss, val_loss) -> None:
            """A call's (n, G, K) losses on the host: its epochs recorded, the bar moved."""
            losses = np.asarray(train_loss), np.asarray(val_loss)
            if G == 1:
                losses = losses[0][:, None], losses[1][:, None]
            for i in range(losses[0].shape[0]):
                _record(trainings, e0 + i, (losses[0][i], losses[1][i]), history, failed)
            bar.set_postfix(val=f"{float(np.min(losses[1][-1])):.3g}", refresh=False)
            bar.update(losses[0].shape[0])

        # The host reads a call's losses after dispatching the next call: the device always
        # has the next epochs queued while the host waits, records and draws.
        pending = None
        for e0 in range(0, first.n_epochs, n):
            if n > 1:
                state, (train_loss, val_loss) = several(state, keys, jnp.int32(e0), data,
                                                        val_data)
            else:
                keys = [jax.random.fold_in(t.key, e0) for t in trainings]
                state, train_loss, val_loss = update(
                    state, keys[0] if G == 1 else jnp.stack(keys), data, val_data)
                train_loss, val_loss = train_loss[None], val_loss[None]
            if pending is not None:
                read(*pending)
            pending = (e0, train_loss, val_loss)
            if G == 1 and failed[0] is not None:
                pending = None  # alone and failed: the rest is not recorded
                break
        if pending is not None:
            read(*pending)
    if G == 1:
        return [failed[0] or (state, np.asarray(history[0]))]
    states = _unstack(state, G)
    return [failed[g] or (states[g], np.asarray(history[g])) for g in range(G)]


def _record(trainings: list[_Training], e: int, losses: tuple, history: list[list],
            failed: list) -> None:
    """Epoch ``e``'s (G, K) training and validation losses into each training's history;
    a training whose loss went non-finite fails (and records no more)."""
    for g, t in enumerate(trainings):
        if failed[g] is not None:
            continue
        history[g].append((losses[0][g], losses[1][g]))
        bad = ~(np.isfinite(losses[0][g]) & np.isfinite(losses[1][g]))
        if bad.any():
            failed[g] = TrainingError(
                f"{t.desc}: the loss went non-finite at epoch {e} (model(s) "
                f"{np.flatnonzero(bad).tolist()}); lower the learning rate or check "
                "the training data")
            continue
        if t.on_epoch is not None:
            t.on_epoch(e, history[g][-1])
