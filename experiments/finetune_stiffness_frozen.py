"""Does the fine-tuning's drop in stiffness make the folds' fine-tuned models weigh the other
file low? (session 40, tried, not adopted)

The folds fine-tune the servo part of the physical torque model (stiffness, offset,
friction and load friction per joint) on the fold's real file; the stiffness drops every
time (1-12 %), and the fine-tuned candidates miss the *other* file's mass low in both
folds. Here each fold's start (a finished run's ``folds/fit_<object>/models_physical*``) is
fine-tuned again as the folds do (``FINETUNE_DEFAULTS``, seed 0, the same samples), once
with the stiffness trainable (the folds' own: it reproduces their folders' numbers) and
once with it frozen at the start's, and judged on the held-out file at session strength
0 (the recipe's mass part: T).

The frozen variant is made by leaving ``stiffness`` out of ``training.SERVO_PARAMS`` (the
names ``--trainable servo`` trains) while it runs: an experiment's switch, not an option
of the library.

    python experiments/finetune_stiffness_frozen.py --run DIR --lbipe-dir DIR \\
        [--starts physical physical_current] [--samples 250 1000] [--out DIR]
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import jaxinertia.training as training  # noqa: E402
from jaxinertia.app.pipeline import evaluate_models, load_real, train  # noqa: E402
from jaxinertia.checkpoints import load_models  # noqa: E402
from jaxinertia.training import FINETUNE_DEFAULTS, SERVO_PARAMS, TrainConfig  # noqa: E402

VARIANTS = {"trainable": SERVO_PARAMS,
            "frozen": tuple(p for p in SERVO_PARAMS if p != "stiffness")}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run", required=True, help="a reproduce output folder (with folds/)")
    p.add_argument("--lbipe-dir", required=True)
    p.add_argument("--starts", nargs="+", default=["physical", "physical_current"])
    p.add_argument("--samples", nargs="+", type=int, default=[250, 1000])
    p.add_argument("--out", default=None, help="where the fine-tuned folders go (a temporary "
                                               "folder by default)")
    a = p.parse_args()
    real = load_real(a.lbipe_dir)
    names = [o.name for o in real.objects]
    out = Path(a.out or tempfile.mkdtemp(prefix="stiffness-frozen-"))
    print(f"{'fit -> judged':16s} {'start':18s} {'samples':>7s} {'stiffness':10s} "
          f"{'T mass':>7s} {'bias':>7s} {'T COM':>7s} {'k j1-j4 (mean of pairs)':>28s}")
    for fit_on in names:
        for held in (n for n in names if n != fit_on):
            i = names.index(held)
            for start in a.starts:
                src = Path(a.run) / "folds" / f"fit_{fit_on}" / f"models_{start}"
                for n in a.samples:
                    for variant, servo in VARIANTS.items():
                        dst = out / f"{fit_on}_{start}_{n}_{variant}"
                        training.SERVO_PARAMS = servo
                        try:
                            train([real.files[names.index(fit_on)]], dst,
                                  TrainConfig(**FINETUNE_DEFAULTS, trainable="servo", seed=0),
                                  overwrite=True, progress=False, init=src,
                                  samples_per_object=n)
                        finally:
                            training.SERVO_PARAMS = SERVO_PARAMS
                        r = evaluate_models(dst, [real.objects[i]], [real.sets[i]],
                                            l_max=[real.l_max[i]], session_strength=0.0)
                        t = r["objects"][held]["T"]
                        m_hat = np.asarray(r["estimates"]["T"][0])[..., 0]
                        bias = 100 * (np.nanmean(m_hat) / real.objects[i].x[0][0] - 1)
                        k = np.asarray(load_models(dst).pair.torque_vars["params"]["stiffness"])
                        print(f"{fit_on + ' -> ' + held:16s} {start:18s} {n:7d} {variant:10s} "
                              f"{t['mass_NMAE_pct']:7.2f} {bias:+7.2f} {t['com_NMAE_pct']:7.2f} "
                              + " ".join(f"{v:6.3f}" for v in k.mean(axis=0)), flush=True)


if __name__ == "__main__":
    main()
