"""Per-sample identification (jaxinertia.sim.identify): the parametrisation, the score and a
search that recovers a known simulator from its own samples.

The reference for the search is the simulator itself: "real" samples are simulated with a
known departure from the starting simulator (joint gains and offsets moved), and the
identification must find a simulator whose replay of those samples matches them better than
the start's does, moving the parameters towards the known departure.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxinertia.errors import UsageError
from jaxinertia.objects import paper_object
from jaxinertia.open_manipulator_x import ARM as OMX
from jaxinertia.plans import random_plan
from jaxinertia.samples import Samples
from jaxinertia.sim.identify import (
    PARAMETERS,
    ESConfig,
    apply_theta,
    group_index,
    group_stats,
    identify,
    replay,
    score,
    target_of,
)
from jaxinertia.sim.params import default_sim_params


@pytest.fixture(scope="module")
def base():
    return default_sim_params()


def test_zero_theta_is_the_start_and_each_coordinate_moves_its_parameter(base):
    N = base.robot.n_joints
    same = apply_theta(base, jnp.zeros((len(PARAMETERS), N)))
    for a, b in zip(jax.tree.leaves(same), jax.tree.leaves(base)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-15, atol=1e-15)
    theta = np.zeros((len(PARAMETERS), N))
    theta[:, 1] = [np.log(1.1), np.log(0.9), 0.01, 0.05, np.log(2.0), 0.02]
    p = apply_theta(base, jnp.asarray(theta))
    sv, fr = base.servo, base.friction
    np.testing.assert_allclose(p.servo.p_gain[1], sv.p_gain[1] * 1.1, rtol=1e-12)
    np.testing.assert_allclose(p.servo.torque_constant[1], sv.torque_constant[1] * 0.9,
                               rtol=1e-12)
    np.testing.assert_allclose(p.friction.static[1], fr.static[1] + 0.01, rtol=1e-12)
    # Coulomb keeps its ratio to breakaway.
    np.testing.assert_allclose(p.friction.coulomb[1] / p.friction.static[1],
                               fr.coulomb[1] / fr.static[1], rtol=1e-12)
    np.testing.assert_allclose(p.friction.load_coefficient[1], fr.load_coefficient[1] + 0.05,
                               rtol=1e-12)
    np.testing.assert_allclose(p.friction.jitter[1], fr.jitter[1] * 2.0, rtol=1e-12)
    offset0 = 0.0 if base.torque_offset is None else np.asarray(base.torque_offset)[1]
    np.testing.assert_allclose(p.torque_offset[1], offset0 + 0.02, rtol=1e-12)
    # Other joints untouched.
    np.testing.assert_allclose(p.servo.p_gain[0], sv.p_gain[0], rtol=1e-15)


def test_groups_are_direction_times_load_tercile_and_the_score_is_zero_on_the_truth():
    rng = np.random.default_rng(0)
    S, N = 600, 4
    tau = rng.normal(size=(S, N))
    direction = rng.choice([-1.0, 1.0], (S, N))
    g = group_index(tau, direction)
    assert g.min() == 0 and g.max() == 5
    np.testing.assert_array_equal(g >= 3, direction < 0)
    for j in range(N):  # terciles of |tau_j|: a third of the samples each
        counts = np.bincount(g[:, j] % 3, minlength=3)
        assert np.all(np.abs(counts - S / 3) <= 1), counts
    qe = jnp.asarray(0.01 * tau + 0.002 * rng.normal(size=(S, N)))
    cur = jnp.asarray(tau + 0.1 * rng.normal(size=(S, N)))
    gj, tj = jnp.asarray(g), jnp.asarray(tau)
    m, s = group_stats(qe, gj, jnp.ones(S))
    sel = g[:, 2] == 4  # numpy references of one group
    np.testing.assert_allclose(m[2, 4], qe[sel, 2].mean(), rtol=1e-12)
    np.testing.assert_allclose(s[2, 4], qe[sel, 2].std(), rtol=1e-6)
    real = target_of(qe, cur, tj, gj)
    b, a = np.polyfit(tau[sel, 2], np.asarray(qe)[sel, 2], 1)
    np.testing.assert_allclose(real.slope[2, 4], b, rtol=1e-9)
    np.testing.assert_allclose(real.level[2, 4], a + b * tau[sel, 2].mean(), rtol=1e-9)
    resid = np.asarray(qe)[sel, 2] - (a + b * tau[sel, 2])
    np.testing.assert_allclose(real.scatter[2, 4], resid.std(), rtol=1e-6)
    rest = jnp.ones(S, bool)
    assert float(score(qe, cur, tj, rest, gj, real)) == pytest.approx(0.0, abs=1e-12)
    assert float(score(qe + 0.002, cur, tj, rest, gj, real)) > 0.5  # a bias
    assert float(score(qe * 1.2, cur, tj, rest, gj, real)) > 0.5  # a softer servo
    assert float(score(qe + 0.001 * rng.normal(size=(S, N)), cur, tj, rest, gj,
                       real)) > 0.01  # more scatter
    # A sample that never came to rest counts against the candidate.
    assert float(score(qe, cur, tj, rest.at[:60].set(False), gj, real)) > 0.05


def test_identification_brings_a_wrong_simulator_closer_to_the_one_that_made_the_samples(base):
    """The 'real' samples come from ``base`` with the joint gains 8 % higher and the joint
    torque offsets moved, replayed by the search's own :func:`replay` with its random
    numbers (so that the truth scores 0); the search starts from ``base`` (small population
    and sample count: CPU time), and must lower the score by a third, returning the
    simulator it scored."""
    N = base.robot.n_joints
    true = np.zeros((len(PARAMETERS), N))
    true[0] = np.log(1.08)
    true[5] = [0.01, -0.02, 0.01, 0.005]
    obj = paper_object("white", tag_in_ee=OMX.tag_in_ee)
    q_d, direction = random_plan(24, 3, workspace=OMX.workspace_deg)
    key = jax.random.key(0)  # ESConfig.seed's key

    def replayed(theta):  # as the search replays a candidate (population 2: 3 replays)
        rec = replay(np.broadcast_to(theta, (3, *theta.shape)), base, obj, q_d, direction, key)
        return jax.tree.map(lambda a: np.asarray(a[0]), rec)

    rec = replayed(true)
    assert rec.at_rest.all()
    real = Samples.from_fields({k: getattr(rec, k) for k in (
        "q_d", "q", "current_tau", "direction", "tau", "tau_g", "A")} | {
        "object_id": np.zeros(24, np.int32), "x": np.asarray(obj.x)[None]}, ["white"],
        need_truth=True)
    logs = []
    found, info = identify(base, obj, real, config=ESConfig(population=2, generations=6,
                                                             seed=0), log=logs.append)
    h = info["history"]
    assert len(h) == 7 and len(logs) == 7
    assert h[-1]["best"] < 0.7 * h[0]["mean"], h
    # The returned simulator is the one that scored best: base moved by the returned theta,
    # whose replay is re-scored here.
    theta = np.asarray(info["theta"])
    assert theta.shape == (len(PARAMETERS), N)
    for a, b in zip(jax.tree.leaves(found), jax.tree.leaves(apply_theta(base,
                                                                        jnp.asarray(theta)))):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    np.testing.assert_allclose(np.asarray(found.servo.p_gain),
                               np.asarray(base.servo.p_gain) * np.exp(theta[0]), rtol=1e-12)
    groups = jnp.asarray(group_index(real.tau, real.direction))
    target = target_of(jnp.asarray(real.q_d - real.q), jnp.asarray(real.current_tau),
                       jnp.asarray(real.tau), groups)
    again = replayed(theta)
    rescored = score(jnp.asarray(again.q_d - again.q), jnp.asarray(again.current_tau),
                     jnp.asarray(again.tau), jnp.asarray(again.at_rest), groups, target)
    np.testing.assert_allclose(float(rescored), h[-1]["best"], rtol=1e-9)
    with pytest.raises(UsageError, match="population"):
        identify(base, obj, real, config=ESConfig(population=5, generations=1))
