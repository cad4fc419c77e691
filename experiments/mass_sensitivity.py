"""What one per cent of a joint's torque costs the mass: the statics of the real files.

A model that reads a recording session's servos a few per cent off predicts every joint
torque that much off, most of it the arm's own gravity ``tau_g``, not the object's
``A x``. How far that moves the answer is a property of the statics and the poses alone,
measurable on the real files with their *known* torques (no model involved): per file and
joint, the mean shift of the least-squares mass (identity weights, the estimator "T" of
the recipe's mass part) over the file's sets when that joint's true torque is scaled by
``1 + eps``, per per cent; and the COM shift (NMAE points, the file's bounding-box
diagonal) likewise. Then, the other way round: the joint-2 torque scale that would explain
a given mass error (``--bias-g``).

    python experiments/mass_sensitivity.py [--lbipe-dir DIR] [--eps 0.01]
"""

from __future__ import annotations

import argparse

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402

from jaxinertia.app.pipeline import load_real  # noqa: E402
from jaxinertia.lbipe import default_lbipe_dir  # noqa: E402


@jax.jit
def _solve_sets(tau, tau_g, A, sets):
    """x per set by ordinary least squares: (B, 4) from (S, N) torques, (S, N, 4) A and
    (B, M) sample indices."""
    def one(idx):
        a = A[idx].reshape(-1, A.shape[-1])
        b = (tau[idx] - tau_g[idx]).reshape(-1)
        return jnp.linalg.lstsq(a, b)[0]

    return jax.vmap(one)(sets)


def _mass_com(x):
    m = x[:, 0]
    return m, x[:, 1:] / m[:, None]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--lbipe-dir", default=None)
    p.add_argument("--eps", type=float, default=0.01, help="torque scale step (0.01: 1 %%)")
    args = p.parse_args()
    real = load_real(args.lbipe_dir or default_lbipe_dir())
    n = real.objects[0].q.shape[1]
    print(f"per +{100 * args.eps:g} % of one joint's true torque: mean shift of the "
          "least-squares mass [g] (and of the COM, NMAE points) over the file's sets")
    print("| file | true mass [g] | " + " | ".join(f"joint {j + 1}" for j in range(n))
          + " | joint torque: arm's own / object's (mean abs, joint 2) |")
    print("| --- | ---: |" + " ---: |" * n + " --- |")
    for obj, sets, l_max in zip(real.objects, real.sets, real.l_max):
        tau, tau_g, A = (jnp.asarray(a) for a in (obj.tau, obj.tau_g, obj.A))
        sets = jnp.asarray(sets)
        m0, c0 = _mass_com(_solve_sets(tau, tau_g, A, sets))
        cells = []
        for j in range(n):
            scale = jnp.ones(n).at[j].add(args.eps)
            m1, c1 = _mass_com(_solve_sets(tau * scale, tau_g, A, sets))
            dm = 1000 * float(jnp.mean(m1 - m0))
            dc = 100 * float(jnp.mean(jnp.linalg.norm(c1 - c0, axis=1))) / l_max
            cells.append(f"{dm:+.2f} g ({dc:.1f})")
        own = float(jnp.mean(jnp.abs(tau_g[:, 1])))
        load = float(jnp.mean(jnp.abs(tau[:, 1] - tau_g[:, 1])))
        print(f"| {obj.name} | {1000 * float(obj.x[0, 0]):.1f} | " + " | ".join(cells)
              + f" | {1000 * own:.0f} / {1000 * load:.0f} N mm |")


if __name__ == "__main__":
    main()
