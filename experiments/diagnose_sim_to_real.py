"""Why simulator-trained models miss on the real data: per-joint torque bias vs scatter.

For every real test file, prints the torque error of the model folder's torque model (mean
over its K pairs) and of its baselines, split into the mean (bias) and the error around
it, and the PE / current baselines fitted on the real samples beside the model folder's
(fitted on its training data).

    python experiments/diagnose_sim_to_real.py MODELS [--lbipe-dir DIR]
"""

from __future__ import annotations

import argparse

import jax

from jaxinertia import apply_xla_workarounds

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from jaxinertia.baselines import fit_baselines  # noqa: E402
from jaxinertia.checkpoints import load_models  # noqa: E402
from jaxinertia.lbipe import default_lbipe_dir, find_layout, load_test_files  # noqa: E402
from jaxinertia.training import torque_predictions  # noqa: E402


def _row(label: str, v) -> str:
    return f"  {label:<34}" + "".join(f"{x:>9.1f}" for x in np.asarray(v))


def main() -> None:
    apply_xla_workarounds()  # XLA:CPU settings, before JAX starts its backend
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("models")
    ap.add_argument("--lbipe-dir", default=None)
    args = ap.parse_args()
    folder = load_models(args.models)
    pair, bl, fc = folder.pair, folder.baselines, folder.features
    layout = find_layout(args.lbipe_dir or default_lbipe_dir())
    print("per joint:" + "".join(f"{f'joint {j + 1}':>9}" for j in range(4)))
    print(_row("model folder PE gain [N m/rad]", bl.pe_gain))
    print(_row("model folder PE intercept [N mm]", np.asarray(bl.pe_offset) * 1e3))
    for r in load_test_files(layout):
        name = r.name
        real = fit_baselines(r.q_d, r.q, r.direction, r.current_tau, r.tau)
        print(f"{name} ({r.n_samples} real samples)")
        print(_row("real PE gain [N m/rad]", real.pe_gain))
        print(_row("real PE intercept [N mm]", np.asarray(real.pe_offset) * 1e3))
        preds = {
            "T": np.asarray(torque_predictions(pair.torque_model, pair.torque_vars, fc,
                                               r)).mean(0),
            "PE": np.asarray(bl.pe(r.q_d, r.q, r.direction)),
            "Sensor": np.asarray(bl.sensor(r.current_tau, r.direction)),
        }
        for m, p in preds.items():
            e = (p - r.tau) * 1e3
            print(_row(f"{m} bias (mean error) [N mm]", e.mean(0)))
            print(_row(f"{m} MAE around the bias [N mm]", np.abs(e - e.mean(0)).mean(0)))


if __name__ == "__main__":
    main()
