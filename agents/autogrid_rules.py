"""Autogrid's parameters and its shared, deterministic rules (pure functions of agreed numbers).

Every function here is computed identically by every robot from numbers the fleet agreed on bit
for bit (the data box, sigma, the agreed function), so every robot derives the same sigma,
lattice and refined grid without sending them. See agents/autogrid.py for the phases.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from agents.admm import FRAME_BUDGET
from agents.kernel import GridBasis
from agents.lsq_model import DEFAULT_LSQ_LAMBDA, check_lsq_lambda
from agents.params import params_from
from protocol.frames import MAX_DIM

#: sigma = (diagonal of the data's bounding box) / SIGMA_DIVISOR
SIGMA_DIVISOR = 8.0
#: spacing of the coarsest lattice, in units of sigma
SPACING_RATIO = 1.5
#: the finest lattice spacing, in units of sigma: below ~0.6 sigma K_G of a full lattice loses
#: numerical rank at agents.kernel.RCOND (measured: 0.6 sigma, 400 points, rank 399), and a
#: truncated K_G changes the problem the reference solves
MIN_SPACING = 0.7
#: the sweep tally packs (errors, held-out points, not-solid) in one exact integer per slot
PACK = 2.0**20
#: slots per (robot, candidate) in the tally: the packed integer and the hinge loss
TALLY_BLOCKS = 2


#: spacing of the level-0 lattice, in units of sigma, for the least-squares model (model "lsq"): the rule
#: frozen in its central emulation (benchmarks/lsq_emulation.py SPACING)
LSQ_SPACING_RATIO = 1.0
#: the least-squares model's ADMM penalty (agents/lsq_admm.py LSQParams.rho: its local curvature's scale)
LSQ_RHO = 1.0
#: rule 2 of the least-squares model (benchmarks/lsq_emulation.py CANDIDATES_NEAR, NEAR): the candidates
#: sigma = diag / k, each on its level-0 lattice's nodes within LSQ_NEAR sigma of some robot's data point
#: (narrow widths fit the budget once the lattice follows the data)
LSQ_DIVISORS = (4.0, 6.0, 8.0, 12.0, 16.0, 24.0, 32.0)
LSQ_NEAR = 1.5
#: what autogrid fits: the soft/hard-margin SVM (refined grids) or the LiDAR least-squares model
AUTOGRID_MODELS = ("svm", "lsq")

#: the largest graph diameter autogrid runs: its stop flags ride as bits of one float (53-bit mantissa)
AUTOGRID_MAX_DIAMETER = 52


@dataclass(frozen=True)
class AutoGridParams:
    """Everything the robots must agree on (the same on every robot)."""

    diameter: int = 1
    max_points: int = 300  # budget M_max of grid points
    max_refinements: int = 4
    sigma: float | None = None  # None: the scale-free rule; a number: the paper's fixed width
    sigma_divisor: float = SIGMA_DIVISOR
    spacing_ratio: float = SPACING_RATIO
    min_spacing: float = MIN_SPACING  # no lattice finer than min_spacing * sigma (K_G full rank)
    near_data: float = 1.0  # refine only within near_data * sigma of some robot's data
    band: float = 1.0  # refine where |f| < band
    improve_tol: float = 0.02  # stop refining when |x|^2 falls by less than this (relative)
    min_growth: float = 0.25  # after a hard-margin solve, refine only to add >= this share of the grid
    max_level: int = 4  # finest lattice: spacing h_0 / 2^max_level (and >= min_spacing * sigma)
    rho: float = 15.0
    relax: float = 1.95
    tol: float = 1e-3
    hard_rounds: int = 3000  # no convergence within this many rounds: treated as infeasible (noted hard-not-converged)
    # an ill-conditioned hard margin is given up early (issues 15 and 10): with a warm start x0 (a function the
    # fleet agreed on), the hard ADMM stops and the soft margin (C = soft_C) is solved as soon as some robot's
    # iterate has |x|^2 > `ill_conditioned_norm2`, the squared norm no hard solution whose multipliers are all
    # <= ill_multiplier x soft_C can have (docs/autogrid.md, "Hard-margin infeasibility"). 0: off
    ill_multiplier: float = 10.0
    soft_rounds: int = 3000
    soft_C: float = 1e3
    C: float | None = None  # a number: soft margin from the start (no hard attempt)
    max_total_rounds: int = 50_000
    warm_duals: bool = True  # carry the edges' z and lambda onto a refined grid
    # sigma by held-out validation (only when sigma is None): candidates diag / d for d in
    # validate_divisors (empty: the fixed rule diag / sigma_divisor); in fold k every robot holds
    # out its pairs u with u % holdout_every == holdout_every - 1 - k; every candidate and fold is
    # a soft-margin ADMM (C = soft_C) on its coarse lattice, all solved in the same rounds
    # (stacked frames), each stopped at validate_tol or validate_rounds
    validate_divisors: tuple[float, ...] = (4.0, 6.0, 8.0, 12.0, 16.0)
    holdout_every: int = 5
    validate_folds: int = 2
    solid_raster: int = 64  # the solid-region check rasterizes the lattice box at this resolution
    validate_tol: float = 1e-2
    validate_rounds: int = 300  # a capped candidate is judged on its iterate (rounds = the slowest task)
    # a complete graph (set by the fleet file): the ADMM sub-machines run the hub form, whose
    # frames carry w beside v (agents/admm.py), so every ADMM slot has room for both
    hub_frames: bool = False
    # with hub_frames, a soft answer solve runs the exact end-game (agents/soft_endgame.py) where its
    # payload fits the frame (grids up to ~(dim - 2 max_points) / 4 points); False: main's soft solves
    soft_polish: bool = True
    # ... and so does a hard answer solve (the same end-game with B empty: C = inf); False: main's hard solves
    hard_endgame: bool = True
    early_drop: bool = True  # end the sweep once a perfect candidate decides it (autogrid_sweep.py)
    # which candidate wins a tie of held-out errors: "smaller" sigma (the default: it follows the
    # outline more closely) or "larger" (issue 15: with narrow refined kernels, narrow_ratio > 1,
    # the wide width only has to fill the interior, so the smoothest width the data allow)
    sigma_ties: str = "smaller"
    # the solid check rejects a candidate whose inside region has islands or holes (False, the
    # default) or islands only (True: an enclosed outside cell in the unobserved interior passes)
    holes_allowed: bool = False
    # a model beyond one width (issue 15): the level-0 lattice's kernels have width sigma, the
    # points refinement adds near the boundary sigma / narrow_ratio (1: one width everywhere, the
    # default: 3 helps the 11 benchmark shapes at 200-240 points but costs the 60-point default
    # run 0.06 IoU, see benchmarks/results/autogrid.md)
    narrow_ratio: float = 1.0
    # the two widths only where the data can carry them (issue 15, step 6): with narrow_ratio > 1,
    # the fleet keeps one width when its sweep held out fewer than this many points per fold on
    # average (a count the tally already agrees on bit for bit; 0: always two widths). 3 x 20
    # points hold out 8-12 per fold, 5 x 40 hold out 23-37: the narrow kernels need the latter
    narrow_min_held: int = 0
    # the sweep's folds where the data are few (issue 15, step 6): when the fleet holds fewer than
    # sparse_units held-out units in all (one inside point with its nearest outside point each;
    # counted in BOUNDS, one slot per robot id), the sweep runs min(validate_folds, sparse_folds)
    # folds (0: always validate_folds). 3 x 20 points have 30 units, 5 x 40 have 100: on the former
    # 2 folds choose what 4 choose (central emulation) at half the sweep's cost
    sparse_units: int = 0
    sparse_folds: int = 2
    # one width or two by the held-out tally (issue 15, step 7): when the run would use two widths
    # (narrow_ratio > 1 after narrow_min_held), the seed is refined twice -- refined points at sigma
    # (one width) and at sigma / narrow_ratio (two) -- and every fold's training data is solved on
    # both grids in one stacked pass (WIDTHS, the sweep's machinery); the two widths are kept only
    # when they make fewer held-out errors in all (ties -> one width)
    narrow_by_holdout: bool = False
    # the model (issue 15): "svm" (the margin, refined grids, everything above) or "lsq" (the LiDAR
    # least-squares model, agents/lsq_model.py): sigma swept over lsq_divisors on near-data level-0 lattices
    # at LSQ_SPACING_RATIO sigma, 5 folds of whole pairs scored by their held-out squared residual, then one
    # fit on the chosen lattice -- rule 2 of benchmarks/lsq_emulation.py (docs/autogrid.md). The default
    # (issue 15): on the default run IoU 0.949 in 159 rounds against the SVM's 0.893 in 424
    # (benchmarks/results/autogrid.md)
    model: str = "lsq"
    lsq_lambda: float = DEFAULT_LSQ_LAMBDA  # the least-squares model's ridge weight (agents/lsq_model.py)
    lsq_rho: float = LSQ_RHO  # its ADMM penalty (rho is the SVM's)
    # rule 2 (docs/autogrid.md): the lsq model's sigma candidates diag / k (validate_divisors are the SVM's),
    # each on the level-0 lattice's nodes within lsq_near sigma of some robot's data (agreed in MARKS); a
    # candidate whose kept nodes exceed max_points is not tried
    lsq_divisors: tuple[float, ...] = LSQ_DIVISORS
    lsq_near: float = LSQ_NEAR

    def __post_init__(self) -> None:
        if not 0 <= self.diameter <= AUTOGRID_MAX_DIAMETER:
            raise ValueError(f"diameter must be in [0, {AUTOGRID_MAX_DIAMETER}] (flag bits carried as exact floats), "
                             f"got {self.diameter}")
        if self.max_points < 4:
            raise ValueError(f"max_points must be at least 4, got {self.max_points}")
        if not (math.isfinite(self.narrow_ratio) and self.narrow_ratio >= 1):
            raise ValueError(f"narrow_ratio must be a number >= 1, got {self.narrow_ratio!r}")
        for name in ("sigma_divisor", "spacing_ratio", "min_spacing", "near_data", "band", "rho", "tol", "soft_C", "lsq_rho",
                     "lsq_near"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value!r}")
        for name in ("sigma", "C"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number or None, got {value!r}")
        for name in ("validate_divisors", "lsq_divisors"):
            if any(not (math.isfinite(d) and d > 0) for d in getattr(self, name)):
                raise ValueError(f"{name} must be positive numbers, got {getattr(self, name)!r}")
        if self.holdout_every < 2 or self.validate_rounds < 1:
            raise ValueError("holdout_every must be >= 2 and validate_rounds >= 1")
        if not 1 <= self.validate_folds <= self.holdout_every:
            raise ValueError(f"validate_folds must be in [1, holdout_every], got {self.validate_folds}")
        if self.sigma_ties not in ("smaller", "larger"):
            raise ValueError(f"sigma_ties must be 'smaller' or 'larger', got {self.sigma_ties!r}")
        if self.sparse_units < 0 or self.sparse_folds < 1:
            raise ValueError(f"sparse_units must be >= 0 and sparse_folds >= 1, "
                             f"got {self.sparse_units}, {self.sparse_folds}")
        if not (math.isfinite(self.ill_multiplier) and (self.ill_multiplier == 0 or self.ill_multiplier >= 1)):
            raise ValueError(f"ill_multiplier must be 0 (off) or a number >= 1, got {self.ill_multiplier!r}")
        if self.narrow_min_held < 0:
            raise ValueError(f"narrow_min_held must be >= 0, got {self.narrow_min_held}")
        if self.solid_raster < 8:
            raise ValueError(f"solid_raster must be at least 8, got {self.solid_raster}")
        if not 0 < self.relax < 2:
            raise ValueError(f"relax must be in (0, 2), got {self.relax}")
        if self.model not in AUTOGRID_MODELS:
            raise ValueError(f"model must be one of {', '.join(AUTOGRID_MODELS)}, got {self.model!r}")
        try:
            check_lsq_lambda(self.lsq_lambda)
        except ValueError as exc:
            raise ValueError(f"lsq_lambda: {exc}") from None
        if self.model == "lsq":
            if self.C is not None:
                raise ValueError("C: the lsq model has no margin (its weight is lsq_lambda)")
            if self.narrow_ratio != 1.0 or self.narrow_by_holdout:
                raise ValueError("narrow_ratio / narrow_by_holdout: the lsq model fits on one level-0 lattice, "
                                 "one width (no refinement)")
        if self.dim > MAX_DIM:
            raise ValueError(f"max_points {self.max_points}: frames of {self.dim} numbers exceed MAX_DIM={MAX_DIM}")

    @classmethod
    def from_params(cls, params: Mapping[str, Any]) -> AutoGridParams:
        """From a fleet file's ``params`` (sigma and C are the fleet file's own fields, added by
        FleetSpec): exactly this class's fields; any other key is an error naming it."""
        return params_from(cls, params, "autogrid")

    @property
    def dim(self) -> int:
        """Length of every frame vector of this fleet: a grid's (x, gamma) with 3 slots, or the
        sweep's stacked blocks, whichever is longer (at most 16 x (max_points + 1); twice that
        with `hub_frames`: w at [max_points : 2 max_points + 1])."""
        solve = 2 * self.max_points + 4 if self.hub_frames else self.max_points + 3
        if self.lsq:
            return max(solve, self.lsq_sweep_frame)
        return max(solve, sum(self.sweep_blocks()), sum(self.width_blocks()))

    @property
    def lsq_sweep_frame(self) -> int:
        """The lsq sweep's frame (rule 2): room for every (candidate, fold) task's block at its largest
        possible lattice, capped at issue 10's FRAME_BUDGET (max_points + 1) floats (4816 for the default
        budget); the tasks share it round by round (agents/autogrid_sweep.py). 0 when sigma is given."""
        if not self.validates:
            return 0
        need = self.sweep_folds * sum(self._fold_blocks())
        return min(need, FRAME_BUDGET * (self.max_points + 1))

    @property
    def sweep_divisors(self) -> tuple[float, ...]:
        """The sigma candidates the sweep tries: the SVM's validate_divisors, or the lsq model's lsq_divisors."""
        return self.lsq_divisors if self.lsq else self.validate_divisors

    @property
    def lsq(self) -> bool:
        """True when the fleet fits the LiDAR least-squares model (no margin, no refinement)."""
        return self.model == "lsq"

    @property
    def coarse_spacing(self) -> float:
        """The level-0 lattice's spacing in units of sigma: spacing_ratio, or the lsq model's own."""
        return LSQ_SPACING_RATIO if self.lsq else self.spacing_ratio

    @property
    def sweep_folds(self) -> int:
        """Folds the sweep runs: validate_folds, or for the lsq model all holdout_every of them (its rule)."""
        return self.holdout_every if self.lsq else self.validate_folds

    def sweep_slot(self, divisor: float) -> int:
        """Grid points of candidate diag/divisor's coarse lattice, at most (any box shape)."""
        return min(self.max_points, max_lattice_nodes(divisor, self.coarse_spacing))

    def _fold_blocks(self) -> list[int]:
        """Frame length of one fold's tasks, one per candidate: x, gamma, flags, verdict (and with
        `hub_frames` the hub's w: its x and gamma)."""
        extra = 1 if self.hub_frames else 0
        return [self.sweep_slot(d) + 3 + extra * (self.sweep_slot(d) + 1) for d in self.sweep_divisors]

    @property
    def sweep_groups(self) -> int:
        """Groups of folds the sweep's frame is sized for (issue 10's frame rule): one, unless every
        task's block together would exceed FRAME_BUDGET (max_points + 1) floats, then the fewest that
        fit; the frame holds the first group's blocks and the tasks share it round by round
        (agents/autogrid_sweep.py; the lsq model's frame is `lsq_sweep_frame`, always shared). Each task
        is the same sub-machine either way: only the rounds change."""
        folds, per_fold = self.sweep_folds, sum(self._fold_blocks())
        budget = FRAME_BUDGET * (self.max_points + 1)
        return next((g for g in range(1, folds + 1) if math.ceil(folds / g) * per_fold <= budget), folds)

    def sweep_group(self, fold: int) -> int:
        """The group of folds `fold` is advanced in (consecutive folds, the first groups the fullest)."""
        return fold // math.ceil(self.sweep_folds / self.sweep_groups)

    def sweep_blocks(self) -> list[int]:
        """Frame length of each task of the sweep's first (largest) group of folds, candidate-major
        then fold: x, gamma, flags, verdict (and with `hub_frames` the hub's w: its x and gamma)."""
        if not self.validates:
            return []
        first = sum(1 for fold in range(self.sweep_folds) if self.sweep_group(fold) == 0)
        return [block for block in self._fold_blocks() for _ in range(first)]

    def width_blocks(self) -> list[int]:
        """Frame length of each task of the width test (one width, then two; each fold): a grid
        of up to max_points, gamma, flags, verdict (and the hub's w)."""
        if not (self.validates and self.narrow_by_holdout and self.narrow_ratio > 1):
            return []
        slot = self.max_points
        return [slot + 3 + (slot + 1 if self.hub_frames else 0)] * (2 * self.validate_folds)

    @property
    def tally_slots(self) -> int:
        """Robot ids must be below this: the tally has TALLY_BLOCKS slots per (id, candidate) (the
        width test's two models use the same slots when there are fewer than two candidates)."""
        models = max(1, len(self.sweep_divisors), 2 if self.width_blocks() else 1)
        return self.dim // (TALLY_BLOCKS * models)

    @property
    def planned_rounds(self) -> int:
        """The rounds a run is planned to take (a progress bar's total, not a bound): the phases
        of fixed length, the sweep at its cap and one solve on the refined grid budgeted like a
        sweep task."""
        d = self.diameter
        solve = self.validate_rounds + 3 * d + 1  # vote, ADMM, flood
        sweep = d + self.validate_rounds + 2 * d if self.validates else d  # bounds, sweep, tally, seed (lsq: marks)
        return min(self.max_total_rounds, sweep + solve)

    @property
    def validates(self) -> bool:
        """True when sigma is chosen by the held-out sweep."""
        return self.sigma is None and len(self.sweep_divisors) > 0


    @staticmethod
    def points_for_robot_ids(highest_id: int) -> int:
        """The smallest max_points whose (default) sigma-sweep tally has a slot for `highest_id`."""
        m = 4
        while AutoGridParams(max_points=m).tally_slots <= highest_id:
            m += 1 if m < 1000 else m // 10
        return m


