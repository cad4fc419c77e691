"""D-optimal pose selection: determinants against numpy, local optimality of the exchange,
plans against random ones, directions, the plan file, the command, compilation."""

from __future__ import annotations

import itertools
import json

import jax.numpy as jnp
import numpy as np
import pytest
from support.compiles import compile_counter

from jaxinertia.app.cli import main
from jaxinertia.design import (
    DEFAULT_MARGIN_DEG,
    arm_plan_kwargs,
    balance_directions,
    information,
    load_plan,
    plan_poses,
    random_logdets,
    regressors,
    save_plan,
    select,
    select_pools,
)
from jaxinertia.errors import FileFormatError, UsageError
from jaxinertia.linalg import logdet_spd
from jaxinertia.open_manipulator_x import ARM as OMX
from jaxinertia.open_manipulator_x import WORKSPACE_DEG
from jaxinertia.plans import planning_plan, random_plan
from jaxinertia.robot import OPEN_MANIPULATOR_X_XML, data_path

#: The OpenMANIPULATOR-X's planning grid and regressor arguments (its record's values).
GRID = dict(step_deg=OMX.planning_step_deg, clearance=OMX.mount_clearance_m,
            robot=OMX.robot(), workspace=OMX.workspace_deg)
REG = dict(robot=GRID["robot"], tag=OMX.tag_in_ee)

# numpy's slogdet of the same (well-conditioned) matrices.
LOGDET_RTOL = 1e-10


def _candidates(rng, S=40):
    q = rng.uniform(np.radians([w[0] for w in WORKSPACE_DEG]),
                    np.radians([w[1] for w in WORKSPACE_DEG]), (S, 4))
    return q, np.asarray(information(regressors(q, **REG)))


def _scaled_logdet(C_all, idx):
    d = np.sqrt(np.mean(np.diagonal(C_all, axis1=-2, axis2=-1), axis=0))
    return np.linalg.slogdet(C_all[np.asarray(idx)].sum(0) / np.outer(d, d))[1]


def test_logdet_against_numpy_and_singular_is_minus_inf():
    rng = np.random.default_rng(0)
    L = rng.normal(size=(50, 4, 4))
    G = L @ np.swapaxes(L, -1, -2) + 0.1 * np.eye(4)
    np.testing.assert_allclose(np.asarray(logdet_spd(jnp.asarray(G))),
                               np.linalg.slogdet(G)[1], rtol=LOGDET_RTOL)
    v = rng.normal(size=(4, 1))
    assert np.asarray(logdet_spd(jnp.asarray(v @ v.T))) == -np.inf


def test_selection_is_a_local_optimum_and_beats_random_subsets():
    """After the exchanges no single swap of a chosen pose for another candidate raises
    log det (checked exhaustively in numpy), and the choice beats 1000 random subsets."""
    rng = np.random.default_rng(1)
    _, C = _candidates(rng, S=40)
    n = 6
    idx, ld, _ = select(jnp.asarray(C), n)
    idx = np.asarray(idx)
    assert len(set(idx.tolist())) == n
    best = _scaled_logdet(C, idx)
    assert float(ld) == pytest.approx(best, rel=1e-8)
    for i, s in itertools.product(range(n), range(len(C))):
        if s in idx:
            continue
        swapped = idx.copy()
        swapped[i] = s
        assert _scaled_logdet(C, swapped) <= best + 1e-9, (i, s)
    assert best > np.max(random_logdets(jnp.asarray(C), n, 1000, seed=2))


def test_pools_choose_within_their_pool_like_select():
    rng = np.random.default_rng(3)
    _, C = _candidates(rng, S=60)
    pools = np.stack([rng.choice(60, 20, replace=False) for _ in range(5)])
    idx, ld, _ = select_pools(jnp.asarray(C), jnp.asarray(pools), 5)
    for r in range(5):
        assert set(np.asarray(idx[r]).tolist()) <= set(pools[r].tolist())
        assert float(ld[r]) == pytest.approx(_scaled_logdet(C, idx[r]), rel=1e-8)
        # The pool's own selection (scaled differently) picks the same poses.
        own, _, _ = select(jnp.asarray(C[pools[r]]), 5)
        assert sorted(pools[r][np.asarray(own)].tolist()) == sorted(np.asarray(idx[r]).tolist())


def test_plan_is_independent_of_the_tag_pose():
    """Moving or turning the COM's reference point is x' = T x with det T = 1."""
    rng = np.random.default_rng(4)
    q, _ = _candidates(rng, S=50)
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    R *= np.sign(np.linalg.det(R))
    a, _, _ = select(information(regressors(q, **REG)), 8)
    b, _, _ = select(information(regressors(q, robot=REG["robot"],
                                             tag=(R, np.array([0.03, -0.01, 0.05])))), 8)
    assert sorted(np.asarray(a).tolist()) == sorted(np.asarray(b).tolist())


