"""The grid basis: kernel values, the preconditioned variable, ill-conditioned grids."""

from __future__ import annotations

import numpy as np
import pytest

from agents.kernel import GridBasis, gaussian_kernel


def lattice(n: int, lo: float = -2.0, hi: float = 2.0) -> np.ndarray:
    g = np.linspace(lo, hi, n)
    gx, gy = np.meshgrid(g, g)
    return np.column_stack([gx.ravel(), gy.ravel()])


def test_kernel_matches_definition():
    rng = np.random.default_rng(1)
    a, b = rng.normal(size=(7, 2)), rng.normal(size=(5, 2))
    k = gaussian_kernel(a, b, 0.7)
    expected = np.exp(-((a[:, None, :] - b[None, :, :]) ** 2).sum(-1) / (2 * 0.7**2))
    np.testing.assert_allclose(k, expected, rtol=1e-12)
    assert np.all(np.diag(gaussian_kernel(a, a, 0.7)) == 1.0)


def test_preconditioned_variable_round_trip_and_norm():
    basis = GridBasis(lattice(4), 1.0)
    rng = np.random.default_rng(2)
    c = rng.normal(size=basis.size)
    x = basis.x_from_c(c)
    np.testing.assert_allclose(basis.c_from_x(x), c, rtol=1e-7, atol=1e-9)
    # the RKHS norm of f is the Euclidean norm of x: the reason for the change of variable
    assert basis.rkhs_norm(c) == pytest.approx(np.linalg.norm(x), rel=1e-9)
    # f(d) = phi(d)' x = k(d, G) c
    pts = rng.uniform(-2, 2, size=(9, 2))
    np.testing.assert_allclose(basis.features(pts) @ x, basis.kernel_to_grid(pts) @ c, rtol=1e-7, atol=1e-9)


def test_features_are_bounded_like_nystroem():
    basis = GridBasis(lattice(6), 0.8)
    pts = np.random.default_rng(3).uniform(-3, 3, size=(200, 2))
    norms = np.linalg.norm(basis.features(pts), axis=1)
    assert norms.max() <= 1.0 + 1e-6  # |phi(d)|^2 = k_d' K^+ k_d <= k(d, d) = 1


def test_dense_grid_is_truncated_not_broken():
    basis = GridBasis(lattice(30), 1.0)  # spacing 0.14 << sigma: K_G numerically singular
    assert basis.rank < basis.size
    assert np.isfinite(basis.condition) and basis.condition < 1e11
    pts = np.random.default_rng(4).uniform(-2, 2, size=(50, 2))
    assert np.all(np.isfinite(basis.features(pts)))


def test_function_error_zero_for_identical_and_scale_free():
    basis = GridBasis(lattice(3), 1.0)
    c = np.arange(basis.size, dtype=float)
    assert basis.function_error(c, 0.5, c, 0.5) == 0.0
    assert basis.function_error(2 * c, 0.0, c, 0.0) == pytest.approx(1.0)


@pytest.mark.parametrize("grid", [np.zeros((0, 2)), np.zeros((3, 3)), np.array([[0.0, np.nan]])])
def test_bad_grids_are_refused(grid):
    with pytest.raises(ValueError):
        GridBasis(grid, 1.0)


def test_bad_sigma_refused():
    with pytest.raises(ValueError, match="sigma"):
        GridBasis(lattice(2), 0.0)


def test_a_width_per_point_spans_the_sum_of_two_spaces():
    """widths: points of one width span one RKHS, f is the sum (K_G block-diagonal by width);
    equal widths are the one-width basis bit for bit."""
    grid = lattice(4)
    same = GridBasis(grid, 0.8, widths=np.full(len(grid), 0.8))
    plain = GridBasis(grid, 0.8)
    assert same.widths is None and np.array_equal(same.gram, plain.gram) and np.array_equal(same.inv_sqrt, plain.inv_sqrt)
    widths = np.where(np.arange(len(grid)) < 8, 0.8, 0.4)
    two = GridBasis(grid, 0.8, widths=widths)
    assert np.array_equal(two.gram[:8, :8], gaussian_kernel(grid[:8], grid[:8], 0.8))
    assert np.array_equal(two.gram[8:, 8:], gaussian_kernel(grid[8:], grid[8:], 0.4))
    assert not two.gram[:8, 8:].any() and not two.gram[8:, :8].any()
    pts = np.array([[0.3, -0.2], [1.1, 0.7]])
    c = np.linspace(-1.0, 1.0, len(grid))
    expected = gaussian_kernel(pts, grid[:8], 0.8) @ c[:8] + gaussian_kernel(pts, grid[8:], 0.4) @ c[8:] + 0.5
    assert np.allclose(two.decision(pts, c, 0.5), expected, rtol=0, atol=1e-14)
    assert np.isclose(two.rkhs_norm(c) ** 2, c @ two.gram @ c)
    with pytest.raises(ValueError, match="widths"):
        GridBasis(grid, 0.8, widths=np.zeros(len(grid)))
