"""Identification of the simulator from real samples, sample by sample (a population ES).

:func:`jaxinertia.sim.real_fit.fit_servo_friction` matches summary statistics of a
real file (one PE gain, friction level and load slope per joint). Here every real sample of
the object is *replayed* (its goal ``q_d``, approach direction, the object and its fitted
tag pose) in candidate simulators, and the candidates are scored on how the simulated rest
discrepancies and currents match the real ones **per approach direction and per load
level** of each joint: the real samples are grouped per joint by direction and by tercile
of ``|tau_j|`` (six groups per joint), and the score compares, group by group, the line of
``q_d - q`` against the load torque (its level and slope: the apparent bias and inverse
stiffness at that load and direction), the scatter around it and the mean Present Current
torque (:func:`score`). A single PE fit averages all of that into one gain and intercept.

The search is a separable evolution strategy (antithetic Gaussian population, rank-weighted
recombination of the best half, per-coordinate step sizes from the selected steps; the
diagonal form of CMA-ES without its covariance path). Per joint it moves six parameters
(:data:`PARAMETERS`) around the starting simulator. One generation is **one jitted call**:
the population of candidate simulators ``vmap``-ed over :func:`simulate_samples`, which
``vmap``s the samples, so that candidates x samples run as lanes of the batched simulator
(the GPU's natural shape). The same random numbers serve every candidate and generation
(common random numbers), so that scores differ by the parameters alone.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxinertia.compile_options import stepping_jit
from jaxinertia.errors import UsageError
from jaxinertia.objects import HeldObject
from jaxinertia.sim.sampling import Record, simulate_samples
from jaxinertia.sim.simulator import SimParams

__all__ = ["PARAMETERS", "ESConfig", "Target", "apply_theta", "group_index", "group_lines",
           "group_stats", "identify", "replay", "score", "target_of"]

#: Per-joint coordinates of a candidate, all relative to the starting simulator.
PARAMETERS = (
    "log P gain scale",  # position-loop gain (the stiffness seen from the encoder)
    "log torque-constant scale",  # torque per current (the Present Current reading's gain)
    "breakaway friction [N m]",  # added to f_s (f_c keeps its ratio to f_s)
    "load friction coefficient",  # added to mu
    "log friction jitter scale",  # the sample-to-sample friction spread
    "constant torque [N m]",  # added to the joint's torque offset
)
#: Initial step sizes of the coordinates above.
INITIAL_STEP = (0.04, 0.04, 0.01, 0.03, 0.2, 0.01)
N_GROUPS = 6  # per joint: 2 directions x 3 load terciles


@dataclass(frozen=True)
class ESConfig:
    population: int = 32  # candidates per generation (even: antithetic pairs)
    generations: int = 15
    seed: int = 0


def apply_theta(base: SimParams, theta: jnp.ndarray) -> SimParams:
    """The simulator ``base`` moved by ``theta`` (len(PARAMETERS), N) (see PARAMETERS)."""
    sv, fr = base.servo, base.friction
    ratio = fr.coulomb / jnp.maximum(fr.static, 1e-9)
    static = jnp.maximum(fr.static + theta[2], 2e-3)
    offset = (jnp.zeros_like(theta[5]) if base.torque_offset is None else base.torque_offset)
    return base.replace(
        servo=sv.replace(p_gain=sv.p_gain * jnp.exp(theta[0]),
                         torque_constant=sv.torque_constant * jnp.exp(theta[1])),
        friction=fr.replace(static=static, coulomb=ratio * static,
                            load_coefficient=jnp.maximum(fr.load_coefficient + theta[3], 0.0),
                            jitter=fr.jitter * jnp.exp(theta[4])),
        torque_offset=offset + theta[5])


def group_index(tau: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """(S, N) group of every sample and joint: 3 * (direction < 0) + tercile of |tau_j|."""
    a = np.abs(np.asarray(tau))
    edges = np.quantile(a, [1 / 3, 2 / 3], axis=0)  # (2, N)
    tercile = (a > edges[0]).astype(int) + (a > edges[1]).astype(int)
    return 3 * (np.asarray(direction) < 0).astype(int) + tercile


def group_stats(values, groups, weight):
    """(N, G) weighted mean and std of ``values`` (S, N) per group."""
    one_hot = jax.nn.one_hot(groups, N_GROUPS, dtype=values.dtype) * weight[:, None, None]
    n = jnp.maximum(one_hot.sum(0), 1.0)  # (N, G)
    mean = jnp.einsum("sn,sng->ng", values, one_hot) / n
    var = jnp.einsum("sng,sng->ng", (values[:, :, None] - mean) ** 2, one_hot) / n
    return mean, jnp.sqrt(var + 1e-14)


def group_lines(y, x, groups, weight, at):
    """Per joint and group (N, G): the weighted least-squares line ``y ~ a + b x`` as its
    value at ``at`` (N, G), its slope and the residual spread."""
    w = jax.nn.one_hot(groups, N_GROUPS, dtype=y.dtype) * weight[:, None, None]
    n = jnp.maximum(w.sum(0), 1.0)
    mx = jnp.einsum("sn,sng->ng", x, w) / n
    my = jnp.einsum("sn,sng->ng", y, w) / n
    dx, dy = x[:, :, None] - mx, y[:, :, None] - my
    sxx = jnp.einsum("sng,sng->ng", dx**2, w)
    b = jnp.einsum("sng,sng->ng", dx * dy, w) / jnp.maximum(sxx, 1e-14)
    r = dy - b * dx
    spread = jnp.sqrt(jnp.einsum("sng,sng->ng", r**2, w) / n + 1e-14)
    return my + b * (at - mx), b, spread


class Target(NamedTuple):
    """The real samples' signature (N, G each) and the scales the score divides by."""

    tau_mean: jnp.ndarray  # the group's mean |tau| position (where the lines are compared)
    tau_spread: jnp.ndarray
    level: jnp.ndarray  # discrepancy at tau_mean
    slope: jnp.ndarray  # d(q_d - q) / d tau: the inverse apparent stiffness
    scatter: jnp.ndarray  # residual spread of the discrepancy around its line
    current: jnp.ndarray  # mean Present Current torque
    current_spread: jnp.ndarray


