"""The fleet chooses its own grid and kernel width: one robot's sans-IO state machine.

`AdaptiveGridCore` has the interface of `ConsensusADMM` (frames in with `receive`, frames out
with `outgoing` / `advance`, the same stop-flag protocol of `agents/rounds.py`) but needs no
grid, no sigma and no bounds from the launcher. Every robot runs the same phases, in the same
rounds, through the same frames (D = the `diameter` parameter, >= the graph diameter):

1. BOUNDS (D rounds): max-consensus on (-xmin, xmax, -ymin, ymax) of the robots' data (a min
   is the max of negatives). A max of floats is exact, so after D rounds every robot holds the
   same four numbers bit for bit, with no central node.
2. The shared scale, computed identically by every robot from those four numbers:
       diag  = |(xmax - xmin, ymax - ymin)|         (the data's bounding-box diagonal)
       sigma = diag / SIGMA_DIVISOR                  (default 8)
       box   = data box widened by sigma on each side
       h_0   = SPACING_RATIO * sigma                 (default 1.5: a deliberately coarse start)
   The level-L lattice has spacing h_0 / 2^L, centred on the box; it is nested (level L is a
   subset of level L+1). Every quantity is a length proportional to diag and nothing else has a
   unit, so multiplying all coordinates by s multiplies sigma, the box and every grid point by
   s and leaves every kernel value k(d, g) = exp(-|d - g|^2 / (2 sigma^2)) -- hence every QP,
   every iterate and the learned function f(s p) -- unchanged: the rule is scale-free.
   Unless sigma is given (or `validate_divisors` is empty, then sigma = diag / sigma_divisor),
   sigma is chosen by a held-out sweep first, for each candidate diag / d, d in
   `validate_divisors` (default 4, 6, 8, 12, 16), in order, and each fold k < validate_folds:
     VALIDATE (ADMM rounds, <= `validate_rounds`): every robot holds out its own units
       u % holdout_every == holdout_every - 1 - k (a unit = an inside point and its nearest
       outside point, `holdout_units`); the fleet solves the soft margin (C = soft_C,
       tol = `validate_tol`) on the candidate's coarse lattice from the remaining points;
     TALLY (D rounds): every robot counts its held-out errors (y f <= 0), held-out points,
       hinge loss and whether its learned inside region is NOT one solid piece (`is_solid` on
       a raster of the lattice box) into its own slots (one block of slots per quantity,
       slot = robot id) of a zero vector; a max-consensus gives every robot every slot bit for
       bit, and the sums are identical everywhere.
   The rule, the same everywhere (`choose_sigma`): among the candidates whose inside region is
   solid on every robot and fold, fewest held-out errors, ties -> the smaller sigma;
   `sigma_reason` says why. Then the run below uses all data. Each candidate is proportional
   to diag, errors are signs and the raster is the lattice box's, so the choice is scale-free.
3. VOTE (D rounds, hard margin only): each robot checks that its own data is separable on the
   grid (its local hard-margin QP); a max-consensus on "infeasible" tells every robot.
4. ADMM: `ConsensusADMM` runs as a sub-machine (its round counter offset by the phase start),
   warm-started on a refined grid at the exact previous function: c_new = [c_old; 0]. Its
   stop flags are the frames' flags, so every robot leaves the phase in the same round.
   Global infeasibility of the hard margin (every robot feasible alone, the union not) shows
   as ADMM not converging: the rule is "not converged within `hard_rounds` rounds" => the grid
   is declared hard-infeasible and the fleet solves the soft margin (penalty `soft_C`) on the
   same grid instead, to have a function to refine from.
5. FLOOD (D rounds): every robot adopts the vector of the lowest robot id it has heard of;
   after D rounds all robots hold robot min-id's (x, gamma) bit for bit.
6. REFINE (no communication): from f alone, every robot computes the same new grid: the nodes
   of the next lattice level not yet in the grid where |f| < `band` (the margin band around
   the zero level set), closest to the zero level set first, at most doubling the grid and
   within `max_points`. The new grid is a superset of the old one, so the warm start is exact.
   The fleet refines again while it helps: after a hard-margin solve, until the squared RKHS
   norm |x|^2 (which can only decrease on a superset grid) drops by less than `improve_tol`
   relative; after a soft-margin solve (hard infeasible), until the hard margin is feasible.
   If the budget of points or refinements runs out while the hard margin is infeasible, the
   soft-margin function is the answer and `result()` says so.

Frames have a fixed length per fleet, so every vector is padded to `max_points` + 2 entries:
x in the first M, zeros up to `max_points`, gamma at index -2 and one meta slot at index -1
(the vote, or the flooded vector's robot id); in TALLY the whole vector is the slots. No I/O, no clock.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import ndimage

from agents.admm import ADMMParams, ConsensusADMM
from agents.kernel import GridBasis
from agents.problem import InfeasibleError, MarginQP
from agents.rounds import RoundCore, from_bytes, to_bytes
from protocol.frames import StateUpdate

#: sigma = (diagonal of the data's bounding box) / SIGMA_DIVISOR
SIGMA_DIVISOR = 8.0
#: spacing of the coarsest lattice, in units of sigma
SPACING_RATIO = 1.5
#: stands for "no data" in the max-consensus on bounds (frames carry finite values only)
_NO_DATA = -1e300

BOUNDS, VOTE, ADMM, FLOOD, DONE = "bounds", "vote", "admm", "flood", "done"
#: the sigma sweep: a soft-margin ADMM on a training part per candidate, then a tally of held-out errors
VALIDATE, TALLY = "validate", "tally"
#: the tally's blocks of slots: held-out errors, held-out points, hinge loss, "inside region not solid"
TALLY_BLOCKS = 4


@dataclass(frozen=True)
class AutoGridParams:
    """Everything the robots must agree on (the same on every robot)."""

    diameter: int = 1
    max_points: int = 300  # budget M_max of grid points; frames carry max_points + 2 floats
    max_refinements: int = 4
    sigma: float | None = None  # None: the scale-free rule; a number: the paper's fixed width
    sigma_divisor: float = SIGMA_DIVISOR
    spacing_ratio: float = SPACING_RATIO
    band: float = 1.0  # refine where |f| < band
    improve_tol: float = 0.02  # stop refining when |x|^2 falls by less than this (relative)
    max_level: int = 4  # finest lattice: spacing h_0 / 2^max_level
    rho: float = 15.0
    relax: float = 1.95
    tol: float = 1e-3
    hard_rounds: int = 3000  # no convergence within this many rounds: hard margin infeasible
    soft_rounds: int = 3000
    soft_C: float = 1e3
    C: float | None = None  # a number: soft margin from the start (no hard attempt)
    max_total_rounds: int = 50_000
    # sigma by held-out validation (only when sigma is None): candidates diag / d for d in
    # validate_divisors (empty: the fixed rule diag / sigma_divisor); in fold k every robot holds
    # out its pairs u with u % holdout_every == holdout_every - 1 - k; each candidate and fold is
    # a soft-margin ADMM (C = soft_C) on its coarse lattice, stopped at validate_tol or
    # validate_rounds
    validate_divisors: tuple[float, ...] = (4.0, 6.0, 8.0, 12.0, 16.0)
    holdout_every: int = 5
    validate_folds: int = 2
    solid_raster: int = 64  # the solid-region check rasterizes the lattice box at this resolution
    validate_tol: float = 1e-2
    validate_rounds: int = 1000

    def __post_init__(self) -> None:
        if not 0 <= self.diameter <= 62:
            raise ValueError(f"diameter must be in [0, 62] (flag bits), got {self.diameter}")
        if self.max_points < 4:
            raise ValueError(f"max_points must be at least 4, got {self.max_points}")
        for name in ("sigma_divisor", "spacing_ratio", "band", "rho", "tol", "soft_C"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value!r}")
        for name in ("sigma", "C"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number or None, got {value!r}")
        if any(not (math.isfinite(d) and d > 0) for d in self.validate_divisors):
            raise ValueError(f"validate_divisors must be positive numbers, got {self.validate_divisors!r}")
        if self.holdout_every < 2 or self.validate_rounds < 1:
            raise ValueError("holdout_every must be >= 2 and validate_rounds >= 1")
        if not 1 <= self.validate_folds <= self.holdout_every:
            raise ValueError(f"validate_folds must be in [1, holdout_every], got {self.validate_folds}")
        if self.solid_raster < 8:
            raise ValueError(f"solid_raster must be at least 8, got {self.solid_raster}")
        if not 0 < self.relax < 2:
            raise ValueError(f"relax must be in (0, 2), got {self.relax}")

    @property
    def dim(self) -> int:
        """Length of every frame vector of this fleet."""
        return self.max_points + 2

    @property
    def validates(self) -> bool:
        """True when sigma is chosen by the held-out sweep."""
        return self.sigma is None and len(self.validate_divisors) > 0

    @property
    def tally_slots(self) -> int:
        """Robot ids must be below this: the tally vector has 4 blocks of one slot per id."""
        return self.dim // TALLY_BLOCKS

    @staticmethod
    def points_for_robot_ids(highest_id: int) -> int:
        """The smallest max_points whose sigma-sweep tally has a slot for robot `highest_id`."""
        return TALLY_BLOCKS * (highest_id + 1) - 2


# -- the shared, deterministic rules (pure functions of agreed numbers) ---------------------------


def scale_from_bounds(
    bounds: tuple[float, float, float, float], params: AutoGridParams
) -> tuple[float, str]:
    """sigma from the agreed data box, and the reason in words (for result.json)."""
    x0, x1, y0, y1 = bounds
    diag = math.hypot(x1 - x0, y1 - y0)
    if params.sigma is not None:
        return float(params.sigma), f"fixed sigma = {params.sigma:g} (given)"
    if not diag > 0:
        return 1.0, "all data at one point: no scale in the data, sigma = 1"
    sigma = diag / params.sigma_divisor
    why = (
        f"sigma = diag / {params.sigma_divisor:g} = {diag:.6g} / {params.sigma_divisor:g} = {sigma:.6g}, "
        "diag = diagonal of the data's bounding box agreed by max/min-consensus (scale-free: "
        "every length of the rule is proportional to diag)"
    )
    return sigma, why


def lattice_box(bounds: tuple[float, float, float, float], sigma: float) -> tuple[float, float, float, float]:
    """The region the lattice covers: the data box widened by sigma on each side."""
    x0, x1, y0, y1 = bounds
    return (x0 - sigma, x1 + sigma, y0 - sigma, y1 + sigma)


def lattice(
    box: tuple[float, float, float, float], h0: float, level: int, *, with_shape: bool = False
) -> np.ndarray | tuple[np.ndarray, tuple[int, int]]:
    """Nodes of the level-`level` lattice (spacing h0 / 2^level) centred on `box`, row-major.

    Level L+1 contains level L: its node 2i is node i of level L.
    """
    x0, x1, y0, y1 = box
    axes = []
    for lo, hi in ((x0, x1), (y0, y1)):
        n0 = max(1, int(math.ceil((hi - lo) / h0 - 1e-9))) + 1
        n = (n0 - 1) * 2**level + 1
        centre = 0.5 * (lo + hi)
        axes.append(centre + (np.arange(n) - (n - 1) / 2.0) * (h0 / 2**level))
    gx, gy = np.meshgrid(axes[0], axes[1])
    nodes = np.column_stack([gx.ravel(), gy.ravel()])
    return (nodes, gx.shape) if with_shape else nodes


def refine_grid(
    grid: np.ndarray,
    basis: GridBasis,
    c: np.ndarray,
    gamma: float,
    box: tuple[float, float, float, float],
    h0: float,
    level: int,
    params: AutoGridParams,
) -> tuple[np.ndarray, int]:
    """The refined grid from f alone: (old grid + chosen nodes, the lattice level used).

    Candidates are the nodes of the first level > `level` that are not already in the grid
    (within a quarter spacing) and lie near the zero level set: in the margin band |f| < band,
    or next to a lattice neighbour where f has the other sign (the outline crosses that cell
    edge, whatever the steepness of f). The closest to the zero level set (smallest |f|) come
    first, ties by lattice index; at most len(grid) of them, within the budget. Returns the grid
    unchanged when there is nothing to add.
    """
    room = min(params.max_points - len(grid), len(grid))
    if room <= 0:
        return grid, level
    for lv in range(level + 1, params.max_level + 1):
        nodes, shape = lattice(box, h0, lv, with_shape=True)
        near = _min_distance(nodes, grid) < 0.25 * h0 / 2**lv
        f = basis.decision(nodes, c, gamma)
        pick = np.flatnonzero(~near & ((np.abs(f) < params.band) | _crossing(f.reshape(shape)).ravel()))
        if len(pick) == 0:
            continue
        order = pick[np.lexsort((pick, np.abs(f[pick])))][:room]
        return np.vstack([grid, nodes[np.sort(order)]]), lv
    return grid, level


def choose_sigma(records: list[dict[str, Any]], diag: float, params: AutoGridParams) -> tuple[float, str]:
    """The sweep's rule, the same on every robot (`records` are the fleet-wide tallies).

    1. Keep the candidates whose learned inside region is one solid piece on every robot and in
       every fold (one connected component, no holes): the object is a solid seen from outside,
       and a too-narrow kernel betrays itself by holes and islands where there are no data.
       If no candidate is solid, keep them all.
    2. Among those, the fewest held-out errors; ties -> the smaller sigma (it follows the outline
       more closely; step 1 guards against the narrow widths that break the region up).
    Returns (sigma, reason in words).
    """
    solid = [r for r in records if r["solid"]]
    pool = solid or records
    best = min(pool, key=lambda r: (r["errors"], r["sigma"]))
    held = best["held_out"]
    ties = [r for r in pool if r["errors"] == best["errors"]]
    table = ", ".join(
        f"diag/{r['divisor']:g}: {r['errors']}" + ("" if r["solid"] else " (not solid)") for r in records
    )
    folds = min(params.validate_folds, params.holdout_every)
    why = (
        f"sigma = diag/{best['divisor']:g} = {best['sigma']:.6g}: "
        + (f"of the {len(solid)} candidates whose inside region is one solid piece (no holes, no islands), "
           if solid else "no candidate gave a solid inside region; of all candidates, ")
        + f"fewest held-out errors ({best['errors']}/{held})"
        + (f" (tied with {len(ties) - 1}, the smaller sigma wins)" if len(ties) > 1 else "")
        + f"; held-out errors {table}; {folds} fold(s), each robot holding out every "
        f"{params.holdout_every}th of its (inside point, nearest outside point) pairs; each candidate a "
        f"soft-margin ADMM (C = {params.soft_C:g}) on its coarse lattice, errors summed exactly by "
        f"max-consensus over one slot per robot id; diag = {diag:.6g} = diagonal of the data's "
        "bounding box (scale-free: every candidate is proportional to diag)"
    )
    return float(best["sigma"]), why


def holdout_units(points: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Unit index of every point for the held-out folds (-1: never held out).

    A unit is an inside point (in data order) with its nearest outside point of the same robot:
    a LiDAR return's two sides, so a held-out unit removes a whole piece of the outline rather
    than leaving its twin 0.6 away in the training set. A robot without inside points uses its
    points one by one. Ties in distance go to the first outside point.
    """
    n = len(labels)
    units = np.full(n, -1, dtype=int)
    inside = np.flatnonzero(labels < 0)
    outside = np.flatnonzero(labels > 0)
    if len(inside) == 0 or len(outside) == 0:
        units[:] = np.arange(n)
        return units
    for u, i in enumerate(inside):
        units[i] = u
        j = outside[int(np.argmin(np.sum((points[outside] - points[i]) ** 2, axis=1)))]
        if units[j] < 0:
            units[j] = u
    return units


