"""``jaxinertia models-real``: ``models_real`` from several training draws, the held-out
folds of finished ``reproduce`` runs on the same real files with different ``--seed``.

A run's training draw (its simulated data, the calibrations' and the trainings' random
draws) moves the folds' score by up to 0.05 (session 41, one tree: 0.963, 0.998 and 1.005
for seeds 0, 1 and 2), more than any recipe change did; the same recipe with the members of
the three draws averaged scored 0.940 on the same held-out files (docs/results.md, "Other
training draws"). :func:`models_from_runs` chooses the recipe over every run's folds (each
run's fold one more fold of :func:`jaxinertia.app.recipe.choose_recipe`), writes
``models_real`` of every run's folders that the recipe names, each a member of its mean
(:func:`jaxinertia.app.models_real.models_from_folds`), and judges it the folds' way: on
each real file, the members of every run's fold that did not see it, together. Beside it,
as ``reproduce`` does, ``models_real_with_released`` (half and half with the authors'
released models, :mod:`jaxinertia.app.with_released`), judged the same way. A run of
several draws (``reproduce --draws``) brings every one of its draws."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path
from types import SimpleNamespace

from jaxinertia.app.commands import LBIPE_DIR_HELP, lbipe_dir_of
from jaxinertia.app.options import enable_x64, write_json_option
from jaxinertia.app.recipe import choose_recipe, fold_draws, pooled_folds
from jaxinertia.errors import UsageError
from jaxinertia.fileio import check_output

__all__ = ["models_from_runs", "register"]


def _held_out(run: Path) -> dict:
    """A finished ``reproduce`` run's held-out folds (its ``tables.json``)."""
    tables = run / "tables.json"
    if not tables.is_file():
        raise UsageError(f"{run}: no tables.json (the output folder of a finished "
                         "`jaxinertia reproduce`)")
    held = json.loads(tables.read_text()).get("held_out")
    if not held:
        raise UsageError(f"{run}: its reproduce ran no held-out folds (they need two or more "
                         "real files in the lbipe folder)")
    return held


def _own_score(run: Path, record: dict, scale) -> float:
    """The run's own ``models_real``'s held-out score: as its ``reproduce`` judged it (all
    its training draws averaged), or, in a run from before that judgement (one draw), its
    recipe's score, the same number."""
    from jaxinertia.app.models_real import recipe_of  # (JAX, with the work's modules)

    judged = (json.loads((run / "tables.json").read_text()).get("real_finetuned") or {})
    return float((judged.get("held_out") or recipe_of(record, scale))["score"])


def _same_protocol(runs: list[Path], records: list[dict]) -> None:
    """Every run's folds are the same folds, judged on the same files and sets."""
    first = records[0]
    for run, rec in zip(runs[1:], records[1:]):
        for key, what in (("sets", "the held-out sets"), ("folds", "the folds")):
            a, b = first[key], rec[key]
            if key == "folds":
                a, b = ({f: sorted(r["held_out"]) for f, r in x.items()} for x in (a, b))
            if a != b:
                raise UsageError(f"{run}: {what} differ from {runs[0]}'s ({b} against {a}): "
                                 "draws of one protocol only (the same lbipe folder)")


def _fold_dirs(run: Path, record: dict, fit: str) -> list[Path]:
    """The run's folders of the folds fitted on ``fit``, one per training draw."""
    return [run / "folds" / d / f"fit_{fit}" for d, _ in fold_draws(record)]


def _sets_seed(sets: dict[str, str]) -> int:
    """The seed of the runs' random sets (``load_real``'s: object i's ``random (seed
    seed + i)``), 0 where every set is golden."""
    for i, source in enumerate(sets.values()):
        if m := re.fullmatch(r"random \(seed (\d+)\)", source):
            return int(m.group(1)) - i
    return 0


