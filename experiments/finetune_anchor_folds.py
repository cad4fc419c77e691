"""The folds' fine-tunings with and without the simulator's loads beside the real one
(``FoldScale.finetune_anchor``, session 40).

For each fold of a finished ``reproduce`` run, every physical start
(``folds/fit_<object>/models_physical*``) is fine-tuned again on the fold's real file at
each size, as the folds do (``FINETUNE_DEFAULTS``, seed 0, ``--trainable servo``): on the
real samples alone, and with ``n`` samples of each load of the start's simulated random
data beside them (the fold's ``data/train_random.npz``, or ``train_random_sessions.npz``
for the drawn-sessions start; where the run's data were not kept, ``--simulate N`` makes
N per load from the fold's ``calibration.json``). Each is judged on the held-out file at
session strength 0 (T, the recipe's mass part), and so is the mean of every candidate
(the fold's four from the simulator alone and the nine fine-tuned, as
``ensemble.judge_mean`` averages them), whose mass score over the released models' T-A is
the recipe's measure.

    python experiments/finetune_anchor_folds.py --run DIR --lbipe-dir DIR [--simulate 1000]
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from candidate_ensemble import _metrics  # noqa: E402

from jaxinertia.app.pipeline import (  # noqa: E402
    evaluate_models,
    load_real,
    released_benchmark,
    train,
)
from jaxinertia.app.simdata import simulate_files  # noqa: E402
from jaxinertia.sim.params import arm_sim_params  # noqa: E402
from jaxinertia.sim.randomize import session_prior  # noqa: E402
from jaxinertia.training import FINETUNE_DEFAULTS, TrainConfig  # noqa: E402

STARTS = ("physical", "physical_current", "physical_current_sessions")
SIM_ONLY = ("models", "models_physical", "models_physical_current",
            "models_physical_current_sessions")
SIZES = (64, 250, 1000)


def _sim_data(fold: Path, start: str, per_load: int | None, out: Path) -> Path:
    """The start's simulated random data: the run's own, else simulated anew."""
    name = "train_random_sessions.npz" if start.endswith("sessions") else "train_random.npz"
    kept = fold / "data" / name
    if kept.is_file():
        return kept
    if per_load is None:
        raise SystemExit(f"{kept}: not kept by the run; --simulate N makes N per load")
    params = arm_sim_params(None, fold / "calibration.json")
    spread = ({"spread": session_prior(params.robot.n_joints), "draws": 4}
              if name.endswith("sessions.npz") else {})
    return simulate_files(params, [(out / f"{fold.name}_{name}", "random", per_load, 0)],
                          progress=False, **spread)[0]


def real_and_released(lbipe_dir: str, prefix: str):
    """The real files, their names, the released models' benchmark on them and a scratch
    folder: what every fine-tuning experiment on a run's folds starts from."""
    real = load_real(lbipe_dir)
    released = released_benchmark(lbipe_dir, real=real)["objects"]
    return real, [o.name for o in real.objects], released, Path(tempfile.mkdtemp(prefix=prefix))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run", required=True, help="a reproduce output folder (with folds/)")
    p.add_argument("--lbipe-dir", required=True)
    p.add_argument("--simulate", type=int, default=None,
                   help="samples per load to simulate where the run's data were not kept")
    a = p.parse_args()
    real, names, released, tmp = real_and_released(a.lbipe_dir, "finetune-anchor-")
    ratios: dict[str, list[float]] = {"alone": [], "anchored": []}
    for fit_on in names:
        fold = Path(a.run) / "folds" / f"fit_{fit_on}"
        for held in (n for n in names if n != fit_on):
            i = names.index(held)
            obj, sets, l_max = real.objects[i], real.sets[i], real.l_max[i]

            def estimates(folder: Path, obj=obj, sets=sets, l_max=l_max) -> np.ndarray:
                r = evaluate_models(folder, [obj], [sets], l_max=[l_max], session_strength=0.0)
                return np.asarray(r["estimates"]["T"][0])

            sim_only = [estimates(fold / c) for c in SIM_ONLY]
            ours = {"alone": list(sim_only), "anchored": list(sim_only)}
            for start in STARTS:
                anchor = _sim_data(fold, start, a.simulate, tmp)
                for n in SIZES:
                    for how, files in (("alone", []), ("anchored", [anchor])):
                        dst = tmp / f"{fit_on}_{start}_{n}_{how}"
                        train([real.files[names.index(fit_on)], *files], dst,
                              TrainConfig(**FINETUNE_DEFAULTS, trainable="servo", seed=0),
                              overwrite=True, progress=False, init=fold / f"models_{start}",
                              samples_per_object=n)
                        x = estimates(dst)
                        ours[how].append(x)
                        mass, com, bias = _metrics(x, obj, l_max)
                        print(f"{fit_on} -> {held}  {start:26s} {n:5d} {how:9s} T mass "
                              f"{mass:6.2f} (bias {bias:+6.2f})  COM {com:6.2f}", flush=True)
            ref = released[held]["T-A"]["mass_NMAE_pct"]
            for how, xs in ours.items():
                mass, com, bias = _metrics(np.nanmean(np.stack(xs), axis=0), obj, l_max)
                ratios[how].append(mass / ref)
                print(f"{fit_on} -> {held}  mean of every candidate ({len(xs)}), {how}: T mass "
                      f"{mass:.2f} (bias {bias:+.2f}), COM {com:.2f}; released T-A {ref:.2f}")
    for how, r in ratios.items():
        print(f"mass score of the mean, fine-tuned {how}: {np.mean(r):.3f}")


if __name__ == "__main__":
    main()