def is_solid(inside: np.ndarray) -> bool:
    """True when a raster's inside cells form one 4-connected piece with no enclosed hole."""
    if not inside.any():
        return False
    _, pieces = ndimage.label(inside)
    outside, n_out = ndimage.label(~inside)
    rim = np.concatenate([outside[0], outside[-1], outside[:, 0], outside[:, -1]])
    touching = set(np.unique(rim).tolist()) - {0}
    return pieces == 1 and n_out == len(touching)


def _crossing(f: np.ndarray) -> np.ndarray:
    """Nodes with a 4-neighbour of the other sign (the zero level set passes next to them)."""
    s = f > 0
    out = np.zeros_like(s)
    out[:, 1:] |= s[:, 1:] != s[:, :-1]
    out[:, :-1] |= s[:, 1:] != s[:, :-1]
    out[1:, :] |= s[1:, :] != s[:-1, :]
    out[:-1, :] |= s[1:, :] != s[:-1, :]
    return out


def _min_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    d2 = np.sum((a[:, None, :] - b[None, :, :]) ** 2, axis=2)
    return np.sqrt(d2.min(axis=1))


class _WarmADMM(ConsensusADMM):
    """ConsensusADMM whose round 0 is a given (x, gamma) instead of the robot's own solution.

    Every robot starts from the same vector, so round 0 sets z = start and lambda = 0: an exact
    warm start at the previous grid's function.
    """

    def __init__(self, *args: Any, start: np.ndarray | None = None, **kwargs: Any) -> None:
        self._start = None if start is None else np.asarray(start, dtype=float).copy()
        super().__init__(*args, **kwargs)

    def _local_step(self) -> np.ndarray:
        if self._start is not None and self.neighbours:  # a lone robot solves it all at round 0
            return self._start.copy()
        return super()._local_step()