def _same_files(runs: list[Path], records: list[dict], fits: list[str], real) -> None:
    """Every run's fold was fitted on the very real file of ``real`` it is named after, as
    far as its folders record (a fine-tuning's ``data``: the file's SHA-256)."""
    sha = {o.name: f.meta.get("sha256") for o, f in zip(real.objects, real.files)}
    for run, record in zip(runs, records):
        for fit in fits:
            for config in sorted(c for d in _fold_dirs(run, record, fit)
                                 for c in d.glob("models*/config.json")):
                for entry in json.loads(config.read_text()).get("data") or ():
                    name = Path(str(entry.get("file", ""))).name
                    if name == f"data_test_{fit}.npz" and entry.get("sha256") != sha[fit]:
                        raise UsageError(
                            f"{config.parent}: fitted on another {name} than the lbipe "
                            "folder's (its SHA-256 differs): draws of the same real files "
                            "only")


def models_from_runs(runs: list[str | Path], out: str | Path, lbipe_dir: str | Path) -> dict:
    """``out/models_real`` from the held-out folds of every run in ``runs`` (the folders of
    finished ``reproduce`` runs on the real files of ``lbipe_dir``, e.g. ``--seed`` 0, 1
    and 2), the recipe chosen over all of them; its score on each held-out file from the
    members that did not see it. Returns the recipe, the score and each run's own."""
    # The work's modules (JAX), not for --help.
    from jaxinertia.app.models_real import models_from_folds, recipe_of  # (JAX)
    from jaxinertia.app.pipeline import load_real  # (JAX)
    from jaxinertia.app.with_released import models_with_released  # (JAX)

    runs, out = [Path(r) for r in runs], Path(out)
    if len(runs) < 2:
        raise UsageError(f"{len(runs)} run given: models from several draws need two or more")
    records = [_held_out(r) for r in runs]
    _same_protocol(runs, records)
    real = load_real(lbipe_dir, seed=_sets_seed(records[0]["sets"]))
    names = [o.name for o in real.objects]
    if dict(zip(names, real.sources)) != records[0]["sets"]:
        raise UsageError(f"{lbipe_dir}: its sets ({dict(zip(names, real.sources))}) are not "
                         f"those the runs' folds were judged on ({records[0]['sets']})")
    fits = list(records[0]["folds"])
    missing = sorted({*fits, *(h for f in records[0]["folds"].values() for h in f["held_out"])}
                     - set(names))
    if missing:
        raise UsageError(f"{lbipe_dir}: no real file of {', '.join(missing)} (the runs' folds "
                         f"fit on and judge {', '.join(sorted(set(fits)))})")
    _same_files(runs, records, fits, real)
    pooled = {f"{i}/{name}": fold for i, rec in enumerate(records)
              for name, fold in pooled_folds(rec)}
    by_part = SimpleNamespace(recipe_by_part=True)  # (reproduce's Scale, as every run's)
    recipe = recipe_of({"recipe": choose_recipe(pooled)}, by_part)
    n_draws = sum(len(fold_draws(rec)) for rec in records)
    recipe = {**recipe, "chosen_by": f"held-out folds of {n_draws} training draws "
                                     f"({len(runs)} runs)"}
    dirs = {fit: [d for r, rec in zip(runs, records) for d in _fold_dirs(r, rec, fit)]
            for fit in fits}
    made = models_from_folds(out, {"folds": fits}, real, recipe,
                             fold_dirs=[d for fit in fits for d in dirs[fit]])
    # Beside it, half and half with the authors' released models (their weights are in the
    # lbipe folder: the runs' folds judged them), as reproduce makes it.
    released = models_with_released(out, real)
    # Judged as the folds judge: on each real file, only the members of the folds that did
    # not see it (every run's), averaged as models_real averages them; and that average
    # half and half with the released models.
    judged: dict = {"ours": {}, "with_released": {}}
    judge = out / ".draws_judged"
    try:
        for fit in fits:
            part = models_from_folds(out, {"folds": [fit]}, real, recipe, fold_dirs=dirs[fit],
                                     dst=judge / f"fit_{fit}")
            both = models_with_released(out, real, src=judge / f"fit_{fit}",
                                        dst=judge / f"fit_{fit}_with_released")
            for name in records[0]["folds"][fit]["held_out"]:
                ref = records[0]["folds"][fit]["released"][name]["T-A"]
                for key, res in (("ours", part), ("with_released", both)):
                    judged[key].setdefault(fit, {})[name] = (res["objects"][name]["T-A"], ref)
    finally:
        shutil.rmtree(judge, ignore_errors=True)
    return {"runs": [str(r) for r in runs], "draws": n_draws, "models": made["models"],
            "recipe": recipe,
            "from_folds": made["from_folds"], "held_out": _scored(judged["ours"]),
            "each_run": [_own_score(r, rec, by_part) for r, rec in zip(runs, records)],
            "objects": made["objects"],  # (not held out: each file seen by half the members)
            "with_released": {"models": released["models"],
                              "released_share": released["released_share"],
                              "held_out": _scored(judged["with_released"]),
                              "objects": released["objects"]}}


