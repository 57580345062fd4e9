"""The LiDAR least-squares model (issue 15): a kernel fit that uses what each LiDAR return says.

A LiDAR pair -- an outside point (+1) `offset` before a return and an inside point (-1) `offset`
past it, consecutive in a robot's data (launcher/scenario.py `sample_robot_data`) -- also says that
the return itself, the pair's midpoint, is ON the outline. Each pair therefore becomes three rows:
(outside, +1), (midpoint, 0), (inside, -1). A point in no such pair (a free-space sample, the
last outside point of an odd count, a data file's loose rows) stays one row with its label as
target and adds no midpoint. In the grid basis (agents/kernel.py: f(p) = phi(p)' x + gamma,
|x|^2 = ||f||_H^2) the model is

    minimise  sum_rows (phi(p_i)' x + gamma - t_i)^2  +  lam |x|^2        (gamma free)

one linear system: the exact reference is its closed-form solve (`solve_central_lsq`). A robot's
share is its own rows plus lam / N |x|^2 (as the SVM splits 1/2 |x|^2), so the shares sum to the
fleet's objective; `LsqLocalStep` is the ADMM local step on that share, a linear solve factored once.

The model's answer is its output region (`output_region`), not {f < 0}: far from every grid node f
is only gamma, which says nothing, and an enclosed hollow no LiDAR ray from outside can reach is inside.

Pure: no I/O, no clock. The functions take a `GridBasis` and assume nothing about how its grid and
sigma were chosen (a fixed grid today; autogrid's may call them per grid).
"""

from __future__ import annotations

import math

import numpy as np
import scipy.linalg
from scipy import ndimage
from scipy.spatial import cKDTree

from agents.kernel import GridBasis
from agents.problem import CentralSolution

#: the ridge weight lam of the model (the lead's central emulation, issue 15)
DEFAULT_LSQ_LAMBDA = 0.1

#: target of a pair's midpoint row: the LiDAR return lies on the outline, f = 0 there
BOUNDARY_TARGET = 0.0

#: the output region's reach, in kernel widths: f says something only within this many widths of a
#: grid node (farther, every kernel term is below exp(-2) ~ 0.14 of its peak and f tends to gamma).
#: The lead's rule 2, frozen on development data (benchmarks/lsq_emulation.py ``MASK``)
OUTPUT_REACH = 2.0


def check_lsq_lambda(lam: float) -> None:
    """ValueError unless lam is a finite positive number: lam = 0 leaves x undetermined where no
    row sees it (a singular system), and nan / inf have no solve."""
    if not (isinstance(lam, (int, float)) and math.isfinite(lam) and lam > 0):
        raise ValueError(f"the least-squares ridge weight lam must be a finite positive number, got {lam!r}")


def model_words(lam: float) -> str:
    """result.json's ``model`` of a least-squares fleet (fixed grid or autogrid), in words."""
    return f"LiDAR least squares (pair: outside +1, return 0, inside -1), lam {lam:g}"


def output_region(values: np.ndarray, points: np.ndarray, shape: tuple[int, int], grid: np.ndarray,
                  sigma: float, widths: np.ndarray | None = None) -> np.ndarray:
    """The least-squares model's inside region on a raster: one flag per raster point.

        region = fill_holes({f < 0} AND {within OUTPUT_REACH widths of a grid node})

    ``values``: f at the raster ``points`` ((m, 2), row-major: x varies fastest, rows go up in y, as
    launcher/scenario.py make_grid orders them), ``shape`` = (rows in y, points in x). Why: far from
    every node f is only gamma, which may be slightly negative or positive and says nothing; and the
    unobserved interior of a large part can come out as a hollow that no LiDAR ray from outside can
    reach, so it is inside (scipy.ndimage.binary_fill_holes, its default structure: a hollow is a
    4-connected outside component that does not touch the raster's edge). A node's reach is
    OUTPUT_REACH times its own width (``widths``, one per node; None: sigma for every node)."""
    values = np.asarray(values, dtype=float).ravel()
    points = np.asarray(points, dtype=float).reshape(-1, 2)
    grid = np.asarray(grid, dtype=float).reshape(-1, 2)
    if len(values) != len(points) or len(points) != shape[0] * shape[1]:
        raise ValueError(f"output_region: {len(values)} values and {len(points)} points for a raster of shape {shape}")
    node_widths = np.full(len(grid), float(sigma)) if widths is None else np.asarray(widths, dtype=float)
    near = np.zeros(len(points), dtype=bool)
    for w in np.unique(node_widths):  # nodes of one width: the nearest one decides
        distance, _ = cKDTree(grid[node_widths == w]).query(points)
        near |= distance <= OUTPUT_REACH * w
    return ndimage.binary_fill_holes(((values < 0) & near).reshape(shape)).ravel()


