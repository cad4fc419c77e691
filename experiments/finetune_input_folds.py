"""The folds' fine-tunings of the current-input starts with the residual's input layer
trainable too (``--trainable servo+input``, session 46), beside the servo part alone.

Session 44 found the drawn-sessions current-input candidates reading every real file
high, the one they were fine-tuned on too (+12 to +43 %): the current reaches these models
only through the residual network, which the servo fine-tuning leaves frozen, so a gap
between the simulator's current and the real one stays. This fine-tunes every
current-input start of a finished ``reproduce`` run's folds again as the folds do
(``FINETUNE_DEFAULTS``, the draw's seed, anchored: ``n`` real samples of the fold's file and ``n``
of each load of the start's simulated data), once per ``--trainable``, and judges each on
the held-out file and (**not held out**) on the fold's own file, T at session strength 0
(the recipe's mass part) and T-A at 1 (the COM part's setting). Then the mean of the
fold's candidates (the four from the simulator alone, the run's own fine-tunings of the
physical start at 64, 250 and 1000 samples, and this experiment's of the current-input
starts) per ``--trainable``:
its mass score over the released models' T-A is the recipe's measure.

    python experiments/finetune_input_folds.py --run DIR --lbipe-dir DIR [--draws 1]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from candidate_ensemble import _metrics  # noqa: E402
from finetune_anchor_folds import _sim_data, real_and_released  # noqa: E402

from jaxinertia.app.pipeline import evaluate_models, train  # noqa: E402
from jaxinertia.training import FINETUNE_DEFAULTS, TrainConfig  # noqa: E402

STARTS = ("physical_current", "physical_current_sessions")
SIM_ONLY = ("models", "models_physical", "models_physical_current",
            "models_physical_current_sessions")
SIZES = (64, 250, 1000)


#: The candidates' kinds (the folders' mean within each, and of some together, is printed).
KINDS = {"without the current": ("models", "models_physical", "models_finetuned_"),
         "current input": ("models_physical_current", "models_finetuned_current_"),
         "sessions drawn": ("models_physical_current_sessions",
                            "models_finetuned_current_sessions_")}
MEANS = (("every kind",), ("current input",), ("without the current", "current input"),
         ("current input", "sessions drawn"))


def _kind(folder: str) -> str:
    """The kind of a candidate folder's name (the longest matching prefix of KINDS')."""
    best = max(((p, k) for k, ps in KINDS.items() for p in ps
                if folder == p or (p.endswith("_") and folder.startswith(p)
                                   and folder[len(p):].isdigit())), key=lambda pk: len(pk[0]))
    return best[1]


def _fold_dirs(run: Path, fit_on: str, draws: int) -> list[Path]:
    """A run's folds of ``fit_on`` (``run/folds/...``; or ``run`` is the folds' folder, as
    ``experiments/folds_alone.py --out`` writes it)."""
    folds = run / "folds" if (run / "folds").is_dir() else run
    dirs = [folds / f"fit_{fit_on}"]
    dirs += sorted(folds.glob(f"seed*/fit_{fit_on}"))
    return [d for d in dirs if d.is_dir()][:draws]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run", required=True, help="a reproduce --full output folder")
    p.add_argument("--lbipe-dir", required=True)
    p.add_argument("--draws", type=int, default=1, help="training draws' folds to redo")
    p.add_argument("--trainable", nargs="+", default=["servo", "servo+input"])
    p.add_argument("--sizes", type=int, nargs="+", default=list(SIZES))
    p.add_argument("--seed", type=int, default=0, help="the fine-tunings' seed where the "
                   "fold's folder does not name it (seed<s>/): the run's --seed")
    p.add_argument("--simulate", type=int, default=None,
                   help="samples per load to simulate where the run's data were not kept")
    a = p.parse_args()
    real, names, released, tmp = real_and_released(a.lbipe_dir, "finetune-input-")

    def judge(folder: Path, i: int, strength: float, method: str) -> np.ndarray:
        r = evaluate_models(folder, [real.objects[i]], [real.sets[i]], l_max=[real.l_max[i]],
                            session_strength=strength)
        return np.asarray(r["estimates"][method][0])

    def line(label: str, x: np.ndarray, i: int) -> str:
        mass, com, bias = _metrics(x, real.objects[i], real.l_max[i])
        return f"{label} {mass:6.2f} ({bias:+6.2f}) / {com:6.2f}"

    scores: dict[tuple, list[float]] = {}
    for fit_on in names:
        f = names.index(fit_on)
        for held in (n for n in names if n != fit_on):
            h = names.index(held)
            ours: dict[str, list[tuple[str, np.ndarray]]] = {t: [] for t in a.trainable}
            for fold in _fold_dirs(Path(a.run), fit_on, a.draws):
                names_fixed = [*SIM_ONLY, *(f"models_finetuned_{n}" for n in SIZES)]
                fixed = [(_kind(c), judge(fold / c, h, 0.0, "T")) for c in names_fixed]
                seed = int(fold.parent.name.removeprefix("seed")) if (
                    fold.parent.name.startswith("seed")) else a.seed
                for t in a.trainable:
                    ours[t].extend(fixed)
                for start in STARTS:
                    anchor = _sim_data(fold, start, a.simulate, tmp)
                    for n in a.sizes:
                        own = fold / f"models_finetuned{start.removeprefix('physical')}_{n}"
                        print(f"{fold.parent.name}/{fit_on} -> {held} {start:26s} {n:5d} "
                              f"{'the run':12s}" + line(" held T0 mass (bias) / COM",
                                                         judge(own, h, 0.0, "T"), h)
                              + line(" | seen T0", judge(own, f, 0.0, "T"), f), flush=True)
                        for t in a.trainable:
                            dst = tmp / f"{fold.parent.name}_{fit_on}_{start}_{n}_{t}"
                            train([real.files[f], anchor], dst,
                                  TrainConfig(**FINETUNE_DEFAULTS, trainable=t, seed=seed),
                                  overwrite=True, progress=False, init=fold / f"models_{start}",
                                  samples_per_object=n)
                            x = judge(dst, h, 0.0, "T")
                            ours[t].append((_kind(own.name), x))
                            print(f"{fold.parent.name}/{fit_on} -> {held} {start:26s} {n:5d} "
                                  f"{t:12s}" + line(" held T0 mass (bias) / COM", x, h)
                                  + line(" | seen T0", judge(dst, f, 0.0, "T"), f)
                                  + line(" | held T-A1", judge(dst, h, 1.0, "T-A"), h),
                                  flush=True)
            ref = released[held]["T-A"]["mass_NMAE_pct"]
            for t, tagged in ours.items():
                for kinds in MEANS:
                    xs = [x for k, x in tagged if kinds == ("every kind",) or k in kinds]
                    mean = np.nanmean(np.stack(xs), axis=0)
                    mass, _, _ = _metrics(mean, real.objects[h], real.l_max[h])
                    scores.setdefault((t, kinds), []).append(mass / ref)
                    print(line(f"{fit_on} -> {held} mean of {len(xs)} ({' + '.join(kinds)}), "
                               f"{t}: T0", mean, h) + f"; released T-A {ref:.2f}", flush=True)
    for (t, kinds), r in scores.items():
        print(f"mass score of the mean of {' + '.join(kinds)}, fine-tuned {t}: "
              f"{np.mean(r):.3f}")


if __name__ == "__main__":
    main()
