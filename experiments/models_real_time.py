"""How long ``models_real`` takes to make from a finished run's folds, as ``reproduce`` makes
it: after the folds' judges (one folder of each kind judged on its fold's held-out file at
the three session strengths, in this process), :func:`~jaxinertia.app.models_real.models_from_folds`
on a copy of the run's folds; seconds and XLA programs compiled, and its numbers.

    python experiments/models_real_time.py --run DIR --lbipe-dir DIR [--tmp DIR]
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

import jax

# The least squares in float64, as the command line solves them (jaxinertia.app.options):
# in float32 a GPU's TF32 products move the attention's solves by percents.
jax.config.update("jax_enable_x64", True)

from jaxinertia.app.folds import SESSION_STRENGTHS  # noqa: E402
from jaxinertia.app.models_real import models_from_folds, recipe_of  # noqa: E402
from jaxinertia.app.pipeline import adapt_objects, load_real, session_reference  # noqa: E402
from jaxinertia.app.reproduce import FULL  # noqa: E402
from jaxinertia.checkpoints import load_models  # noqa: E402
from jaxinertia.evaluation import evaluate  # noqa: E402

#: One folder of each kind of model a fold judges (paper network, physical, with the
#: current input, fine-tuned).
KINDS = ("models", "models_physical", "models_physical_current", "models_finetuned_250")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run", required=True, help="a reproduce --full output folder")
    p.add_argument("--lbipe-dir", required=True)
    p.add_argument("--tmp", default="/tmp/models_real_time")
    a = p.parse_args()
    compiles = [0]
    jax.monitoring.register_event_duration_secs_listener(
        lambda event, secs, **kw: compiles.__setitem__(
            0, compiles[0] + (event == "/jax/core/compile/backend_compile_duration")))
    out = Path(a.tmp)
    shutil.rmtree(out, ignore_errors=True)
    shutil.copytree(Path(a.run) / "folds", out / "folds")
    folds = json.loads((Path(a.run) / "tables.json").read_text())["held_out"]
    real = load_real(a.lbipe_dir)
    names = [o.name for o in real.objects]
    t = time.perf_counter()
    for fold in folds["folds"]:
        (held,) = [n for n in names if n != fold]
        o = names.index(held)
        for kind in KINDS:
            folder = load_models(out / "folds" / f"fit_{fold}" / kind)
            for s in SESSION_STRENGTHS:
                adapted, _ = adapt_objects([real.objects[o]],
                                           session_reference(folder.config, s))
                evaluate(adapted, [real.sets[o]], pair=folder.pair, baselines=folder.baselines,
                         fc=folder.features, l_max=[real.l_max[o]])
    print(f"the folds' judges: {time.perf_counter() - t:.1f} s, {compiles[0]} programs compiled")
    compiles[0] = 0
    t = time.perf_counter()
    res = models_from_folds(out, folds, real, recipe_of(folds, FULL))
    print(f"models_from_folds: {time.perf_counter() - t:.1f} s, {compiles[0]} programs compiled")
    for name, r in res["objects"].items():
        print(f"  {name}: T-A mass NMAE {r['T-A']['mass_NMAE_pct']:.4f} %, "
              f"COM NMAE {r['T-A']['com_NMAE_pct']:.4f} % (not held out)")


if __name__ == "__main__":
    main()