def max_lattice_nodes(divisor: float, spacing_ratio: float) -> int:
    """An upper bound of the level-0 lattice size for sigma = diag / divisor, over every box shape.

    The box is the data box (width diag cos t, height diag sin t) widened by sigma on each side;
    `lattice` puts ceil(side / h0) + 1 nodes on a side. Sampled finely in t, plus one node per
    side for the samples in between.
    """
    t = np.linspace(0.0, 0.5 * math.pi, 721)
    sides = [(divisor * np.cos(t) + 2.0) / spacing_ratio, (divisor * np.sin(t) + 2.0) / spacing_ratio]
    nx, ny = (np.ceil(s - 1e-9) + 2 for s in sides)
    return int(np.max(nx * ny))


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


def hinge_sum(features: np.ndarray, labels: np.ndarray, v: np.ndarray) -> float:
    """sum_i max(0, 1 - y_i f(p_i)) of the function v = (x, gamma) on one robot's data (features on
    the current grid): the slack that v leaves, what the soft margin pays C for."""
    if not len(labels):
        return 0.0
    margins = np.asarray(labels, dtype=float) * (features @ v[:-1] + v[-1])
    return math.fsum(np.maximum(0.0, 1.0 - margins).tolist())


def ill_conditioned_norm2(warm: np.ndarray, hinge_max: float, n_robots: int, params: AutoGridParams) -> float:
    """The squared norm |x|^2 above which a hard margin is given up for the soft one (0: no test).

    The bound. Hard margin: min |x|^2 / 2 s.t. y_i (a_i' x + gamma) >= 1, optimum x_h with multipliers
    alpha_h >= 0; strong duality gives |x_h|^2 = sum alpha_h. Soft margin at C: optimum P*_C, dual
    D_C(alpha) = sum alpha - |sum alpha_i y_i a_i|^2 / 2 over 0 <= alpha <= C, sum alpha_i y_i = 0. If every
    alpha_h <= K C, then alpha_h / K is dual feasible at C, so
        P*_C >= D_C(alpha_h / K) = |x_h|^2 / K - |x_h|^2 / (2 K^2),   i.e.   |x_h|^2 <= 2 K^2 / (2K - 1) P*_C.
    Any function bounds P*_C from above; the fleet holds one, the warm start v0 = (x0, gamma0):
        P*_C <= |x0|^2 / 2 + C sum_i max(0, 1 - y_i f0(p_i)) <= |x0|^2 / 2 + C N max_l hinge_l
    (N robots, hinge_l = robot l's own hinge sum, agreed by max-consensus). So a hard solution above the
    returned value has a multiplier > K C = ill_multiplier x soft_C: a model that leans on single points
    far harder than the soft margin the fleet falls back to. The fleet tests its ADMM iterates (they converge
    to x_h) against it, not x_h itself: a test of the running estimate, with K's factor as the margin against
    an iterate's overshoot (held-out 4: the castellated nut's and the pliers' iterates reach 350 and 3000 x
    P_C(x0), exact |x_h|^2 1.9e7 and 3.3e7; on the 33 benchmark runs where it does not fire, no robot's
    iterate passes 0.064 x this bound).
    Scale-free: |x|^2, P_C and hinges are numbers of the unitless f.
    """
    K = params.ill_multiplier
    if K <= 0:
        return 0.0
    x0 = warm[:-1]
    with np.errstate(over="ignore", invalid="ignore"):  # (an overflow is handled below, not printed)
        upper = 0.5 * float(x0 @ x0) + params.soft_C * n_robots * hinge_max
        bound = 2.0 * K * K / (2.0 * K - 1.0) * upper
    return bound if math.isfinite(bound) else 0.0  # (frames carry finite numbers: an overflow means no test)


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


