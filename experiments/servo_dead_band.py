"""The real servos' current against the discrepancy: a dead band, and what it does to the
session's current gain (issue 30).

Per real file and joint: the mean current torque (k_t times Present Current) and the mean
true torque per tick of discrepancy; the current gain as a straight line through every
sample and beyond the fitted dead band (:func:`jaxinertia.session.dead_band_fit`); and, as
a check that uses the ground truth, the samples of both files compared at the same true
torque. With ``--sim FILE`` the same for a simulated file, per object.

    python experiments/servo_dead_band.py [--lbipe-dir DIR] [--sim runs/demo/data/test.npz]
"""

from __future__ import annotations

import argparse

import numpy as np

from jaxinertia.lbipe import default_lbipe_dir, find_layout, load_test_files
from jaxinertia.samples import load_samples
from jaxinertia.session import dead_band_fit

TICK = 2 * np.pi / 4096


def line_gain(e: np.ndarray, cur: np.ndarray) -> np.ndarray:
    """(N,) the slope of a straight line with intercept through every sample."""
    return np.array([np.polyfit(e[:, j], cur[:, j], 1)[0] for j in range(e.shape[1])])


def per_tick(name: str, e: np.ndarray, cur: np.ndarray, tau: np.ndarray, j: int) -> str:
    ticks = np.round(e[:, j] / TICK).astype(int)
    cells = []
    for t in range(ticks.min(), ticks.max() + 1):
        m = ticks == t
        if m.sum() >= 5:
            cells.append(f"{t}:{1e3 * cur[m, j].mean():.0f}/{1e3 * tau[m, j].mean():.0f}")
    return f"  {name:8s} " + " ".join(cells)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--lbipe-dir", default=None)
    ap.add_argument("--sim", default=None, help="a simulated sample file to compare")
    a = ap.parse_args()
    files = load_test_files(find_layout(a.lbipe_dir or default_lbipe_dir()))
    data = [(o.name, np.asarray(o.q_d - o.q, float), np.asarray(o.current_tau, float),
             np.asarray(o.tau, float)) for o in files]
    n = data[0][1].shape[1]
    print("ticks of discrepancy: mean current torque / mean true torque [N mm]")
    for j in range(n):
        print(f"joint {j + 1}")
        for name, e, cur, tau in data:
            print(per_tick(name, e, cur, tau, j))
    print("\ncurrent gain [N m/rad]: a line through every sample | beyond the dead band "
          "[dead band, ticks]")
    gains = {}
    for name, e, cur, _ in data:
        g, se, d = dead_band_fit(e, cur)
        gains[name] = (line_gain(e, cur), g)
        print(f"  {name:8s} " + " ".join(f"{x:6.2f}" for x in gains[name][0]) + " | "
              + " ".join(f"{x:6.2f} [{dd / TICK:.1f}]" for x, dd in zip(g, d)))
    if len(data) >= 2:
        (a0, g0), (a1, g1) = gains[data[0][0]], gains[data[1][0]]
        print(f"  {data[1][0]}/{data[0][0]}: line {np.round(a1 / a0, 3)}, beyond the dead "
              f"band {np.round(g1 / g0, 3)}")
        print("\nat the same true torque (ground truth, a check): mean discrepancy [mrad] / "
              "current torque [N mm] per torque bin")
        for j in range(n):
            lo = max(np.quantile(t[:, j], 0.05) for *_, t in data[:2])
            hi = min(np.quantile(t[:, j], 0.95) for *_, t in data[:2])
            edges = np.linspace(lo, hi, 5)
            cells = []
            for b0, b1 in zip(edges[:-1], edges[1:]):
                part = []
                for _name, e, cur, tau in data[:2]:
                    m = (tau[:, j] >= b0) & (tau[:, j] < b1)
                    part.append(f"{1e3 * e[m, j].mean():.1f}/{1e3 * cur[m, j].mean():.0f}")
                cells.append(f"{1e3 * (b0 + b1) / 2:.0f}: " + " vs ".join(part))
            print(f"  joint {j + 1}  " + " | ".join(cells))
    if a.sim:
        s = load_samples(a.sim)[0]
        print(f"\nsimulated ({a.sim}): line | beyond the dead band [ticks]")
        for i, name in enumerate(s.names):
            o = s.take(np.flatnonzero(np.asarray(s.object_id) == i))
            e, cur = np.asarray(o.q_d - o.q, float), np.asarray(o.current_tau, float)
            g, _, d = dead_band_fit(e, cur)
            print(f"  {name:8s} " + " ".join(f"{x:6.2f}" for x in line_gain(e, cur)) + " | "
                  + " ".join(f"{x:6.2f} [{dd / TICK:.1f}]" for x, dd in zip(g, d)))


if __name__ == "__main__":
    main()
