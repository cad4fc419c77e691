"""A first check that the servo's current carries what transfers between recording
sessions (issue 30, item 2), on the two real files alone, without the simulator: a linear
law per joint fitted on one file and applied to the other, with and without the current
torque as a regressor; the mass from all samples and NMAE over 300 sets of 64.

    python experiments/current_regressor_transfer.py [--lbipe-dir DIR]
"""

from __future__ import annotations

import argparse

import numpy as np

from jaxinertia.lbipe import default_lbipe_dir, find_layout, load_test_files
from jaxinertia.session import servo_session

TICK = 2 * np.pi / 4096


def regressors(o, j: int, kind: str, ratio: float = 1.0) -> np.ndarray:
    """(S, K) the law's regressors of joint j: discrepancy [ticks], direction, 1, their
    product, the joint's pose; ``cur``: and the current torque with its direction product;
    ``curonly``: the current torque, direction and 1 alone."""
    e = np.asarray(o.q_d - o.q)[:, j] / TICK * ratio
    d, c = np.asarray(o.direction)[:, j], np.asarray(o.current_tau)[:, j]
    q = np.asarray(o.q)[:, j]
    if kind == "curonly":
        return np.column_stack([c, d, np.ones_like(e), c * d])
    cols = [e, d, np.ones_like(e), e * d, np.cos(q), np.sin(q)]
    return np.column_stack(cols + ([c, c * d] if kind == "cur" else []))


def transfer(fit, held, kind: str, ratio: np.ndarray, n_sets: int = 300):
    """Mass error of all held-out samples [g], mass NMAE over sets [%], median COM error
    over sets [mm]."""
    n = np.asarray(fit.q).shape[1]
    tau_hat = np.stack([regressors(held, j, kind, ratio[j]) @ np.linalg.lstsq(
        regressors(fit, j, kind), fit.tau[:, j], rcond=None)[0] for j in range(n)], 1)
    A, y = np.asarray(held.A), tau_hat - np.asarray(held.tau_g)
    x, *_ = np.linalg.lstsq(A.reshape(-1, 4), y.reshape(-1), rcond=None)
    xt = np.asarray(held.x[0])
    rng = np.random.default_rng(0)
    m_err, c_err = [], []
    for _ in range(n_sets):
        i = rng.choice(len(y), 64, replace=False)
        xs, *_ = np.linalg.lstsq(A[i].reshape(-1, 4), y[i].reshape(-1), rcond=None)
        m_err.append(abs(xs[0] - xt[0]) / xt[0])
        c_err.append(np.linalg.norm(xs[1:] / xs[0] - xt[1:] / xt[0]))
    return (x[0] - xt[0]) * 1e3, 100 * np.mean(m_err), 1e3 * np.median(c_err)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--lbipe-dir", default=None)
    a = ap.parse_args()
    files = {o.name: o for o in load_test_files(find_layout(a.lbipe_dir
                                                            or default_lbipe_dir()))}
    for f, h in (("cube", "white"), ("white", "cube")):
        ratio = servo_session(files[h]).current_gain / servo_session(files[f]).current_gain
        for kind in ("pe", "cur", "curonly"):
            for label, r in (("unadapted", np.ones_like(ratio)), ("adapted", ratio)):
                m, nmae, com = transfer(files[f], files[h], kind, r)
                print(f"{f}->{h} {kind:8s} {label:9s} all-sample mass err {m:+6.1f} g, "
                      f"sets NMAE {nmae:5.1f} %, COM median {com:5.1f} mm")


if __name__ == "__main__":
    main()
