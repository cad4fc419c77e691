"""Trainings side by side as one program (jaxinertia.training_group): the trainings alone,
up to float rounding, and no member waits for one that has left."""

from __future__ import annotations

import dataclasses
import logging
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from support.asserts import assert_tree_close, assert_tree_equal
from support.synthetic import synthetic_samples

from jaxinertia import checkpoints, training, training_group
from jaxinertia.app.programs import side_by_side
from jaxinertia.errors import TrainingError
from jaxinertia.estimation import ModelPair, estimate_sets
from jaxinertia.evaluation import stack
from jaxinertia.networks import AttentionModel, PhysicalTorqueModel, TorqueModel
from jaxinertia.training import TrainConfig, train_attention_models, train_torque_models
from jaxinertia.training_group import TrainingGroup
from jaxinertia.training_setup import draw_sets, feature_config_from, split_validation

#: test_folds' and test_learning's training configuration and sample count: their
#: programs, already compiled in the session's cache.
CFG = TrainConfig(n_models=2, torque_epochs=3, attention_epochs=2, attention_sets=8,
                  attention_val_sets=4, val_fraction=0.2)
N = 160


def _job(seed: int, n: int = N, *, physical: bool = False, nan: bool = False):
    """A training pair's inputs: its own data, seed and key."""
    d = synthetic_samples(np.random.default_rng(seed), n=n, n_obj=4)
    if nan:
        d = dataclasses.replace(d, tau=np.where(np.arange(n)[:, None] == 3, np.nan, d.tau))
    tr, va = split_validation(d, CFG.val_fraction, seed)
    cfg = CFG.replace(seed=seed, torque_model="physical" if physical else "paper")
    return cfg, feature_config_from(tr), tr, va, jax.random.key(seed)


def _torque(job):
    cfg, fc, tr, va, key = job
    return train_torque_models(cfg, fc, tr, va, jax.random.split(key)[0], progress=False)


def _pair(job):
    """Torque, then attention: a training's two calls of run_epochs."""
    cfg, fc, tr, va, key = job
    torque = _torque(job)
    return torque, train_attention_models(cfg, fc, torque, tr, va, jax.random.split(key)[1],
                                          progress=False)


def _assert_same(got, want, what):
    for g, w, part in zip(got, want, ("torque", "attention")):
        assert_tree_equal(g.variables, w.variables, what=f"{what} {part} parameters")
        np.testing.assert_array_equal(g.history, w.history, err_msg=f"{what} {part} history")
        np.testing.assert_array_equal(g.best_epoch, w.best_epoch)


def _assert_torque_close(got, want, what):
    """The training alone up to float32 rounding: vmapped over the group, a minibatch's
    bias gradient may be summed in another order (last-bit differences, 1e-7 relative
    here, that three epochs carry); another member's data or key, or a wrong slice of the
    group, would move them by orders of magnitude more."""
    assert_tree_close(got.variables, want.variables, rtol=1e-5, atol=1e-9,
                      what=f"{what} torque parameters")
    np.testing.assert_allclose(got.history, want.history, rtol=1e-5)
    np.testing.assert_array_equal(got.best_epoch, want.best_epoch)


def _assert_attention_close(got, want, job, what):
    """The attention trained in a group against alone, by what it gives: the T-A mass of
    every validation set. Not by parameter: an attention model's score bias shifts every
    joint's score alike (the softmax ignores it), so its gradient is zero up to rounding
    and Adam turns any rounding into a full step of the learning rate, in either run."""
    cfg, fc, tr, va, _ = job
    pair_got, pair_want = (ModelPair(torque_vars=t.variables, attention_vars=a.variables,
                                     tau_scale=jnp.asarray(fc.tau_scale, jnp.float32),
                                     torque_model=t.model, attention_model=a.model)
                           for t, a in (got, want))
    sets = draw_sets(va.object_id, 16, CFG.set_size, 0)
    masses = []
    for pair in (pair_got, pair_want):
        batch = stack([va], [sets], fc)
        est = estimate_sets(pair, batch.features, batch.A, batch.tau_g, batch.sets)
        masses.append(np.asarray(est.TA.x)[..., 0])
    np.testing.assert_allclose(masses[0], masses[1], rtol=1e-4, atol=1e-6,
                               err_msg=f"{what}: T-A mass of the validation sets")


