"""Every model folder of a finished run on every real file, one by one: the members of its
``models_real`` and every fold's candidates (session 25's diagnosis of ``models_real``).

Per folder and real file: T mass NMAE and bias [%] at strength 0 (the recipe's mass part;
``--strength`` another),
and whether the folder saw the file: a ``models_real`` member or a fold's folder on its
own ``fit_on`` file is **not held out**; a fold's folder on the other file is. Then the
mean of ``models_real``'s members (what it answers for the mass) and of each fold's
candidates (every training draw's folds, ``folds/seed<s>/fit_*`` too, and their pooled mean
per fitted file).

    python experiments/members_on_real_files.py --run DIR --lbipe-dir DIR
"""

from __future__ import annotations

import argparse
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from candidate_ensemble import _metrics  # noqa: E402

from jaxinertia.app.ensemble import members_of  # noqa: E402
from jaxinertia.app.pipeline import adapt_objects, load_real, session_reference  # noqa: E402
from jaxinertia.checkpoints import load_models  # noqa: E402
from jaxinertia.evaluation import evaluate  # noqa: E402


def _judge(folder_dir: Path, real, strength: float = 0.0) -> np.ndarray:
    """T estimates (O, K, B, 4) of one folder on every real file, at session adaptation's
    ``strength`` (0: the recipe's mass part)."""
    folder = load_models(folder_dir)
    adapted, _ = adapt_objects(real.objects, session_reference(folder.config, strength))
    return np.asarray(evaluate(adapted, real.sets, pair=folder.pair, fc=folder.features,
                               l_max=real.l_max)["estimates"]["T"])


def _row(label: str, x: np.ndarray, real, seen: set[str]) -> str:
    cells = []
    for o, obj in enumerate(real.objects):
        mass, _, bias = _metrics(x[o], obj, real.l_max[o])
        cells.append(f"{obj.name} {mass:6.2f} ({bias:+7.2f})"
                     + (" seen" if obj.name in seen else " held out"))
    return f"{label:52s} " + " | ".join(cells)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run", required=True, help="a reproduce output folder")
    p.add_argument("--lbipe-dir", required=True)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--strength", type=float, default=0.0,
                   help="session adaptation's strength (0: off, the recipe's mass part)")
    a = p.parse_args()
    run, real = Path(a.run), load_real(a.lbipe_dir, seed=a.seed)
    names = {o.name for o in real.objects}
    dst = run / "models_real"
    if (dst / "config.json").is_file():
        folders = [dst, *members_of(dst, load_models(dst).config)]
        xs = [_judge(f, real, a.strength) for f in folders]
        for f, x in zip(folders, xs):
            src = Path(load_models(f).config.get("copied_from", f)).name
            print(_row(f"models_real {f.relative_to(run)} ({src})", x, real, names))
        print(_row("models_real: the members' mean", np.mean(xs, axis=0), real, names))
    pooled: dict[str, list[np.ndarray]] = {}  # fit_on -> every draw's candidates
    folds = sorted((run / "folds").glob("fit_*")) + sorted((run / "folds").glob("seed*/fit_*"))
    for fold in folds:
        name = str(fold.relative_to(run / "folds"))
        fit = fold.name.removeprefix("fit_")
        xs = []
        for f in sorted(fold.glob("models*")):
            if (f / "config.json").is_file() and "randomized" not in f.name:
                xs.append(_judge(f, real, a.strength))
                print(_row(f"{name}/{f.name}", xs[-1], real, {fit}))
        print(_row(f"{name}: the candidates' mean", np.mean(xs, axis=0), real, {fit}))
        pooled.setdefault(fit, []).extend(xs)
    if len(folds) > len(pooled):  # several training draws (reproduce --draws)
        for fit, xs in pooled.items():
            print(_row(f"fit_{fit}, every draw: the candidates' mean", np.mean(xs, axis=0),
                       real, {fit}))


if __name__ == "__main__":
    main()
