"""Is the held-out mass error the COM's coupling? The mass with the COM held at its truth.

The weighted least squares solves the mass and the first moment together (x = [m, m p]); a
torque error could reach the mass through the COM it also moves. With the COM known, the
mass is a one-unknown fit: tau - tau_g = m (A_0 + A_{1:} p). This script compares, with the
released models' torques (which saw neither real file: held out), T (every joint weighted
alike) over the golden sets: the joint solve, the mass with p at its truth (an oracle no
estimate has), and with p at the mean of the joint solve's own COM over the sets. Mass
NMAE and mean signed error [%], the mean of the ten pairs; 2-core CPU, seconds:

    python experiments/com_fixed_mass.py [--lbipe-dir DIR]
"""

from __future__ import annotations

import argparse

import numpy as np

from jaxinertia.app.pipeline import load_real
from jaxinertia.lbipe import default_lbipe_dir, golden_path, load_golden


def _mass_given_com(As, ys, p):
    """The least-squares mass per set with the COM p (S, 3): As (S, R, 4), ys (S, R)."""
    a = As[..., 0] + np.einsum("srj,sj->sr", As[..., 1:], p)
    return np.einsum("sr,sr->s", a, ys) / np.einsum("sr,sr->s", a, a)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--lbipe-dir", default=None)
    args = p.parse_args()
    real = load_real(args.lbipe_dir or default_lbipe_dir())
    print("| object | the joint solve | COM at its truth | COM at the joint solve's mean |")
    print("| --- | --- | --- | --- |")
    for o, sets in zip(real.objects, real.sets):
        tau_model = load_golden(golden_path(real.layout, o.name), o.n_samples)["tau_model"]
        A, tau_g = np.asarray(o.A), np.asarray(o.tau_g)  # (N, J, 4), (N, J)
        x_true = np.asarray(o.x).reshape(-1)[:4]
        m_true, p_true = x_true[0], x_true[1:] / x_true[0]
        S, M = sets.shape
        As = A[sets].reshape(S, M * A.shape[1], 4)
        rows = {"joint": [], "truth": [], "own mean": []}
        for f in tau_model:  # each released pair
            ys = (f - tau_g)[sets].reshape(S, -1)
            x = np.stack([np.linalg.lstsq(As[s], ys[s], rcond=None)[0] for s in range(S)])
            p_own = np.broadcast_to((x[:, 1:] / x[:, :1]).mean(0), (S, 3))
            for key, m in (("joint", x[:, 0]),
                           ("truth", _mass_given_com(As, ys, np.broadcast_to(p_true, (S, 3)))),
                           ("own mean", _mass_given_com(As, ys, p_own))):
                rows[key].append((np.abs(m - m_true).mean(), (m - m_true).mean()))
        cells = [np.mean(v, axis=0) / m_true * 100 for v in rows.values()]
        print(f"| {o.name} | " + " | ".join(f"{c[0]:.2f} ({c[1]:+.2f})" for c in cells) + " |")


if __name__ == "__main__":
    main()
