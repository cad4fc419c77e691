"""Domain randomization: simulated arms drawn around the identified one.

The simulator fit (:mod:`jaxinertia.sim.real_fit`) fits one servo per joint to a real
object's samples; what it cannot pin down is how the real arm departs from that servo as
the load changes. That departure is measured on the same real samples, not guessed: the
position-error law ``tau ~ k (q_d - q) - s f + c`` fitted per joint on the lighter and the
heavier half of the samples (by the joint's true |tau|) gives two gains and two intercepts;
their relative gain difference and intercept difference are the spreads
(:func:`spread_from_samples`). Each simulated arm then draws its servo torque constant
(the gain) from ``(1 + N(0, gain_rel))`` and its constant joint torque from ``N(0, offset)``
around the identified values (:func:`perturbed`).
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from jaxinertia.baselines import fit_pe_law
from jaxinertia.sim.simulator import SimParams

__all__ = ["DomainSpread", "SESSION_PRIOR_REL", "SessionSpread", "drawn", "perturbed",
           "session_drawn", "session_prior", "session_spread", "spread_from_samples"]


@dataclass(frozen=True)
class DomainSpread:
    """Per-joint (N,) standard deviations of the simulated arms around the identified one."""

    gain_rel: np.ndarray  # relative std of the servo torque constant (its P-loop gain) [-]
    offset: np.ndarray  # std of the constant joint torque [N m]

    def to_dict(self) -> dict:
        return {"gain_rel": np.asarray(self.gain_rel).tolist(),
                "offset_Nm": np.asarray(self.offset).tolist()}


def spread_from_samples(q_d, q, direction, tau) -> DomainSpread:
    """The load dependence of the position-error law in real samples of known objects:
    per joint, the relative gain difference and the intercept difference between the
    lighter and the heavier half of the samples (split at the median |tau|)."""
    qe, s, tau = np.asarray(q_d) - np.asarray(q), np.asarray(direction), np.asarray(tau)
    gain, offset = [], []
    for j in range(qe.shape[1]):
        heavy = np.abs(tau[:, j]) > np.median(np.abs(tau[:, j]))
        (k_lo, _, c_lo), (k_hi, _, c_hi) = (fit_pe_law(qe[m, j], s[m, j], tau[m, j])
                                            for m in (~heavy, heavy))
        gain.append(abs(k_hi - k_lo) / (0.5 * (k_hi + k_lo)))
        offset.append(abs(c_hi - c_lo))
    return DomainSpread(np.asarray(gain), np.asarray(offset))


def perturbed(params: SimParams, key: jax.Array, spread: DomainSpread) -> SimParams:
    """One simulated arm drawn around ``params``."""
    k_gain, k_off = jax.random.split(key)
    N = params.robot.n_joints
    dtype = params.servo.torque_constant.dtype
    scale = 1.0 + jnp.asarray(spread.gain_rel, dtype) * jax.random.normal(k_gain, (N,), dtype)
    offset = jnp.zeros(N, dtype) if params.torque_offset is None else params.torque_offset
    offset = offset + jnp.asarray(spread.offset, dtype) * jax.random.normal(k_off, (N,), dtype)
    servo = params.servo.replace(torque_constant=params.servo.torque_constant
                                 * jnp.maximum(scale, 0.5))
    return params.replace(servo=servo, torque_offset=offset)


# ---- recording sessions: the servo's state of the day ---------------------------------


@dataclass(frozen=True)
class SessionSpread:
    """Per-joint (N,) log-normal spreads of a recording session's servo state."""

    #: Supply voltage over winding resistance (temperature, supply): scales the motor
    #: current and so the torque per tick of error, and the Present Current with it [-].
    electrical_rel: np.ndarray
    #: Torque per ampere (magnet temperature, gear wear): the torque alone [-].
    torque_rel: np.ndarray

    def to_dict(self) -> dict:
        return {"electrical_rel": np.asarray(self.electrical_rel).tolist(),
                "torque_rel": np.asarray(self.torque_rel).tolist()}


def session_spread(current_gains, torque_gains) -> SessionSpread:
    """The spread that real sessions show: per joint, the standard deviation over sessions
    of log current gain (the electrical part, measured without ground truth) and of log
    torque gain beyond it (the torque per tick of known objects, whose load range also
    moves it, so an upper bound). ``current_gains``, ``torque_gains``: (sessions, N)."""
    lc, lt = np.log(np.asarray(current_gains)), np.log(np.asarray(torque_gains))
    if lc.shape[0] < 2:
        raise ValueError("a spread needs at least two sessions")
    return SessionSpread(np.std(lc, axis=0, ddof=1), np.std(lt - lc, axis=0, ddof=1))


def session_drawn(params: SimParams, key: jax.Array, spread: SessionSpread, *,
                  scale: float = 1.0) -> SimParams:
    """One recording session drawn around ``params``: supply voltage (the electrical gain)
    times ``exp(N(0, electrical_rel))``, torque constant times ``exp(N(0, torque_rel))``,
    both per joint; ``scale`` widens the draw (an unusual day)."""
    k_el, k_kt = jax.random.split(key)
    N = params.robot.n_joints
    sv = params.servo
    dtype = sv.torque_constant.dtype

    def factor(k, rel):
        return jnp.exp(scale * jnp.asarray(rel, dtype) * jax.random.normal(k, (N,), dtype))

    servo = sv.replace(supply_voltage=sv.supply_voltage * factor(k_el, spread.electrical_rel),
                       torque_constant=sv.torque_constant * factor(k_kt, spread.torque_rel))
    return params.replace(servo=servo)


#: The electrical spread of a recording session assumed before any is measured, per joint
#: (log-normal std): the supply (11.1-12 V: +-4 %) and the winding's temperature (copper,
#: 0.39 %/K over +-20 K: +-8 %) scale the motor current and the torque per tick alike. The
#: two real OpenMANIPULATOR-X files differ by 2.6-6 % (their spread, std over the two:
#: 1.9-4.2 %), within it.
SESSION_PRIOR_REL = 0.05


def session_prior(n_joints: int, measured: SessionSpread | None = None) -> SessionSpread:
    """The sessions a model is trained over: the electrical part at least
    :data:`SESSION_PRIOR_REL` (or the ``measured`` spread where wider); no torque-only part
    (a torque constant's change is invisible to the current; drawn in training it costs
    accuracy, docs/results.md, "Sessions")."""
    rel = np.full(n_joints, SESSION_PRIOR_REL)
    if measured is not None:
        rel = np.maximum(rel, np.asarray(measured.electrical_rel))
    return SessionSpread(rel, np.zeros(n_joints))


def drawn(params: SimParams, key: jax.Array, spread: DomainSpread | SessionSpread) -> SimParams:
    """One simulated arm drawn around ``params``: another arm (:func:`perturbed`) or
    another recording session of it (:func:`session_drawn`)."""
    if isinstance(spread, SessionSpread):
        return session_drawn(params, key, spread)
    return perturbed(params, key, spread)
