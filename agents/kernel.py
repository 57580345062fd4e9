"""Gaussian kernel and the shared grid basis.

The learned function is f(x) = sum_j c_j k(x, g_j) + gamma over grid points g_j that every
robot shares. We work in the preconditioned variable x = K_G^{1/2} c (the paper's change of
variable): the RKHS norm c' K_G c becomes |x|^2 and f(d) = phi(d)' x + gamma with the
Nystroem feature map phi(d) = K_G^{+1/2} k(G, d). Using the *symmetric* square root keeps x
unique (no eigenvector sign ambiguity), so robots on different machines agree on its meaning.
"""

from __future__ import annotations

import math
import sys

import numpy as np

#: Eigenvalues of K_G below RCOND * largest are treated as zero. A grid dense relative to
#: sigma makes K_G numerically singular; truncating those directions keeps the problem well
#: posed (they carry functions of RKHS norm ~0 that no data can see) and the solver stable.
RCOND = 1e-10


def _squared_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """|a_i - b_j|^2 for every pair of rows (clipped at 0 against round-off)."""
    a = np.atleast_2d(np.asarray(a, dtype=float))
    b = np.atleast_2d(np.asarray(b, dtype=float))
    sq = (
        np.sum(a * a, axis=1)[:, None]
        + np.sum(b * b, axis=1)[None, :]
        - 2.0 * a @ b.T
    )
    np.maximum(sq, 0.0, out=sq)
    return sq


def gaussian_kernel(a: np.ndarray, b: np.ndarray, sigma: float) -> np.ndarray:
    """k(a_i, b_j) = exp(-|a_i - b_j|^2 / (2 sigma^2)) for every pair of rows."""
    return np.exp(-_squared_distances(a, b) / (2.0 * sigma * sigma))


def width_kernel(a: np.ndarray, b: np.ndarray, widths: np.ndarray) -> np.ndarray:
    """k_j(a_i, b_j) = exp(-|a_i - b_j|^2 / (2 widths_j^2)): column j at its own width."""
    return np.exp(-_squared_distances(a, b) / (2.0 * np.asarray(widths, dtype=float)[None, :] ** 2))


def padded_bounds(points: np.ndarray, pad: float, min_pad: float) -> tuple[float, float, float, float]:
    """The points' bounding box (x0, x1, y0, y1) widened on each side by `pad` times its size,
    at least `min_pad`: the default region of the grid."""
    low, high = points.min(axis=0), points.max(axis=0)
    margin = np.maximum(pad * (high - low), min_pad)
    low, high = low - margin, high + margin
    return (float(low[0]), float(high[0]), float(low[1]), float(high[1]))


def lattice(nx: int, ny: int, bounds: tuple[float, float, float, float]) -> np.ndarray:
    """nx*ny points at the cell centres of an nx-by-ny split of `bounds`; x varies fastest.

    Cell centres keep every point strictly inside the region (the lattice the paper draws).
    """
    x0, x1, y0, y1 = bounds
    xs = x0 + (np.arange(nx) + 0.5) * ((x1 - x0) / nx)
    ys = y0 + (np.arange(ny) + 0.5) * ((y1 - y0) / ny)
    gx, gy = np.meshgrid(xs, ys)
    return np.column_stack([gx.ravel(), gy.ravel()])


def check_squarable_width(sigma: float) -> None:
    """ValueError unless 2 sigma^2, the kernel's denominator, is a finite normal float (1e-300 squares
    to 0: the Gram matrix became 0/0; 1e300 to inf)."""
    square = float(sigma) * float(sigma)  # (a product overflows to inf; ** would raise)
    if not (math.isfinite(square) and square >= sys.float_info.min):
        raise ValueError(f"{sigma!r} cannot be squared in floating point (the kernel divides by 2 sigma^2)")