def _program_sizes(monkeypatch) -> list[int]:
    """The member count of every program the groups run from now on, appended as each
    starts."""
    sizes = []
    stacked = training_group._run_stacked

    def spy(trainings):
        sizes.append(len(trainings))
        return stacked(trainings)

    monkeypatch.setattr(training_group, "_run_stacked", spy)
    return sizes


def test_a_group_trains_its_members_as_alone_in_one_program_per_shape(
        monkeypatch):
    jobs = {"a": _job(1), "b": _job(2), "c": _job(3, physical=True),
            "d": _job(4, n=200)}  # d: other shapes, so another program
    alone = {name: _pair(job) for name, job in jobs.items()}
    sizes = _program_sizes(monkeypatch)
    group = TrainingGroup(jobs)

    def member(name):
        with group.member(name):
            return _pair(jobs[name])

    got = dict(zip(jobs, side_by_side([lambda n=n: member(n) for n in jobs], workers=4)))
    # Torque: paper a+b as one program, the physical c and the larger d alone. Attention
    # (one attention model for all): a, b, c as one program, d alone.
    assert sorted(sizes) == [1, 1, 1, 2, 3], sizes
    for name in "ab":
        _assert_torque_close(got[name][0], alone[name][0], name)
    assert_tree_equal(got["c"][0].variables, alone["c"][0].variables, what="c torque alone")
    for name in "abc":  # the attention trained in one program: its estimates the same
        _assert_attention_close(got[name], alone[name], jobs[name], name)
    _assert_same(got["d"], alone["d"], "d")  # alone in the group: the same programs


def test_training_sets_trimmed_alike_train_as_one_program(monkeypatch):
    """Two held-out folds' training sets that differ by a sample the simulator dropped
    (one object one sample short) have other shapes: their torque models train in two
    programs. Trimmed to the same count of each object of each file
    (``subset_per_object``, what ``FoldScale.per_load`` asks ``train`` for), in one."""
    from jaxinertia.training import subset_per_object

    full = synthetic_samples(np.random.default_rng(5), n=N, n_obj=4)  # 40 of each object
    short = full.take(np.arange(1, N))  # object 0: 39
    sizes = _program_sizes(monkeypatch)

    def two_folds(per_object):
        group = TrainingGroup(["a", "b"])

        def member(name, data, seed):
            with group.member(name):
                tr, va = split_validation(subset_per_object([data], per_object, seed),
                                          CFG.val_fraction, seed)
                cfg = CFG.replace(seed=seed)
                return train_torque_models(cfg, feature_config_from(tr), tr, va,
                                           jax.random.key(seed), progress=False)

        sizes.clear()
        side_by_side([lambda: member("a", full, 1), lambda: member("b", short, 2)], workers=2)
        return sorted(sizes)

    assert two_folds(None) == [1, 1]
    assert two_folds([39]) == [2]


def test_a_member_that_leaves_or_fails_holds_no_one_up():
    want = _torque(_job(5))
    group = TrainingGroup(["fails", "trains", "never", "nan"])
    group.leave(["never"])  # a member whose thread never ran

    def fails():
        with group.member("fails"):
            raise ValueError("before any training")

    def nan():
        with group.member("nan"):
            return _torque(_job(6, nan=True))

    def trains():
        with group.member("trains"):
            return _torque(_job(5))

    calls = {"fails": fails, "trains": trains, "nan": nan}
    out = {}

    def run(name):
        try:
            out[name] = calls[name]()
        except Exception as exc:  # noqa: BLE001 - what each member raised, checked below
            out[name] = exc

    side_by_side([lambda n=n: run(n) for n in calls], workers=3)
    assert isinstance(out["fails"], ValueError)
    # The member whose loss went non-finite gets the error alone trainings raise ...
    assert isinstance(out["nan"], TrainingError)
    assert "non-finite at epoch 0" in str(out["nan"])
    # ... and the member trained beside it (one program) is untouched by it.
    _assert_torque_close(out["trains"], want, "trains")
    with pytest.raises(ValueError, match="not a member"):
        with group.member("stranger"):
            pass