def lidar_pairs(labels: np.ndarray) -> np.ndarray:
    """Start indices i of the LiDAR pairs in one robot's labels: rows (i, i + 1) labelled (+1, -1),
    read left to right, a row in at most one pair."""
    labels = np.asarray(labels)
    starts, i = [], 0
    while i + 1 < len(labels):
        if labels[i] == 1 and labels[i + 1] == -1:
            starts.append(i)
            i += 2
        else:
            i += 1
    return np.asarray(starts, dtype=np.intp)


def lsq_rows(points: np.ndarray, labels: np.ndarray, keep: np.ndarray | None = None
             ) -> tuple[np.ndarray, np.ndarray]:
    """The model's rows of one robot's data, in data order: (row points (n, 2), targets (n,)).

    A pair (outside, inside) gives outside +1, midpoint 0, inside -1; any other point one row,
    its label as target (no midpoint: nothing says where its boundary is). ``keep`` (one flag per
    pair of `lidar_pairs`, None: all) leaves the other pairs out -- a fold's training rows, whose
    held-out pairs are scored instead (agents/autogrid_sweep.py); points in no pair always stay."""
    points = np.asarray(points, dtype=float).reshape(-1, 2)
    labels = np.asarray(labels)
    starts = lidar_pairs(labels)
    in_pair = np.zeros(len(points), dtype=bool)
    in_pair[starts], in_pair[starts + 1] = True, True
    if keep is not None:
        starts = starts[np.asarray(keep, dtype=bool)]
    loose = np.flatnonzero(~in_pair)
    out, inside = points[starts], points[starts + 1]
    rows = np.vstack([out, 0.5 * (out + inside), inside, points[loose]])
    n = len(starts)
    targets = np.concatenate([np.ones(n), np.full(n, BOUNDARY_TARGET), -np.ones(n), labels[loose].astype(float)])
    # data order: a pair's three rows where the pair stands (keys 3s, 3s + 1, 3s + 2), a loose point i at 3i
    order = np.argsort(np.concatenate([3 * starts, 3 * starts + 1, 3 * starts + 2, 3 * loose]), kind="stable")
    return rows[order].reshape(-1, 2), targets[order]


def design(features: np.ndarray) -> np.ndarray:
    """A = [phi, 1]: the rows of the model's linear map v = (x, gamma) -> f at the row points."""
    features = np.asarray(features, dtype=float)
    return np.hstack([features, np.ones((len(features), 1))])


def objective_share(features: np.ndarray, targets: np.ndarray, v: np.ndarray, lam: float, n_robots: int) -> float:
    """One robot's share of the fleet's objective at v = (x, gamma): its rows' squared residuals
    plus lam / N |x|^2; the shares of the N robots sum to the central objective."""
    v = np.asarray(v, dtype=float)
    r = design(features) @ v - np.asarray(targets, dtype=float)
    return float(r @ r + lam / n_robots * (v[:-1] @ v[:-1]))


def normal_equations(features: np.ndarray, targets: np.ndarray, x_weight: float) -> tuple[np.ndarray, np.ndarray]:
    """(A'A + x_weight E, A't), E = diag(1, ..., 1, 0): the gradient of |A v - t|^2 + x_weight |x|^2
    is 2 (first) v - 2 (second); gamma carries no ridge."""
    A = design(features)
    H = A.T @ A
    H[np.arange(len(H) - 1), np.arange(len(H) - 1)] += x_weight
    return H, A.T @ np.asarray(targets, dtype=float)


