"""One held-out fold (:mod:`jaxinertia.app.folds`): its scale (:class:`FoldScale`) and what
its stages share (:class:`Fold`: where it writes, the real file it fits on, the files it
is judged on, its training draw and its place in the training groups, and its judge)."""

from __future__ import annotations

import contextlib
import functools
from dataclasses import dataclass, field
from pathlib import Path

from jaxinertia.app.ensemble import NETWORK_METHODS
from jaxinertia.app.fold_groups import FoldGroups
from jaxinertia.app.pipeline import RealData, adapt_objects, evaluate_models, session_reference
from jaxinertia.checkpoints import load_models
from jaxinertia.evaluation import evaluate
from jaxinertia.open_manipulator_x import ARM as OMX_ARM
from jaxinertia.plans import planning_plan
from jaxinertia.session import ServoSession, servo_session
from jaxinertia.training import FINETUNE_DEFAULTS, TrainConfig

__all__ = ["SESSION_STRENGTHS", "Fold", "FoldScale"]


#: Session adaptation off and on: every candidate of a fold is judged both ways.
SESSION_STRENGTHS = (0.0, 0.5, 1.0)


@dataclass(frozen=True)
class FoldScale:
    calibration_iterations: int  # servo/friction fixed-point iterations (then the offsets)
    random_per_load: int  # simulated training samples per training load
    planning: bool  # also the planning grid per load
    train: TrainConfig
    finetune_samples: tuple[int, ...] = (1000,)  # real samples of fit_on per fine-tuning
    finetune: TrainConfig = TrainConfig(**FINETUNE_DEFAULTS, trainable="servo")
    #: > 0: also models trained on domain-randomized data (that many simulated arms drawn
    #: around the fold's calibration with the spread measured on the fold's object).
    randomize_draws: int = 0
    #: > 0: after the fixed-point calibration, identify the simulator sample by sample on
    #: the fold's object (:mod:`jaxinertia.sim.identify`, this many ES generations of
    #: ``identify_population`` candidates); the fold then trains on the identified one.
    identify_generations: int = 0
    identify_population: int = 32
    #: The identification's cost grows with the samples it replays: > 0 identifies on that
    #: many of the fold's samples (a seeded random choice), 0 on all of them.
    identify_samples: int = 0
    #: The session strengths every candidate is judged at (:data:`SESSION_STRENGTHS`).
    session_strengths: tuple[float, ...] = SESSION_STRENGTHS
    #: Also the physical model and its fine-tunings with the servo's current torque as a
    #: fifth input per joint (``train --current-input``): more candidates, more training.
    current_input: bool = False
    #: > 0 (with ``current_input``): also the current-input candidates trained on data of
    #: that many recording sessions drawn around the fold's calibration
    #: (:func:`jaxinertia.sim.randomize.session_prior`): each session's current and torque
    #: per tick scaled alike, so the current, not the discrepancy, tells the torque.
    session_draws: int = 0
    #: The fine-tunings also see ``n`` samples of each load of their start's simulated data
    #: (docs/results.md, "The simulator's loads beside the real one").
    finetune_anchor: bool = True

    @property
    def per_load(self) -> tuple[int, ...]:
        """Simulated samples of each training load that every fold's trainings from scratch
        keep of each of their files (``train``'s ``samples_per_object``: the random
        scenario's, then the planning grid's when the scale has it): the file's count less
        a thousandth (all of fewer than a thousand). The simulator drops a sample that does
        not come to rest, a different few in each fold; trimmed alike, every fold's
        trainings of a kind have the same shapes, and on an accelerator train as one program
        (:mod:`jaxinertia.app.fold_groups`) instead of one per sample count
        (docs/benchmarks.md, "Session 43")."""
        counts = [self.random_per_load] + ([_planning_per_load()] if self.planning else [])
        return tuple(n - n // 1000 for n in counts)


@functools.cache
def _planning_per_load() -> int:
    """Goals of the OpenMANIPULATOR-X's planning grid (each training load's)."""
    arm = OMX_ARM
    return len(planning_plan(arm.planning_step_deg, clearance=arm.mount_clearance_m,
                             robot=arm.robot(), workspace=arm.workspace_deg).q_d)


@dataclass(frozen=True)
class Fold:
    """What one fold's stages share: where it writes, which object it fits and judges."""

    dir: Path
    fit_on: str
    held: list[str]
    real: RealData
    scale: FoldScale
    seed: int
    progress: bool
    groups: FoldGroups | None = None
    #: The fold's training draw (:func:`jaxinertia.app.folds.run_folds`' ``draws``): "" for
    #: the first, else ``seed<seed>`` (the folder its folds write under).
    draw: str = ""
    #: (folder name, strength) -> {method: held-out estimates (O, K, B, 4)} of every folder
    #: judged: the members of the candidates' mean
    #: (:func:`jaxinertia.app.folds.run_folds`' average of every candidate).
    estimates: dict = field(default_factory=dict)

    def member(self, group: str, name: str):
        """This thread's trainings as the member ``fit_on/name`` of the fold's ``group``
        ("scratch" or "finetune"), when trainings are grouped."""
        if self.groups is None:
            return contextlib.nullcontext()
        return getattr(self.groups, group).member(f"{self.key}/{name}")

    def branch(self, fn, name: str | None = None):
        """``fn`` as a call whose end (normal or not) releases the fold's members under
        ``name`` (all of them when None)."""
        def call():
            try:
                return fn()
            finally:
                if self.groups is not None:
                    self.groups.leave(self.key if name is None else f"{self.key}/{name}")
        return call

    @property
    def key(self) -> str:
        """The fold's name in its training groups: ``[seed<seed>/]fit_on``."""
        return f"{self.draw}/{self.fit_on}" if self.draw else self.fit_on

    def workers(self, n_calls: int) -> int | None:
        """Side by side for ``n_calls`` calls that hold group members: a thread each
        (a member waiting for one not yet started would wait forever)."""
        return None if self.groups is None else n_calls

    def index(self, name: str) -> int:
        return [o.name for o in self.real.objects].index(name)

    def record(self, name: str):
        """The real object's samples as the command read them (never read again)."""
        return self.real.objects[self.index(name)]

    @property
    def session(self) -> ServoSession:
        """The session of ``fit_on``'s real file: the servo state its simulator imitates,
        the reference of every model the fold trains."""
        return servo_session(self.record(self.fit_on))

    @property
    def held_index(self) -> list[int]:
        return [self.index(n) for n in self.held]

    def judge(self, models: Path) -> dict:
        """The folder on the held-out objects at every strength of the scale's
        ``session_strengths`` (``objects``, ``torque``: at the folder's own)."""
        idx = self.held_index
        objects = [self.real.objects[i] for i in idx]
        sets, l_max = [self.real.sets[i] for i in idx], [self.real.l_max[i] for i in idx]
        folder = load_models(models)
        own = session_reference(folder.config)
        out = {"by_strength": {}}
        for s in self.scale.session_strengths:
            adapted, ratios = adapt_objects(objects, session_reference(folder.config, s))
            res = evaluate(adapted, sets, pair=folder.pair, baselines=folder.baselines,
                           fc=folder.features, l_max=l_max)
            out["by_strength"][str(s)] = res["objects"]
            self.estimates[(models.name, s)] = {m: res["estimates"][m] for m in NETWORK_METHODS}
            if own is None or own.strength == s:
                out.update(objects=res["objects"], torque=res["torque"],
                           session_ratio={o.name: r for o, r in zip(objects, ratios)})
        if "objects" not in out:  # a strength outside the grid: judged once more
            res = evaluate_models(models, objects, sets, l_max=l_max)
            out.update(objects=res["objects"], torque=res["torque"],
                       session_ratio=res["session_ratio"])
        return out
