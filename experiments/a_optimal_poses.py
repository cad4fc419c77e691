"""Would an A-optimal criterion aimed at the mass and COM errors choose better poses than
``plan-poses``' D-optimal one? (Issue 17: 16 planned poses against 64 random ones.)

    python experiments/a_optimal_poses.py [--n 16] [--margins 0 10 15]

Predicted standard errors only (no torque is measured): for independent torque errors of
one level per joint, ``Cov(x) = sigma^2 (sum_s A_s^T A_s)^-1``; the errors of the mass [g]
and COM [mm] of an object of ``--mass`` with its COM at ``--com`` (tag frame, the training
loads' 20 mm below the tag) are ``L dx`` with ``L`` the first-order map of ``(m, m p) ->
(m, p)``. The A-optimal plan starts from the D-optimal one (:func:`jaxinertia.design.select`)
and swaps poses with grid candidates while one lowers ``trace(L Cov L^T)`` (Fedorov
exchanges). Every row is relative to the median of random 64-pose subsets of the same grid.
"""

from __future__ import annotations

import argparse
import sys

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

from jaxinertia import apply_xla_workarounds  # noqa: E402
from jaxinertia.design import information, inner_workspace, regressors, select  # noqa: E402
from jaxinertia.open_manipulator_x import ARM as OMX  # noqa: E402
from jaxinertia.open_manipulator_x import WORKSPACE_DEG  # noqa: E402
from jaxinertia.plans import planning_plan  # noqa: E402


def error_map(mass: float, com) -> np.ndarray:
    """(4, 4) L: ``L dx`` = (mass error [g], COM error [mm]) to first order at (mass, com)."""
    p = np.asarray(com, np.float64)
    L = np.zeros((4, 4))
    L[0, 0] = 1e3
    L[1:, 0] = -1e3 * p / mass
    L[1:, 1:] = 1e3 * np.eye(3) / mass
    return L


def predicted(G: np.ndarray, L: np.ndarray) -> np.ndarray:
    """(..., 2) predicted standard error of the mass and of the COM (root of the trace of its
    covariance) per unit torque error, for information matrices G (..., 4, 4)."""
    V = L @ np.linalg.inv(G) @ L.T
    d = np.diagonal(V, axis1=-2, axis2=-1)
    return np.stack([np.sqrt(d[..., 0]), np.sqrt(d[..., 1:].sum(-1))], axis=-1)


def a_exchange(C: np.ndarray, idx: np.ndarray, L: np.ndarray, max_swaps: int = 500):
    """Swap chosen candidates for others while one lowers ``trace(L G^-1 L^T)``."""
    idx = np.array(idx)

    def value(G):
        return np.trace(L @ np.linalg.inv(G) @ L.T, axis1=-2, axis2=-1)

    swaps = 0
    G = C[idx].sum(0)
    while swaps < max_swaps:
        trial = G[None, None] - C[idx][:, None] + C[None]  # (n, S, 4, 4)
        with np.errstate(all="ignore"):
            v = value(trial)
        v[:, idx] = np.inf
        v[~np.isfinite(v) | (np.linalg.det(trial) <= 0)] = np.inf
        i, s = np.unravel_index(np.argmin(v), v.shape)
        if not v[i, s] < value(G) * (1 - 1e-9):
            break
        G = G - C[idx[i]] + C[s]
        idx[i] = s
        swaps += 1
    return idx, swaps


def main(argv=None) -> int:
    apply_xla_workarounds()  # XLA:CPU settings, before JAX starts its backend
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=16)
    ap.add_argument("--margins", type=float, nargs="*", default=[0.0, 10.0, 15.0])
    ap.add_argument("--mass", type=float, default=0.1, help="[kg]")
    ap.add_argument("--com", type=float, nargs=3, default=[0.0, 0.0, -0.02], help="[m]")
    ap.add_argument("--draws", type=int, default=1000)
    args = ap.parse_args(argv)
    L = error_map(args.mass, args.com)
    rng = np.random.default_rng(0)
    robot, grid = OMX.robot(), dict(clearance=OMX.mount_clearance_m)
    reg = dict(robot=robot, tag=OMX.tag_in_ee)
    q_all = np.unique(planning_plan(10.0, robot=robot, workspace=WORKSPACE_DEG, **grid)[0],
                      axis=0)
    C_all = np.asarray(information(regressors(q_all, **reg)))
    ref = np.median(predicted(np.stack([C_all[rng.choice(len(C_all), 64, replace=False)].sum(0)
                                        for _ in range(args.draws)]), L), axis=0)
    rand = np.median(predicted(np.stack([C_all[rng.choice(len(C_all), args.n, replace=False)]
                                         .sum(0) for _ in range(args.draws)]), L), axis=0)
    print(f"predicted standard errors relative to random 64-pose subsets of the grid "
          f"({len(q_all)} configurations, medians of {args.draws}); mass {args.mass} kg, "
          f"COM {args.com} m in the tag frame")
    print(f"{'poses':<34} {'mass':>6} {'COM':>6}")
    print(f"{'random 64':<34} {1.0:6.3f} {1.0:6.3f}")
    print(f"{f'random {args.n}':<34} {rand[0] / ref[0]:6.3f} {rand[1] / ref[1]:6.3f}")
    for margin in args.margins:
        q = np.unique(planning_plan(10.0, robot=robot, **grid,
                                    workspace=inner_workspace(WORKSPACE_DEG, margin))[0],
                      axis=0)
        C = np.asarray(information(regressors(q, **reg)))
        d_idx = np.asarray(select(C, args.n)[0])
        a_idx, swaps = a_exchange(C, d_idx, L)
        for name, idx in ((f"D-optimal, {margin:g} deg inside", d_idx),
                          (f"A-optimal, {margin:g} deg inside ({swaps} swaps)", a_idx)):
            e = predicted(C[idx].sum(0), L)
            print(f"{name:<34} {e[0] / ref[0]:6.3f} {e[1] / ref[1]:6.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
