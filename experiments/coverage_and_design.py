"""Issue 17, measured: coverage of the intervals, and D-optimal poses against random ones.

    python experiments/coverage_and_design.py --models runs/demo/models \\
        --sim-test runs/demo/data/test.npz --lbipe-dir ../shared/lbipe --out runs/issue17

Coverage: every object's 1000 sets of 64 (simulated test objects: random sets, seed 0 + i,
as ``jaxinertia evaluate --samples``; real cube/white: the golden sets), for the model
folder (floor: its validation error) and the authors' released models (no training data:
residuals and ensemble only); ablations leave out the floor or keep only one term.
Inflation on the real files: fitted on one object, checked on the other.

Design: R = 1000 repeats per object. Each repeat draws a pool (150 of the 300 simulated
samples of an object, 500 of the 1000 real ones) and takes from it 16 samples chosen by
the D-optimal criterion (log det sum_s A_s^T A_s, unit joint weights: what a plan knows
before any torque is measured), 16 random ones and 64 random ones; the paper's Table I
metrics of T and T-A over the K pairs x 1000 sets.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

from jaxinertia import apply_xla_workarounds  # noqa: E402
from jaxinertia.checkpoints import load_models  # noqa: E402
from jaxinertia.design import (  # noqa: E402
    DEFAULT_MARGIN_DEG,
    information,
    inner_workspace,
    plan_poses,
    select_pools,
    subset_logdets,
)
from jaxinertia.estimation import estimate_sets  # noqa: E402
from jaxinertia.evaluation import choose_sets, evaluate, l_max_of, stack  # noqa: E402
from jaxinertia.features import LBIPE_FEATURES  # noqa: E402
from jaxinertia.lbipe import find_layout, golden_path, load_golden, load_released_models  # noqa: E402
from jaxinertia.lbipe import load_test_files as real_files  # noqa: E402
from jaxinertia.open_manipulator_x import WORKSPACE_DEG  # noqa: E402
from jaxinertia.samples import load_samples  # noqa: E402
from jaxinertia.uncertainty import (  # noqa: E402
    fit_inflation,
    interval_coverage,
    training_validation_error,
    uncertainty_of,
)

METHODS = ("T", "T-A")


def _summary(cal: dict) -> dict:
    """Per object and method: 68/95 % coverage of the mass and the COM coordinates."""
    return {name: {m: {"mass_68": c[0.68]["mass"], "mass_95": c[0.95]["mass"],
                       "com_68": c[0.68]["com"], "com_95": c[0.95]["com"],
                       "com_xyz_95": c[0.95]["com_xyz"], "com_region_95": c[0.95]["com_region"],
                       "median_se_g_mm": [c["median_se"][0] * 1e3,
                                          *(v * 1e3 for v in c["median_se"][1:])],
                       "rms_error_g_mm": [c["rms_error"][0] * 1e3,
                                          *(v * 1e3 for v in c["rms_error"][1:])],
                       "n_sets": c["n_sets"]}
                   for m, c in per.items()} for name, per in cal["objects"].items()}


def _mean(summary: dict, method: str) -> dict:
    keys = ("mass_68", "mass_95", "com_68", "com_95", "com_region_95")
    rows = [v[method] for v in summary.values() if method in v]
    return {k: float(np.mean([r[k] for r in rows])) for k in keys}


def _variants(answers: dict, no_floor: dict) -> dict:
    """The full covariance and ablations: without the floor, noise term only, ensemble only."""
    out = {"full": answers, "no floor": no_floor}
    out["residual only"] = {m: u._replace(cov=u.cov_noise) for m, u in no_floor.items()}
    out["ensemble only"] = {m: u._replace(cov=u.cov_ensemble) for m, u in answers.items()}
    return out


def coverage_section(objects, sets, pair, fc, floor, baselines=None) -> dict:
    t = time.perf_counter()
    answers = uncertainty_of(objects, sets, pair=pair, fc=fc, floor=floor, baselines=baselines)
    jax.block_until_ready(answers)
    wall = time.perf_counter() - t
    no_floor = (answers if floor is None else
                uncertainty_of(objects, sets, pair=pair, fc=fc, floor=None))
    out = {"wall_s_incl_compile": wall, "variants": {}}
    for name, ans in _variants(answers, no_floor).items():
        s = _summary(interval_coverage(objects, ans))
        out["variants"][name] = {"objects": s, "mean": {m: _mean(s, m) for m in ans}}
    return out, answers


def inflation_section(objects, answers) -> dict:
    """A factor on the standard errors fitted on one real object, checked on the other."""
    out = {}
    for m in METHODS:
        u = answers[m]
        for fit, check in ((0, 1), (1, 0)):
            kappa = fit_inflation(u.x[fit], u.cov[fit], objects[fit].x[0])
            cal = interval_coverage([objects[check]], {m: u._replace(
                x=u.x[check:check + 1], cov=u.cov[check:check + 1])}, inflate=kappa)
            c = cal["objects"][objects[check].name][m]
            out[f"{m}: fit {objects[fit].name} -> check {objects[check].name}"] = {
                "kappa_mass": float(kappa[0]), "kappa_com": float(kappa[1]),
                "mass_95": c[0.95]["mass"], "com_95": c[0.95]["com"],
                "mass_68": c[0.68]["mass"], "com_68": c[0.68]["com"]}
    return out


def design_section(objects, pair, fc, *, pool: int, repeats: int, seed: int) -> dict:
    """16 D-optimal vs 16 and 64 random samples of each object, ``repeats`` pools each.
    "planned 16": the pose-only criterion (unit joint weights); "planned 16, T-A weights":
    the information of the T-A solve itself (the measured samples' attention weights, mean
    over the pairs), which needs the pool measured first."""
    designs: dict[str, list[np.ndarray]] = {"planned 16": [], "planned 16, T-A weights": [],
                                            "planned 16, margin": [], "random 16": [],
                                            "random 64": []}
    lo, hi = (np.radians(a) for a in zip(*inner_workspace(WORKSPACE_DEG, DEFAULT_MARGIN_DEG)))
    logdets: dict[str, list[float]] = {k: [] for k in designs}
    everything = stack(objects, [np.arange(o.n_samples)[None] for o in objects], fc)
    weights = np.asarray(estimate_sets(pair, everything.features, everything.A,
                                       everything.tau_g, everything.sets).weights).mean(axis=1)
    for i, obj in enumerate(objects):
        rng = np.random.default_rng(seed + i)
        pools = np.stack([rng.permutation(obj.n_samples)[:pool] for _ in range(repeats)])
        C = information(jnp.asarray(obj.A))
        idx, ld, _ = select_pools(C, jnp.asarray(pools), 16)
        designs["planned 16"].append(np.asarray(idx))
        C_ta = jnp.einsum("snp,sn,snq->spq", jnp.asarray(obj.A),
                          jnp.asarray(weights[i, : obj.n_samples]), jnp.asarray(obj.A))
        designs["planned 16, T-A weights"].append(
            np.asarray(select_pools(C_ta, jnp.asarray(pools), 16)[0]))
        # plan-poses' default: only poses DEFAULT_MARGIN_DEG inside the limits (the others
        # carry no information, so they are chosen only if a pool has too few inside).
        inside = np.all((np.asarray(obj.q_d) >= lo) & (np.asarray(obj.q_d) <= hi), axis=1)
        designs["planned 16, margin"].append(np.asarray(select_pools(
            C * jnp.asarray(inside, C.dtype)[:, None, None], jnp.asarray(pools), 16)[0]))
        designs["random 16"].append(pools[:, :16])
        designs["random 64"].append(pools[:, :64])
        for k in designs:
            logdets[k].append(float(np.median(np.asarray(subset_logdets(
                C, jnp.asarray(designs[k][-1]))))))
    out = {}
    l_max = l_max_of(objects)
    for k, sets in designs.items():
        res = evaluate(objects, sets, pair=pair, fc=fc, l_max=l_max)
        out[k] = {"objects": {n: {m: e[m] for m in METHODS} for n, e in res["objects"].items()},
                  "median_logdet": dict(zip([o.name for o in objects], logdets[k]))}
        out[k]["average"] = {m: {key: float(np.mean([e[m][key] for e in
                                                     out[k]["objects"].values()]))
                                 for key in ("mass_MAE_g", "com_MAE_mm")} for m in METHODS}
    return out


def mean_attention(pair, fc, data) -> np.ndarray:
    """(N,) the model pairs' attention weights averaged over the pairs and ``data``'s
    samples (their training file: what a plan may know before any test object is seen)."""
    from jaxinertia.estimation import predict_weights  # noqa: PLC0415
    from jaxinertia.features import featurize  # noqa: PLC0415

    feats = featurize(fc, jnp.asarray(data.q), jnp.asarray(data.q_d),
                      jnp.asarray(data.direction)).astype(jnp.float32)
    w = jax.vmap(lambda av: predict_weights(pair.attention_model, av, feats))(
        pair.attention_vars)
    return np.asarray(jnp.mean(w, axis=(0, 1)), np.float64)


def simulated_plans_section(objects, pair, fc, *, repeats: int, seed: int,
                            directions_only: bool = False, joint_weights=None) -> dict:
    """The plan itself on the simulator: ``plan-poses --n 16`` (grid poses, balanced
    directions) simulated ``repeats`` times per test object (fresh friction draws), against
    ``repeats`` random plans of 16 and of 64 poses (uniform in the workspace, as the test
    scenario draws them); Table I metrics over the repeats."""
    from jaxinertia import __version__  # noqa: PLC0415 (the simulator only here)
    from jaxinertia.design import arm_plan_kwargs  # noqa: PLC0415
    from jaxinertia.objects import paper_object  # noqa: PLC0415
    from jaxinertia.open_manipulator_x import ARM as OMX  # noqa: PLC0415
    from jaxinertia.plans import random_plan  # noqa: PLC0415
    from jaxinertia.samples import Samples  # noqa: PLC0415
    from jaxinertia.sim.params import default_sim_params  # noqa: PLC0415
    from jaxinertia.sim.run import native_fields, run_plans  # noqa: PLC0415

    omx = arm_plan_kwargs(OMX)
    ws, tag = dict(workspace=OMX.workspace_deg), dict(tag_in_ee=OMX.tag_in_ee)
    plan = plan_poses(16, **omx)  # the command's defaults: 10 deg grid, DEFAULT_MARGIN_DEG in
    at_limits = plan_poses(16, **omx, margin_deg=0.0)  # the same without the margin
    params = default_sim_params()
    flip = np.random.default_rng(seed + 3).choice([-1.0, 1.0], plan.direction.shape)
    ablation = {"planned 16, random directions": lambda r: (np.tile(plan.q_d, (r, 1)),
                                                            np.tile(flip, (r, 1))),
                "planned 16, all +1": lambda r: (np.tile(plan.q_d, (r, 1)),
                                                 np.ones((16 * r, plan.q_d.shape[1])))}
    designs = {"planned 16": lambda r: (np.tile(plan.q_d, (r, 1)), np.tile(plan.direction,
                                                                          (r, 1))),
               "random 16": lambda r: random_plan(16 * r, seed + 1, **ws),
               "random 64": lambda r: random_plan(64 * r, seed + 2, **ws),
               "limits 16": lambda r: (np.tile(at_limits.q_d, (r, 1)),
                                       np.tile(at_limits.direction, (r, 1)))}
    if directions_only:  # the same poses with other approach directions
        designs = {"planned 16": designs["planned 16"], **ablation}
    if joint_weights is not None:  # the criterion weighted as the T-A solve weights joints
        weighted = plan_poses(16, **omx, joint_weights=np.asarray(joint_weights))
        designs["planned 16, attention-weighted"] = lambda r: (
            np.tile(weighted.q_d, (r, 1)), np.tile(weighted.direction, (r, 1)))
    jobs = [(k, o.name) for k in designs for o in objects]
    key = jax.random.key(seed)
    plans = [(paper_object(name, **tag), *designs[k](repeats), jax.random.fold_in(key, i))
             for i, (k, name) in enumerate(jobs)]
    t = time.perf_counter()
    results = run_plans(params, plans, descs=[f"{k}/{n}" for k, n in jobs], progress=False)
    wall = time.perf_counter() - t
    out = {"wall_s": wall, "n_samples": int(sum(len(r["q"]) for r in results)),
           "plan_logdet": plan.logdet}
    by_design: dict = {}
    for (k, name), (obj, *_), res in zip(jobs, plans, results):
        by_design.setdefault(k, {})[name] = (obj, res)
    for k, per in by_design.items():
        fields, meta = native_fields(per, params, scenario="issue17", seed=seed,
                                     version=__version__)
        data = Samples.from_fields(fields, meta["objects"], need_truth=True)
        objs = data.by_object()
        n = 64 if k == "random 64" else 16
        sets = [np.arange(o.n_samples).reshape(repeats, n) for o in objs]
        res = evaluate(objs, sets, pair=pair, fc=fc, l_max=l_max_of(objs))
        out[k] = {"objects": {nm: {m: e[m] for m in METHODS}
                              for nm, e in res["objects"].items()},
                  "not_at_rest": int(np.sum(~np.asarray(data.at_rest)))
                  if data.at_rest is not None else 0}
        out[k]["average"] = {m: {key_: float(np.mean([e[m][key_] for e in
                                                       out[k]["objects"].values()]))
                                 for key_ in ("mass_MAE_g", "com_MAE_mm")} for m in METHODS}
    return out


def _real(lbipe_dir):
    layout = find_layout(lbipe_dir)
    objects = real_files(layout)
    sets = [load_golden(golden_path(layout, o.name), o.n_samples)["sets"] for o in objects]
    return layout, objects, sets


def _print_coverage(title: str, cov: dict) -> None:
    print(f"\n## {title}")
    for variant, v in cov["variants"].items():
        for m in METHODS:
            print(f"  {variant:<14} {m:<4} mean: " + ", ".join(
                f"{k} {100 * x:.1f}" for k, x in v["mean"][m].items()))
    for name, per in cov["variants"]["full"]["objects"].items():
        for m in METHODS:
            r = per[m]
            print(f"    {name:<6} {m:<4} mass 68/95 {100 * r['mass_68']:.1f}/"
                  f"{100 * r['mass_95']:.1f}  COM 68/95 {100 * r['com_68']:.1f}/"
                  f"{100 * r['com_95']:.1f}  region95 {100 * r['com_region_95']:.1f}  se "
                  + " ".join(f"{s:.1f}" for s in r["median_se_g_mm"]) + "  rms err "
                  + " ".join(f"{s:.1f}" for s in r["rms_error_g_mm"]))


def main(argv=None) -> int:
    apply_xla_workarounds()  # XLA:CPU settings, before JAX starts its backend
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--models", type=Path, default=Path("runs/demo/models"))
    p.add_argument("--sim-test", type=Path, default=Path("runs/demo/data/test.npz"))
    p.add_argument("--lbipe-dir", type=Path, default=Path("../shared/lbipe"))
    p.add_argument("--out", type=Path, default=Path("runs/issue17"))
    p.add_argument("--repeats", type=int, default=1000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--skip", nargs="*", default=[], choices=["coverage", "design"])
    p.add_argument("--weights-from", type=Path, default=None, metavar="FILE",
                   help="with --simulate: also a plan weighted by the models' mean attention "
                   "weights on FILE (their training file)")
    p.add_argument("--simulate", type=int, default=0, metavar="R",
                   help="also simulate the 16-pose plan and random 16/64-pose plans R times "
                   "per test object (a 2-core CPU: ~600 samples/s)")
    p.add_argument("--directions-only", action="store_true",
                   help="with --simulate: only the plan with its balanced directions, random "
                   "ones and all +1")
    args = p.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    results: dict = {"argv": sys.argv, "machine": str(jax.devices()[0])}
    folder = load_models(args.models)
    pair, baselines, fc, config = folder.pair, folder.baselines, folder.features, folder.config
    floor, why = training_validation_error(config)
    results["floor"] = {"Nm": None if floor is None else floor.tolist(), "source": why}
    print(f"torque error floor: {why}: {floor}")
    sim, _ = load_samples(args.sim_test)
    sim_objects = sim.by_object()
    sim_sets, _ = choose_sets(sim_objects, n_sets=1000, set_size=64, seed=args.seed)
    layout, real_objects, real_sets = _real(args.lbipe_dir)
    released = load_released_models(layout.weights_dir, prefer=layout.prefer)
    if "coverage" not in args.skip:
        cov = {}
        cov["simulated, trained models"], _ = coverage_section(
            sim_objects, sim_sets, pair, fc, floor, baselines)
        cov["real, trained models"], ans_ours = coverage_section(
            real_objects, real_sets, pair, fc, floor)
        cov["real, released models"], ans_rel = coverage_section(
            real_objects, real_sets, released, LBIPE_FEATURES, None)
        cov["inflation"] = {"trained models": inflation_section(real_objects, ans_ours),
                            "released models": inflation_section(real_objects, ans_rel)}
        results["coverage"] = cov
        for k in ("simulated, trained models", "real, trained models", "real, released models"):
            _print_coverage(k, cov[k])
        print("\n## inflation (fit on one real object, check on the other)")
        for who, v in cov["inflation"].items():
            for k, r in v.items():
                print(f"  {who:<15} {k:<28} kappa mass {r['kappa_mass']:.2f} COM "
                      f"{r['kappa_com']:.2f}: mass 68/95 "
                      f"{100 * r['mass_68']:.1f}/{100 * r['mass_95']:.1f}  COM 68/95 "
                      f"{100 * r['com_68']:.1f}/{100 * r['com_95']:.1f}")
    if "design" not in args.skip:
        des = {}
        t = time.perf_counter()
        des["simulated, trained models"] = design_section(
            sim_objects, pair, fc, pool=150, repeats=args.repeats, seed=args.seed)
        des["real, trained models"] = design_section(
            real_objects, pair, fc, pool=500, repeats=args.repeats, seed=args.seed)
        des["real, released models"] = design_section(
            real_objects, released, LBIPE_FEATURES, pool=500, repeats=args.repeats,
            seed=args.seed)
        des["wall_s"] = time.perf_counter() - t
        results["design"] = des
        for who, d in des.items():
            if who == "wall_s":
                continue
            print(f"\n## design: {who}")
            for k, v in d.items():
                print(f"  {k:<24} " + "  ".join(
                    f"{m}: mass MAE {v['average'][m]['mass_MAE_g']:.2f} g, COM MAE "
                    f"{v['average'][m]['com_MAE_mm']:.2f} mm" for m in METHODS)
                    + "  (median log det " + ", ".join(
                        f"{n} {x:.2f}" for n, x in v["median_logdet"].items()) + ")")
                for n, e in v["objects"].items():
                    print(f"      {n:<6} " + "  ".join(
                        f"{m}: {e[m]['mass_MAE_g']:.2f} g {e[m]['com_MAE_mm']:.2f} mm"
                        for m in METHODS))
    if args.simulate:
        weights = None
        if args.weights_from is not None:
            weights = mean_attention(pair, fc, load_samples(args.weights_from)[0])
            results["plan_joint_weights"] = weights.tolist()
            print(f"plan joint weights (mean attention on {args.weights_from}): "
                  f"{np.round(weights, 4)}")
        sim_des = simulated_plans_section(sim_objects, pair, fc, repeats=args.simulate,
                                          seed=args.seed,
                                          directions_only=args.directions_only,
                                          joint_weights=weights)
        results["simulated_plans"] = sim_des
        print(f"\n## design on the simulator: plan simulated {args.simulate} times "
              f"({sim_des['n_samples']} samples, {sim_des['wall_s']:.0f} s)")
        for k in [k for k in sim_des if isinstance(sim_des[k], dict)]:
            v = sim_des[k]
            print(f"  {k:<11} " + "  ".join(
                f"{m}: mass MAE {v['average'][m]['mass_MAE_g']:.2f} g, COM MAE "
                f"{v['average'][m]['com_MAE_mm']:.2f} mm" for m in METHODS)
                + f"  (not at rest: {v['not_at_rest']})")
            for n, e in v["objects"].items():
                print(f"      {n:<6} " + "  ".join(
                    f"{m}: {e[m]['mass_MAE_g']:.2f} g {e[m]['com_MAE_mm']:.2f} mm"
                    for m in METHODS))
    path = args.out / "coverage_and_design.json"
    path.write_text(json.dumps(results, indent=1, default=lambda o: np.asarray(o).tolist()))
    print(f"\nwrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
