"""Can any law of the observed state carry one real file's servo behaviour to the other?

Issue "Sim-to-real I", item 3: check what the simulator may lack against the data. The two
real files differ in the apparent position-error gain (joint 2: 22.0 N m/rad on the 41.5 g
cube, 20.1 on the 88 g white object). If that difference came from a mechanism the
simulator could carry (load-dependent stiffness or friction, position-dependent friction,
cable torques, coupling to the other joints' loads, supply-voltage sag), a static law of
that state fitted on one file would reproduce the other file's gain. This script fits, per
joint, the rest discrepancy ``q_d - q`` as a linear function of feature families of the
observed state on the *training* object of a fold, replays the *held-out* object's samples
through it (its true torques, directions and poses; residuals bootstrapped from the fit,
so that the replay has the training file's scatter), and fits the position-error law
``tau ~ k (q_d - q) - s f + c`` to the replayed discrepancies: the gain and intercept
errors against the held-out file's own fit are what a simulator with that mechanism,
identified perfectly on the training object, could reach at best. Nothing is fitted on the
object a number is reported on.

It also fits the servo's own Present Current against the tick error per file: at rest the
current is ``PWM / 885 * V / R`` with ``PWM = KP e``, whatever the load, so a change of that
slope between files is a change of the servo itself (winding temperature, supply), not of
the mechanics.

    python experiments/load_dependence.py [--lbipe-dir DIR] [--draws 20] [--json OUT]
"""

from __future__ import annotations

import argparse

import numpy as np

from jaxinertia.fileio import write_json
from jaxinertia.lbipe import default_lbipe_dir, find_layout, load_test_files

#: Feature families, cumulative: each adds columns to the ones before it.
FAMILIES = {
    "linear (k, Coulomb by direction, offset)": "base",
    "+ load-proportional friction, tau |tau| stiffness": "load",
    "+ pose (cos, sin of every joint and of q2+q3, q2+q3+q4)": "pose",
    "+ the other joints' torques and load friction": "other",
    "+ the other joints' directions": "dirs",
    "+ stiffness and friction varying with the joint's angle": "posetau",
    "+ supply sag (tau_j and s_j times the summed |tau|)": "sag",
}


def features(q, tau, s, j: int, level: str) -> np.ndarray:
    """(S, F) columns of the feature families up to ``level`` for joint ``j``."""
    order = list(FAMILIES.values())
    upto = order[: order.index(level) + 1]
    tj, sj = tau[:, j], s[:, j]
    cols = [tj, sj, np.ones_like(tj)]
    if "load" in upto:
        cols += [sj * np.abs(tj), tj * np.abs(tj)]
    if "pose" in upto:
        for a in (*q.T, q[:, 1] + q[:, 2], q[:, 1] + q[:, 2] + q[:, 3]):
            cols += [np.cos(a), np.sin(a)]
    others = [k for k in range(q.shape[1]) if k != j]
    if "other" in upto:
        cols += [tau[:, k] for k in others] + [np.abs(tau[:, k]) * sj for k in others]
    if "dirs" in upto:
        cols += [s[:, k] for k in others]
    if "posetau" in upto:
        cols += [tj * q[:, j], tj * q[:, j] ** 2, sj * q[:, j]]
    if "sag" in upto:
        total = np.abs(tau).sum(1)
        cols += [tj * total, sj * total]
    return np.stack(cols, 1)


def pe_law(qe, s, tau) -> np.ndarray:
    """[k, f, c] of ``tau ~ k qe - s f + c`` (the PE baseline's law)."""
    X = np.column_stack([qe, -s, np.ones_like(qe)])
    return np.linalg.lstsq(X, tau, rcond=None)[0]


def replay(train, test, level: str, draws: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """Per joint: the relative gain error [%] and intercept error [N mm] of the held-out
    file's PE law when its discrepancies come from the law fitted on ``train``."""
    gain, icpt = [], []
    for j in range(train.n_joints):
        X = features(train.q, train.tau, train.direction, j, level)
        qe_train = train.q_d[:, j] - train.q[:, j]
        c = np.linalg.lstsq(X, qe_train, rcond=None)[0]
        resid = qe_train - X @ c
        Xt = features(test.q, test.tau, test.direction, j, level)
        real = pe_law(test.q_d[:, j] - test.q[:, j], test.direction[:, j], test.tau[:, j])
        fits = np.array([pe_law(Xt @ c + rng.choice(resid, len(Xt)), test.direction[:, j],
                                test.tau[:, j]) for _ in range(draws)])
        gain.append(100.0 * (fits[:, 0].mean() / real[0] - 1.0))
        icpt.append(1e3 * (fits[:, 2].mean() - real[2]))
    return np.asarray(gain), np.asarray(icpt)


def current_slope(d) -> np.ndarray:
    """(N,) Present Current torque per radian of tick error, ``cur ~ a e + b``."""
    qe = d.q_d - d.q
    return np.array([np.polyfit(qe[:, j], d.current_tau[:, j], 1)[0]
                     for j in range(d.n_joints)])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lbipe-dir", default=None)
    ap.add_argument("--draws", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    files = {d.name: d for d in load_test_files(find_layout(args.lbipe_dir or default_lbipe_dir()))}
    if len(files) < 2:
        raise SystemExit(f"need two real objects, have {sorted(files)}")
    rng = np.random.default_rng(args.seed)
    out = {"replay": [], "current_slope": {}}
    fmt = lambda v: " / ".join(f"{x:+.1f}" for x in v)  # noqa: E731
    print("| fit on | replayed | state the law may use | gain error [%] | intercept error "
          "[N mm] |\n| --- | --- | --- | --- | --- |")
    for train_name, test_name in ((a, b) for a in files for b in files if a != b):
        for label, level in FAMILIES.items():
            g, c = replay(files[train_name], files[test_name], level, args.draws, rng)
            print(f"| {train_name} | {test_name} | {label} | {fmt(g)} | {fmt(c)} |")
            out["replay"].append({"fit_on": train_name, "replayed": test_name, "state": label,
                                  "gain_error_pct": g.tolist(),
                                  "intercept_error_Nmm": c.tolist()})
    print("\n| object | Present Current per radian of tick error [N m/rad] |\n| --- | --- |")
    for name, d in files.items():
        a = current_slope(d)
        out["current_slope"][name] = a.tolist()
        print(f"| {name} | {' / '.join(f'{x:.2f}' for x in a)} |")
    if args.json:
        write_json(args.json, out)


if __name__ == "__main__":
    main()
