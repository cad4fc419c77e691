"""Fine-tune the attention on the real object too? (issue 30: T-A worse than T on real data)

The folds fine-tune only the physical torque model's servo part on the fold's real object
and keep the attention the simulator taught. This script takes a finished ``reproduce``
run's folds and, per fold and start folder (a simulator-trained physical model), fine-tunes
on N of the fold's real samples with ``--trainable servo`` and ``servo+attention``, then
judges both on the held-out file at each session strength (T and T-A NMAE, %).

    python experiments/attention_finetune_folds.py --run DIR --lbipe-dir DIR \
        [--starts models_physical_current ...] [--samples 1000] [--out results.json]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

from jaxinertia.app.pipeline import evaluate_models, load_real, train  # noqa: E402
from jaxinertia.training import FINETUNE_DEFAULTS, TrainConfig  # noqa: E402

STRENGTHS = (0.0, 0.5, 1.0)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run", required=True, help="a reproduce output folder (with folds/)")
    p.add_argument("--lbipe-dir", required=True)
    p.add_argument("--starts", nargs="+", default=["models_physical_current"])
    p.add_argument("--samples", type=int, nargs="+", default=[1000])
    p.add_argument("--modes", nargs="+", default=["servo", "servo+attention"])
    p.add_argument("--work", default=None, help="where the fine-tuned folders go "
                   "(default: RUN/attention_finetune)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None)
    a = p.parse_args()

    real = load_real(a.lbipe_dir, seed=a.seed)
    names = [o.name for o in real.objects]
    work = Path(a.work or Path(a.run) / "attention_finetune")
    rows = []
    for i, fit_on in enumerate(names):
        held = [j for j, n in enumerate(names) if n != fit_on]
        objects = [real.objects[j] for j in held]
        sets, l_max = [real.sets[j] for j in held], [real.l_max[j] for j in held]
        for start in a.starts:
            init = Path(a.run) / "folds" / f"fit_{fit_on}" / start
            for n in a.samples:
                for mode in a.modes:
                    out = work / f"fit_{fit_on}" / f"{start}_{mode.replace('+', '_')}_{n}"
                    cfg = TrainConfig(**FINETUNE_DEFAULTS, trainable=mode, seed=a.seed)
                    train([real.files[i]], out, cfg, overwrite=True, progress=False,
                          init=init, samples_per_object=n)
                    for s in STRENGTHS:
                        res = evaluate_models(out, objects, sets, l_max=l_max,
                                              session_strength=s)
                        for obj, e in res["objects"].items():
                            row = {"fit_on": fit_on, "judged_on": obj, "start": start,
                                   "samples": n, "trainable": mode, "strength": s,
                                   **{f"{m} {k}": e[m][f"{k}_NMAE_pct"]
                                      for m in ("T", "T-A") for k in ("mass", "com")}}
                            rows.append(row)
                            print(f"fit {fit_on:6s} judge {obj:6s} {start:34s} {n:5d} "
                                  f"{mode:16s} @{s:g}  T {row['T mass']:6.2f} "
                                  f"{row['T com']:6.2f}  T-A {row['T-A mass']:6.2f} "
                                  f"{row['T-A com']:6.2f}", flush=True)
    if a.out:
        Path(a.out).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
