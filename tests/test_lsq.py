"""The LiDAR least-squares model (agents/lsq_model.py) and its fleet (agents/lsq_admm.py):
the exact central solve, the fleet reaching it, crashes, and the shells' checks."""

from __future__ import annotations

import numpy as np
import pytest

from agents.lsq_model import (
    LsqLocalStep,
    design,
    lidar_pairs,
    lsq_rows,
    objective_share,
    solve_central_lsq,
)
from agents.spec import build_core, restore_core
from launcher.world import Options, build_world

from .conftest import max_function_error, run_to_end, step_all


def _world(**kwargs):
    kwargs.setdefault("fleet_id", "test")
    kwargs.setdefault("algorithm", "lsq")
    kwargs.setdefault("grid", "8x6")
    kwargs.setdefault("sigma", 1.0)
    world, spec = build_world(Options(**kwargs))
    return world, spec, spec.central([(r.id, r.points, r.labels) for r in world.robots])


def _stacked_rows(world):
    parts = [lsq_rows(r.points, r.labels) for r in world.robots]
    return np.vstack([p for p, _ in parts]), np.concatenate([t for _, t in parts])


def test_pairs_give_three_rows_and_loose_points_one():
    points = np.array([[0.0, 0.0], [1.0, 0.0], [5.0, 5.0], [2.0, 2.0], [2.0, 4.0], [7.0, 7.0]])
    labels = np.array([1, -1, 1, 1, -1, -1])
    assert lidar_pairs(labels).tolist() == [0, 3]
    rows, targets = lsq_rows(points, labels)
    assert targets.tolist() == [1, 0, -1, 1, 1, 0, -1, -1]
    assert rows[1].tolist() == [0.5, 0.0] and rows[5].tolist() == [2.0, 3.0]  # the midpoints
    assert rows[2].tolist() == [1.0, 0.0] and rows[7].tolist() == [7.0, 7.0]


def test_central_solve_equals_the_stacked_least_squares():
    world, spec, ref = _world()
    basis, lam = spec.basis, spec.algorithm_params.lam
    rows, targets = _stacked_rows(world)
    m = basis.size
    stacked = np.vstack([design(basis.features(rows)), np.hstack([np.sqrt(lam) * np.eye(m), np.zeros((m, 1))])])
    v = np.linalg.lstsq(stacked, np.concatenate([targets, np.zeros(m)]), rcond=None)[0]
    assert np.max(np.abs(v[:-1] - ref.x)) < 1e-10 and abs(v[-1] - ref.gamma) < 1e-10
    assert np.count_nonzero(targets == 0) > 0  # the midpoint rows are in the fit


def test_robot_shares_sum_to_the_central_objective():
    world, spec, ref = _world(robots=4)
    lam, v = spec.algorithm_params.lam, np.append(ref.x, ref.gamma)
    shares = [objective_share(spec.share(i).features, spec.share(i).labels, v, lam, 4) for i in spec.robot_ids]
    rows, targets = _stacked_rows(world)
    central = objective_share(spec.basis.features(rows), targets, v, lam, 1)
    assert sum(shares) == pytest.approx(central, rel=1e-12)


def test_local_step_is_the_minimiser_of_its_share():
    _, spec, _ = _world()
    share = spec.share(0)
    rng = np.random.default_rng(1)
    prox, q = rng.uniform(1, 5, share.dim), rng.normal(size=share.dim)
    step = LsqLocalStep(share.features, share.labels, x_weight=0.03, prox_weight=prox)
    v = step.solve_v(q)
    A = design(share.features)
    grad = 2 * A.T @ (A @ v - share.labels) + q + prox * v
    grad[:-1] += 2 * 0.03 * v[:-1]
    assert np.max(np.abs(grad)) < 1e-9 * max(1.0, np.max(np.abs(q)))


def test_a_pair_split_between_robots_is_not_a_pair():
    world, spec, _ = _world(robots=2)
    a, b = world.robots
    merged = solve_central_lsq(spec.basis, np.vstack([a.points[-1:], b.points[1:2]]), np.array([1, -1]))
    split = solve_central_lsq(spec.basis, np.vstack([a.points[-1:], b.points[1:2]]), np.array([1, -1]),
                              robot_of=np.array([0, 1]))
    assert merged.x.tolist() != split.x.tolist()  # merged holds a midpoint row, split does not