@pytest.mark.parametrize("margin", [0.0, DEFAULT_MARGIN_DEG])
def test_plan_poses_beats_random_plans_on_log_det(margin):
    plan = plan_poses(16, **arm_plan_kwargs(OMX), n_random=1000, margin_deg=margin)
    assert plan.q_d.shape == (16, 4) and plan.direction.shape == (16, 4)
    assert plan.logdet > np.max(plan.random_logdet)  # 1000 random 16-pose subsets of its grid
    # ... and 20 random plans over the whole workspace, all scored with one scaling.
    q_grid, _ = planning_plan(**GRID)
    q_grid = np.unique(q_grid, axis=0)
    C_grid = np.asarray(information(regressors(q_grid, **REG)))
    d = np.sqrt(np.mean(np.diagonal(C_grid, axis1=-2, axis2=-1), axis=0))

    def logdet(q):
        return np.linalg.slogdet(np.asarray(information(regressors(q, **REG))).sum(0)
                                 / np.outer(d, d))[1]

    planned = logdet(plan.q_d)
    for seed in range(20):
        assert logdet(random_plan(16, seed, workspace=OMX.workspace_deg)[0]) < planned, seed
    # Every planned pose is a collision-free grid configuration inside the margin, none twice.
    grid = {tuple(np.round(v, 9)) for v in q_grid}
    assert all(tuple(np.round(v, 9)) in grid for v in plan.q_d)
    assert len({tuple(v) for v in plan.q_d}) == 16
    lo, hi = (np.radians(a) for a in zip(*WORKSPACE_DEG))
    assert np.all(plan.q_d >= lo + np.radians(margin) - 1e-9)
    assert np.all(plan.q_d <= hi - np.radians(margin) + 1e-9)


def test_a_margin_that_leaves_no_workspace_is_refused():
    with pytest.raises(UsageError, match="leaves no room"):
        plan_poses(4, **arm_plan_kwargs(OMX), margin_deg=25.0)


def test_balanced_directions_cancel_a_friction_like_error():
    """The x error caused by torque errors d_sj f_j is smaller with the balanced directions
    than with almost any random pattern (median of 200)."""
    rng = np.random.default_rng(5)
    q, _ = _candidates(rng, S=16)
    A = regressors(q, **REG)
    f = np.array([0.02, 0.05, 0.03, 0.01])
    G = np.einsum("snp,snq->pq", A, A)

    def x_error(d):
        return np.linalg.norm(np.linalg.solve(G, np.einsum("snp,sn->p", A, d * f)))

    d = np.asarray(balance_directions(jnp.asarray(A)))
    assert set(np.unique(d).tolist()) <= {-1.0, 1.0}
    random = [x_error(rng.choice([-1.0, 1.0], (16, 4))) for _ in range(200)]
    assert x_error(d) < np.median(random)
    assert x_error(d) < x_error(np.ones((16, 4)))


def test_plan_file_round_trip_and_refusals(tmp_path):
    plan = plan_poses(6, **arm_plan_kwargs(OMX), n_random=50)
    path = save_plan(tmp_path / "plan.json", plan, robot="open_manipulator_x")
    q_d, direction = load_plan(path)
    np.testing.assert_array_equal(q_d, plan.q_d)
    np.testing.assert_array_equal(direction, plan.direction)
    doc = json.loads(path.read_text())
    for change, field in (({"format": "x"}, "format"), ({"q_d": [[0.1, "a"]]}, "q_d"),
                          ({"direction": [[2, 1, 1, 1]] * 6}, "direction"),
                          ({"direction": [[1, 1, 1]] * 6}, "direction"),
                          ({"q_d": [[float("nan")] * 4] * 6}, "q_d")):
        bad = tmp_path / "bad.json"
        bad.write_text(json.dumps({**doc, **change}))
        with pytest.raises(FileFormatError, match=rf"\[{field}\]"):
            load_plan(bad)
    bad.write_text("{")
    with pytest.raises(FileFormatError, match="not JSON"):
        load_plan(bad)


def test_plan_poses_command(tmp_path, capsys):
    out = tmp_path / "plan.json"
    assert main(["plan-poses", "--n", "16", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "log det" in printed and f"wrote {out}" in printed
    q_d, direction = load_plan(out)
    assert q_d.shape == (16, 4) and direction.shape == (16, 4)
    assert main(["plan-poses", "--n", "16", "--out", str(out)]) == 2  # exists
    assert "--overwrite" in capsys.readouterr().err
    assert main(["plan-poses", "--n", "100000", "--out", str(tmp_path / "p2.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "collision-free configurations" in err[0]


def test_select_compiles_once_per_shape():
    rng = np.random.default_rng(6)
    _, C1 = _candidates(rng, S=33)
    _, C2 = _candidates(rng, S=33)
    with compile_counter("select") as seen:
        a = select(jnp.asarray(C1), 5)
        b = select(jnp.asarray(C2), 5)
    assert seen.compiles["select"] == 1, seen
    assert not np.array_equal(np.asarray(a[0]), np.asarray(b[0]))


def test_plan_poses_for_a_description_file_matches_the_embedded_arm(tmp_path, capsys):
    """--robot FILE (the embedded arm's own MJCF, no tag mount) plans the same poses: the
    criterion depends on the kinematics only."""
    default, from_file = tmp_path / "a.json", tmp_path / "b.json"
    assert main(["plan-poses", "--n", "8", "--out", str(default)]) == 0
    ranges = ",".join(f"{lo:g}:{hi:g}" for lo, hi in WORKSPACE_DEG)
    assert main(["plan-poses", "--n", "8", "--out", str(from_file), "--robot",
                 str(data_path(OPEN_MANIPULATOR_X_XML)), f"--workspace={ranges}"]) == 0
    np.testing.assert_allclose(load_plan(from_file)[0], load_plan(default)[0], atol=1e-12)
    capsys.readouterr()
    assert main(["plan-poses", "--n", "8", "--out", str(tmp_path / "c.json"), "--robot",
                 str(data_path(OPEN_MANIPULATOR_X_XML))]) == 2
    assert "--workspace" in capsys.readouterr().err
