"""The mass part's mean of every candidate with each kind of candidate read at its own
session strength (session 46, looked at).

``models_real``'s mass is the mean of a fold's candidates, all read at one session
strength (0 since session 41). The kinds differ in what they can see of a session: the
candidates without the current input see only the discrepancy, which a weaker servo's
session enlarges; the current-input ones also see the current, which moves with the
servo's supply (docs/results.md, "Sessions"). This judges, on a finished run's folds
(every training draw's), the mean with the kinds read at different strengths, and with
the drawn-sessions kind left out, T mass NMAE (bias) [%] on each held-out file and the
mass score over the released models' T-A.

    python experiments/kind_strengths.py --run DIR --lbipe-dir DIR
"""

from __future__ import annotations

import argparse
import itertools
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from candidate_ensemble import _metrics  # noqa: E402
from finetune_input_folds import KINDS, _fold_dirs, _kind  # noqa: E402

from jaxinertia.app.pipeline import evaluate_models, load_real, released_benchmark  # noqa: E402

STRENGTHS = (0.0, 0.5, 1.0)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run", required=True, help="a reproduce output folder (or its folds/)")
    p.add_argument("--lbipe-dir", required=True)
    p.add_argument("--draws", type=int, default=3)
    a = p.parse_args()
    real = load_real(a.lbipe_dir)
    names = [o.name for o in real.objects]
    released = released_benchmark(a.lbipe_dir, real=real)["objects"]
    kinds = list(KINDS)
    # (kind strengths: one per kind, None = left out) -> per held-out file the mass ratio
    combos = [dict(zip(kinds, c)) for c in itertools.product((*STRENGTHS, None), repeat=3)
              if any(s is not None for s in c)]
    ratios: dict[tuple, list[float]] = {}
    for fit_on in names:
        for held in (n for n in names if n != fit_on):
            h = names.index(held)
            obj, sets, l_max = real.objects[h], real.sets[h], real.l_max[h]
            by_kind: dict[str, dict[float, list[np.ndarray]]] = {
                k: {s: [] for s in STRENGTHS} for k in kinds}
            for fold in _fold_dirs(Path(a.run), fit_on, a.draws):
                for folder in sorted(fold.glob("models*")):
                    if not (folder / "config.json").is_file() or "randomized" in folder.name:
                        continue
                    for s in STRENGTHS:
                        r = evaluate_models(folder, [obj], [sets], l_max=[l_max],
                                            session_strength=s)
                        by_kind[_kind(folder.name)][s].append(
                            np.asarray(r["estimates"]["T"][0]))
            ref = released[held]["T-A"]["mass_NMAE_pct"]
            for k in kinds:
                for s in STRENGTHS:
                    mass, _, bias = _metrics(np.mean(by_kind[k][s], axis=0), obj, l_max)
                    print(f"{fit_on} -> {held}  {k:20s} s={s:.1f} ({len(by_kind[k][s])}): "
                          f"mass {mass:6.2f} ({bias:+6.2f})")
            for c in combos:
                xs = [x for k, s in c.items() if s is not None for x in by_kind[k][s]]
                mass, _, bias = _metrics(np.mean(xs, axis=0), obj, l_max)
                key = tuple(c.values())
                ratios.setdefault(key, []).append(mass / ref)
                ratios.setdefault(key + ("text",), []).append(f"{mass:5.2f} ({bias:+6.2f})")
    rows = sorted((float(np.mean(v)), k) for k, v in ratios.items() if k[-1] != "text")
    print("strengths (" + " / ".join(kinds) + "; - left out): mass score; per held-out file")
    for score, k in rows:
        label = " / ".join("-" if s is None else f"{s:.1f}" for s in k)
        print(f"  {label:17s} {score:.3f}   " + "   ".join(ratios[k + ("text",)]))


if __name__ == "__main__":
    main()