def coarse_lattice(
    bounds: tuple[float, float, float, float], sigma: float, spacing_ratio: float, budget: int
) -> tuple[tuple[float, float, float, float], float, np.ndarray]:
    """(box, h0, level-0 lattice) for sigma, coarsened (h0 doubled) until it fits `budget`."""
    box = lattice_box(bounds, sigma)
    h0 = spacing_ratio * sigma
    grid = lattice(box, h0, 0)
    while len(grid) > budget:  # keep the budget: coarsen (still scale-free)
        h0 *= 2.0
        grid = lattice(box, h0, 0)
    return box, h0, grid


def finest_level(h0: float, sigma: float, params: AutoGridParams) -> int:
    """The finest lattice level whose spacing h0 / 2^L stays >= min_spacing * sigma."""
    level = 0
    while level < params.max_level and h0 / 2 ** (level + 1) >= params.min_spacing * sigma * (1 - 1e-12):
        level += 1
    return level


def grid_widths(
    grid: np.ndarray, box: tuple[float, float, float, float], h0: float, sigma: float, params: AutoGridParams,
    wide_points: np.ndarray | None = None,
) -> np.ndarray | None:
    """The kernel width of every grid point: sigma on the level-0 lattice (and on `wide_points`,
    a given start grid), sigma / narrow_ratio on the points refinement added near the boundary.
    None when every point has width sigma (one width: the paper's model). A pure function of the
    grid and agreed numbers, so every robot and the central reference derive the same widths."""
    if params.narrow_ratio == 1.0:
        return None
    wide = lattice(box, h0, 0)
    if wide_points is not None and len(wide_points):
        wide = np.vstack([wide, wide_points])
    on = min_distance(grid, wide) < 0.25 * h0 / 2**params.max_level
    if on.all():
        return None
    return np.where(on, sigma, sigma / params.narrow_ratio)


