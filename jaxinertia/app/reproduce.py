"""``jaxinertia reproduce``: the paper end to end on the simulator, then sim-to-real.

Stages (each timed): simulate the training, test and continuous data; train K model pairs;
evaluate Tables I-III on the simulated test objects; the switching-load run; evaluate the
trained models on the real lbipe files beside the authors' released models; write
``report.md``, ``tables.json`` and the plots into the run folder.

``QUICK`` (the default, ``make demo``) keeps the paper's hyperparameters but simulates fewer
samples, trains five model pairs and draws fewer attention training sets, to finish in a few
minutes on a 2-core CPU. ``FULL`` is the paper's scale (GPU recommended).
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import platform
import time
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import jax

from jaxinertia.app import plots
from jaxinertia.app.folds import FoldScale, run_folds
from jaxinertia.app.models_real import (
    models_from_folds,
    models_real,
    recipe_of,
    sim_fit_files,
    sim_fit_session,
)
from jaxinertia.app.pipeline import (
    RealData,
    adapt_objects,
    evaluate_samples,
    load_real,
    session_reference,
    sim_to_real,
    train,
)
from jaxinertia.app.programs import side_by_side
from jaxinertia.app.provenance import record_fitted_on
from jaxinertia.app.report import reproduce_report
from jaxinertia.app.simdata import cached, params_digest, simulate_files
from jaxinertia.app.with_released import (
    drop_with_released,
    judge_draws,
    judge_each_draw,
    judge_with_released,
    models_with_released,
)
from jaxinertia.arm import Arm
from jaxinertia.arms import DEFAULT_ARM, get_arm
from jaxinertia.checkpoints import load_models
from jaxinertia.errors import UsageError
from jaxinertia.evaluation import choose_sets, continuous_force
from jaxinertia.fileio import replacing, write_json, write_text
from jaxinertia.lbipe import default_lbipe_dir
from jaxinertia.samples import SampleFile
from jaxinertia.sim.continuous import simulate_continuous_run, walk_lanes
from jaxinertia.sim.params import arm_sim_params
from jaxinertia.training import TrainConfig
from jaxinertia.uncertainty import (
    interval_coverage,
    training_validation_error,
    uncertainty_of,
    z_of,
)

__all__ = ["FULL", "QUICK", "Scale", "reproduce"]


@dataclass(frozen=True)
class Scale:
    planning: bool  # the 10 deg planning grid per training load
    random_per_load: int
    test_per_object: int
    continuous_samples: int
    switch_every: int
    train: TrainConfig
    n_sets: int = 1000  # evaluation repeats per object (the paper's 1000)
    #: Held-out folds (fit on one real object, judge on the other): servo/friction
    #: calibration iterations per fold; 0 leaves the folds out.
    fold_calibration_iterations: int = 6
    #: Per fold, fine-tunings of its simulator-trained models on that many real samples of
    #: the object it was calibrated on (judged on the other object).
    fold_finetune_samples: tuple[int, ...] = (1000,)
    #: The models for a new real object (0: left out): where the folds ran, their own
    #: folders (``models_real.models_from_folds``); else the physical torque model trained
    #: on the run's simulated data, its servo part fine-tuned on this many samples of
    #: *every* real object in the lbipe folder (beside as many of each simulated training
    #: load, as the folds' fine-tunings). Their numbers on those objects are not
    #: held out; the folds' rows are the honest estimate of such models.
    real_finetune_samples: int = 1000
    #: The folds also judge the physical model with the servo's current as an input
    #: (``FoldScale.current_input``; the quick scale leaves it out for ``make demo``'s time).
    fold_current_input: bool = False
    #: With ``fold_current_input``: also the current-input candidates trained on this many
    #: drawn recording sessions (``FoldScale.session_draws``; 0: left out).
    fold_session_draws: int = 0
    #: The held-out folds of that many training draws (seeds ``seed``, ``seed + 1``, ...;
    #: ``run_folds``' ``draws``): the recipe chosen over all of them and ``models_real`` the
    #: mean of every draw's folders it names (docs/results.md, "Several training draws
    #: averaged").
    fold_draws: int = 1
    #: ``models_real`` takes the mass and the COM each from the candidate the folds judge
    #: best for it, where those differ (:mod:`jaxinertia.app.by_part`).
    recipe_by_part: bool = True


QUICK = Scale(planning=False, random_per_load=800, test_per_object=300,
              continuous_samples=2048, switch_every=512,
              # 3,200 training samples give 12 minibatches an epoch (the full run: 289), so
              # the torque model gets a larger step to converge in its 300 epochs.
              train=TrainConfig(n_models=5, attention_sets=250, attention_val_sets=50,
                                torque_lr=1e-3))
FULL = Scale(planning=True, random_per_load=9000, test_per_object=1000,
             continuous_samples=4096, switch_every=1024, train=TrainConfig(),
             fold_finetune_samples=(64, 250, 1000), fold_current_input=True,
             fold_session_draws=4, fold_draws=3)


def _machine() -> str:
    dev = jax.devices()[0]
    kind = getattr(dev, "device_kind", dev.platform)
    return (f"{platform.machine()} {os.cpu_count()} CPU cores, JAX {jax.__version__} on "
            f"{dev.platform} ({kind})")


CONTINUOUS_OBJECTS = ["empty", "cube", "white", "black"]


def _continuous(params, path: Path, scale: Scale, seed: int,
                arm: Arm | None = None) -> SampleFile:
    kw = dict(n=scale.continuous_samples, objects=CONTINUOUS_OBJECTS,
              switch_every=scale.switch_every, seed=seed,
              lanes=walk_lanes(scale.continuous_samples))
    other = {} if arm is None or arm.name == DEFAULT_ARM else {"arm": arm.name}

    def make():
        return simulate_continuous_run(params, **kw, arm=arm)

    return cached(path, {"scenario": "continuous", **kw, "simulator": params_digest(params),
                         **other}, make, only_at_rest=False)  # read without waiting for rest


def _coverage(models: Path, test_file: SampleFile, real: RealData | None, *, n_sets: int,
              set_size: int, seed: int) -> dict:
    """Coverage of the trained models' intervals on the simulated test objects (the sets of
    the evaluate stage) and, when there are real files, on them."""
    folder = load_models(models)
    pair, fc, config = folder.pair, folder.features, folder.config
    floor, why = training_validation_error(config)
    objects, _ = adapt_objects(test_file.samples.by_object(),
                               session_reference(config, simulated=True))
    sets, _ = choose_sets(objects, n_sets=n_sets, set_size=set_size, seed=seed)
    out = {"floor": {"Nm": None if floor is None else floor.tolist(), "source": why},
           "simulated": interval_coverage(objects, uncertainty_of(objects, sets, pair=pair, fc=fc,
                                                            floor=floor))}
    if real is not None:
        real_objects, _ = adapt_objects(real.objects, session_reference(config))
        out["real"] = interval_coverage(real_objects, uncertainty_of(
            real_objects, real.sets, pair=pair, fc=fc, floor=floor))
    return out


def plot_interval_width(cal: dict, path: Path, title: str, method: str = "T-A") -> Path:
    """|error| against the 95 % interval's half-width, per set: mass and COM coordinates;
    points under the diagonal are sets whose interval holds the truth."""
    plt = plots.pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.2))
    se, err = cal["per_set"][method]["se"], cal["per_set"][method]["error"]
    z = z_of(0.95)
    for o, name in enumerate(cal["objects"]):
        c = cal["objects"][name][method][0.95]
        for ax, cols, scale, unit in ((axes[0], [0], 1e3, "g"), (axes[1], [1, 2, 3], 1e3, "mm")):
            w = (z * se[o][:, cols] * scale).ravel()
            e = (abs(err[o][:, cols]) * scale).ravel()
            share = c["mass"] if cols == [0] else c["com"]
            ax.scatter(w, e, s=4, alpha=0.35, label=f"{name}: {100 * share:.0f} % inside")
            ax.set(xlabel=f"95 % half-width [{unit}]", ylabel=f"|error| [{unit}]")
    for ax, what in zip(axes, ("mass", "COM coordinates")):
        hi = max(ax.get_xlim()[1], ax.get_ylim()[1])
        ax.plot([0, hi], [0, hi], "k--", lw=1)
        ax.set(title=f"{method}: {what}")
        ax.legend(fontsize=8, markerscale=3)
        ax.grid(alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    with replacing(path, suffix=path.suffix) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
    return path


class _Stages:
    """Times each stage of a run (printed as it starts and ends)."""

    def __init__(self):
        self.timings: dict[str, float] = {}
        self.t0 = time.perf_counter()

    @contextlib.contextmanager
    def __call__(self, name: str):
        print(f"== {name}", flush=True)
        t = time.perf_counter()
        yield
        self.timings[name] = time.perf_counter() - t
        print(f"   {name}: {self.timings[name]:.1f} s", flush=True)

    def total(self) -> dict[str, float]:
        return {**self.timings, "total": time.perf_counter() - self.t0}


def reproduce(out: str | os.PathLike, *, full: bool = False, seed: int = 0,
              lbipe_dir: str | os.PathLike | None = None, scale: Scale | None = None,
              progress: bool = True, arm: Arm | str | None = None,
              draws: int | None = None) -> dict:
    """Runs every stage into the folder ``out``; returns the results (also in tables.json).
    The real-data folder is read once, here, and handed down. ``arm``: the simulated arm
    (default the OpenMANIPULATOR-X); the real-data stages (sim-to-real, held-out folds,
    models for a new real object) are the OpenMANIPULATOR-X's only and are skipped, with a
    note, for another arm.

    The held-out folds need nothing of the simulated stages: on an accelerator they run
    beside them (:func:`jaxinertia.app.programs.side_by_side`; the stage times then
    overlap), on a CPU after them. The models for a new real object are then the folds' own
    (:func:`jaxinertia.app.models_real.models_from_folds`): nothing more is trained.
    ``draws``: the folds' training draws (default the scale's ``fold_draws``)."""
    scale = scale or (FULL if full else QUICK)
    if draws is not None:
        if draws < 1:
            raise UsageError(f"--draws {draws}: one training draw or more")
        scale = dataclasses.replace(scale, fold_draws=draws)
    out = Path(out)
    stage = _Stages()
    arm = get_arm(arm)
    lbipe_dir = Path(lbipe_dir) if lbipe_dir else default_lbipe_dir()
    real_skipped = None if arm.name == DEFAULT_ARM else (
        f"the real lbipe files are the {DEFAULT_ARM}'s; this run simulates the {arm.name} "
        "(sim-to-real, held-out folds and the models for a new real object need its real "
        "samples)")
    real = (load_real(lbipe_dir, seed=seed, n_sets=scale.n_sets)
            if lbipe_dir.is_dir() and real_skipped is None else None)

    judged: dict = {}  # the folds' estimates, for judging models_real_with_released

    def held_out() -> dict | None:
        if real is None or scale.fold_calibration_iterations <= 0:
            return None
        with stage("held-out folds"):
            return run_folds(out / "folds", lbipe_dir, FoldScale(
                calibration_iterations=scale.fold_calibration_iterations,
                random_per_load=scale.random_per_load, planning=scale.planning,
                train=scale.train, finetune_samples=scale.fold_finetune_samples,
                current_input=scale.fold_current_input,
                session_draws=scale.fold_session_draws),
                seed=seed, draws=scale.fold_draws, progress=progress, real=real, keep=judged)

    sim, folds = side_by_side([
        partial(_simulated_stages, out, scale, arm, real, lbipe_dir, real_skipped, seed,
                progress, stage), held_out])
    real_ft = None
    if real is not None and scale.real_finetune_samples > 0:
        recipe = recipe_of(folds, scale)
        with stage("models for a new real object"):
            # The folds' own models where they ran (what they judged, each on one real
            # file); else the default recipe on the shipped calibration and every file.
            real_ft = (models_from_folds(out, folds, real, recipe) if folds else
                       models_real(out, sim["train_files"], real, scale, recipe, seed,
                                   progress, sim["session"]))
            if folds:  # judged held out, each file by the members that did not see it
                real_ft["held_out"] = {
                    **judge_draws(folds, judged["estimates"], real, recipe),
                    "each_draw": judge_each_draw(folds, judged["estimates"], real, recipe)}
                # (the folds judged the released models: their weights are there)
                # Beside them, half and half with the authors' released models, judged by
                # the same folds (app.with_released).
                real_ft["with_released"] = {
                    **models_with_released(out, real),
                    "held_out": judge_with_released(folds, judged["estimates"],
                                                    judged["released"], real, recipe)}
            elif (stale := drop_with_released(out)) is not None:
                print(f"removed {stale}: a previous run's average of another models_real "
                      "(this run's folds did not run)")
    info, ev, coverage, cres, s2r = (sim[k] for k in ("info", "evaluation", "coverage",
                                                       "continuous", "sim-to-real"))
    results = {
        "machine": _machine(), "arm": arm.name, "real_skipped": real_skipped,
        "scale": dataclasses.asdict(scale), "timings_s": stage.total(),
        "training": {k: info[k] for k in ("samples", "best_epoch", "wall_time_s", "data")},
        "simulated": {k: ev[k] for k in ("objects", "torque", "diagnostics", "unavailable")},
        "continuous": {m: v["MAE_N"] for m, v in cres["methods"].items()},
        "real": None if s2r is None else {k: v for k, v in s2r.items() if k != "note"},
        "held_out": folds,
        "real_finetuned": real_ft,
        "coverage": {"floor": coverage["floor"],
                     **{k: coverage[k]["objects"] for k in ("simulated", "real") if k in coverage}},
    }
    write_json(out / "tables.json", results)
    figs = _figures(out, info, ev, cres, coverage, s2r)
    write_text(out / "report.md", reproduce_report(
        results, figs, full=full, seed=seed, scale=scale, continuous=sim["continuous_run"],
        real_note=None if s2r is None else s2r.get("note", ""), lbipe_dir=lbipe_dir))
    print(f"wrote {out / 'report.md'}, {out / 'tables.json'} and {len(figs)} plots")
    return results


def _simulated_stages(out: Path, scale: Scale, arm: Arm, real: RealData | None,
                      lbipe_dir: Path, real_skipped: str | None, seed: int, progress: bool,
                      stage: _Stages) -> dict:
    """The stages on the simulator's data (simulate, train, evaluate, uncertainty, the
    switching-load run) and sim-to-real: their records by name."""
    data_dir = out / "data"
    params = arm_sim_params(arm)
    with stage("simulate"):
        wanted = [(data_dir / "test.npz", "test", scale.test_per_object, seed + 1000),
                  (data_dir / "train_random.npz", "random", scale.random_per_load, seed)]
        if scale.planning:
            wanted.append((data_dir / "train_planning.npz", "planning", None, seed))
        test_file, *train_files = simulate_files(params, wanted, progress=progress, arm=arm)
    session = sim_fit_session(real)
    with stage("train"):
        # Before the switching-load run's simulation: beside the folds (an accelerator),
        # this training then runs while theirs have not started (their calibrations and
        # simulations leave the device mostly idle), not as one more program per epoch
        # beside their trainings.
        info = train(train_files, out / "models", scale.train.replace(seed=seed), overwrite=True,
                     progress=progress, session=session, arm=arm.name)
        record_fitted_on(out / "models", sim_fit_files(real))  # the simulator's real files
    with stage("simulate continuous"):
        cont_file = _continuous(params, data_dir / "continuous.npz", scale, seed, arm)
    with stage("evaluate"):
        ev = evaluate_samples(out / "models", test_file, n_sets=scale.n_sets, seed=seed,
                              arm=arm.name)
    with stage("uncertainty"):
        coverage = _coverage(out / "models", test_file, real, n_sets=scale.n_sets,
                             set_size=scale.train.set_size, seed=seed)
    with stage("continuous"):
        cres, cont = _continuous_force(out / "models", cont_file)
    with stage("sim-to-real"):
        s2r = None if real_skipped else sim_to_real(out / "models", lbipe_dir, seed=seed,
                                                    real=real)
    return {"train_files": train_files, "session": session, "info": info, "evaluation": ev,
            "coverage": coverage, "continuous": cres, "continuous_run": cont,
            "sim-to-real": s2r}


def _continuous_force(models: Path, cont_file: SampleFile) -> tuple[dict, dict]:
    """The switching-load run's vertical force by every method, and what it held."""
    folder = load_models(models)
    run = cont_file.samples
    names = [run.names[i] for i in run.object_id]
    return (continuous_force(run, folder.pair, folder.baselines, folder.features),
            {"n": len(names), "objects": names})


def _figures(out: Path, info: dict, sim: dict, cres: dict, coverage: dict,
             s2r: dict | None) -> dict[str, Path]:
    figs = {"training": plots.plot_training(info["history"], out / "training.png"),
            "table1": plots.plot_table1(sim["objects"], out / "table1_sim.png",
                                        "simulated test objects"),
            "continuous": plots.plot_continuous(cres, out / "continuous.png"),
            "coverage": plot_interval_width(coverage["simulated"], out / "coverage_sim.png",
                                            "simulated test objects: interval width against "
                                            "error")}
    if s2r and "ours" in s2r:
        figs["real"] = plots.plot_table1(s2r["ours"]["objects"], out / "table1_real.png",
                                         "real lbipe files, models trained on the simulator")
    return figs
