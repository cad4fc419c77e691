"""A known object at the same poses as a reference: does it carry across recording sessions?

The two real files were recorded at the same 1,000 commanded poses (q_d within 0.2 mrad)
with the same approach directions, each in its own session. A model's torque error at a
pose is mostly the arm's own gravity read a few per cent off (docs/results.md, "What one
per cent of joint 2 costs the answer"). With a *known* object at the same poses, that
error is known there, and an unknown object's torques could be corrected by it before the
weighted least squares. This script measures that with the released models (which saw
neither file: every number is held out), the reference being the other file:

* ``per pose``: subtract the reference's torque error at the same pose index;
* ``per joint and direction``: subtract its mean error per joint and approach direction;
* ``gain and offset per joint``: map the predicted torque through a line per joint fitted
  on the reference (predicted -> true torque).

T-A mass / COM NMAE [%] (each released pair's metric, then their mean, as the benchmark)
and the mean signed mass error [g] over the golden sets; 2-core CPU, a few seconds:

    python experiments/reference_object.py [--lbipe-dir DIR]

The reference is the other object in another session, which is what the held-out files
allow; a reference in the same session (an empty-gripper pass before the object) cannot be
tested on them.
"""

from __future__ import annotations

import argparse
from types import SimpleNamespace

import numpy as np

from jaxinertia.app.pipeline import load_real
from jaxinertia.lbipe import default_lbipe_dir, golden_path, load_golden
from jaxinertia.metrics import inertial_metrics


def _solve(A, y, w, sets):
    """Weighted least squares per pair and set: A (N, J, 4), y and w (K, N, J), sets (S, M)
    -> x (K, S, 4)."""
    As, ys, ws = A[sets], y[:, sets], w[:, sets]
    G = np.einsum("smji,ksmj,smjl->ksil", As, ws, As)
    r = np.einsum("smji,ksmj,ksmj->ksi", As, ws, ys)
    return np.linalg.solve(G, r[..., None])[..., 0]


def _corrections(obj, ref, f, f_ref) -> dict[str, np.ndarray]:
    """Each way of correcting the predicted torques f (K, N, J) of ``obj`` by the
    reference's known errors at the same pose indices."""
    err = f_ref - (ref.tau_g + np.einsum("nji,i->nj", ref.A, ref.x))[None]  # (K, N, J)
    by_dir = np.zeros_like(f)
    for j in range(f.shape[-1]):
        for d in (-1.0, 1.0):
            mean = err[:, ref.direction[:, j] == d, j].mean(axis=1)  # (K,)
            by_dir[:, obj.direction[:, j] == d, j] = mean[:, None]
    line = np.empty_like(f)
    truth = ref.tau_g + np.einsum("nji,i->nj", ref.A, ref.x)
    for k in range(f.shape[0]):
        for j in range(f.shape[-1]):
            X = np.stack([f_ref[k, :, j], np.ones(f.shape[1])], axis=1)
            a, b = np.linalg.lstsq(X, truth[:, j], rcond=None)[0]
            line[k, :, j] = a * f[k, :, j] + b
    return {"none (absolute)": f, "per pose": f - err, "per joint and direction": f - by_dir,
            "gain and offset per joint": line}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--lbipe-dir", default=None)
    args = p.parse_args()
    real = load_real(args.lbipe_dir or default_lbipe_dir())
    if len(real.objects) != 2:
        raise SystemExit("needs exactly the two real files (cube and white)")
    golden = [load_golden(golden_path(real.layout, o.name), o.n_samples) for o in real.objects]
    objs = [SimpleNamespace(name=o.name, A=np.asarray(o.A), tau_g=np.asarray(o.tau_g),
                            x=np.asarray(o.x).reshape(-1)[:4], q_d=np.asarray(o.q_d),
                            direction=np.asarray(o.direction)) for o in real.objects]
    shift = np.abs(np.asarray(objs[0].q_d) - np.asarray(objs[1].q_d)).max()
    same_dir = bool((objs[0].direction == objs[1].direction).all())
    print(f"poses: largest q_d difference {1e3 * shift:.2f} mrad; same directions: {same_dir}")
    print("| unknown (reference) | correction | T mass / COM [%] | T-A mass / COM [%] | "
          "T-A mean mass error [g] |")
    print("| --- | --- | --- | --- | ---: |")
    for u, r in ((1, 0), (0, 1)):
        obj, ref, sets = objs[u], objs[r], real.sets[u]
        f, f_ref = golden[u]["tau_model"], golden[r]["tau_model"]
        for name, tau in _corrections(obj, ref, f, f_ref).items():
            y = tau - obj.tau_g[None]
            cells = []
            for w in (np.ones_like(f), golden[u]["weights"]):
                x = _solve(obj.A, y, w, sets)
                per = [inertial_metrics(xk, obj.x, real.l_max[u]) for xk in x]
                cells.append(f"{np.mean([m['mass_NMAE_pct'] for m in per]):.2f} / "
                             f"{np.mean([m['com_NMAE_pct'] for m in per]):.2f}")
            bias = 1e3 * (x[..., 0].mean() - obj.x[0])
            print(f"| {obj.name} ({ref.name}) | {name} | {cells[0]} | {cells[1]} | {bias:+.2f} |")


if __name__ == "__main__":
    main()