def near_data_marks(points: np.ndarray, nodes: np.ndarray, radius: float) -> np.ndarray:
    """1.0 at the nodes with one of `points` within `radius`, else 0.0 (a robot's own marks)."""
    if len(points) == 0 or len(nodes) == 0:
        return np.zeros(len(nodes))
    return (min_distance(nodes, points) <= radius).astype(float)


def refine_grid(
    grid: np.ndarray,
    basis: GridBasis,
    c: np.ndarray,
    gamma: float,
    box: tuple[float, float, float, float],
    h0: float,
    level: int,
    params: AutoGridParams,
    allowed: np.ndarray | None = None,
    min_new: int = 1,
) -> tuple[np.ndarray, int]:
    """The refined grid from f alone: (old grid + chosen nodes, the lattice level used).

    Candidates are the nodes of the lattice levels from max(level, 1) to the finest the kernel
    can use (`finest_level`) that are not already in the grid (within a quarter spacing), lie
    in a level-0 cell the fleet marked as near data (`allowed`, one flag per level-0 node: the
    cell of the nearest node) and near the zero level set: in the margin band |f| < band, or
    next to a lattice neighbour where f has the other sign. The closest to the zero level set
    (smallest |f|) come first, ties by lattice index, within the budget of points (all of
    them at once: the finest level the kernel can use is usually level 1). A refined grid whose K_G would lose numerical rank is refused. Returns the grid
    unchanged when there is nothing to add.
    """
    room = params.max_points - len(grid)
    if room <= 0:
        return grid, level
    coarse, coarse_shape = lattice(box, h0, 0, with_shape=True)
    narrow = basis.sigma / params.narrow_ratio  # the width of the points added here
    old_widths = np.full(len(grid), basis.sigma) if basis.widths is None else basis.widths
    for lv in range(max(level, 1), finest_level(h0, narrow, params) + 1):
        nodes, shape = lattice(box, h0, lv, with_shape=True)
        near = min_distance(nodes, grid) < 0.25 * h0 / 2**lv
        if allowed is not None and len(allowed) == len(coarse):
            near |= ~allowed_by_index(allowed.reshape(coarse_shape), lv).ravel()
        f = basis.decision(nodes, c, gamma)
        pick = np.flatnonzero(~near & ((np.abs(f) < params.band) | _crossing(f.reshape(shape)).ravel()))
        if len(pick) < min_new:
            continue
        order = pick[np.lexsort((pick, np.abs(f[pick])))][:room]
        new = np.vstack([grid, nodes[np.sort(order)]])
        widths = np.concatenate([old_widths, np.full(len(order), narrow)])
        if GridBasis(new, basis.sigma, widths=widths).rank < len(new):
            return grid, level
        return new, lv
    return grid, level