class GridBasis:
    """The function space spanned by kernels on the shared grid, with its preconditioning."""

    def __init__(
        self, grid: np.ndarray, sigma: float, rcond: float = RCOND, widths: np.ndarray | None = None
    ) -> None:
        """`widths` (one per grid point, optional): a kernel width per point. Points of one width
        span one RKHS; points of different widths span different ones, and f is their sum with
        the sum of the squared norms (K_G block-diagonal by width): a model beyond one width
        (coarse points wide, refined points near the boundary narrow). None: every point sigma."""
        grid = np.asarray(grid, dtype=float)
        if grid.ndim != 2 or grid.shape[1] != 2 or len(grid) == 0:
            raise ValueError(f"grid must be an (M, 2) array of points, got shape {grid.shape}")
        if not np.all(np.isfinite(grid)):
            raise ValueError("grid points must be finite")
        if not (np.isfinite(sigma) and sigma > 0):
            raise ValueError(f"sigma must be a positive number, got {sigma!r}")
        check_squarable_width(sigma)
        self.grid = grid
        self.sigma = float(sigma)
        self.widths: np.ndarray | None = None
        if widths is not None:
            widths = np.asarray(widths, dtype=float)
            if widths.shape != (len(grid),) or not np.all(np.isfinite(widths) & (widths > 0)):
                raise ValueError(f"widths must be {len(grid)} positive numbers, one per grid point")
            if np.all(widths == self.sigma):
                widths = None
        self.widths = widths
        if widths is None:
            self.gram = gaussian_kernel(grid, grid, sigma)
        else:
            self.gram = width_kernel(grid, grid, widths) * (widths[:, None] == widths[None, :])
        eigval, eigvec = np.linalg.eigh(self.gram)
        keep = eigval > rcond * eigval[-1]
        u, lam = eigvec[:, keep], eigval[keep]
        self.rank = int(keep.sum())
        self.sqrt = (u * np.sqrt(lam)) @ u.T  # K_G^{1/2}
        self.inv_sqrt = (u / np.sqrt(lam)) @ u.T  # K_G^{+1/2}, on the kept range
        #: condition number of K_G on the kept range (what the solver actually sees)
        self.condition = float(eigval[-1] / lam[0])

    @property
    def size(self) -> int:
        """Number of grid points M."""
        return len(self.grid)

    def kernel_to_grid(self, points: np.ndarray) -> np.ndarray:
        """k(points, G): (n, M) (column j at grid point j's width)."""
        if self.widths is not None:
            return width_kernel(points, self.grid, self.widths)
        return gaussian_kernel(points, self.grid, self.sigma)

    def features(self, points: np.ndarray) -> np.ndarray:
        """phi(d) for every row: f(d) = phi(d)' x + gamma in the preconditioned variable."""
        return self.kernel_to_grid(points) @ self.inv_sqrt

    def c_from_x(self, x: np.ndarray) -> np.ndarray:
        """Grid coefficients c = K_G^{+1/2} x."""
        return self.inv_sqrt @ np.asarray(x, dtype=float)

    def x_from_c(self, c: np.ndarray) -> np.ndarray:
        """Preconditioned variable x = K_G^{1/2} c."""
        return self.sqrt @ np.asarray(c, dtype=float)

    def decision(self, points: np.ndarray, c: np.ndarray, gamma: float) -> np.ndarray:
        """f(points) = k(points, G) c + gamma."""
        return self.kernel_to_grid(points) @ np.asarray(c, dtype=float) + float(gamma)

    def rkhs_norm(self, c: np.ndarray) -> float:
        """||f||_H = sqrt(c' K_G c)."""
        c = np.asarray(c, dtype=float)
        return float(np.sqrt(max(c @ self.gram @ c, 0.0)))

    def function_error(self, c: np.ndarray, gamma: float, c_ref: np.ndarray, gamma_ref: float) -> float:
        """||f - f*||_H / ||f*||_H + |gamma - gamma*| / max(1, |gamma*|): the fleet's yardstick."""
        ref_norm = self.rkhs_norm(c_ref)
        diff = self.rkhs_norm(np.asarray(c, dtype=float) - np.asarray(c_ref, dtype=float))
        return diff / max(ref_norm, 1e-12) + abs(float(gamma) - float(gamma_ref)) / max(
            1.0, abs(float(gamma_ref))
        )