def solve_central_lsq(basis: GridBasis, points: np.ndarray, labels: np.ndarray, lam: float = DEFAULT_LSQ_LAMBDA,
                      *, robot_of: np.ndarray | None = None) -> CentralSolution:
    """All data in one least-squares fit: the exact reference of the lsq fleet.

    ``points``/``labels`` are every robot's data; ``robot_of`` (one robot id per point) keeps the
    pairs inside each robot's own data as the fleet reads them (None: the data is one robot's, in
    order). ValueError when the data has no row (nothing to fit) or lam is not positive."""
    check_lsq_lambda(lam)
    points = np.asarray(points, dtype=float).reshape(-1, 2)
    labels = np.asarray(labels)
    if robot_of is None:
        rows, targets = lsq_rows(points, labels)
    else:
        robot_of = np.asarray(robot_of)
        parts = [lsq_rows(points[robot_of == r], labels[robot_of == r]) for r in dict.fromkeys(robot_of.tolist())]
        rows = np.vstack([p for p, _ in parts]) if parts else np.zeros((0, 2))
        targets = np.concatenate([t for _, t in parts]) if parts else np.zeros(0)
    if not len(rows):
        raise ValueError("the least-squares model has no rows to fit (no data)")
    H, b = normal_equations(basis.features(rows), targets, lam)
    v = scipy.linalg.solve(H, b, assume_a="pos")
    return CentralSolution(basis.c_from_x(v[:-1]), v[:-1], float(v[-1]), "solved", certified=True)


class LsqLocalStep:
    """The ADMM local step on one robot's share, in the interface of agents/problem.py `MarginQP`
    that `ConsensusADMM` drives (`solve_v`, `set_prox`):

        argmin_v  |A v - t|^2 + x_weight |x|^2 + q' v + 1/2 v' diag(prox) v
        <=>  (2 A'A + 2 x_weight E + diag(prox)) v = 2 A't - q

    The matrix changes only with the proximal weights (once per run, and when a neighbour is
    dropped), so it is factored there (LAPACK's Cholesky) and every round is two triangular solves.
    A local step is this robot's own (no other robot recomputes it), so LAPACK's bits, the same on one
    machine (one BLAS thread: agents/__init__.py), suffice: simulate and launch, and a robot restored
    from its checkpoint, take the same bits. (agents/admm.py's exactly rounded Cholesky, the hub's, cost
    3.1 ms a solve at M = 208 against ~0.03 ms: measured on letter_e, benchmarks/results/lsq.md.) A robot
    with no rows and no proximal weight on gamma (round 0's own solve) keeps gamma at 0."""

    #: (MarginQP's fields the hub core reads; the least-squares step has no margin multipliers)
    keep_multipliers = False
    multipliers = None

    def __init__(self, features: np.ndarray, targets: np.ndarray, *, x_weight: float,
                 prox_weight: float | np.ndarray) -> None:
        gram, rhs = normal_equations(features, targets, x_weight)
        self.dim = len(gram)
        self._gram2 = 2.0 * gram
        self._rhs2 = 2.0 * rhs
        self._factor: tuple[np.ndarray, bool] = (np.zeros((0, 0)), True)
        self.set_prox(prox_weight)

    def set_prox(self, prox: float | np.ndarray) -> None:
        """Change the proximal weights (0: the robot's own fit) and factor the step's matrix."""
        H = self._gram2 + np.diag(np.broadcast_to(np.asarray(prox, dtype=float), (self.dim,)))
        if not H[-1, -1] > 0:  # no row and no proximal weight on gamma: pin it at 0
            H[-1, -1] = 1.0
        self._factor = scipy.linalg.cho_factor(H, lower=True, check_finite=False)

    def solve_v(self, q: np.ndarray, guess: np.ndarray | None = None) -> np.ndarray:
        """The step's v for the linear cost q (``guess`` unused: the solve is exact)."""
        return scipy.linalg.cho_solve(self._factor, self._rhs2 - np.asarray(q, dtype=float), check_finite=False)
