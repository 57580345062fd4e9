"""A scikit-learn-style estimator around the centralized solve: the fleet's reference.

    clf = GridKernelSVC(grid_shape=(5, 3), sigma=1.0).fit(points, labels)   # labels in {-1, +1}
    clf.decision_function(xy)   # f(x) = sum_j coef_[j] k(x, grid_[j]) + intercept_
    clf.predict(xy)             # +1 outside, -1 inside

Hyper-parameters go to __init__, learning happens in fit, learned state ends in an underscore,
bad input raises ValueError naming the problem -- the scikit-learn conventions.
"""

from __future__ import annotations

import numpy as np

from agents.kernel import GridBasis, lattice, padded_bounds
from agents.problem import InfeasibleError, solve_central


MIN_PAD = 0.1  # as `shapefleet`'s default grid region: data on a line still gets a 2-D box


def _check_points(X: object, name: str = "X") -> np.ndarray:
    X = np.asarray(X, dtype=float)
    if X.ndim != 2 or X.shape[1] != 2:
        raise ValueError(f"{name} must be an (n, 2) array of points, got shape {X.shape}")
    if len(X) == 0:
        raise ValueError(f"{name} has no points")
    if not np.all(np.isfinite(X)):
        raise ValueError(f"{name} holds NaN or infinite coordinates")
    return X


class GridKernelSVC:
    """Gaussian-kernel SVM whose function lives on a grid of points (the paper's relaxation).

    grid: explicit (M, 2) grid points; otherwise a `grid_shape` lattice over the data's bounding
    box widened by `pad` of its size on each side (cell centres, as `shapefleet --grid`).
    C: None for the hard margin (the paper), a positive penalty for a soft margin.
    widths: optional kernel width per grid point (autogrid's two-width model, its result's
    "widths"): points of one width span one RKHS, f is the sum (agents.kernel.GridBasis).
    """

    def __init__(
        self,
        grid: np.ndarray | None = None,
        grid_shape: tuple[int, int] = (5, 3),
        sigma: float = 1.0,
        C: float | None = None,
        pad: float = 0.15,
        widths: np.ndarray | None = None,
    ) -> None:
        self.grid = grid
        self.grid_shape = grid_shape
        self.sigma = sigma
        self.C = C
        self.pad = pad
        self.widths = widths

    def fit(self, X: object, y: object) -> GridKernelSVC:
        """Solve the centralized QP; InfeasibleError (a ValueError) if no grid function separates."""
        X = _check_points(X)
        y = np.asarray(y)
        if y.shape != (len(X),):
            raise ValueError(f"y must hold one label per point ({len(X)}), got shape {y.shape}")
        if not np.all(np.isin(y, (-1, 1))):
            raise ValueError(f"labels must be -1 (inside) or +1 (outside), got {sorted(set(np.unique(y).tolist()))}")
        if not (np.isfinite(self.sigma) and self.sigma > 0):
            raise ValueError(f"sigma must be a positive number, got {self.sigma!r}")
        if self.C is not None and not (np.isfinite(self.C) and self.C > 0):
            raise ValueError(f"C must be None (hard margin) or a positive number, got {self.C!r}")
        self.grid_ = self._grid(X)
        self.basis_ = GridBasis(self.grid_, self.sigma, widths=self.widths)
        solution = solve_central(self.basis_, X, y.astype(int), self.C)
        if not solution.solved:
            raise InfeasibleError(solution.message)
        self.coef_ = solution.c
        self.intercept_ = solution.gamma
        self.x_ = solution.x  # the preconditioned variable K_G^{1/2} c the fleet agrees on
        return self

    def decision_function(self, X: object) -> np.ndarray:
        """f(x): positive outside, negative inside, zero on the learned outline."""
        self._check_fitted()
        return self.basis_.decision(_check_points(X), self.coef_, self.intercept_)

    def predict(self, X: object) -> np.ndarray:
        """+1 (outside) or -1 (inside) for every point."""
        return np.where(self.decision_function(X) >= 0, 1, -1)

    def score(self, X: object, y: object) -> float:
        """Mean accuracy on (X, y)."""
        return float(np.mean(self.predict(X) == np.asarray(y)))

    def _grid(self, X: np.ndarray) -> np.ndarray:
        if self.grid is not None:
            return _check_points(self.grid, "grid")
        nx, ny = self.grid_shape
        if not (int(nx) == nx >= 1 and int(ny) == ny >= 1):
            raise ValueError(f"grid_shape must be two positive integers, got {self.grid_shape!r}")
        return lattice(int(nx), int(ny), padded_bounds(X, self.pad, MIN_PAD))

    def _check_fitted(self) -> None:
        if not hasattr(self, "coef_"):
            raise ValueError("this GridKernelSVC is not fitted yet: call fit(X, y) first")