def _scored(judged: dict) -> dict:
    """Held-out metrics ``{fit: {file: (ours, the released models')}}`` (T-A) as a score:
    NMAE over the released models', mean over the files, mass and COM apart and together."""
    held = {fit: {name: {k: ours[k] for k in ("mass_NMAE_pct", "com_NMAE_pct", "mass_MAE_g",
                                               "com_MAE_mm")}
                  for name, (ours, _) in files.items()} for fit, files in judged.items()}
    pairs = [pair for files in judged.values() for pair in files.values()]
    mass, com = (sum(o[f"{p}_NMAE_pct"] / r[f"{p}_NMAE_pct"] for o, r in pairs) / len(pairs)
                 for p in ("mass", "com"))
    return {"folds": held, "mass_score": mass, "com_score": com, "score": 0.5 * (mass + com)}


def cmd_models_real(args) -> int:
    for name in ("models_real", "models_real_with_released"):
        check_output(args.out / name, overwrite=args.overwrite, folder=True)
    enable_x64()
    res = models_from_runs(args.runs, args.out, lbipe_dir_of(args))
    h = res["held_out"]
    print(f"{res['models']}: {res['draws']} training draws of {len(res['runs'])} runs; the mass: "
          f"{res['recipe']['candidate']}; the COM: "
          f"{res['recipe'].get('com', res['recipe'])['candidate']}")
    print("held out (each file judged by the members that did not see it), T-A NMAE [%]:")
    for fit, objects in h["folds"].items():
        for name, r in objects.items():
            print(f"  fit on {fit}, judged on {name}: mass {r['mass_NMAE_pct']:.2f}, "
                  f"COM {r['com_NMAE_pct']:.2f}")
    print(f"score over the released models' T-A: {h['score']:.4f} (mass {h['mass_score']:.4f}"
          f", COM {h['com_score']:.4f}); each run's own models_real: "
          + ", ".join(f"{s:.4f}" for s in res["each_run"]))
    w = res["with_released"]
    print(f"{w['models']}: half and half with the authors' released models; held out "
          f"{w['held_out']['score']:.4f} (mass {w['held_out']['mass_score']:.4f}, COM "
          f"{w['held_out']['com_score']:.4f})")
    return write_json_option(args, res)


def register(sub) -> None:
    """Adds this module's subcommand to the ``jaxinertia`` argparse subparsers."""
    p = sub.add_parser(
        "models-real",
        help="models_real from several reproduce runs (training draws) on the same real files",
        description="Writes OUT/models_real from the held-out folds of finished `jaxinertia "
        "reproduce` runs on the same real files with different --seed: the recipe chosen "
        "over every run's folds, every run's folders it names averaged, and its held-out "
        "score (each real file judged by the members that did not see it).")
    p.add_argument("--runs", type=Path, nargs="+", required=True, metavar="RUN",
                   help="output folders of finished reproduce runs (two or more)")
    p.add_argument("--out", type=Path, required=True, help="write OUT/models_real here")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing OUT/models_real")
    p.add_argument("--lbipe-dir", type=Path, help=LBIPE_DIR_HELP)
    p.add_argument("--json", type=Path, help="write the recipe and scores here")
    p.set_defaults(func=cmd_models_real)