class AdaptiveGridCore(RoundCore):
    """One robot: agree on bounds, choose sigma and grid, solve, agree on f, refine, repeat."""

    algorithm = "autogrid"

    def __init__(
        self,
        robot_id: int,
        neighbours: tuple[int, ...],
        points: np.ndarray,
        labels: np.ndarray,
        *,
        n_robots: int,
        params: AutoGridParams,
        start_grid: np.ndarray | None = None,
        neighbour_degrees: dict[int, int] | None = None,
        keep_trace: bool = False,
    ) -> None:
        super().__init__(
            robot_id,
            neighbours,
            params.dim,
            diameter=params.diameter,
            round_cap=params.max_total_rounds,
            keep_trace=keep_trace,
        )
        points = np.asarray(points, dtype=float).reshape(-1, 2)
        labels = np.asarray(labels)
        if len(labels) != len(points):
            raise ValueError(f"{len(points)} points but {len(labels)} labels")
        if start_grid is not None:
            start_grid = np.asarray(start_grid, dtype=float).reshape(-1, 2)
            if not 1 <= len(start_grid) <= params.max_points:
                raise ValueError(f"start grid has {len(start_grid)} points, budget is {params.max_points}")
        if params.validates and not 0 <= robot_id < params.tally_slots:
            raise ValueError(
                f"robot id {robot_id}: the sigma sweep tallies one slot per id, ids must be in "
                f"[0, {params.tally_slots}) (raise max_points)"
            )
        self.params = params
        self._points = points
        self._labels = labels
        self._n_robots = n_robots
        self._degrees = dict(neighbour_degrees or {})
        self._start_grid = start_grid
        # agreed state (identical on every robot once reached)
        self.phase = BOUNDS
        self.bounds: tuple[float, float, float, float] | None = None
        self.sigma: float | None = None
        self.sigma_reason = ""
        self.grid: np.ndarray | None = None
        self.grid_history: list[dict[str, Any]] = []
        self.margin = "hard" if params.C is None else "soft"
        self.message = ""
        self._box: tuple[float, float, float, float] | None = None
        self._h0 = 0.0
        self._level = 0
        self._mode = self.margin  # margin of the current ADMM phase
        self._left = 0  # rounds left in a fixed-length phase
        self._phase_start = 0
        self._warm: np.ndarray | None = None
        self._sub: _WarmADMM | None = None
        self._sub_converged = False
        self._best_norm2: float | None = None
        self._refinements = 0
        self._admm_rounds = 0
        self._final: np.ndarray | None = None  # (x, gamma) agreed by the fleet
        self._final_flags = 0
        # the sigma sweep: which pairs are held out, the candidate being solved, the tallies
        self._units = holdout_units(points, labels)
        self._fold = 0
        self._held = self._held_mask(0)
        self._fold_tallies: list[dict[str, Any]] = []  # the current candidate's folds so far
        self._cand = 0
        self._diag = 0.0
        self.sigma_validation: list[dict[str, Any]] = []
        self._enter_bounds()
        self._settle()
        self._record()

    # -- vectors ------------------------------------------------------------------------------
    def _pad(self, x: np.ndarray, gamma: float, meta: float = 0.0) -> np.ndarray:
        v = np.zeros(self.dim)
        v[: len(x)] = x
        v[-2] = gamma
        v[-1] = meta
        return v

    def _unpad(self, v: np.ndarray) -> np.ndarray:
        """(x, gamma) on the current grid from a padded frame vector."""
        m = len(self.grid)
        return np.append(v[:m], v[-2])

    # -- phases -------------------------------------------------------------------------------
    def _enter_bounds(self) -> None:
        v = np.zeros(self.dim)
        if len(self._points):
            lo, hi = self._points.min(axis=0), self._points.max(axis=0)
            v[:4] = (-lo[0], hi[0], -lo[1], hi[1])
        else:
            v[:4] = _NO_DATA
        self.phase, self._left, self._phase_start = BOUNDS, self.params.diameter, self.round
        self._values, self._flags = v, 0

    def _finish_bounds(self) -> None:
        nx0, nx1, ny0, ny1 = (float(t) for t in self._values[:4])
        self.bounds = (-nx0, nx1, -ny0, ny1)
        x0, x1, y0, y1 = self.bounds
        self._diag = math.hypot(x1 - x0, y1 - y0)
        if self.params.validates and self._diag > 0:
            self._cand = 0
            self._enter_validate()
            return
        self.sigma, self.sigma_reason = scale_from_bounds(self.bounds, self.params)
        self._start_final()

    def _start_final(self) -> None:
        """The run on all data at the agreed sigma: first grid, then vote/ADMM/flood/refine."""
        self._box = lattice_box(self.bounds, self.sigma)
        self._h0 = self.params.spacing_ratio * self.sigma
        if self._start_grid is not None:
            grid = self._start_grid.copy()
        else:
            grid = lattice(self._box, self._h0, 0)
            if len(grid) > self.params.max_points:  # keep the budget: coarsen (still scale-free)
                while len(grid) > self.params.max_points:
                    self._h0 *= 2.0
                    grid = lattice(self._box, self._h0, 0)
        self._set_grid(grid, warm=None)

    # -- the sigma sweep ----------------------------------------------------------------------
    def _coarse_lattice(self, sigma: float) -> tuple[tuple[float, float, float, float], float, np.ndarray]:
        box = lattice_box(self.bounds, sigma)
        h0 = self.params.spacing_ratio * sigma
        grid = lattice(box, h0, 0)
        while len(grid) > self.params.max_points:  # keep the budget: coarsen (still scale-free)
            h0 *= 2.0
            grid = lattice(box, h0, 0)
        return box, h0, grid

    def _held_mask(self, fold: int) -> np.ndarray:
        """The points this robot holds out in `fold` (whole units, see `holdout_units`)."""
        k = self.params.holdout_every
        return (self._units >= 0) & (self._units % k == k - 1 - fold)

    def _validation_setup(self) -> None:
        """sigma, grid, basis and training features of candidate self._cand, fold self._fold."""
        self.sigma = self._diag / self.params.validate_divisors[self._cand]
        self._held = self._held_mask(self._fold)
        box, _, grid = self._coarse_lattice(self.sigma)
        self._box = box
        self.grid = grid
        self._basis = GridBasis(grid, self.sigma)
        train = self._points[~self._held]
        self._features = self._basis.features(train) if len(train) else np.zeros((0, len(grid)))
        self._warm = None

    def _enter_validate(self) -> None:
        self._validation_setup()
        self._enter_admm("soft", validation=True)

    def _finish_validate(self) -> None:
        sub = self._sub
        rounds = self.round - self._phase_start
        v = sub.values
        c = self._basis.c_from_x(v[:-1])
        held_pts, held_y = self._points[self._held], self._labels[self._held]
        if len(held_y):
            yf = held_y * self._basis.decision(held_pts, c, float(v[-1]))
            errors, hinge = float(np.sum(yf <= 0)), float(np.sum(np.maximum(0.0, 1.0 - yf)))
        else:
            errors, hinge = 0.0, 0.0
        # the learned inside region on a raster of the lattice box: one solid piece?
        r = self.params.solid_raster
        x0, x1, y0, y1 = self._box
        gx, gy = np.meshgrid(np.linspace(x0, x1, r), np.linspace(y0, y1, r))
        f = self._basis.decision(np.column_stack([gx.ravel(), gy.ravel()]), c, float(v[-1]))
        not_solid = 0.0 if is_solid((f < 0).reshape(r, r)) else 1.0
        self._sub_converged = sub.converged
        self._admm_rounds = rounds
        self._sub = None
        b = self.params.tally_slots
        t = np.zeros(self.dim)
        t[self.robot_id] = errors
        t[b + self.robot_id] = float(len(held_y))
        t[2 * b + self.robot_id] = hinge
        t[3 * b + self.robot_id] = not_solid
        self.phase, self._left, self._phase_start = TALLY, self.params.diameter, self.round
        self._values, self._flags = t, 0

    def _finish_tally(self) -> None:
        # every robot holds the same vector bit for bit (a max of floats rounds nothing), so
        # these sums -- in the same order everywhere -- are identical on every robot
        b = self.params.tally_slots
        v = self._values
        d = self.params.validate_divisors[self._cand]
        self._fold_tallies.append(
            {
                "errors": int(round(float(np.sum(v[:b])))),
                "held_out": int(round(float(np.sum(v[b : 2 * b])))),
                "hinge": float(np.sum(v[2 * b : 3 * b])),
                "solid": not np.any(v[3 * b : 4 * b] > 0),
                "rounds": self._admm_rounds,
                "converged": self._sub_converged,
            }
        )
        self._fold += 1
        if self._fold < self.params.validate_folds:
            self._enter_validate()
            return
        folds, self._fold_tallies, self._fold = self._fold_tallies, [], 0
        self.sigma_validation.append(
            {
                "divisor": float(d),
                "sigma": self.sigma,
                "grid_points": len(self.grid),
                "errors": sum(t["errors"] for t in folds),
                "held_out": sum(t["held_out"] for t in folds),
                "hinge": math.fsum(t["hinge"] for t in folds),
                "solid": all(t["solid"] for t in folds),
                "folds": len(folds),
                "rounds": sum(t["rounds"] for t in folds),
                "converged": all(t["converged"] for t in folds),
            }
        )
        self._cand += 1
        if self._cand < len(self.params.validate_divisors):
            self._enter_validate()
            return
        self.sigma, self.sigma_reason = choose_sigma(self.sigma_validation, self._diag, self.params)
        self._mode = self.margin
        self._start_final()

    def _set_grid(self, grid: np.ndarray, warm: np.ndarray | None) -> None:
        self.grid = grid
        self._basis = GridBasis(grid, self.sigma)
        self._features = self._basis.features(self._points) if len(self._points) else np.zeros((0, len(grid)))
        self._warm = warm
        if self.margin == "hard":
            self._enter_vote()
        else:
            self._enter_admm("soft")

    def _enter_vote(self) -> None:
        infeasible = 0.0
        if len(self._points):
            qp = MarginQP(self._features, self._labels, x_weight=1.0 / self._n_robots, prox_weight=0.0, C=None)
            try:
                qp.solve(np.zeros(qp.dim))
            except InfeasibleError:
                infeasible = 1.0
        self.phase, self._left, self._phase_start = VOTE, self.params.diameter, self.round
        self._values, self._flags = self._pad(np.zeros(0), 0.0, infeasible), 0

    def _finish_vote(self) -> None:
        if self._values[-1] > 0:
            self._note(status="hard-infeasible", detected_by="vote (a robot's own data not separable)", rounds=self.params.diameter)
            self._enter_admm("soft")
        else:
            self._enter_admm("hard")

    def _enter_admm(self, mode: str, *, validation: bool = False) -> None:
        p = self.params
        C = (p.C if p.C is not None else p.soft_C) if mode == "soft" else None
        labels = self._labels
        if validation:
            C, labels = p.soft_C, self._labels[~self._held]
        sub_params = ADMMParams(
            rho=p.rho,
            relax=p.relax,
            tol=p.validate_tol if validation else p.tol,
            max_rounds=p.validate_rounds if validation else (p.hard_rounds if mode == "hard" else p.soft_rounds),
            diameter=p.diameter,
        )
        self._mode = mode
        self._sub = _WarmADMM(
            self.robot_id,
            self.neighbours,
            self._features,
            labels,
            n_robots=self._n_robots,
            params=sub_params,
            C=C,
            neighbour_degrees={j: self._degrees.get(j, 1) for j in self.neighbours},
            keep_trace=False,
            start=self._warm,
        )
        self.phase, self._phase_start = (VALIDATE if validation else ADMM), self.round
        v = self._sub.values
        self._values, self._flags = self._pad(v[:-1], v[-1]), 0

    def _finish_admm(self) -> None:
        sub = self._sub
        rounds = self.round - self._phase_start
        if not sub.converged and self._mode == "hard":
            # the rule: a hard margin that does not converge within hard_rounds is infeasible
            self._note(status="hard-infeasible", detected_by=f"ADMM not converged in {rounds} rounds", rounds=rounds)
            self._enter_admm("soft")
            return
        self._sub_converged = sub.converged
        self._admm_rounds = rounds
        v = sub.values
        self._sub = None
        self.phase, self._left, self._phase_start = FLOOD, self.params.diameter, self.round
        self._values, self._flags = self._pad(v[:-1], v[-1], float(self.robot_id)), 0

    def _finish_flood(self) -> None:
        agreed = self._unpad(self._values)
        x, gamma = agreed[:-1], float(agreed[-1])
        norm2 = float(x @ x)
        self._note(
            status=f"{self._mode}-margin solved" if self._sub_converged else f"{self._mode}-margin round cap",
            rounds=self._admm_rounds,
            norm2=norm2,
            agreed_from=int(self._values[-1]),
        )
        self._final = agreed
        helps = True
        if self._mode == "hard":
            self.margin = "hard"
            if self._best_norm2 is not None and norm2 > (1.0 - self.params.improve_tol) * self._best_norm2:
                helps = False
            self._best_norm2 = norm2 if self._best_norm2 is None else min(norm2, self._best_norm2)
        new_grid, level = self.grid, self._level
        if helps and self._refinements < self.params.max_refinements:
            c = self._basis.c_from_x(x)
            new_grid, level = refine_grid(self.grid, self._basis, c, gamma, self._box, self._h0, self._level, self.params)
        if len(new_grid) == len(self.grid):
            self._done()
            return
        c_old = self._basis.c_from_x(x)
        self._level = level
        self._refinements += 1
        new_basis = GridBasis(new_grid, self.sigma)
        warm = np.append(new_basis.x_from_c(np.append(c_old, np.zeros(len(new_grid) - len(self.grid)))), gamma)
        if self._mode == "soft" and self.params.C is None:
            self.margin = "hard"  # the refined grid may separate the data: try the hard margin again
        self._set_grid(new_grid, warm)

    def _done(self) -> None:
        if self._mode == "soft" and self.params.C is None:
            self.margin = "soft"
            self.message = (
                "the hard margin stayed infeasible within the budget of "
                f"{self.params.max_points} grid points / {self.params.max_refinements} refinements: "
                f"fell back to a soft margin (C = {self.params.soft_C:g})"
            )
        self.phase = DONE
        x, gamma = self._final[:-1], self._final[-1]
        self._values = self._pad(x, gamma, float(self.robot_id))
        self._flags = 0
        self.finished = True
        self.residual = 0.0

    def _note(self, **fields: Any) -> None:
        self.grid_history.append(
            {"size": len(self.grid), "level": self._level, "margin": self._mode, "grid": self.grid.tolist(), **fields}
        )

    def _settle(self) -> None:
        """Leave every phase that is already complete (length-0 phases when D = 0, a lone robot)."""
        while not self.finished:
            if self.phase in (BOUNDS, VOTE, FLOOD, TALLY) and self._left == 0:
                {
                    BOUNDS: self._finish_bounds,
                    VOTE: self._finish_vote,
                    FLOOD: self._finish_flood,
                    TALLY: self._finish_tally,
                }[self.phase]()
            elif self.phase == ADMM and self._sub.finished:
                self._finish_admm()
            elif self.phase == VALIDATE and self._sub.finished:
                self._finish_validate()
            else:
                return

    # -- the round ----------------------------------------------------------------------------
    def advance(self):  # noqa: ANN201 -- a StateUpdate, as RoundCore.advance
        theirs, their_flags = self._take_round()
        mine = self._values
        flags = 0
        if self.phase in (BOUNDS, VOTE, TALLY):
            new = np.max(np.vstack([mine, *theirs.values()]), axis=0)
            self._left -= 1
        elif self.phase == FLOOD:
            new = min([mine, *theirs.values()], key=lambda v: v[-1])
            self._left -= 1
        else:  # ADMM: hand the neighbours' exact round values to the sub-machine
            sub = self._sub
            for j, v in theirs.items():
                sub.receive(StateUpdate(j, sub.round, self._unpad(v), int(their_flags.get(j, 0)), None))
            sub.advance()
            self.residual = sub.residual
            out = sub.values
            new = self._pad(out[:-1], out[-1])
            flags = sub.outgoing().flags
        self._prev_values, self._prev_flags = mine, self._flags
        self._values, self._flags = new, flags
        self.round += 1
        self._inbox.forget_before(self.round)
        self._settle()
        if not self.finished and self.round >= self._round_cap:
            self.finished = True
            self.message = f"stopped at the round cap {self._round_cap} in phase {self.phase}"
        self._record()
        return self.outgoing()

    def drop_neighbour(self, j: int) -> None:
        super().drop_neighbour(j)
        if self._sub is not None:
            self._sub.drop_neighbour(j)

    def _forget_edge(self, j: int) -> None:
        pass  # the ADMM edge lives in the sub-machine (dropped there)

    # -- what the fleet learned ---------------------------------------------------------------
    @property
    def converged(self) -> bool:
        return self.phase == DONE

    def function(self) -> tuple[np.ndarray, np.ndarray, float]:
        """(grid, c, gamma) of the agreed function (after the run) or of the current iterate."""
        if self.phase == DONE:
            v = self._final
        elif self.grid is not None and self.phase in (ADMM, FLOOD):
            v = self._unpad(self._values)
        else:
            raise RuntimeError("no function yet: the fleet has not chosen a grid")
        return self.grid.copy(), self._basis.c_from_x(v[:-1]), float(v[-1])

    def decision(self, points: np.ndarray) -> np.ndarray:
        grid, c, gamma = self.function()
        return self._basis.decision(points, c, gamma)

    def status(self) -> dict[str, Any]:
        m = None if self.grid is None else len(self.grid)
        return {**super().status(), "phase": self.phase, "grid_points": m, "margin": self.margin}

    def result(self) -> dict[str, Any]:
        out = {
            "id": self.robot_id,
            "algorithm": self.algorithm,
            "rounds": self.round,
            "converged": self.converged,
            "residual": self.residual,
            "neighbours": list(self.neighbours),
            "dropped": list(self.dropped),
            "phase": self.phase,
            "bounds": None if self.bounds is None else list(self.bounds),
            "sigma": self.sigma,
            "sigma_reason": self.sigma_reason,
            "sigma_validation": [dict(r) for r in self.sigma_validation],
            "margin": self.margin,
            "message": self.message,
            "grid_history": [{k: v for k, v in h.items()} for h in self.grid_history],
        }
        if self.phase == DONE:
            grid, c, gamma = self.function()
            out.update(grid=grid.tolist(), x=self._final[:-1].tolist(), c=c.tolist(), gamma=gamma)
        return out

    # -- checkpoint ---------------------------------------------------------------------------
    def _save_state(self) -> dict[str, Any]:
        sub = None if self._sub is None else self._sub.checkpoint()
        return {
            "phase": self.phase,
            "left": self._left,
            "phase_start": self._phase_start,
            "bounds": None if self.bounds is None else list(self.bounds),
            "h0": self._h0,
            "sigma": self.sigma,
            "sigma_reason": self.sigma_reason,
            "diag": self._diag,
            "cand": self._cand,
            "fold": self._fold,
            "fold_tallies": [dict(t) for t in self._fold_tallies],
            "sigma_validation": [dict(r) for r in self.sigma_validation],
            "level": self._level,
            "grid": to_bytes(None if self.grid is None else self.grid.ravel()),
            "margin": self.margin,
            "mode": self._mode,
            "message": self.message,
            "warm": to_bytes(self._warm),
            "sub": sub,
            "sub_converged": self._sub_converged,
            "admm_rounds": self._admm_rounds,
            "refinements": self._refinements,
            "best_norm2": self._best_norm2,
            "final": to_bytes(self._final),
            "history": [
                {**{k: v for k, v in h.items() if k != "grid"}, "grid": to_bytes(np.ravel(h["grid"]))}
                for h in self.grid_history
            ],
        }

    def _load_state(self, state: dict[str, Any]) -> None:
        self.bounds = None if state["bounds"] is None else tuple(float(b) for b in state["bounds"])
        self.sigma = None if state["sigma"] is None else float(state["sigma"])
        self.sigma_reason = state["sigma_reason"]
        self._diag = float(state["diag"])
        self._cand = int(state["cand"])
        self._fold = int(state["fold"])
        self._fold_tallies = [dict(t) for t in state["fold_tallies"]]
        self.sigma_validation = [dict(r) for r in state["sigma_validation"]]
        validating = state["phase"] in (VALIDATE, TALLY)
        if self.bounds is not None and not validating and self.sigma is not None:
            self._box = lattice_box(self.bounds, self.sigma)
        self._h0 = float(state["h0"])
        self._level = int(state["level"])
        self.margin = state["margin"]
        self._mode = state["mode"]
        self.message = state["message"]
        self._left = int(state["left"])
        self._phase_start = int(state["phase_start"])
        self._sub_converged = bool(state["sub_converged"])
        self._admm_rounds = int(state["admm_rounds"])
        self._refinements = int(state["refinements"])
        self._best_norm2 = state["best_norm2"]
        self._final = from_bytes(state["final"])
        self.grid_history = [
            {**{k: v for k, v in h.items() if k != "grid"}, "grid": from_bytes(h["grid"]).reshape(-1, 2).tolist()}
            for h in state["history"]
        ]
        grid = from_bytes(state["grid"])
        self._sub = None
        if validating:
            self._validation_setup()
        elif grid is not None:
            self.grid = grid.reshape(-1, 2)
            self._basis = GridBasis(self.grid, self.sigma)
            self._features = self._basis.features(self._points) if len(self._points) else np.zeros((0, len(self.grid)))
        self._warm = from_bytes(state["warm"])
        self.phase = state["phase"]
        if state["sub"] is not None:
            phase = self.phase
            self._enter_admm(self._mode, validation=phase == VALIDATE)  # rebuild, then resume exactly
            self.phase = phase
            self._sub.restore(state["sub"])
            self._phase_start = int(state["phase_start"])
        if self.phase == DONE:
            self.finished = True
        # RoundCore.restore set values and flags before this call; _enter_admm overwrote them
        return None

    def restore(self, state: dict[str, Any]) -> None:
        super().restore(state)
        self._values = from_bytes(state["values"])
        self._flags = int(state["flags"])
        self.finished = bool(state["finished"])
        self.trace = {}
        self._record()