def target_of(qe, current, tau, groups) -> Target:
    """The signature of real samples (every sample weighted 1)."""
    ones = jnp.ones(qe.shape[0], qe.dtype)
    tm, ts = group_stats(tau, groups, ones)
    level, slope, scatter = group_lines(qe, tau, groups, ones, tm)
    c, cs = group_stats(current, groups, ones)
    return Target(tm, ts, level, slope, scatter, c, jnp.maximum(cs, 1e-3))


def score(sim_qe, sim_current, sim_tau, at_rest, groups, real: Target) -> jnp.ndarray:
    """Mismatch of one simulated replay with the real samples (lower is better). Per joint
    and group (approach direction x load tercile), the discrepancy's line against the load
    torque: its level at the group's mean torque and its slope over the group's torque
    spread, both in units of the real residual scatter, the log ratio of the scatters, and
    the mean current in units of its real spread; squared and averaged. A sample that did
    not come to rest counts as a miss of 1 per joint."""
    w = at_rest.astype(sim_qe.dtype)
    level, slope, scatter = group_lines(sim_qe, sim_tau, groups, w, real.tau_mean)
    c, _ = group_stats(sim_current, groups, w)
    terms = (((level - real.level) / real.scatter) ** 2
             + ((slope - real.slope) * real.tau_spread / real.scatter) ** 2
             + jnp.log(scatter / real.scatter) ** 2
             + ((c - real.current) / real.current_spread) ** 2)
    return jnp.mean(terms) + jnp.mean(~at_rest)


def replay(thetas, base: SimParams, obj: HeldObject, q_d, direction, key) -> Record:
    """The plan ``q_d``, ``direction`` (S, N) replayed by every candidate simulator
    ``apply_theta(base, thetas[c])``, each with ``key``'s random draws (as
    :func:`jaxinertia.sim.sampling.simulate_samples`): a Record with a leading candidate
    axis. One compiled program per plan size and candidate count serves every object, fold
    and simulator: they are arguments, not constants of the program."""
    # Strongly typed leaves: an object built from Python floats (weakly typed) would trace
    # and compile its own program for the same shapes.
    base, obj = jax.tree.map(lambda v: jnp.asarray(v, jnp.result_type(v)), (base, obj))
    dtype = base.servo.p_gain.dtype
    return _replay(jnp.asarray(thetas, dtype), base, obj, jnp.asarray(q_d, dtype),
                   jnp.asarray(direction, dtype), key)