def test_short_trainings_compile_their_epochs_without_the_gpu_autotuner(monkeypatch):
    """A training of few minibatch steps (a fine-tuning) compiles its epoch without XLA's
    GPU autotuner, alone and in a group (its compile time would not be paid back); a long
    one, and any on a CPU, with XLA's defaults."""
    options = training.epoch_compiler_options
    assert options(training.AUTOTUNE_MIN_STEPS - 1, backend="gpu") == (
        ("xla_gpu_autotune_level", 0),)
    assert options(training.AUTOTUNE_MIN_STEPS, backend="gpu") == ()
    assert options(1, backend="cpu") == ()
    # The folds' largest fine-tuning (1,000 real samples and as many of each of the four
    # simulated loads, 90 % of them trained on in minibatches of 64, 200 epochs) is short;
    # a training from scratch of the paper's scale (300 epochs of 289 minibatches) is long.
    assert options(200 * (5 * 1000 * 9 // 10 // 64), backend="gpu") != ()
    assert options(300 * 289, backend="gpu") == ()
    want = {name: _torque(_job(seed)) for name, seed in (("a", 1), ("b", 2))}
    # The options reach the epoch's programs alone and in a group: a misspelt one fails
    # to compile there (the CPU's compiler checks every option's name, the GPU's too).
    steps = []
    monkeypatch.setattr(training, "epoch_compiler_options",
                        lambda n: steps.append(n) or (("xla_no_such_option", 0),))
    with pytest.raises(Exception, match="No such compile option"):
        _torque(_job(1))
    train_n = _job(1)[2].n_samples
    assert steps == [CFG.torque_epochs * (train_n // min(CFG.torque_batch, train_n))]

    def grouped():
        group = TrainingGroup(["a", "b"])

        def member(name, seed):
            with group.member(name):
                return _torque(_job(seed))
        return side_by_side([lambda: member("a", 1), lambda: member("b", 2)], workers=2)

    with pytest.raises(Exception, match="No such compile option"):
        grouped()
    # The attention, however long, as a short training: compiled without the autotuner on
    # a GPU (a rehearsal compiles it beside a training on the GPU: rehearse).
    steps.clear()
    with pytest.raises(Exception, match="No such compile option"):
        _, fc, tr, va, key = _job(1)
        train_attention_models(CFG, fc, want["a"], tr, va, key, progress=False)
    assert steps == [0]
    # The GPU's option on a CPU: ignored, the numbers without it bit for bit.
    monkeypatch.setattr(training, "epoch_compiler_options",
                        lambda n: (("xla_gpu_autotune_level", 0),))
    assert_tree_equal(_torque(_job(1)).variables, want["a"].variables, what="alone")
    for got, name in zip(grouped(), "ab"):
        _assert_torque_close(got, want[name], name)


def test_a_gpus_epochs_train_the_same_models_up_to_rounding(monkeypatch):
    """On a GPU the epochs compute the joints' embedding layers as batched products and
    ravel Adam's parameters (``training.accelerated_epochs``: fewer kernels per step); the
    models are the same up to float rounding (a group vmaps the same epoch), and their folders
    keep the per-joint architecture. On a CPU the epochs are the plain ones."""
    assert training.accelerated_epochs("gpu") == {"stacked": True, "flat": True}
    assert training.accelerated_epochs("cpu") == {"stacked": False, "flat": False}
    x = np.random.default_rng(0).normal(size=(32, 4, 4)).astype(np.float32)
    for cls in (TorqueModel, PhysicalTorqueModel, AttentionModel):
        variables = cls().init(jax.random.key(0), x)
        assert_tree_equal(cls(stacked_joints=True).init(jax.random.key(0), x), variables,
                          what=f"{cls.__name__}'s parameters")
        np.testing.assert_allclose(cls(stacked_joints=True).apply(variables, x),
                                   cls().apply(variables, x), rtol=1e-5, atol=1e-6)
    job = _job(3, physical=True)  # the group test's physical job: its plain programs
    want = _pair(job)
    monkeypatch.setattr(training, "accelerated_epochs",
                        lambda: {"stacked": True, "flat": True})
    got = _pair(job)  # the torque and the attention epochs, as a GPU builds them
    # Every product's terms in another order: float32 rounding, which three epochs carry
    # (Adam turns a rounding of a near-zero gradient into a step of up to its learning
    # rate: here up to 5e-7 in a parameter). Compared by what the models give: the
    # validation losses of every epoch and the torques at the validation samples. A
    # joint's layer applied to another joint's features, or Adam's state raveled in
    # another order than the parameters, would move them by orders of magnitude more.
    # (A group vmaps the same epoch: tests above.)
    np.testing.assert_allclose(got[0].history, want[0].history, rtol=1e-5)
    _, fc, _, va, _ = job
    np.testing.assert_allclose(
        training.torque_predictions(got[0].model, got[0].variables, fc, va),
        training.torque_predictions(want[0].model, want[0].variables, fc, va),
        rtol=1e-4, atol=1e-6, err_msg="torques at the validation samples [N m]")
    _assert_attention_close(got, want, job, "attention")
    assert got[0].model == want[0].model == PhysicalTorqueModel(n_joints=4)
    assert got[1].model == want[1].model == AttentionModel(n_joints=4)
    for model in (PhysicalTorqueModel(stacked_joints=True), AttentionModel(stacked_joints=True)):
        assert checkpoints._arch(model) == checkpoints._arch(model.clone(stacked_joints=False))



def test_several_epochs_per_call_train_the_same_models_as_one_per_call(monkeypatch):
    """A training of short epochs (a fine-tuning's) runs several epochs per program call, a
    ``lax.scan`` over them with each epoch's key folded inside: alone and in a group, the
    same models, losses and best epochs as one epoch per call, bit for bit on a CPU (the
    same epoch, the same keys); a loss gone non-finite names its epoch either way."""
    per_call = training_group.epochs_per_call
    assert per_call(200, 1) == 25  # a fine-tuning on 64 samples: 8 calls
    assert per_call(200, 14) == 25  # on 1000
    assert per_call(300, 289) == 1  # the paper's torque training from scratch
    assert per_call(30, 281) == 1  # its attention
    assert per_call(60, 100) == 5  # at most 512 steps a call, dividing the epochs
    assert per_call(7, 1) == per_call(1, 1) == per_call(200, 0) == 1
    assert per_call(15, 1) == 1 and per_call(16, 1) == 2  # on_epoch's timings: per epoch
    cfg = CFG.replace(torque_epochs=16)  # N samples: one step an epoch, 2 epochs a call

    def torque(seed, nan=False):
        c, fc, tr, va, key = _job(seed, nan=nan)
        return train_torque_models(cfg.replace(seed=seed), fc, tr, va,
                                   jax.random.split(key)[0], progress=False)

    def grouped():
        group = TrainingGroup(["a", "b"])

        def member(name, seed):
            with group.member(name):
                return torque(seed)
        return side_by_side([lambda: member("a", 1), lambda: member("b", 2)], workers=2)

    calls = []
    several = training_group._epochs_of
    monkeypatch.setattr(training_group, "_epochs_of",
                        lambda *a: calls.append(a[1:]) or several(*a))
    got = {"alone": [torque(1)], "group": grouped()}
    assert calls == [(False, 2), (True, 2)]
    with pytest.raises(TrainingError, match="non-finite at epoch 0"):
        torque(6, nan=True)
    monkeypatch.setattr(training_group, "STEPS_PER_CALL", 0)  # one epoch a call
    want = {"alone": [torque(1)], "group": grouped()}
    assert len(calls) == 3  # the non-finite training's; none since
    for how in want:
        for g, w in zip(got[how], want[how]):
            assert g.history.shape == (16, 2, CFG.n_models)
            assert_tree_equal(g.variables, w.variables, what=f"{how}: parameters")
            np.testing.assert_array_equal(g.history, w.history, err_msg=f"{how}: history")
            np.testing.assert_array_equal(g.best_epoch, w.best_epoch)
    with pytest.raises(TrainingError, match="non-finite at epoch 0"):
        torque(6, nan=True)


def test_threads_building_the_same_epoch_at_once_get_one_program(monkeypatch):
    """A group runs trainings together only if their epochs are the same object; threads
    (the folds' branches) that ask for the same epoch at once must all get it, however
    their building interleaves (here made slow: a plain ``lru_cache`` let each build its
    own, and a group of four then ran as three and one)."""
    make = training.make_epoch

    def slow(*args, **kwargs):
        time.sleep(0.05)
        return make(*args, **kwargs)

    monkeypatch.setattr(training, "make_epoch", slow)
    model = PhysicalTorqueModel(n_joints=4)
    args = (model, 1.25e-4, "servo", 57)  # a setting no other test builds
    epochs = side_by_side([lambda: training._torque_epoch(*args)] * 4, workers=4)
    assert all(e is epochs[0] for e in epochs)
    assert training._torque_epoch(*args) is epochs[0]
    attention = (AttentionModel(n_joints=4), 1.25e-4, "all", 7, 1.0, 0.3)
    epochs = side_by_side([lambda: training._attention_epoch(*attention)] * 4, workers=4)
    assert all(e is epochs[0] for e in epochs)


@pytest.mark.parametrize("attention_epochs", [2, 16])  # one epoch a program call, and two
def test_a_rehearsal_compiles_the_groups_attention_program_and_changes_nothing(
        monkeypatch, attention_epochs):
    """``rehearse`` (the folds' attention, compiled while the torque models train): the
    group's later attention training compiles no epoch program of its own, and its members'
    models are those of the same group without the rehearsal, bit for bit."""
    cfg = CFG.replace(attention_epochs=attention_epochs)
    # Shapes no other test trains (n = 172; the two cases share the torque's programs):
    # the attention's programs are compiled here, by the rehearsal.
    jobs = {name: (cfg.replace(seed=seed), *_job(seed, n=172)[1:])
            for name, seed in (("a", 11), ("b", 12), ("c", 13))}
    compiled: list[list[str]] = []  # per real attention program: the programs it compiled
    stacked = training_group._run_stacked

    class Programs(logging.Handler):  # the names of the programs XLA compiles
        def emit(self, record):
            if "Finished XLA compilation" in record.getMessage():
                compiled[-1].append(record.getMessage())

    def spy(trainings):
        if trainings[0].compile_only or trainings[0].desc != "attention model":
            return stacked(trainings)
        logger, handler = logging.getLogger("jax"), Programs()
        compiled.append([])
        logger.addHandler(handler)
        propagate, logger.propagate = logger.propagate, False
        try:
            with jax.log_compiles(True):
                return stacked(trainings)
        finally:
            logger.removeHandler(handler)
            logger.propagate = propagate

    monkeypatch.setattr(training_group, "_run_stacked", spy)

    def run(rehearsed: bool):
        group = TrainingGroup(jobs)
        rehearsals = []

        def member(name):
            cfg, fc, tr, va, key = jobs[name]
            with group.member(name):
                if rehearsed:
                    rehearsals.append(training.rehearse_attention(
                        cfg, fc, tr, va, jax.random.split(key)[1]))
                    rehearsals[-1].join()  # here: compiled before the torque trains
                return _pair(jobs[name])

        out = side_by_side([lambda n=n: member(n) for n in jobs], workers=3)
        assert all(not t.is_alive() for t in rehearsals) and len(rehearsals) == 3 * rehearsed
        return out

    got = run(rehearsed=True)
    # The members' attention as one program, found compiled: nothing named after an epoch
    # program ("update", or "run" for several epochs a call) compiled in it.
    assert len(compiled) == 1
    assert not [m for m in compiled[0] if "jit(update)" in m or "jit(run)" in m], compiled
    assert training_group.rehearse(lambda: None) is None  # outside a group: nothing to do
    if attention_epochs == 2:
        return  # the control (all compiled anew: 20 s of a 2-core CI) once, below
    jax.clear_caches()  # the programs forgotten: without the rehearsal, compiled anew
    want = run(rehearsed=False)
    # ... which the same group without the rehearsal compiles there (the check can fail).
    assert [m for m in compiled[1] if "jit(update)" in m or "jit(run)" in m], compiled
    for name, g, w in zip(jobs, got, want):
        _assert_same(g, w, name)
