"""Fine-tuning on a known real object, judged on the other one (issue "Sim-to-real II").

For each fold folder of a ``jaxinertia reproduce`` run (``DIR/folds/fit_<object>/``: the
simulator calibrated on that object and models trained on it), fine-tunes the
simulator-trained models on 64 / 250 / 1000 real samples of the fold's object, in each
variant (all parameters; per-joint encoders frozen), and judges every result on the
*other* real object's golden sets beside the simulator-only models and the released ones.
No number here is used to choose anything: the shipped defaults were set beforehand; this
is the ablation.

    python experiments/finetune_ablation.py runs/demo/folds --out runs/finetune_ablation

``--run-folds quick|full`` first runs the folds (``reproduce``'s held-out stage at that
scale) into the folder when it has none.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from jaxinertia import apply_xla_workarounds
from jaxinertia.app.folds import FoldScale, run_folds
from jaxinertia.app.options import enable_x64
from jaxinertia.app.pipeline import evaluate_models, load_real, released_benchmark, train
from jaxinertia.app.report import format_folds
from jaxinertia.app.reproduce import FULL, QUICK
from jaxinertia.evaluation import average
from jaxinertia.fileio import write_json, write_text
from jaxinertia.lbipe import default_lbipe_dir
from jaxinertia.training import FINETUNE_DEFAULTS, TrainConfig

#: Fine-tuning variants: the fold's models to start from ("paper": the fold's own
#: simulator-trained folder; "physical": the physics-structured torque model trained on the
#: same simulated data), what may change, and whether simulated samples of the fold's
#: training loads are mixed in (as many per load as real samples).
VARIANTS = {
    "paper, all, real": ("paper", "all", False),
    "paper, all, real + sim": ("paper", "all", True),
    "paper, head, real": ("paper", "head", False),
    "physical, servo, real": ("physical", "servo", False),
    "physical, all, real + sim": ("physical", "all", True),
}


def _row(fold, held, label, res):
    a = res if len(res) == 1 else {"average": average(res)}
    e = next(iter(a.values()))
    return [fold, held, label, *(f"{e[m][k]:.2f}" for m in ("PE", "T", "T-A") if m in e
                                  for k in ("mass_NMAE_pct", "com_NMAE_pct"))]


def main() -> None:
    apply_xla_workarounds()  # XLA:CPU settings, before JAX starts its backend
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folds", type=Path, help="a reproduce run's folds/ folder")
    ap.add_argument("--out", type=Path, default=Path("runs/finetune_ablation"))
    ap.add_argument("--lbipe-dir", type=Path, default=None)
    ap.add_argument("--samples", type=int, nargs="+", default=[64, 250, 1000])
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--scale", choices=["quick", "full"], default="quick",
                    help="the folds' scale (their training of the physical model)")
    ap.add_argument("--randomize-draws", type=int, default=4,
                    help="with --run-folds: simulated arms of the domain-randomized data")
    ap.add_argument("--run-folds", action="store_true",
                    help="run the held-out folds at --scale first (when absent)")
    args = ap.parse_args()
    enable_x64()
    lbipe_dir = args.lbipe_dir or default_lbipe_dir()
    scale = FULL if args.scale == "full" else QUICK
    if args.run_folds and not any(args.folds.glob("fit_*/models")):
        t0 = time.perf_counter()
        res = run_folds(args.folds, lbipe_dir, FoldScale(
            calibration_iterations=scale.fold_calibration_iterations,
            random_per_load=scale.random_per_load, planning=scale.planning, train=scale.train,
            finetune_samples=(), randomize_draws=args.randomize_draws), seed=args.seed,
            progress=False)
        write_json(args.folds / "folds.json", res)
        write_text(args.folds / "folds.md", format_folds(res))
        print(f"folds ({args.scale}) in {time.perf_counter() - t0:.0f} s: "
              f"{ {k: v['wall_time_s'] for k, v in res['folds'].items()} }", flush=True)
    real = load_real(lbipe_dir, seed=args.seed)
    names = [o.name for o in real.objects]
    released = released_benchmark(lbipe_dir, real=real)["objects"]
    rows, results = [], {}
    for fit_on in names:
        fold = args.folds / f"fit_{fit_on}"
        if not (fold / "models").is_dir():
            print(f"skip {fit_on}: no {fold / 'models'}")
            continue
        idx = [i for i, n in enumerate(names) if n != fit_on]
        objs, sets = [real.objects[i] for i in idx], [real.sets[i] for i in idx]
        l_max = [real.l_max[i] for i in idx]
        held = ", ".join(names[i] for i in idx)
        # The fold's own simulated training files (not the domain-randomized one).
        sim_files = [f for f in (fold / "data" / "train_random.npz",
                                 fold / "data" / "train_planning.npz") if f.exists()]
        inits = {"paper": fold / "models", "physical": fold / "models_physical"}
        if not inits["physical"].is_dir() and any(VARIANTS[v][0] == "physical"
                                                  for v in args.variants):
            t0 = time.perf_counter()
            train(sim_files, inits["physical"], scale.train.replace(
                seed=args.seed, torque_model="physical"), progress=False)
            print(f"{fit_on}: physical model trained in {time.perf_counter() - t0:.0f} s")
        results[fit_on] = {}
        inits_eval = dict(inits, **{"paper, domain-randomized": fold / "models_randomized"})
        for kind, init in inits_eval.items():
            if init.is_dir():
                base = evaluate_models(init, objs, sets, l_max=l_max)["objects"]
                results[fit_on][f"{kind}, simulator only"] = base
                rows.append(_row(fit_on, held, f"{kind}, simulator only", base))
        for variant in args.variants:
            kind, trainable, mix = VARIANTS[variant]
            for n in args.samples:
                cfg = TrainConfig(**FINETUNE_DEFAULTS, seed=args.seed, trainable=trainable)
                out = args.out / f"fit_{fit_on}" / f"{variant.replace(' ', '_')}_{n}"
                t0 = time.perf_counter()
                files = [real.layout.test_files[fit_on], *(sim_files if mix else [])]
                info = train(files, out, cfg, overwrite=True, progress=False,
                             init=inits[kind], samples_per_object=n)
                res = evaluate_models(out, objs, sets, l_max=l_max)["objects"]
                label = f"fine-tuned: {variant}, {n} samples"
                results[fit_on][label] = res
                rows.append(_row(fit_on, held, label, res))
                _save(args.out, rows, results)
                print(" | ".join(rows[-1]), f"({time.perf_counter() - t0:.0f} s, best epochs "
                      f"{info['best_epoch']})", flush=True)
        rel = {names[i]: released[names[i]] for i in idx}
        rows.append([fit_on, held, "released models", "", "",
                     *(f"{next(iter(rel.values()))[m][k]:.2f}" for m in ("T", "T-A")
                       for k in ("mass_NMAE_pct", "com_NMAE_pct"))])
    print(_save(args.out, rows, results))


def _save(out: Path, rows, results) -> str:
    """The table so far (written after every row: a run cut short keeps what it did)."""
    header = ["fit on", "judged on", "models", "PE mass", "PE COM", "T mass", "T COM",
              "T-A mass", "T-A COM"]
    table = "\n".join(["| " + " | ".join(header) + " |",
                       "| --- | --- | --- |" + " ---: |" * 6,
                       *("| " + " | ".join(r) + " |" for r in rows)])
    write_text(out / "ablation.md", "NMAE [%] on the held-out object\n\n" + table + "\n")
    write_json(out / "ablation.json", results)
    return table


if __name__ == "__main__":
    main()