def _replay_fn(thetas, base, obj, q_d, direction, key) -> Record:
    return jax.vmap(lambda th: simulate_samples(apply_theta(base, th), obj, q_d, direction,
                                                key))(thetas)


_replay = stepping_jit(_replay_fn)


@jax.jit
def _scores(rec: Record, groups, target: Target) -> jnp.ndarray:
    """The score of every candidate's replay (leading axis of ``rec``)."""
    return jax.vmap(lambda r: score(r.q_d - r.q, r.current_tau, r.tau, r.at_rest, groups,
                                    target))(rec)


def identify(base: SimParams, obj: HeldObject, real, *, config: ESConfig = ESConfig(),
             log: Callable[[str], None] = print) -> tuple[SimParams, dict]:
    """Identifies ``base``'s servo, friction and torque offsets on one real object's samples.

    Args:
      base: the starting simulator (e.g. the fixed-point simulator fit on the same object).
      obj: the held object (mass, COM, fitted tag pose), as
        :func:`jaxinertia.sim.real_fit.real_plan` builds it.
      real: the object's real samples (``q_d``, ``q``, ``direction``, ``tau``,
        ``current_tau``; (S, N) each).
    Returns the identified simulator and the history (score of the mean and of the best
    candidate per generation, the final theta)."""
    if config.population < 2 or config.population % 2:
        raise UsageError(f"population must be even and >= 2, got {config.population}")
    N = base.robot.n_joints
    dtype = base.servo.p_gain.dtype
    groups = jnp.asarray(group_index(real.tau, real.direction))
    target = target_of(jnp.asarray(real.q_d - real.q, dtype),
                       jnp.asarray(real.current_tau, dtype), jnp.asarray(real.tau, dtype),
                       groups)
    key = jax.random.key(config.seed)
    base = jax.tree.map(lambda v: jnp.asarray(v, jnp.result_type(v)), base)

    def scores(thetas):
        return _scores(replay(thetas, base, obj, real.q_d, real.direction, key), groups, target)

    D = (len(PARAMETERS), N)
    mean = jnp.zeros(D, dtype)
    step = jnp.broadcast_to(jnp.asarray(INITIAL_STEP, dtype)[:, None], D)
    half = config.population // 2
    w = np.log(half + 0.5) - np.log(np.arange(1, half + 1))  # the better half recombines
    w = jnp.asarray(w / w.sum(), dtype)
    rng = jax.random.key(config.seed + 1)
    # Generation 0 scores the start; every call scores the current mean (row 0) beside the
    # population, so that one program (one shape) serves the whole search.
    eps = jnp.zeros((config.population, *D), dtype)
    best_theta, best, history = mean, np.inf, []
    for g in range(config.generations + 1):
        sc = scores(jnp.concatenate([mean[None], mean + step * eps]))
        at_mean, pop = float(sc[0]), sc[1:]
        if at_mean < best:
            best, best_theta = at_mean, mean
        i = int(jnp.argmin(pop))
        if g > 0 and float(pop[i]) < best:
            best, best_theta = float(pop[i]), mean + step * eps[i]
        history.append({"generation": g, "mean": at_mean, "best": best,
                        "population_median": float(jnp.median(pop)) if g else at_mean})
        log(f"identify: generation {g}: score of the mean {at_mean:.4f}, best {best:.4f}")
        if g > 0:
            elite = eps[jnp.argsort(pop)[:half]]
            mean = mean + step * jnp.einsum("e,e...->...", w, elite)
            # sep-CMA's rank-mu variance update of each coordinate's step (rate 0.3).
            step = step * jnp.sqrt(0.7 + 0.3 * jnp.einsum("e,e...->...", w, elite**2))
        if g < config.generations:
            rng, k = jax.random.split(rng)
            e = jax.random.normal(k, (half, *D), dtype)
            eps = jnp.concatenate([e, -e])
    return apply_theta(base, best_theta), {
        "history": history, "theta": np.asarray(best_theta).tolist(),
        "parameters": list(PARAMETERS), "population": config.population,
        "generations": config.generations}
