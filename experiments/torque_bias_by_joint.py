"""Where a fold candidate's mass bias on a real file comes from, joint by joint.

Each candidate's torque model (strength 0, the recipe's mass part) predicts every sample's
joint torques on both real files; the file's true torques (the known object's statics)
give the signed error per joint. Its mean is shown in N mm and as a percentage of the
object's own torque at that joint (``A x``). The least-squares mass over all the file's
samples, ``x = lstsq(A, tau_hat - tau_g)``, is linear in the error, so its bias splits
exactly into one share per joint (the error of that joint alone, the others' set to zero).
The mean over the candidates of each kind answers which joints make the drawn-sessions
candidates read even their own file high (session 44's table).

    python experiments/torque_bias_by_joint.py --run DIR --lbipe-dir DIR [--seed 0]
        [--current-scale 1.0] [--current-map]

``--current-scale`` multiplies every file's current torque before the models read it (a
probe of how much of the current-input candidates' bias their current path carries; the
candidates without the current do not move). ``--current-map`` maps each file's current
torque per joint onto the fold's simulator before the models read it: the affine law
``current = a tau + b`` fitted by least squares on the fold's own real file (its known
torques) and on the fold's simulated ``data/train_random.npz``, ``c -> a_sim / a_real
(c - b_real) + b_sim``; fitted on the seen file only, so the other file stays held out.

A fold's folder on its own ``fit_on`` file is **not held out** (marked "seen").
"""

from __future__ import annotations

import argparse
from collections import defaultdict
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from jaxinertia.app.pipeline import load_real  # noqa: E402
from jaxinertia.checkpoints import load_models, read_config  # noqa: E402
from jaxinertia.samples import load_samples  # noqa: E402
from jaxinertia.session import adapt_objects, session_reference  # noqa: E402
from jaxinertia.training import torque_predictions  # noqa: E402


def kind_of(name: str) -> str:
    """The candidate's kind from its folder name (``models_current_sessions_finetuned_250``
    -> ``current input, sessions drawn``; the paper network and the physical model, from
    scratch or fine-tuned, are the kind without the current)."""
    if "sessions" in name:
        return "current input, sessions drawn"
    if "current" in name:
        return "current input"
    return "without the current"


def mass_shares(obj, tau_hat: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Per joint: mean signed torque error [N m], the error along the sign of the object's
    own torque over that torque's mean magnitude [1] (> 0: the joint reads more object),
    and the least-squares mass bias [kg] that each joint's error alone causes; and the
    whole mass bias (their sum)."""
    tau, A, x = np.asarray(obj.tau), np.asarray(obj.A), np.asarray(obj.x)[0]
    err = tau_hat - tau  # (S, N)
    obj_tau = np.einsum("snk,k->sn", A, x)  # (S, N) the object's own torque
    # the error along the object's torque: > 0 reads more of the object than there is
    along = (err * np.sign(obj_tau)).mean(0) / np.abs(obj_tau).mean(0)
    flat_A = A.reshape(-1, 4)
    pinv = np.linalg.pinv(flat_A)  # (4, S N)
    shares = []
    for j in range(err.shape[1]):
        e = np.zeros_like(err)
        e[:, j] = err[:, j]
        shares.append((pinv @ e.reshape(-1))[0])
    shares = np.asarray(shares)
    return err.mean(0), along, float(shares.sum()), shares


def current_law(obj) -> np.ndarray:
    """(2, N): per joint the slope and offset of the current torque on the true torque."""
    c, t = np.asarray(obj.current_tau), np.asarray(obj.tau)
    return np.asarray([np.polyfit(t[:, j], c[:, j], 1) for j in range(c.shape[1])]).T


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run", required=True, help="a folds folder or a reproduce output folder")
    p.add_argument("--lbipe-dir", required=True)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--current-scale", type=float, default=1.0)
    p.add_argument("--current-map", action="store_true")
    a = p.parse_args()
    real = load_real(a.lbipe_dir, seed=a.seed)
    run = Path(a.run)
    folds = sorted({c.parent for c in run.rglob("config.json")
                    if c.parent.parent.name.startswith("fit_")})
    rows: dict[tuple, list] = defaultdict(list)
    laws = {}
    for folder in folds:
        fit_on = folder.parent.name.removeprefix("fit_")
        cfg = read_config(folder)
        models = load_models(folder)
        adapted, _ = adapt_objects(real.objects, session_reference(cfg, 0.0))
        if a.current_map and fit_on not in laws:
            sim = load_samples(folder.parent / "data" / "train_random.npz")
            sim = sim[0] if isinstance(sim, (list, tuple)) else sim
            seen_file = next(o for o in real.objects if o.name == fit_on)
            laws[fit_on] = (current_law(seen_file), current_law(sim))
            print(f"fit on {fit_on}: current slope real / sim per joint",
                  np.round(laws[fit_on][0][0], 3), np.round(laws[fit_on][1][0], 3))
        for obj in adapted:
            c = np.asarray(obj.current_tau) * a.current_scale
            if a.current_map:
                (ar, br), (as_, bs) = laws[fit_on]
                c = as_ / ar * (c - br) + bs
            obj = obj.replace(current_tau=c)
            tau_hat = np.asarray(torque_predictions(models.pair.torque_model,
                                                    models.pair.torque_vars,
                                                    models.features, obj)).mean(0)
            mean_err, rel, bias, shares = mass_shares(obj, tau_hat)
            m = float(np.asarray(obj.x)[0, 0])
            seen = "seen" if obj.name == fit_on else "held out"
            rows[(fit_on, obj.name, seen, kind_of(folder.name))].append(
                (mean_err, rel, bias / m, shares / m))
    print("fit on | file | | kind (n) | mean torque error per joint [N mm] | over the "
          "object's torque, along it [%] | LS mass bias [%] = joint shares [%]")
    for (fit_on, name, seen, kind), v in sorted(rows.items()):
        mean_err = np.mean([r[0] for r in v], 0) * 1e3
        rel = np.mean([r[1] for r in v], 0) * 100
        bias = np.mean([r[2] for r in v]) * 100
        shares = np.mean([r[3] for r in v], 0) * 100
        print(f"{fit_on:5s} | {name:5s} | {seen:8s} | {kind:30s} ({len(v)}) | "
              + " ".join(f"{e:+6.1f}" for e in mean_err) + " | "
              + " ".join(f"{r:+6.1f}" for r in rel) + f" | {bias:+6.1f} = "
              + " ".join(f"{s:+6.1f}" for s in shares))


if __name__ == "__main__":
    main()
