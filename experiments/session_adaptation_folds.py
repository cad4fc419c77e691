"""Test-time session adaptation on the held-out folds of a run (issue 30, item 2).

For every fold of ``RUN/folds`` (``jaxinertia reproduce``), each model folder is evaluated on
the held-out real object with its discrepancy rescaled per joint by
``(g_held / g_ref) ** strength`` (:mod:`jaxinertia.session`), where ``g_ref`` is the current
gain of the folder's own training files (no ground truth of the held-out object is used).
Strength 0 is the folder as trained.

    python experiments/session_adaptation_folds.py runs/demo [--strengths 0 0.5 1]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax
import numpy as np

from jaxinertia import apply_xla_workarounds
from jaxinertia.app.pipeline import load_real
from jaxinertia.checkpoints import load_models
from jaxinertia.evaluation import METHODS, evaluate
from jaxinertia.lbipe import default_lbipe_dir
from jaxinertia.samples import load_samples
from jaxinertia.session import SessionReference, adapt, servo_session


def main():
    apply_xla_workarounds()  # XLA:CPU settings, before JAX starts its backend
    jax.config.update("jax_enable_x64", True)
    ap = argparse.ArgumentParser()
    ap.add_argument("run")
    ap.add_argument("--strengths", type=float, nargs="+", default=[0.0, 0.5, 1.0])
    ap.add_argument("--lbipe-dir", default=None)
    ap.add_argument("--json", default=None)
    ap.add_argument("--reference", choices=["training", "fit"], default="training",
                    help="the folder's own training files' current gain, or the real file "
                         "the fold was fitted on")
    a = ap.parse_args()
    real = load_real(a.lbipe_dir or default_lbipe_dir())
    names = [o.name for o in real.objects]
    rows, out = [], {}
    for fold in sorted(Path(a.run, "folds").glob("fit_*")):
        fit_on = fold.name[4:]
        for models in sorted(p for p in fold.glob("models*") if (p / "config.json").is_file()):
            folder = load_models(models)
            pair, baselines, fc = folder.pair, folder.baselines, folder.features
            config = folder.config
            if a.reference == "fit":
                ref = servo_session(real.objects[names.index(fit_on)])
            else:
                ref = servo_session([load_samples(d["file"])[0] for d in config["data"]])
            for held in (n for n in names if n != fit_on):
                i = names.index(held)
                obj = real.objects[i]
                for s in a.strengths:
                    adapted, ratio = adapt(obj, SessionReference(ref.current_gain, s))
                    res = evaluate([adapted], [real.sets[i]], pair=pair, baselines=baselines,
                                   fc=fc, l_max=[real.l_max[i]])["objects"][held]
                    key = f"{fit_on}->{held} {models.name} s={s}"
                    cols = ("mass_NMAE_pct", "com_NMAE_pct", "mass_MAE_g")
                    out[key] = {m: {k: res[m][k] for k in cols} for m in res if m in METHODS}
                    out[key]["ratio"] = ratio.tolist()
                    r = res["T-A"]
                    rows.append(f"{fit_on:>5} -> {held:<5} {models.name:<22} s={s:<4} "
                                f"ratio {np.round(ratio, 3)}  T {res['T']['mass_NMAE_pct']:6.2f} "
                                f"{res['T']['com_NMAE_pct']:6.2f}  T-A {r['mass_NMAE_pct']:6.2f} "
                                f"{r['com_NMAE_pct']:6.2f}  PE {res['PE']['mass_NMAE_pct']:6.2f}")
                    print(rows[-1], flush=True)
    if a.json:
        Path(a.json).write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
