"""Adaptation from the statics alone (issue 30, item 2: "a short self-supervised
adaptation"), checked on the real files with models that never saw them.

On a file of one unknown object, ``tau - tau_g = A x`` must hold with one ``x`` for every
sample. A servo whose gain today differs from the models' by a few per cent makes the
models' torque wrong by a few per cent of the *whole* joint torque, most of it the arm's
own (``tau_g``), which varies with the configuration unlike the object's ``A x``: the
factor per joint on the discrepancy that makes the torques most consistent with the
statics (least squares over the factors and x) needs no ground truth.

Judged here: the authors' released models (trained on their own 82k real samples, other
recording sessions) and, with ``--models``, a model folder, on each real file of shared/
(its golden sets), read as recorded, with the statics factors, and with the factors that
the file's known torques give (an oracle: what the best per-joint factor could do).

    python experiments/statics_adaptation.py [--models DIR ...] [--lbipe-dir DIR]
"""

from __future__ import annotations

import argparse
import json

import jax
import jax.numpy as jnp
import numpy as np

from jaxinertia import apply_xla_workarounds


def main():
    apply_xla_workarounds()  # XLA:CPU settings, before JAX starts its backend
    jax.config.update("jax_enable_x64", True)
    from jaxinertia.app.pipeline import load_real
    from jaxinertia.checkpoints import load_models
    from jaxinertia.evaluation import evaluate
    from jaxinertia.features import LBIPE_FEATURES
    from jaxinertia.lbipe import default_lbipe_dir, load_released_models
    from jaxinertia.session_terms import (
        apply_session_terms,
        fit_discrepancy_factor,
        fit_session_terms,
    )

    def fit_statics_terms(pair, fc, obj):
        """The factor per joint that makes the models' torques most consistent with the
        statics, one x for every sample (x by least squares inside the residual)."""
        scale = jnp.asarray(pair.tau_scale, jnp.float32)

        def residual(tau_hat, target):
            tau_g, A = target
            b = ((tau_hat - tau_g) / scale).reshape(-1)
            Aw = (A / scale[:, None]).reshape(-1, A.shape[-1])
            return b - Aw @ jnp.linalg.solve(Aw.T @ Aw, Aw.T @ b)

        return fit_discrepancy_factor(pair, fc, obj, residual, (
            jnp.asarray(obj.tau_g, jnp.float32), jnp.asarray(obj.A, jnp.float32)))

    ap = argparse.ArgumentParser()
    ap.add_argument("--models", nargs="*", default=[])
    ap.add_argument("--lbipe-dir", default=None)
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    real = load_real(a.lbipe_dir or default_lbipe_dir())
    candidates = {"released": (load_released_models(real.layout.weights_dir), LBIPE_FEATURES)}
    for m in a.models:
        f = load_models(m)
        candidates[m] = (f.pair, f.features)
    out = {}
    for label, (pair, fc) in candidates.items():
        for obj, sets, l_max in zip(real.objects, real.sets, real.l_max):
            u_stat = fit_statics_terms(pair, fc, obj)
            u_true = fit_session_terms(pair, fc, [obj])[0]
            row = {"statics factor": u_stat.tolist(), "truth factor": u_true.tolist()}
            for how, u in (("as recorded", None), ("statics", u_stat), ("truth (oracle)", u_true)):
                o = obj if u is None else apply_session_terms(obj, np.zeros(obj.n_samples, int),
                                                              u[None])
                res = evaluate([o], [sets], pair=pair, fc=fc, l_max=[l_max])["objects"][obj.name]
                row[how] = {m: [res[m]["mass_NMAE_pct"], res[m]["com_NMAE_pct"]]
                            for m in ("T", "T-A")}
            out[f"{label} / {obj.name}"] = row
            print(f"{label} / {obj.name}: statics x {np.round(u_stat, 3)}, "
                  f"truth x {np.round(u_true, 3)}")
            for how in ("as recorded", "statics", "truth (oracle)"):
                print(f"   {how:<15} " + "  ".join(
                    f"{m} {v[0]:6.2f} / {v[1]:6.2f}" for m, v in row[how].items()), flush=True)
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(out, fh, indent=2)


if __name__ == "__main__":
    main()
