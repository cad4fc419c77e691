"""A reference recorded in the same session, checked on the simulator (issue 30).

The servo's state of the day (supply, winding temperature, wear) scales the torque one
tick of error buys; on the OpenMANIPULATOR-X 1 % of joint 2's torque moves a cube's mass by
11 %. The current gain (session adaptation) sees the electrical part of it and nothing of
a change of the torque constant. A *known* load recorded in the same session (the empty
gripper, or a known weight, at a few hundred poses just before or after the unknown
object) sees all of it: its true joint torques are known, so each joint's gain and offset
between the models' torques and the truth can be fitted on it
(:func:`jaxinertia.session.reference_correction`) and applied to the unknown object's.

Recording sessions are drawn around the simulator with the spread the two real files
show (electrical and torque-only, as ``experiments/session_sim_check.py``), times
``--test-scale``. In each, the four test objects and a reference (``--reference``: a
training load of the random scenario, ``--reference-n`` poses of it) are simulated. One
model folder trained on the nominal simulator (``--models``, e.g. ``runs/demo/models``, or
trained here at ``--scale``) judges them read as recorded, with session adaptation, with
the reference's correction, and with both. Reported: T and T-A mass / COM NMAE [%], mean
over objects and sessions, and the fitted gains against each session's true factors.

    python experiments/reference_sim_check.py --out runs/reference_sim [--models DIR]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import numpy as np
from session_sim_check import sessions_spread  # (experiments/: the script's folder)

from jaxinertia import apply_xla_workarounds
from jaxinertia.app.pipeline import adapt_objects, session_reference, train
from jaxinertia.app.reproduce import FULL, QUICK
from jaxinertia.app.simdata import simulate_files
from jaxinertia.checkpoints import load_models
from jaxinertia.evaluation import choose_sets, evaluate
from jaxinertia.reference import apply_reference, reference_correction
from jaxinertia.samples import Samples, save_native
from jaxinertia.sim.params import default_sim_params
from jaxinertia.sim.randomize import session_drawn
from jaxinertia.training import TrainConfig
from jaxinertia.training_setup import FINETUNE_DEFAULTS

METHODS = ("T", "T-A")


def judged(folder, objects, sets, correction=None):
    pair, objs = folder.pair, objects
    if correction is not None:
        pair, objs = apply_reference(pair, objects, correction)
    res = evaluate(objs, sets, pair=pair, baselines=folder.baselines, fc=folder.features)
    return {m: {q: float(np.mean([res["objects"][o.name][m][q] for o in objects]))
                for q in ("mass_NMAE_pct", "com_NMAE_pct")} for m in METHODS}


def main():
    apply_xla_workarounds()  # XLA:CPU settings, before JAX starts its backend
    jax.config.update("jax_enable_x64", True)
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default="runs/reference_sim")
    ap.add_argument("--models", default=None, help="a folder trained on the nominal "
                    "simulator (default: train one here at --scale)")
    ap.add_argument("--scale", choices=["quick", "full"], default="quick")
    ap.add_argument("--test-sessions", type=int, default=4)
    ap.add_argument("--test-scale", type=float, default=1.5)
    ap.add_argument("--torque-rel-scale", type=float, default=1.0)
    ap.add_argument("--reference", nargs="+", default=["0g", "100g", "0g,100g"],
                    help="references to try, each a comma-separated list of training loads "
                    "recorded as known objects and pooled (0g: the empty gripper, 50g, 100g, "
                    "150g)")
    ap.add_argument("--reference-n", type=int, nargs="+", default=[64, 250, 1000],
                    help="poses per load of a reference")
    ap.add_argument("--finetune", type=int, default=0, metavar="N",
                    help="also fine-tune the folder (every part, the fine-tuning defaults, "
                    "read as recorded) on N poses per load of the first reference, and "
                    "judge that folder as recorded")
    ap.add_argument("--n-sets", type=int, default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--lbipe-dir", default=None)
    a = ap.parse_args()
    scale = FULL if a.scale == "full" else QUICK
    out = Path(a.out)
    t0 = time.perf_counter()
    spread, _ = sessions_spread(a.lbipe_dir, a.torque_rel_scale)  # item 5's sessions
    print("session spread:", spread.to_dict())
    base = default_sim_params()
    models = Path(a.models) if a.models else out / "models"
    if not a.models:
        data = simulate_files(base, [(out / "data" / "train.npz", "random",
                                      scale.random_per_load, a.seed)])
        train(data, models, scale.train.replace(seed=a.seed), overwrite=True, progress=False)
    folder = load_models(models)
    ref_strength = session_reference(folder.config, 1.0, simulated=True)
    k_test = jax.random.fold_in(jax.random.key(a.seed + 4242), 1)
    n_ref = max(a.reference_n)
    rows: dict = {}
    fitted = []
    # The floor: the test objects in the simulator's own session (what no session changed).
    nominal, = simulate_files(base, [(out / "data" / "test_nominal.npz", "test",
                                      scale.test_per_object, a.seed + 999)], progress=False)
    nominal_objects = nominal.samples.by_object()
    floor = judged(folder, nominal_objects, choose_sets(
        nominal_objects, n_sets=a.n_sets or scale.n_sets, seed=a.seed)[0])
    print("  nominal session (no change)                        " + "  ".join(
        f"{m} {floor[m]['mass_NMAE_pct']:6.2f} / {floor[m]['com_NMAE_pct']:6.2f}"
        for m in METHODS), flush=True)
    for s in range(a.test_sessions):
        p = session_drawn(base, jax.random.fold_in(k_test, s), spread, scale=a.test_scale)
        true = {"electrical": (np.asarray(p.servo.supply_voltage)
                               / np.asarray(base.servo.supply_voltage)).tolist(),
                "torque": (np.asarray(p.servo.torque_constant)
                           / np.asarray(base.servo.torque_constant)).tolist()}
        test, ref = simulate_files(p, [
            (out / "data" / f"test_session_{s}.npz", "test", scale.test_per_object,
             a.seed + 1000 + s),
            (out / "data" / f"reference_session_{s}.npz", "random", n_ref,
             a.seed + 2000 + s)], progress=False)
        objects = test.samples.by_object()
        loads = {o.name: o for o in ref.samples.by_object()}
        sets, _ = choose_sets(objects, n_sets=a.n_sets or scale.n_sets, seed=a.seed)
        adapted, _ = adapt_objects(objects, ref_strength)
        variants = {"as recorded": judged(folder, objects, sets),
                    "current gain (adapted)": judged(folder, adapted, sets)}
        session_fit = {"true": true}
        for spec in a.reference:
            known = [loads[name] for name in spec.split(",")]
            known_adapted, _ = adapt_objects(known, ref_strength)
            for n in sorted(a.reference_n):
                for label, objs, ks, offset in (
                        ("", objects, known, True),
                        ("adapted + ", adapted, known_adapted, True),
                        ("adapted + ", adapted, known_adapted, False)):
                    part = Samples.concatenate([k.take(np.arange(min(n, k.n_samples)))
                                                for k in ks])
                    corr = reference_correction(folder.pair, folder.features, part,
                                                offset=offset)
                    name = (f"{label}reference {spec} x {n}"
                            + ("" if offset else ", gain only"))
                    variants[name] = judged(folder, objs, sets, corr)
                    session_fit[name] = corr.to_dict()
        if a.finetune:
            spec = a.reference[0]
            part = Samples.concatenate([loads[name].take(np.arange(
                min(a.finetune, loads[name].n_samples))) for name in spec.split(",")])
            path = out / "data" / f"finetune_session_{s}.npz"
            save_native(path, part, {"robot": ref.meta.get("robot"), "source": "test",
                                     "objects": list(part.names)})
            tuned = out / f"models_finetuned_session_{s}"
            train([path], tuned, TrainConfig(**FINETUNE_DEFAULTS, trainable="all",
                                             session_strength=0.0, seed=a.seed),
                  init=models, overwrite=True, progress=False)
            variants[f"fine-tuned on {spec} x {a.finetune}"] = judged(load_models(tuned),
                                                                      objects, sets)
        fitted.append(session_fit)
        for name, v in variants.items():
            rows.setdefault(name, []).append(v)
        print(f"session {s}: true electrical {np.round(true['electrical'], 3)}, torque "
              f"{np.round(true['torque'], 3)}", flush=True)
        for name, v in variants.items():
            print(f"  {name:<50} " + "  ".join(f"{m} {v[m]['mass_NMAE_pct']:6.2f} / "
                                               f"{v[m]['com_NMAE_pct']:6.2f}"
                                               for m in METHODS), flush=True)
    table = {name: {m: {q: float(np.mean([r[m][q] for r in rs]))
                        for q in ("mass_NMAE_pct", "com_NMAE_pct")} for m in METHODS}
             for name, rs in rows.items()}
    print(f"\nmean over {a.test_sessions} sessions (mass / COM NMAE [%]):")
    for name, v in table.items():
        print(f"  {name:<50} " + "  ".join(f"{m} {v[m]['mass_NMAE_pct']:6.2f} / "
                                           f"{v[m]['com_NMAE_pct']:6.2f}" for m in METHODS))
    results = {"args": vars(a), "spread": spread.to_dict(), "nominal": floor, "table": table,
               "rows": rows,
               "fitted": fitted, "wall_time_s": time.perf_counter() - t0}
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps(results, indent=2))
    print(f"wrote {out / 'results.json'} ({results['wall_time_s']:.0f} s)")


if __name__ == "__main__":
    main()