def allowed_by_index(allowed: np.ndarray, level: int) -> np.ndarray:
    """Per node of lattice level `level`: is one of its nearest level-0 nodes marked?

    Computed on lattice indices, not float distances: a level-1 node halfway between two level-0
    nodes is at the same distance from both, and a float argmin broke that tie by round-off, so
    data in other units (x1000) could pick the other neighbour and another grid (issue 19). A
    node whose nearest level-0 nodes tie is allowed when any of them is marked.
    """
    step = 2**level
    out = np.zeros(((allowed.shape[0] - 1) * step + 1, (allowed.shape[1] - 1) * step + 1), dtype=bool)
    for axis_lo in (0, 1):
        rows = _nearest_coarse(out.shape[0], step, axis_lo)
        for other_lo in (0, 1):
            cols = _nearest_coarse(out.shape[1], step, other_lo)
            out |= allowed[np.ix_(rows, cols)]
    return out


def _nearest_coarse(n: int, step: int, low: int) -> np.ndarray:
    """Index of a nearest level-0 node for each of n fine indices: the lower one on a tie when
    `low` is 1, the upper one when 0 (the two calls cover both ends of every tie)."""
    i = np.arange(n)
    base, rest = np.divmod(i, step)
    half = step / 2.0
    up = (rest > half) | ((rest == half) & (low == 0))
    return np.minimum(base + up, (n - 1) // step)


def choose_sigma(records: list[dict[str, Any]], diag: float, params: AutoGridParams) -> tuple[float, str]:
    """The sweep's rule, the same on every robot (`records` are the fleet-wide tallies).

    1. Keep the candidates whose learned inside region is one solid piece on every robot and in
       every fold (one connected component, no holes): the object is a solid seen from outside,
       and a too-narrow kernel betrays itself by holes and islands where there are no data.
       If no candidate is solid, keep them all.
    2. Among those, the fewest held-out errors; ties -> the smaller sigma (it follows the outline
       more closely; step 1 guards against the narrow widths that break the region up), or with
       ``params.sigma_ties == "larger"`` the larger one (`tie_sign`).
    Returns (sigma, reason in words).
    """
    solid = [r for r in records if r["solid"]]
    pool = solid or records
    sign = tie_sign(params)
    best = min(pool, key=lambda r: (r["errors"], sign * r["sigma"]))
    held = best["held_out"]
    ties = [r for r in pool if r["errors"] == best["errors"]]
    table = ", ".join(
        f"diag/{r['divisor']:g}: {r['errors']}" + ("" if r["solid"] else " (not solid)") for r in records
    )
    folds = min(params.validate_folds, params.holdout_every)
    why = (
        f"sigma = diag/{best['divisor']:g} = {best['sigma']:.6g}: "
        + (f"of the {len(solid)} candidates whose inside region is one solid piece "
           f"({'no islands, holes allowed' if params.holes_allowed else 'no holes, no islands'}), "
           if solid else "no candidate gave a solid inside region; of all candidates, ")
        + f"fewest held-out errors ({best['errors']}/{held})"
        + (f" (tied with {len(ties) - 1}, the {params.sigma_ties} sigma wins)" if len(ties) > 1 else "")
        + f"; held-out errors {table}; {folds} fold(s), each robot holding out every "
        f"{params.holdout_every}th of its (inside point, nearest outside point) pairs; every candidate and "
        f"fold a soft-margin ADMM (C = {params.soft_C:g}) on its coarse lattice, all solved in the same "
        f"rounds, errors summed exactly by max-consensus over one slot per robot id; diag = {diag:.6g} = "
        "diagonal of the data's bounding box (scale-free: every candidate is proportional to diag)"
    )
    return float(best["sigma"]), why


def choose_lsq_sigma(records: list[dict[str, Any]], diag: float, params: AutoGridParams) -> tuple[float, str]:
    """The lsq model's rule 2 (benchmarks/lsq_emulation.py `choice_near`), the same on every robot from the agreed
    marks and tally: among the candidates tried (their near-data lattice fits the budget), the smallest mean
    held-out squared residual per pair; ties -> the larger sigma. No solid check (the model's f is a fit of the
    returns, not a margin: its region is what it is). Returns (sigma, reason)."""
    best = min((r for r in records if r["tried"]), key=lambda r: (r["score"], -r["sigma"]))
    table = ", ".join(
        f"diag/{r['divisor']:g}: {r['grid_points']} nodes, " + (f"{r['score']:.6g}" if r["tried"] else "not tried")
        for r in records)
    fallback = "; no near-data lattice fits: " if best["grid"] != "near data" else "; "
    why = (
        f"sigma = diag/{best['divisor']:g} = {best['sigma']:.6g}: the smallest mean held-out squared residual per "
        f"LiDAR pair among the candidates whose grid fits {params.max_points} points ({table}){fallback}grids: "
        f"{best['grid']} (level-0 lattice at {params.coarse_spacing:g} sigma, the nodes within {params.lsq_near:g} "
        f"sigma of some robot's data, agreed by max-consensus); {params.sweep_folds} folds of whole pairs (a robot's "
        f"k-th pair in fold (k + id) mod {params.sweep_folds}), every candidate and fold the least-squares fit "
        f"(lam = {params.lsq_lambda:g}) of the other folds' rows, sharing a frame of {params.dim} floats round by "
        f"round, residuals summed by max-consensus over one slot per robot id; diag = {diag:.6g} = diagonal of the "
        "data's bounding box"
    )
    return float(best["sigma"]), why


def lsq_lattices(bounds: tuple[float, float, float, float], diag: float, params: AutoGridParams) -> list[np.ndarray]:
    """Every lsq candidate's full level-0 lattice (rule 2's nodes before the near-data marks keep some)."""
    out = []
    for d in params.lsq_divisors:
        sigma = diag / d
        out.append(lattice(lattice_box(bounds, sigma), params.coarse_spacing * sigma, 0))
    return out


def lsq_near_marks(points: np.ndarray, lattices: list[np.ndarray], diag: float, params: AutoGridParams) -> np.ndarray:
    """One robot's near-data marks on every candidate's lattice, concatenated in candidate order: 1.0 at the
    nodes within lsq_near sigma of one of its points (the emulation's `<=`); a max-consensus gives the fleet's."""
    return np.concatenate([near_data_marks(points, nodes, params.lsq_near * diag / d)
                           for nodes, d in zip(lattices, params.lsq_divisors)])


def folds_for_data(params: AutoGridParams, units: int) -> tuple[AutoGridParams, str]:
    """The sweep's parameters for a fleet holding `units` held-out units in all (agreed in
    BOUNDS, the same on every robot): min(validate_folds, sparse_folds) folds below
    `sparse_units`, else `params` unchanged. Frames keep the given params' length (the fewer
    folds' blocks are a prefix of it). Returns (params, a note for sigma_reason)."""
    folds = min(params.validate_folds, params.sparse_folds)
    if params.sparse_units <= 0 or units >= params.sparse_units or folds == params.validate_folds:
        return params, ""
    return dataclasses.replace(params, validate_folds=folds), (
        f"; {folds} folds instead of {params.validate_folds}: {units} held-out units in all < {params.sparse_units}")


def widths_for_data(params: AutoGridParams, records: list[dict[str, Any]]) -> tuple[AutoGridParams, str]:
    """The parameters of the run after the sweep: one width (narrow_ratio 1) when the fleet's
    held-out points per fold (from the agreed tally, so the same on every robot) are fewer than
    `narrow_min_held` -- narrow refined kernels on sparse data leave gaps the few points cannot
    close (measured: 3 x 20 points, r = 3 loses 0.03-0.12 IoU on star and bracket) -- else
    `params` unchanged. Returns (params, a note for sigma_reason; empty when nothing changed)."""
    if params.narrow_ratio == 1.0 or params.narrow_min_held <= 0 or not records:
        return params, ""
    per_fold = records[0]["held_out"] / max(1, records[0]["folds"])
    if per_fold >= params.narrow_min_held:
        return params, (f"; two widths (refined points sigma / {params.narrow_ratio:g}): {per_fold:g} held-out "
                        f"points per fold >= {params.narrow_min_held}")
    return dataclasses.replace(params, narrow_ratio=1.0), (
        f"; one width: {per_fold:g} held-out points per fold < {params.narrow_min_held}, too few for "
        f"narrow refined kernels (sigma / {params.narrow_ratio:g})")


def choose_widths(params: AutoGridParams, records: list[dict[str, Any]]) -> tuple[AutoGridParams, str]:
    """The width test's rule (`narrow_by_holdout`), the same on every robot from the agreed tally:
    `records` are the one-width model's then the two-width model's (each every fold's training data
    solved on the seed refined at that width, errors on the held-out points). The two widths only
    when they make fewer held-out errors; a tie keeps one width, the model of the sweep that chose
    sigma (measured: the two widths lose 0.028 IoU to one width at the same sigma on letter_f and
    slotted_mm). Returns (params, a note for sigma_reason)."""
    one, two = records
    counts = f"held-out errors one width {one['errors']}/{one['held_out']}, two widths {two['errors']}/{two['held_out']}"
    if two["errors"] < one["errors"]:
        return params, f"; width test: two widths (refined points sigma / {params.narrow_ratio:g}), {counts}"
    return dataclasses.replace(params, narrow_ratio=1.0), f"; width test: one width, {counts} (ties -> one width)"


def tie_sign(params: AutoGridParams) -> float:
    """+1 when a tie of held-out errors goes to the smaller sigma, -1 when to the larger: the
    order in which `choose_sigma` ranks tied candidates (and early drop drops the losers)."""
    return 1.0 if params.sigma_ties == "smaller" else -1.0


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


def is_solid(inside: np.ndarray, holes_allowed: bool = False) -> bool:
    """True when a raster's inside cells form one 4-connected piece with no enclosed hole (with
    `holes_allowed`: one piece, enclosed outside cells allowed)."""
    if not inside.any():
        return False
    from scipy import ndimage  # here, not at the top: ~0.5 s of every robot process's start-up

    _, pieces = ndimage.label(inside)
    if holes_allowed:
        return pieces == 1
    outside, n_out = ndimage.label(~inside)
    rim = np.concatenate([outside[0], outside[-1], outside[:, 0], outside[:, -1]])
    touching = set(np.unique(rim).tolist()) - {0}
    return pieces == 1 and n_out == len(touching)


def solid_on_raster(basis: GridBasis, c: np.ndarray, gamma: float, box: tuple[float, float, float, float], r: int,
                    holes_allowed: bool = False) -> bool:
    """`is_solid` of the learned inside region {f < 0} on an r x r raster of `box`."""
    x0, x1, y0, y1 = box
    gx, gy = np.meshgrid(np.linspace(x0, x1, r), np.linspace(y0, y1, r))
    f = basis.decision(np.column_stack([gx.ravel(), gy.ravel()]), c, gamma)
    return is_solid((f < 0).reshape(r, r), holes_allowed)


def _crossing(f: np.ndarray) -> np.ndarray:
    """Nodes with a 4-neighbour of the other sign (the zero level set passes next to them)."""
    s = f > 0
    out = np.zeros_like(s)
    out[:, 1:] |= s[:, 1:] != s[:, :-1]
    out[:, :-1] |= s[:, 1:] != s[:, :-1]
    out[1:, :] |= s[1:, :] != s[:-1, :]
    out[:-1, :] |= s[1:, :] != s[:-1, :]
    return out


def _sq_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.sum((a[:, None, :] - b[None, :, :]) ** 2, axis=2)


def min_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance from every row of `a` to the nearest row of `b`."""
    return np.sqrt(_sq_distances(a, b).min(axis=1))
