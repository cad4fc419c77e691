"""Joint friction with true sticking: a velocity-level, maximally dissipative box model.

MuJoCo's ``frictionloss`` is a soft constraint, and a PD-held link creeps to the same
gravity equilibrium from either side (DESIGN.md). Here friction is a *hard* constraint,
solved every time step on the velocity of the next step::

    M~ (v+ - v_free) = dt f,   |f_i| <= F_i,   f_i = -F_i sign(v+_i) where v+_i != 0

so a joint whose required holding torque stays under its bound F_i has v+_i = 0 exactly
(it sticks; it does not creep), and one that breaks away slides against F_i. The bound
carries the measured structure of the real servos' friction:

    F_i = (f_c + (f_s - f_c) exp(-(v / v_s)^2))       Coulomb + Stribeck (breakaway f_s)
          + mu |tau_load|                             load-dependent (gear mesh)
          + a cos(n q + phi)                          position-dependent ripple

Viscous friction ``b v`` is integrated implicitly with the joint damping.
The box problem is solved by projected Gauss-Seidel (exact for one joint, converging
fast for the weakly coupled N x N case).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from flax import struct

__all__ = ["FrictionParams", "friction_bound", "solve_box_friction"]


@struct.dataclass
class FrictionParams:
    """Per-joint (N,) friction parameters (SI)."""

    coulomb: jnp.ndarray  # f_c [N m]
    static: jnp.ndarray  # f_s >= f_c, breakaway [N m]
    stribeck_velocity: jnp.ndarray  # v_s [rad/s]
    viscous: jnp.ndarray  # b [N m s/rad]
    load_coefficient: jnp.ndarray  # mu [-]
    ripple_amplitude: jnp.ndarray  # a [N m]
    ripple_frequency: jnp.ndarray  # n [1/rad]
    ripple_phase: jnp.ndarray  # phi [rad]
    jitter: jnp.ndarray  # relative std of a per-sample scale on f_c, f_s (log-normal) [-]

    @classmethod
    def create(cls, n_joints: int, **values) -> FrictionParams:
        """Defaults for ``n_joints`` joints (``values``: per-joint or shared overrides)."""
        base = dict(coulomb=0.03, static=0.05, stribeck_velocity=0.02, viscous=0.01,
                    load_coefficient=0.3, ripple_amplitude=0.0, ripple_frequency=1.0,
                    ripple_phase=0.0, jitter=0.0)
        base.update(values)
        return cls(**{k: jnp.asarray(np.broadcast_to(v, (n_joints,)), jnp.result_type(float))
                      for k, v in base.items()})


def friction_bound(
    params: FrictionParams, q: jnp.ndarray, qd: jnp.ndarray, tau_load: jnp.ndarray
) -> jnp.ndarray:
    """The friction torque bound F (N,) [N m] at velocity qd and transmitted load."""
    stribeck = params.coulomb + (params.static - params.coulomb) * jnp.exp(
        -((qd / params.stribeck_velocity) ** 2))
    ripple = params.ripple_amplitude * jnp.cos(
        params.ripple_frequency * q + params.ripple_phase)
    return jnp.maximum(stribeck + params.load_coefficient * jnp.abs(tau_load) + ripple, 0.0)


def solve_box_friction(
    W: jnp.ndarray, v_free: jnp.ndarray, bound: jnp.ndarray, iterations: int = 30,
    f0: jnp.ndarray | None = None,
) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Projected Gauss-Seidel on ``v = v_free + W f``, ``|f_i| <= bound_i``, max dissipation.

    Args:
      W: (N, N) Delassus matrix ``dt M~^-1`` (symmetric positive definite).
      v_free: (N,) next-step velocity without friction; bound: (N,) torque bounds.
      f0: (N,) warm start (the previous step's friction); zero when None. The box problem
        is a strictly convex QP, so the start changes only how fast the sweeps converge.
    Returns the friction torques f (N,) and the next-step velocity v (N,).

    The sweeps are unrolled into scalar operations on the (batched) entries, so that the
    whole solve fuses into a few elementwise kernels under ``vmap``; a rolled loop costs
    one device loop iteration (and its kernel launches) per sweep on a GPU.
    """
    n = v_free.shape[-1]
    w = [[W[..., i, j] for j in range(n)] for i in range(n)]
    lo = [-bound[..., i] for i in range(n)]
    hi = [bound[..., i] for i in range(n)]
    if f0 is None:
        f = [jnp.zeros_like(v_free[..., i]) for i in range(n)]
    else:
        f = [jnp.clip(f0[..., i], lo[i], hi[i]) for i in range(n)]
    for _ in range(iterations):
        for i in range(n):
            v_i = v_free[..., i] + sum(w[i][j] * f[j] for j in range(n))
            f[i] = jnp.clip(f[i] - v_i / w[i][i], lo[i], hi[i])
    v = [v_free[..., i] + sum(w[i][j] * f[j] for j in range(n)) for i in range(n)]
    return jnp.stack(f, axis=-1), jnp.stack(v, axis=-1)
