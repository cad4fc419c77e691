"""The fold candidates' held-out mass with each real file's current mapped onto the fold's
simulator (session 47's lead, looked at): the recipe's mass judgement (T at strength 0, the
1000 sets of 64 of each held-out file, mass score over the released models' T-A), per kind
and for the mean of every candidate, with the current as measured and mapped.

The map is ``experiments/torque_bias_by_joint.py``'s: per joint the affine law of the
current torque on the true torque, fitted by least squares on the fold's own real file and
on the fold's simulated ``data/train_random.npz``, ``c -> a_sim / a_real (c - b_real) +
b_sim``. It is fitted on the seen file alone, so the other file stays held out.

    python experiments/current_map_folds.py --run DIR --lbipe-dir DIR [--draws 3]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from candidate_ensemble import _metrics  # noqa: E402
from finetune_input_folds import KINDS, _fold_dirs, _kind  # noqa: E402
from torque_bias_by_joint import current_law  # noqa: E402

from jaxinertia.app.pipeline import evaluate_models, load_real, released_benchmark  # noqa: E402
from jaxinertia.samples import load_samples  # noqa: E402


def mapped(obj, seen, sim):
    """``obj`` with its current torque mapped from ``seen``'s law onto ``sim``'s."""
    (ar, br), (as_, bs) = current_law(seen), current_law(sim)
    return obj.replace(current_tau=as_ / ar * (np.asarray(obj.current_tau) - br) + bs)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run", required=True, help="a reproduce output folder (or its folds/)")
    p.add_argument("--lbipe-dir", required=True)
    p.add_argument("--draws", type=int, default=3)
    a = p.parse_args()
    real = load_real(a.lbipe_dir)
    names = [o.name for o in real.objects]
    released = released_benchmark(a.lbipe_dir, real=real)["objects"]
    groups = (*((k,) for k in KINDS), tuple(KINDS))
    ratios: dict[tuple, list[float]] = {}
    for fit_on in names:
        seen = real.objects[names.index(fit_on)]
        for held in (n for n in names if n != fit_on):
            h = names.index(held)
            obj, sets, l_max = real.objects[h], real.sets[h], real.l_max[h]
            ref = released[held]["T-A"]["mass_NMAE_pct"]
            xs = {(k, m): [] for k in KINDS for m in (False, True)}
            for fold in _fold_dirs(Path(a.run), fit_on, a.draws):
                sim = load_samples(fold / "data" / "train_random.npz")
                sim = sim[0] if isinstance(sim, (list, tuple)) else sim
                versions = {False: obj, True: mapped(obj, seen, sim)}
                for folder in sorted(fold.glob("models*")):
                    if not (folder / "config.json").is_file() or "randomized" in folder.name:
                        continue
                    for m, o in versions.items():
                        r = evaluate_models(folder, [o], [sets], l_max=[l_max],
                                            session_strength=0.0)
                        xs[(_kind(folder.name), m)].append(np.asarray(r["estimates"]["T"][0]))
            for g in groups:
                for m in (False, True):
                    x = [e for k in g for e in xs[(k, m)]]
                    mass, _, bias = _metrics(np.mean(x, axis=0), obj, l_max)
                    ratios.setdefault((g, m), []).append(mass / ref)
                    print(f"{fit_on} -> {held}  {' + '.join(g):50s} "
                          f"{'mapped' if m else 'as read':7s} ({len(x):2d}): "
                          f"mass {mass:6.2f} ({bias:+6.2f})  over the released {mass / ref:.3f}")
    print("mass score (mean over the held-out files of the NMAE over the released models' T-A)")
    for (g, m), v in ratios.items():
        print(f"  {' + '.join(g):50s} {'mapped' if m else 'as read':7s} {np.mean(v):.3f}")


if __name__ == "__main__":
    main()
