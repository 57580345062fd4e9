"""benchmarks/lsq_emulation.py (issue 15): its least-squares fit is the exact solution of the stated objective,
its rows are the LiDAR pairs' three points, its rule picks what it says, and bad use exits 2 with one message."""

from __future__ import annotations

import numpy as np
import pytest

from agents.kernel import GridBasis
from benchmarks import lsq_emulation as lsq
from launcher.world import Options, build_world


@pytest.fixture(scope="module")
def default_world():
    world, _ = build_world(Options(fleet_id="lsq-test"))
    return world


def test_rows_are_each_pair_outside_return_inside(default_world):
    outside, inside, fold = lsq.lidar_rows(default_world.robots)
    assert len(outside) == len(inside) == len(fold) == len(default_world.labels) // 2  # the default run: all pairs
    points, targets = lsq.stacked(outside, inside)
    n = len(outside)
    np.testing.assert_array_equal(targets, np.repeat([1.0, 0.0, -1.0], n))
    np.testing.assert_allclose(points[n:2 * n], (outside + inside) / 2)  # the return lies between its pair
    assert set(fold) == set(range(lsq.FOLDS))


def test_the_fit_is_the_exact_least_squares_solution(default_world):
    """Against numpy's lstsq of the stacked system [A; sqrt(lam) (I 0)] v = [t; 0] (gamma unregularised)."""
    outside, inside, _ = lsq.lidar_rows(default_world.robots)
    points, targets = lsq.stacked(outside, inside)
    gx, gy = np.meshgrid(np.linspace(-2, 2, 6), np.linspace(-1.5, 1.5, 5))
    basis = GridBasis(np.column_stack([gx.ravel(), gy.ravel()]), 0.8)
    f = lsq.fit(basis, points, targets)
    a = np.hstack([basis.features(points), np.ones((len(points), 1))])
    m = basis.size
    reg = np.hstack([np.sqrt(lsq.LAM) * np.eye(m), np.zeros((m, 1))])
    v = np.linalg.lstsq(np.vstack([a, reg]), np.concatenate([targets, np.zeros(m)]), rcond=None)[0]
    q = np.random.default_rng(0).uniform(-3, 3, size=(50, 2))
    np.testing.assert_allclose(f(q), basis.features(q) @ v[:-1] + v[-1], atol=1e-9)


def test_the_rule_takes_the_smallest_score_and_ties_go_to_the_larger_sigma():
    row = {"lsq": {k: {"score": s} for k, s in zip(lsq.CANDIDATES, (0.5, 0.2, 0.3, 0.2, 0.9))}}
    assert lsq.choice(row) == lsq.CANDIDATES[1]  # 0.2 twice: the smaller divisor, the wider kernel


@pytest.mark.parametrize("argv, says", [([], "error:"), (["frob", "."], "invalid choice"),
                                        (["dev", ".", "--jobs", "0"], "--jobs must be >= 1")])
def test_bad_use_exits_2_with_one_message(argv, says, capsys):
    with pytest.raises(SystemExit) as exit_info:
        lsq.main(argv)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert says in err and "Traceback" not in err


def test_an_out_path_that_is_a_file_exits_2(tmp_path, capsys):
    target = tmp_path / "file"
    target.write_text("x")
    with pytest.raises(SystemExit) as exit_info:
        lsq.main(["dev", str(target)])
    assert exit_info.value.code == 2 and "not a directory" in capsys.readouterr().err


def test_rule_2_tries_only_what_fits_and_ties_go_to_the_larger_sigma():
    near = {k: {"fits": True, "score": 0.4} for k in lsq.CANDIDATES_NEAR}
    near[32] = {"fits": False}  # over the budget: never chosen, whatever it would have scored
    near[24]["score"] = near[12]["score"] = 0.1
    assert lsq.choice_near({"near": near}) == 12


def test_rule_2_lattice_keeps_only_nodes_near_data_and_the_output_fills_enclosed_holes():
    from scipy.spatial import cKDTree
    points = np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 3.0]])
    sigma = 0.5
    grid = lsq.near_lattice((0.0, 4.0, 0.0, 3.0), sigma, points)
    assert len(grid) > 0 and np.all(cKDTree(points).query(grid)[0] <= lsq.NEAR * sigma)
    # a ring of grid nodes whose f is negative on the ring only: the output fills the ring's inside
    t = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    ring = np.column_stack([np.cos(t), np.sin(t)]) * 2.0
    basis = GridBasis(ring, 0.4)
    f = lambda q: -np.exp(-(cKDTree(ring).query(q)[0] ** 2) / 0.08) + 0.5  # noqa: E731  (< 0 near the ring)
    gx, gy = np.meshgrid(np.linspace(-3, 3, 61), np.linspace(-3, 3, 61))
    q = np.column_stack([gx.ravel(), gy.ravel()])
    mask = lsq.output_mask(f, basis, q, (61, 61))
    assert mask[30 * 61 + 30] and not (f(q[[30 * 61 + 30]]) < 0)[0]  # the centre: filled, though f > 0 there
    assert not mask[0]  # the box's corner: outside
