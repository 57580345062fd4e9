"""Decentralized consensus ADMM as one robot's sans-IO state machine.

Each robot l keeps its own copy v_l = (x_l, gamma_l) of the shared function and, for every
neighbour j, an edge variable z_lj (both ends hold the same value) and a dual lambda_lj. With
over-relaxation alpha, one round reads (k -> k+1, given every neighbour's v_j^k):

    h_l = alpha v_l^k + (1 - alpha) z_lj,   h_j = alpha v_j^k + (1 - alpha) z_lj
    z_lj <- (h_l + h_j) / 2                  lambda_lj <- lambda_lj + rho (h_l - z_lj)
    v_l^{k+1} = argmin  f_l(v) + sum_j lambda_lj' v + rho/2 |v - z_lj|^2   (a small QP, piqp)

where f_l(v) = |x|^2 / (2N) (+ C sum of l's slacks) subject to l's margin constraints, so that
sum_l f_l is exactly the centralized objective. lambda_lj = -lambda_jl holds at every round, which
is why the fleet converges to the centralized solution -- and why a robot must use the *exact*
v_j^k of every neighbour: a stale substitute breaks that invariant and biases the answer.

Stopping: a robot estimates its distance to the fixed point from its residual r (relative
change of its own values and disagreement with its neighbours) and the contraction seen over the
last rounds, error ~ r / (1 - rate); tol is a bound on that estimate, in the units of the function
error. Slowly contracting fleets (long rings, many robots) thus run longer instead of stopping
early on a small per-round change. The fleet-wide agreement to stop, the frames and the inbox
are the shared round protocol of `agents/rounds.py`.

Complete graphs (the paper's setting) run a faster form instead: every robot hears every
robot's v_l each round, so each runs the fleet's global-consensus (hub) ADMM -- z the mean, one
scaled dual u_l per robot -- as an identical copy, and extrapolates its fixed-point map with
type-II Anderson acceleration (memory `anderson`, safeguarded). The arithmetic that mixes robots is
exactly rounded, so the copies stay bit-for-bit equal on any machine; sum_l u_l = 0 is kept, so
the fixed point is still the centralized solution. The map is built from shared data -- each robot
sends w_l = h_l + u_l from its own copy beside v_l -- so copies that came to differ (survivors
dropping a dead robot in different rounds) still share one map and its exact fixed point; they
take plain steps until they agree again. `anderson = 0` keeps the edge form everywhere. On hard
margins the hub's stop is guarded by a proven bound on the error (agents/certificate.py, `certify`):
the rule proposes, the bound must agree (where the fleet file names `certify`: a complete fleet silent on it
runs the exact end-game, agents/soft_endgame.py, by default; agents/spec.py `endgame_default`).

No I/O, no clock: frames in (`receive`), frames out (`outgoing`, `advance`).
"""

from __future__ import annotations

import hashlib
import math
import operator
import threading
from collections import OrderedDict
from itertools import islice
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from agents import certificate as cert_math
from agents.certificate import Certificate, fleet_certificate
from agents.messages import StateUpdate
from agents.params import check_counts, check_diameter, check_positive, params_from
from agents.problem import MarginQP
from agents.rounds import RobotShare, RoundCore, check_iterate, from_bytes, relative_gap, relative_gaps, to_bytes

if TYPE_CHECKING:
    from agents.soft_endgame import SoftEndgame


@dataclass(frozen=True)
class ADMMParams:
    """Penalty, over-relaxation, acceleration and stopping rule (the same on every robot)."""

    rho: float = 15.0
    gamma_penalty: float = 3.0  # the offset's consensus penalty relative to x's (see edge_penalty)
    relax: float = 1.95
    tol: float = 1e-3  # bound on the estimated relative function error at the stop
    max_rounds: int = 5000
    diameter: int = 1
    anderson: int = 30  # memory of the Anderson acceleration on a complete graph (0: plain ADMM)
    safeguard: float = 2.0  # restart Anderson when the fixed-point residual exceeds this x its best
    relay: bool = True  # sparse graphs of <= 16 robots run the relay hub (agents/relay_hub.py); False: edge form
    polish: bool = False  # hub form, hard margin: the exact active-set end-game (`_Polish`, docs/algorithm.md)
    # hub form, soft margin: the exact end-game by a block Krylov solve (agents/soft_endgame.py); autogrid's
    # soft answer solves turn it on, False keeps main's frames and bits
    soft_polish: bool = False
    # with soft_polish, hard margins run the same end-game with B empty and no upper bound (C = inf);
    # autogrid's hard answer solves and complete admm fleets by default (agents/spec.py) turn it on, False
    # keeps the hard frames' payload zeros (main's bits)
    hard_endgame: bool = False
    # hub form, hard margin, no polish: a stop also needs the fleet's certified error bound
    # (agents/certificate.py) <= certify x max(tol, 1e-3); 0 = the rule alone (main's frames and bits)
    certify: float = 10.0
    # hub form: the stop's rate estimate only from residuals of one stretch of the acceleration (`settled`);
    # autogrid's answer solves (no certified guard) turn it on, False keeps main's stops and bits
    settled_rate: bool = False

    def __post_init__(self) -> None:
        check_positive(self, "rho", "gamma_penalty")
        if not 0 < self.relax < 2:
            raise ValueError(f"over-relaxation must be in (0, 2), got {self.relax}")
        check_positive(self, "tol")
        check_counts(self, "max_rounds")
        check_diameter(self.diameter)
        if not 0 <= self.anderson <= 100:
            raise ValueError(f"anderson memory must be in [0, 100], got {self.anderson}")
        if not self.safeguard > 1:
            raise ValueError(f"safeguard must be above 1, got {self.safeguard}")
        if not (isinstance(self.certify, (int, float)) and 0 <= self.certify < math.inf):
            raise ValueError(f"certify must be a number >= 0 (0: off), got {self.certify!r}")
        if self.polish and self.soft_polish:
            raise ValueError("polish (hard margins) and soft_polish (soft margins) have different frames: choose one")

    @classmethod
    def from_params(cls, params: Mapping[str, Any]) -> ADMMParams:
        """From a fleet file's ``params``: exactly this class's fields; any other key is an
        error naming it."""
        return params_from(cls, params, "admm")


class _Edge:
    """One edge's ADMM state, held identically by both ends in the orientation low id -> high id.

    Both robots compute every update from the same two vectors in the same order, so their
    copies stay bit-for-bit equal and the dual of the high end is exactly minus the low end's:
    the invariant sum(lambda) = 0 that makes the fleet reach the centralized solution.
    """

    def __init__(self, dim: int, mine_is_low: bool, rho: np.ndarray) -> None:
        self.sign = 1.0 if mine_is_low else -1.0
        self.rho = rho  # per variable, fixed for the run: both ends always use the same values
        self.z = np.zeros(dim)  # the edge's consensus value
        self.lam = np.zeros(dim)  # the low end's multiplier

    def update(self, v_low: np.ndarray, v_high: np.ndarray, relax: float) -> None:
        """z and lambda after both ends' primal steps (over-relaxed by `relax`)."""
        h_low = relax * v_low + (1.0 - relax) * self.z
        h_high = relax * v_high + (1.0 - relax) * self.z
        self.z = 0.5 * (h_low + h_high)
        self.lam = self.lam + self.rho * (h_low - self.z)

    def state(self) -> list[bytes | None]:
        return [to_bytes(self.z), to_bytes(self.lam)]

    def load(self, state: list[bytes]) -> None:
        self.z, self.lam = from_bytes(state[0]), from_bytes(state[1])


_max_reduce, _all_reduce = np.maximum.reduce, np.logical_and.reduce  # (np.max / .all() without their wrappers)


def _two_sum(a: np.ndarray, b: np.ndarray, out: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """a + b rounded (into ``out`` if given), and its rounding error exactly (Knuth's TwoSum,
    elementwise)."""
    x = np.add(a, b, out)
    z = x - a
    return x, (a - (x - z)) + (b - z)


def _pairwise_sum(q: np.ndarray) -> np.ndarray:
    """Sum over the first axis, in practice exactly rounded, the same bits on every machine.

    With h the largest power of two below n, terms h..n-1 are added onto terms 0..n-h-1, then
    halves are added (q[:w] + q[w:2w]) until one term is left; every addition keeps its rounding
    error (TwoSum) and the errors are summed alongside, so the result -- sum + errors, rounded once
    -- is the correctly rounded sum except when the exact sum lies within ~n^2 eps^2 sum|q| of a
    rounding boundary (then one ulp off). It therefore reproduces math.fsum's bits in practice
    (checked: the default autogrid run and the paper preset give the same bits as before, and
    tests/test_admm.py compares with math.fsum on random and cancelling sums), at a fraction of
    its cost: one vectorised pass over all columns instead of one fsum call per dot product
    (~10 us each, 300k of them per default autogrid run). Only elementwise IEEE additions run in
    a pairing that depends on n alone -- no BLAS, no reduction order chosen by numpy or by a CPU's
    SIMD width -- so identical inputs give identical bits on any host with the same packages; and
    each column's result depends on that column alone, so sums may be batched side by side.

    The levels' sums run one level after another into one buffer; the TwoSum errors of all levels
    after the first are then computed at once, each from its own sum and two terms (the same
    operations on the same operands as level by level: ~30 numpy calls instead of ~46 for the
    hub's 64 terms, 35 -> ~31 us; tests/test_exact_arith.py compares with the level-by-level form).
    """
    n = len(q)
    if n == 0:
        return np.zeros(q.shape[1:])
    h, halvings, lows, highs = _pairing(n)
    s = np.empty((2 * h - 1,) + q.shape[1:])  # every level's sums, one level after another
    if n == 2 * h:  # a power of two: the first pairing covers every term (no copy, no zero errors)
        e = _two_sum(q[:h], q[h:], s[:h])[1]
    else:
        e = np.zeros((h,) + q.shape[1:])
        s[n - h : h] = q[n - h : h]
        e[: n - h] = _two_sum(q[: n - h], q[h:], s[: n - h])[1]
    if not halvings:
        return s[0] + e[0]
    add, sub = np.add, np.subtract
    for low, high, out, _e_low, _e_high, _err in halvings:  # the halves' sums, level after level
        add(s[low], s[high], s[out])
    # then the TwoSum errors of all those sums at once, each from its own two terms (the same
    # operations as level by level): (a - (x - (x - a))) + (b - (x - a)), x = a + b
    x, a, b = s[h:], s[lows], s[highs]
    xa = x - a
    t = x - xa
    sub(a, t, t)
    sub(b, xa, xa)
    err = add(t, xa, t)
    for _low, _high, _out, e_low, e_high, level in halvings:  # the errors' own sums, the same pairing
        e = (e[e_low] + e[e_high]) + err[level]
    return s[-1] + e[0]


#: `_pairing`'s plans, per number of terms
_PAIRINGS: dict[int, tuple[int, list[tuple[slice, ...]], np.ndarray, np.ndarray]] = {}


def _pairing(n: int) -> tuple[int, list[tuple[slice, ...]], np.ndarray, np.ndarray]:
    """`_pairwise_sum`'s plan for n terms, made once per n (read-only, shared by threads): h, the
    largest power of two below n (level 0 leaves h sums, at rows 0..h of the levels' buffer);
    per later level of w = h/2, h/4, ..., 1 sums: the buffer rows of its low and high halves and
    of its sums, the rows of e's halves (0..w, w..2w) and of the level's errors among all the
    errors (its sums' rows less h); the buffer rows of every later sum's two terms."""
    plan = _PAIRINGS.get(n)
    if plan is None:
        h = 1 << (max(n - 1, 1).bit_length() - 1)
        halvings, lows, highs = [], [], []
        prev, w, at = 0, h, h
        while w > 1:
            w //= 2
            halvings.append((slice(prev, prev + w), slice(prev + w, prev + 2 * w), slice(at, at + w),
                             slice(0, w), slice(w, 2 * w), slice(at - h, at - h + w)))
            lows += range(prev, prev + w)
            highs += range(prev + w, prev + 2 * w)
            prev, at = at, at + w
        rows = np.array(lows, dtype=np.intp), np.array(highs, dtype=np.intp)
        for r in rows:
            r.flags.writeable = False
        plan = _PAIRINGS.setdefault(n, (h, halvings, *rows))
    return plan


def _row_sums(p: np.ndarray) -> np.ndarray:
    """Sums along the last axis (`_pairwise_sum`, the terms laid out along the first axis so that
    each addition runs over one contiguous block)."""
    lead, n = p.shape[:-1], p.shape[-1]
    return _pairwise_sum(np.ascontiguousarray(p.reshape(-1, n).T)).reshape(lead)


def _dots(rows: np.ndarray, v: np.ndarray) -> np.ndarray:
    """rows @ v (broadcast over leading axes), reproducible bit for bit: see `_pairwise_sum`."""
    return _row_sums(rows * v)


def _solve_spd(H: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Cholesky solve of a small symmetric positive definite system, deterministic on any machine:
    right-looking updates are elementwise numpy (each entry updated in the same order), the
    triangular solves exactly rounded sums (math.fsum over Python floats: the same products, less
    overhead than numpy for vectors this short) -- no BLAS call whose summation order varies.

    The factorisation runs on the lower triangle alone, packed column after column in a work
    vector kept per size and thread (`_spd_workspace`: its views and index arrays made once), a hub
    step's largest cost: every step's operands contiguous, the last few columns on Python floats
    (`_spd_factor`), each entry the same operations in the same order as the plain right-looking
    form on a fresh square matrix (tests/test_exact_arith.py compares with that form)."""
    return _spd_solve(_spd_factor(H), g)


#: `_spd_factor`'s L for `_spd_solve`: its rows one after another (row i: L[i][0..i], the diagonal
#: last), its columns below the diagonal read upwards, from the last column to the first (column
#: i: L[n-1][i], ..., L[i+1][i]), and its diagonal
SpdFactor = tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...]]


def _spd_factor(H: np.ndarray) -> SpdFactor:
    """`_solve_spd`'s Cholesky factor L of H, laid out for the solves (`SpdFactor`) as Python
    floats: factor once, solve many times with `_spd_solve` (the same operations as `_solve_spd`,
    the same bits).

    Why packed: the square form's rank-1 update ran its three numpy calls over strided 2-D views
    of the whole trailing block (both triangles), one inner loop per row. Here H's lower triangle
    is packed column after column (column k = L[k:, k], then column k + 1, ...), so column k's
    entries and the trailing triangle are contiguous: a step divides the column (by a 0-d view of
    its pivot, cheaper to pass than a Python float), gathers the two factors of every trailing
    entry's product (l_ik, l_jk for i >= j; precomputed index arrays), multiplies and subtracts --
    each trailing entry a_ij gets a_ij - l_ik l_jk at step k, as in the square form (l_ik l_jk ==
    l_jk l_ik in IEEE arithmetic), and nothing else touches it. The last SPD_SCALAR_TAIL columns
    run on the packed list's Python floats: the same subtractions of the same products in the same
    order, cheaper than numpy calls for a trailing triangle of a few entries. Measured on the paper
    preset's Anderson systems (m ~23): 102 -> ~60 us a factor (benchmarks/results/round_cost.md,
    branch cholblock)."""
    H = np.asarray(H, dtype=float)
    n = len(H)
    if H.shape != (n, n):  # (the gather below would clip, not refuse)
        raise ValueError(f"not a square matrix: {H.shape}")
    packed, src, steps, tail, pick = _spd_workspace(n)
    H.take(src, None, packed, "clip")  # (the indices are in range: "clip" only spares numpy a buffered copy)
    sqrt, divide, multiply, subtract, item = math.sqrt, np.divide, np.multiply, np.subtract, packed.item
    for off, pivot, col, trail, i, j, prod in steps:  # the numpy columns
        akk = item(off)
        if not akk > 0:
            raise np.linalg.LinAlgError("not positive definite")
        pivot[()] = sqrt(akk)  # L[k][k], in place
        divide(col, pivot, col)
        multiply(col[i], col[j], prod)  # l_ik l_jk for every trailing entry (i, j), packed like the entries
        subtract(trail, prod, trail)
    flat = packed.tolist()
    for off, below, updates in tail:  # the same steps on Python floats: (entry, l_ik, l_jk) positions
        akk = flat[off]
        if not akk > 0:
            raise np.linalg.LinAlgError("not positive definite")
        flat[off] = lkk = sqrt(akk)
        for p in below:
            flat[p] /= lkk
        for p, a, b in updates:
            flat[p] -= flat[a] * flat[b]
    rows, cols_up, diagonal = pick
    return rows(flat), cols_up(flat), diagonal(flat)


def _spd_solve(factor: SpdFactor, g: np.ndarray) -> np.ndarray:
    """L L' x = g by the two triangular solves of `_solve_spd` (exactly rounded sums: math.fsum's
    result does not depend on the order of its terms). Each substitution walks one flat sequence:
    map(mul, done, terms) stops when the solved values `done` run out, having taken exactly one
    term per value -- row i's i products (the diagonal, next, divides), column i's n - 1 - i
    products against x[n-1], ..., x[i+1] -- so nothing is sliced."""
    rows, cols_up, diagonal = factor
    rhs = g.tolist() if isinstance(g, np.ndarray) else [float(v) for v in g]
    fsum, mul = math.fsum, operator.mul
    y: list[float] = []
    terms = iter(rows)
    for b in rhs:
        y.append((b - fsum(map(mul, y, terms))) / next(terms))
    x_up: list[float] = []  # x[n-1], x[n-2], ...
    terms = iter(cols_up)
    for b, d in zip(y[::-1], diagonal[::-1]):
        x_up.append((b - fsum(map(mul, x_up, terms))) / d)
    x_up.reverse()
    return np.array(x_up)


#: columns of `_spd_factor` done on Python floats (trailing triangles of at most 15 entries)
SPD_SCALAR_TAIL = 6

_SPD_WORK = threading.local()  # fleets run in worker threads (launcher/api.py run_async)


def _picker(positions: list[int]) -> Callable[[list[float]], tuple[float, ...]]:
    """The entries of a list at `positions`, as a tuple, in one C call (operator.itemgetter,
    which returns a bare item or refuses for fewer than two positions)."""
    if len(positions) > 1:
        return operator.itemgetter(*positions)
    return lambda seq: tuple(seq[p] for p in positions)


_TRAILING_PAIRS: dict[int, tuple[np.ndarray, np.ndarray]] = {}
_INTS: list[int] = []


def _shared_ints(n: int) -> list[int]:
    """0..n-1 as one list of int objects kept across calls (a longer list made when asked for
    more, reusing the old one's objects; a race only makes two equal lists)."""
    global _INTS
    ints = _INTS
    if len(ints) < n:
        ints = _INTS = ints + list(range(len(ints), n))
    return ints


def _trailing_pairs(r: int) -> tuple[np.ndarray, np.ndarray]:
    """Row and column indices (i, j), i >= j, of an r x r lower triangle packed column after
    column: which entries of a step's column multiply for each trailing entry. Shared by every
    size and thread (read-only; ~r^2 entries each: Anderson's memory may reach 100)."""
    pairs = _TRAILING_PAIRS.get(r)
    if pairs is None:
        j, i = np.triu_indices(r)
        i, j = i.astype(np.intp), j.astype(np.intp)
        i.flags.writeable = j.flags.writeable = False
        pairs = _TRAILING_PAIRS.setdefault(r, (i, j))
    return pairs


def _spd_workspace(n: int) -> tuple[np.ndarray, np.ndarray, list[tuple[Any, ...]], list[tuple[Any, ...]],
                                    tuple[Callable[[list[float]], tuple[float, ...]], ...]]:
    """This thread's packed work vector for `_spd_factor` (H's lower triangle column after column)
    and what its steps use, made once per size and tail (Anderson's memory bounds the sizes): the
    positions in H of the packed entries; per numpy column k, its pivot's position and a 0-d view
    of it, the views of column k below the diagonal and of the trailing triangle, the index arrays
    giving every trailing entry's two factors within that column, a buffer for the products; per
    Python column, its pivot's position, the positions below it and the (entry, factor, factor)
    positions of its updates; the pickers of `SpdFactor`'s three sequences."""
    by_n = getattr(_SPD_WORK, "by_n", None)
    if by_n is None:
        by_n = _SPD_WORK.by_n = {}
    cut = max(n - SPD_SCALAR_TAIL, 0)
    ws = by_n.get((n, cut))
    if ws is None:
        offs = [k * n - k * (k - 1) // 2 for k in range(n + 1)]  # column k: L[k:, k] at offs[k]:offs[k + 1]
        ints = _shared_ints(offs[-1])  # (not fresh ints: the pickers' tuples share them across sizes)
        at = [[ints[offs[j] + i - j] for j in range(i + 1)] for i in range(n)]  # at[i][j]: L[i][j]'s position
        src = np.array([i * n + k for k in range(n) for i in range(k, n)], dtype=np.intp)
        packed, products = np.empty(offs[-1]), np.empty(offs[-1] - n)  # (products: the first step's, the largest)
        steps = []
        for k in range(cut):
            i, j = _trailing_pairs(n - k - 1)
            steps.append((offs[k], packed[offs[k] : offs[k] + 1].reshape(()), packed[offs[k] + 1 : offs[k + 1]],
                          packed[offs[k + 1] :], i, j, products[: len(i)]))
        tail = [(offs[k], range(offs[k] + 1, offs[k + 1]),
                 [(at[i][j], at[i][k], at[j][k]) for j in range(k + 1, n) for i in range(j, n)]) for k in range(cut, n)]
        pick = (_picker([p for row in at for p in row]),
                _picker([at[j][i] for i in range(n - 1, -1, -1) for j in range(n - 1, i, -1)]),
                _picker(offs[:-1]))
        ws = by_n[(n, cut)] = (packed, src, steps, tail, pick)
    return ws


def _read_only_scalar(x: float) -> np.ndarray:
    """``x`` as a read-only 0-d float64 array (a factor numpy multiplies without converting it)."""
    a = np.array(x, dtype=np.float64)
    a.flags.writeable = False
    return a


class _Hub:
    """Global-consensus ADMM with Anderson acceleration, held identically by every robot.

    On a complete graph every robot receives every robot's local solution v_l each round, so each
    can run the hub form of consensus ADMM (z = mean, one scaled dual u_l per robot) for the whole
    fleet, and accelerate its fixed-point map s = (z, u_1..u_N) -> T(s) with type-II Anderson
    acceleration (Zhang, O'Donoghue & Boyd 2018). All arithmetic that mixes robots runs in an order
    fixed by the sizes alone -- sums compensated to math.fsum's bits in practice (`_dots`), exactly
    rounded (`_solve_spd`) or elementwise, in robot-id order -- so the copies stay bit-for-bit
    equal; every extrapolation is an affine combination of states with sum_l u_l = 0, and the
    plain map restores that invariant anyway, so the fixed point is the centralized solution.

    Copies in one process (the in-process fleet, robots sharing a process) take the very same
    steps: `token` digests everything a copy's state follows from, and a step already taken from an
    equal token with equal inputs is adopted (`snapshot` / `adopt`, ConsensusADMM._shared_step)
    instead of computed again -- the same bits, computed once per process instead of once per robot.
    """

    def __init__(self, ids: tuple[int, ...], dim: int, penalty: np.ndarray, params: ADMMParams) -> None:
        self.ids = ids
        self.dim = dim
        self.penalty = penalty
        self.relax = params.relax
        self.memory = params.anderson
        self.safeguard = params.safeguard
        self.s: np.ndarray | None = None  # the state at which the robots' current v were computed
        self.hist_s: list[np.ndarray] = []  # past states s_k and their images T(s_k)
        self.hist_f: list[np.ndarray] = []
        self._dg = np.zeros((0, 0))  # successive differences of residuals and of images, a row each
        self._df = np.zeros((0, 0))
        self._gram = np.zeros((0, 0))  # dg_i . dg_j (`_dots`: the same bits on every copy)
        self._rhs = np.zeros(0)  # dg_i . g of the current step
        self.best = math.inf  # smallest fixed-point residual since the last restart
        self.stalled = 0  # rounds since `best` last improved
        self.desynced = False  # the last step found the copies differing
        # the stall switch (`stall_watch`): the fleet residual's last 10x-lower mark, rounds since
        # it was set (on the plain map: rounds on it), and whether the map is plain Douglas-Rachford
        self.mark = math.inf
        self.since = 0
        self.plain = False
        self.resync = False  # the last step was (or ended) a desynchronised stretch: copies may have differed
        # steps since the acceleration last restarted itself (its safeguard or its stall restart, `step`) or
        # the fleet lost a robot: the stop's rate estimate is read only from residuals of one such stretch
        # (`settled`). The stall switch's plain stretch and re-arm do not count: the plain map's residuals
        # measure its contraction, and the stops just after a re-arm were honest (1e-7 to 6e-5, 36 runs)
        self.age = 0
        self._dual0: np.ndarray | None = None  # duals to start from (`seed_duals`), used by `start`
        self.token = _digest(repr((ids, dim, self.relax, self.memory, self.safeguard, STALL, ANDERSON_REG,
                                   STALL_WINDOW, STALL_DROP)).encode(), penalty)

    @property
    def relax(self) -> float:
        """The over-relaxation (a benchmark may change it between rounds: set, not patched)."""
        return self._relax

    @relax.setter
    def relax(self, value: float) -> None:
        # relax and 1 - relax also as read-only 0-d arrays: an array times a Python float converts
        # the float every call (~0.2 us more than a 0-d array's multiply: `message`, every
        # robot-round); the products are the same IEEE multiplications of the same float64 values
        self._relax = value
        self._relax_a = _read_only_scalar(value)
        self._keep_a = _read_only_scalar(1.0 - value)

    def center(self, me: int) -> np.ndarray:
        """Robot `me`'s proximal centre z - u_me."""
        assert self.s is not None
        k = self.ids.index(me)
        return self.s[: self.dim] - self.s[(k + 1) * self.dim : (k + 2) * self.dim]

    @staticmethod
    def _mean(rows: np.ndarray | list[np.ndarray]) -> np.ndarray:
        """The rows' mean, added one row after another in id order (numpy's reduction over the
        first, slow axis adds row by row: the same bits as a loop, in one call)."""
        return np.add.reduce(np.array(rows), axis=0) / len(rows)

    def start(self, ws: list[np.ndarray]) -> None:
        """After round 0 (each robot's own solution, w_l = v_l): z = their mean, u_l = v_l - z
        (+ the seeded duals, centred: `seed_duals`)."""
        self.s = self._map(ws)
        if self._dual0 is not None:
            U = self._dual0
            self.s[self.dim :] += (U - np.add.reduce(U, axis=0) / len(U)).ravel()
            self._dual0 = None

    def seed_duals(self, U: np.ndarray) -> None:
        """Start the duals from U (a row per robot, in id order; the same bits on every copy) instead of
        zero: a warm start of the iteration, not of its fixed point (sum_l u_l = 0 is kept)."""
        self._dual0 = np.array(U, dtype=float)
        self.token = _digest(self.token, b"duals", self._dual0)

    def message(self, me: int, v: np.ndarray) -> np.ndarray:
        """w_me = h_me + u_me from this copy (h = relax v + (1 - relax) z): robot `me`'s share of
        the plain map, sent beside v so that every copy builds the map from the same numbers."""
        assert self.s is not None
        d, k = self.dim, self.ids.index(me)
        h = self._relax_a * v + self._keep_a * self.s[:d]
        return h + self.s[(k + 1) * d : (k + 2) * d]

    def _map(self, ws: list[np.ndarray]) -> np.ndarray:
        """T: z' = mean_l w_l, u'_l = w_l - z', from the robots' own w_l only (shared data).

        Each w_l is computed from robot l's copy, so the image is the same on every copy even
        after copies differed (survivors that dropped a dead robot in different rounds), and
        sum_l u'_l = 0 always: a fixed point is the members' exact optimum. When the copies agree
        it is the usual over-relaxed update bit for bit (h + u == u + h)."""
        w = np.array(ws)
        d = w.shape[1]
        out = np.empty(d * (len(w) + 1))
        out[:d] = z_new = np.add.reduce(w, axis=0) / len(w)  # = _mean(ws)
        np.subtract(w, z_new, out=out[d:].reshape(w.shape))
        return out

    def synced(self, values: np.ndarray | list[np.ndarray], ws: np.ndarray | list[np.ndarray]) -> bool:
        """True when every robot's w is what this copy computes for it: all copies agree (bits).
        (`message` for every robot at once: the same elementwise operations.)"""
        assert self.s is not None
        d = self.dim
        h = self._relax_a * np.asarray(values) + self._keep_a * self.s[:d]  # (elementwise: any layout)
        h += self.s[d:].reshape(h.shape)
        w = np.asarray(ws)
        return h.shape == w.shape and bool(_all_reduce(h == w, axis=None))  # np.array_equal, without its wrappers

    def step(self, ws: list[np.ndarray], synced: bool = True) -> float:
        """Fold in the robots' w at s, move s to the next point; returns |T - s|.

        While the copies differ (`synced` False: after a drop seen in different rounds) every
        copy takes the plain step s = T, the same on all of them, and once more in the first
        round they agree, so that all restart the acceleration from one common history."""
        assert self.s is not None
        f = self._map(ws)
        g = f - self.s
        self.resync = not synced or self.desynced
        if self.plain:  # after a stall: the plain map, s = T(s), no history (memory 0)
            self.desynced = not synced
            self.s = f
            self.age += 1
            return math.sqrt(float(_pairwise_sum((g * g)[:, None])[0]))
        if not synced or self.desynced:
            self._forget()
        self.desynced = not synced
        m = len(self._dg)
        if self.hist_s:  # this step's difference: the Gram matrix gets a row
            dg = g - (self.hist_f[-1] - self.hist_s[-1])
            dgs = np.empty((m + 1, len(g)))
            if m:
                dgs[:m] = self._dg
            dgs[m] = dg
            # one pass of exactly rounded sums, side by side: dg_i . dg (the new row), dg_i . g
            # (the right-hand side) and g . g (the residual); columns are summed independently
            terms = np.empty((len(g), 2 * m + 3))
            np.multiply(dgs.T, dg[:, None], out=terms[:, : m + 1])
            np.multiply(dgs.T, g[:, None], out=terms[:, m + 1 : 2 * m + 2])
            np.multiply(g, g, out=terms[:, -1])
            sums = _pairwise_sum(terms)
        else:
            sums = _pairwise_sum((g * g)[:, None])
        res = math.sqrt(float(sums[-1]))
        if res > self.safeguard * self.best or self.stalled > STALL * self.memory:
            self._forget()  # the extrapolation went astray or stopped helping: restart from the plain step
            self.age = 0
        self.stalled = 0 if res < self.best else self.stalled + 1
        self.best = min(self.best, res)
        if self.hist_s:  # (still there: not forgotten above)
            df = np.empty((m + 1, len(f)))
            if m:
                df[:m] = self._df
            np.subtract(f, self.hist_f[-1], out=df[m])
            gram = np.empty((m + 1, m + 1))
            gram[:m, :m] = self._gram
            gram[m, :] = gram[:, m] = sums[: m + 1]
            self._dg, self._df, self._gram, self._rhs = dgs, df, gram, sums[m + 1 : 2 * m + 2]
        self.hist_s.append(self.s)
        self.hist_f.append(f)
        if len(self._dg) > self.memory:  # keep the last `memory` differences
            self.hist_s, self.hist_f = self.hist_s[1:], self.hist_f[1:]
            self._dg, self._df = self._dg[1:], self._df[1:]
            self._gram = self._gram[1:, 1:].copy()
            self._rhs = self._rhs[1:]
        self.s = self._extrapolate() if len(self._dg) else f
        self.age += 1
        return res

    def watch(self, residual: float) -> None:
        """Fold in the round's fleet residual (the same on every copy). When the fleet stalls
        (`stall_watch`) every copy switches, in the same round, to the plain map for STALL_WINDOW
        rounds, then re-arms Anderson from the point reached, with a fresh watch. Measured: plain
        steps for good cure the stall but slow fleets that Anderson finishes late (48 robots not
        converged in 5000 rounds against 1724); with the re-arm every stalled 24-48-robot fleet
        stops earlier than before (docs/algorithm.md)."""
        if self.plain:
            self.since += 1
            if self.since >= STALL_WINDOW:  # re-arm: Anderson again from here, the watch afresh
                self.plain, self.mark, self.since = False, math.inf, 0
            return
        if self.resync:  # copies that dropped a dead robot in different rounds saw different
            self.mark, self.since = math.inf, 0  # residuals: all restart the watch alike
            return
        self.mark, self.since, fired = stall_watch(self.mark, self.since, residual)
        if fired:
            self.plain, self.since = True, 0
            self._forget()

    def _forget(self) -> None:
        self.hist_s, self.hist_f, self.best = [], [], math.inf
        self._dg, self._df = np.zeros((0, 0)), np.zeros((0, 0))
        self._gram, self._rhs = np.zeros((0, 0)), np.zeros(0)
        self.stalled = 0

    def _rebuild(self) -> None:
        """The differences and their Gram matrix from the history: the same bits as built step by
        step (`_dots` of the same two vectors, in either order, sums the same products)."""
        gs = [f - s for s, f in zip(self.hist_s, self.hist_f)]
        dgs = [b - a for a, b in zip(gs[:-1], gs[1:])]
        dfs = [b - a for a, b in zip(self.hist_f[:-1], self.hist_f[1:])]
        self._dg = np.array(dgs) if dgs else np.zeros((0, 0))
        self._df = np.array(dfs) if dfs else np.zeros((0, 0))
        m = len(self._dg)
        self._gram = _dots(self._dg[None, :, :], self._dg[:, None, :]) if m else np.zeros((0, 0))

    def _extrapolate(self) -> np.ndarray:
        """Type-II Anderson: T(s) minus the combination of past steps that best cancels g
        (the least squares' right-hand side dg_i . g is `_rhs`, from `step`)."""
        m = len(self._dg)
        H = self._gram.copy()
        scale = math.fsum(H.diagonal().tolist()) / m
        H.reshape(-1)[:: m + 1] += ANDERSON_REG * max(scale, 1e-300)  # (the diagonal as a view: no index arrays)
        try:
            coef = _solve_spd(H, self._rhs)
        except np.linalg.LinAlgError:
            return self.hist_f[-1]
        # T(s) - coef_1 df_1 - coef_2 df_2 - ..., one term after another (numpy's reduction over
        # the first, slow axis subtracts row by row: the same bits as a loop, in one call)
        terms = np.empty((m + 1, self._df.shape[1]))
        terms[0] = self.hist_f[-1]
        np.multiply(coef[:, None], self._df, out=terms[1:])
        return np.subtract.reduce(terms, axis=0)

    def drop(self, j: int) -> None:
        """Continue over the survivors: the dead robot's dual goes, the acceleration restarts."""
        k = self.ids.index(j)
        d = self.dim
        self.ids = tuple(i for i in self.ids if i != j)
        if self.s is not None:
            self.s = np.concatenate([self.s[: (k + 1) * d], self.s[(k + 2) * d :]])
        self._forget()
        self.age = 0
        self.token = _digest(self.token, b"drop %d" % j)

    def snapshot(self) -> tuple[Any, ...]:
        """The state a step leaves, for copies that take the same step (`adopt`): arrays are never
        changed in place once made, so copies may hold the same ones; the lists are copied."""
        return (self.s, list(self.hist_s), list(self.hist_f), self._dg, self._df, self._gram, self._rhs,
                self.best, self.stalled, self.desynced, self.mark, self.since, self.plain, self.age)

    def adopt(self, snap: tuple[Any, ...]) -> None:
        (self.s, hist_s, hist_f, self._dg, self._df, self._gram, self._rhs,
         self.best, self.stalled, self.desynced, self.mark, self.since, self.plain, self.age) = snap
        self.hist_s, self.hist_f = list(hist_s), list(hist_f)

    def state(self) -> dict[str, Any]:
        return {
            "ids": list(self.ids),
            "s": to_bytes(self.s),
            "hist_s": [to_bytes(a) for a in self.hist_s],
            "hist_f": [to_bytes(a) for a in self.hist_f],
            "best": self.best,
            "stalled": self.stalled,
            "desynced": self.desynced,
            "mark": self.mark,
            "since": self.since,
            "plain": self.plain,
            "age": self.age,
        }

    def load(self, state: dict[str, Any]) -> None:
        self.ids = tuple(int(i) for i in state["ids"])
        self.s = from_bytes(state["s"])
        self.hist_s = [from_bytes(a) for a in state["hist_s"]]
        self.hist_f = [from_bytes(a) for a in state["hist_f"]]
        self.best = float(state["best"])
        self.stalled = int(state["stalled"])
        self.desynced = bool(state["desynced"])
        # checkpoints written before the stall switch existed: not switched, the watch starts afresh
        self.mark = float(state.get("mark", math.inf))
        self.since = int(state.get("since", 0))
        self.plain = bool(state.get("plain", False))
        self.age = int(state["age"])  # (checkpoint version 4: every hub state has it)
        self._rebuild()
        self.token = _digest(self.token, b"load", repr((self.ids, self.best, self.stalled, self.desynced, self.mark,
                                                        self.since, self.plain, self.age)).encode(),
                             b"" if self.s is None else self.s, *self.hist_s, b"|", *self.hist_f)


def shared_step(cache: OrderedDict[bytes, Any], key: bytes, compute: Callable[[], Any], kept: int) -> tuple[Any, bool]:
    """The value of a step every copy of a replicated state takes alike, computed once per process:
    (the cached value, True) when a copy already took the step with this key (the digest of its
    state and inputs), else (compute(), False), kept among the last ``kept`` steps (0: no sharing)."""
    with _SHARED_LOCK:
        done = cache.get(key)
        if done is not None:
            cache.move_to_end(key)
            return done, True
    done = compute()
    with _SHARED_LOCK:
        if kept > 0:
            cache[key] = done
        while len(cache) > kept:
            cache.popitem(last=False)
    return done, False


def shared_input_step(cache: OrderedDict[bytes, list[tuple[Any, ...]]], key: bytes, inputs: np.ndarray,
                      compute: Callable[[], Any], kept: int) -> tuple[Any, bool]:
    """:func:`shared_step` for a step whose large input is compared, not hashed: ``key`` digests the
    copy's state and small inputs, ``inputs`` (a contiguous array: a round's frames) must then equal
    a kept step's byte for byte (and in shape) to be adopted. A copy that adopts thus pays a copy and
    a compare of the frames (~3 us for 35 kB) where hashing them cost ~35 us (branch authhash: 1.6 s
    of a 16-robot autogrid run, 15 of 16 copies adopting); ``compute`` (the one copy that steps)
    may still digest them. Kept: the last ``kept`` keys, a few inputs each (copies that differ)."""
    raw = inputs.tobytes()
    with _SHARED_LOCK:
        for shape, seen, done in cache.get(key, ()):
            if seen == raw and shape == inputs.shape:
                cache.move_to_end(key)
                return done, True
    done = compute()
    with _SHARED_LOCK:
        if kept > 0:
            entries = cache.setdefault(key, [])
            entries.append((inputs.shape, raw, done))
            del entries[:-_INPUTS_PER_KEY]
            cache.move_to_end(key)
        while len(cache) > kept:
            cache.popitem(last=False)
    return done, False


_INPUTS_PER_KEY = 4  # steps kept per state: copies with the same history but different frames (desynced)


def _digest(*parts: bytes | np.ndarray) -> bytes:
    """A 20-byte digest of byte strings and contiguous arrays (their raw bytes)."""
    h = hashlib.blake2b(digest_size=20)
    for part in parts:
        h.update(part)
    return h.digest()


#: hub steps taken lately in this process, by the digest of the copy's token and the round's
#: small inputs, with the round's frames beside each to compare (ConsensusADMM._shared_step,
#: shared_input_step): (hub snapshot, mean of the v's, residual, step costs, new token). A process's
#: robots are at most a round apart and autogrid's sweep runs ~10 hubs side by side; a step that
#: is no longer here is simply computed again. SHARED_STEPS_KEPT = 0 turns the sharing off.
_SHARED_STEPS: OrderedDict[bytes, list[tuple[Any, ...]]] = OrderedDict()
SHARED_STEPS_KEPT = 64
#: certificates computed lately in this process (ConsensusADMM._certify), by the digest of their inputs
_SHARED_CERTS: OrderedDict[bytes, tuple[Any, ...]] = OrderedDict()
_SHARED_LOCK = threading.Lock()  # fleets run in worker threads (launcher/api.py run_async) share it


#: the local step QPs (hard margin, n >= dim) first try the exact KKT solve on the active rows of
#: the robot's previous v (agents/problem.py `_WarmKKT`, piqp when it does not certify): ~25-30 %
#: cheaper per solve than piqp, and its multipliers are exact, so the certified guard's bound has no
#: floor from piqp's interior point (docs/algorithm.md, "A certified stop"). It moves the last bits and
#: with them the chaotic Anderson path: on the L shape of tests/test_simulate.py the rule alone then
#: stops on a plateau at error 6.7e-2 (branch core3). So it runs only where the guard decides
#: (`ConsensusADMM.cert_active`): certify = 0, soft margins, the polish and the edge form keep piqp and
#: main's bits. The relay hub keeps piqp (relay_hub.RELAY_WARM_QP: its 16-robot fleets have no guard)
WARM_QP = True

#: restart the acceleration when its best residual has not improved for STALL x memory rounds
STALL = 1.0
#: Tikhonov regularisation of Anderson's least squares, relative to the mean diagonal
ANDERSON_REG = 1e-5


#: rounds per window of the contraction estimate; the estimate needs two full windows
RATE_WINDOW = 20

#: the hub's stall switch: the fleet residual must fall STALL_DROP x below its last mark within
#: STALL_WINDOW rounds, else Anderson has stalled and the hub takes STALL_WINDOW plain steps
#: before it re-arms Anderson (docs/algorithm.md, "Stall switch")
STALL_WINDOW = 300
STALL_DROP = 10.0
#: on the plain map the stop test is STALL_STOP_MARGIN x the edge form's estimate (window maxima)
#: below tol, STALL_HOLD rounds in a row (the relay hub's rule)
STALL_STOP_MARGIN = 2.0
STALL_HOLD = 40


def stall_watch(mark: float, since: int, residual: float) -> tuple[float, int, bool]:
    """One round of the stall rule: (new mark, rounds since it was set, fired).

    The mark is the residual the fleet must beat by STALL_DROP x; it is reset (and the count
    restarted) whenever a residual does. Firing means STALL_WINDOW rounds without that: Anderson's
    residual falls while the error stalls on 24-48-robot complete fleets (docs). A pure function of
    the fleet residual, which every copy holds alike, so all copies fire in the same round."""
    if residual < mark / STALL_DROP or mark == math.inf:
        return residual, 0, False
    since += 1
    return mark, since, since >= STALL_WINDOW


def error_estimate(residuals: list[float], *, typical_older: bool = False, window: int = RATE_WINDOW) -> float:
    """Distance to the fixed point implied by recent residuals: r / (1 - observed rate).

    ADMM's residuals oscillate, so the rate compares the largest residual of the last window
    (`window` rounds; the relay hub's fast stop test uses a shorter one) with that of the window
    before (a per-round geometric rate), which is robust to the swings.
    With `typical_older` the window before counts with its median instead: Anderson's restarts
    put single spikes into the residual, and a spike in the older window would fake a fast rate
    on a slow plateau (measured: a stop at 2.4e-3 for tol 1e-3 on a crescent). Only a residual
    that falls below the old window's typical level -- Anderson's final, fast phase -- counts.
    Infinite until two windows exist or while the residual is not shrinking.
    """
    w = window
    n = len(residuals)
    if n < 2 * w:
        return float("inf")
    recent = max(islice(residuals, n - w, n))  # (no slices: every robot runs this twice a round)
    before = residuals[-2 * w : -w]
    older = _median(before) if typical_older else max(before)
    if not older > 0:
        return 0.0 if recent == 0 else float("inf")
    rate = (recent / older) ** (1.0 / w)
    if rate >= 1.0:
        return float("inf")
    return recent / (1.0 - rate)


def settled(age: int) -> bool:
    """True when the last 2 RATE_WINDOW residuals all come from one stretch of the acceleration:
    ``age`` steps since the last restart (or re-arm), the first of which was computed from the
    state before it."""
    return age > 2 * RATE_WINDOW


def plain_stop_held(residuals: list[float], held: int, tol: float) -> int:
    """Rounds in a row the plain map's stop test has passed, after this round's residual: twice
    the edge form's estimate (window maxima) below tol; the fleet stops after STALL_HOLD of them.
    The hub's own estimate (median of the older window) stopped a 48-robot fleet on the plain map
    at 3.1e-3 for tol 1e-3; this one is the relay hub's rule, safe on the slow plain map (docs)."""
    return held + 1 if STALL_STOP_MARGIN * error_estimate(residuals) < tol else 0


def _median(xs: list[float]) -> float:
    """np.median's value (the two middle values' mean, (a + b) / 2, for an even count) without
    its ~50 us of overhead per call; NaN as np.median gives it. (Every robot runs it twice a
    round: a NaN anywhere makes the plain sum NaN, so a sum that is not NaN -- 0.15 us for the
    20 residuals, against 1.5 for the 20 comparisons -- clears them; a NaN sum, also of an inf
    and a -inf, is looked at entry by entry.)"""
    if math.isnan(sum(xs)) and not all(map(operator.eq, xs, xs)):  # a NaN (x != x; operator.eq has no identity shortcut)
        return float("nan")
    s, h = sorted(xs), len(xs) // 2
    return s[h] if len(xs) % 2 else (s[h - 1] + s[h]) / 2


def edge_penalty(params: ADMMParams, dim: int, my_degree: int, their_degree: int) -> np.ndarray:
    """The ADMM penalty of one edge, per variable of (x, gamma), the same at both ends.

    Dividing by the larger of the two degrees (Metropolis-style) keeps the value symmetric and a
    robot's total proximal weight sum_j rho_lj at most `rho`, whatever the graph; measured over
    3 to 16 robots and several topologies, the best `rho` then hardly moves (benchmarks/).
    The offset gamma has no curvature of its own in the objective, only the margins pin it: a
    stiffer consensus on it (`gamma_penalty` = 3) cut the rounds to 1e-3 by about a quarter over
    the benchmark's fleets (1 and 5 were both slower).
    """
    rho = np.full(dim, params.rho / max(my_degree, their_degree, 1))
    rho[-1] *= params.gamma_penalty
    return rho


def hub_penalty(params: ADMMParams, dim: int) -> np.ndarray:
    """The hub form's penalty per variable of (x, gamma): `rho`, as a robot's total proximal
    weight in the edge form, with the same stiffer consensus on gamma (measured: x0.5 and x1.5
    were slower over the benchmark's complete fleets)."""
    rho = np.full(dim, params.rho)
    rho[-1] *= params.gamma_penalty
    return rho


def complete_graph(n_robots: int, neighbours: tuple[int, ...], degrees: dict[int, int]) -> bool:
    """True when this robot and every neighbour are linked to all others: the graph is complete,
    and every robot of it reaches the same verdict from its own neighbour list and degrees."""
    return n_robots > 1 and len(neighbours) == n_robots - 1 and all(degrees.get(j, 0) == n_robots - 1 for j in neighbours)


def hub_form(params: ADMMParams, n_robots: int, neighbours: tuple[int, ...], degrees: dict[int, int]) -> bool:
    """True when a robot runs the accelerated hub form (a complete graph, Anderson on); its
    frames then carry [v; w], 2 (M + 1) floats (the fleet file's frame length follows)."""
    return params.anderson > 0 and complete_graph(n_robots, neighbours, degrees)


# -- the exact end-game ("polish") of the hub form ------------------------------------------------
#: the method of multipliers on the polish set (`polish_solve`): penalty and iteration cap (certified
#: solves took 7-19 iterations in benchmarks/polish.py; sets that are not the optimum's often do not
#: converge, and a cap of 30 instead of 100 left the rounds of 3-16-robot fleets unchanged). The
#: margin rows are scale-free (|phi| <= 1, last entry +-1), so one value serves every fleet
POLISH_RHO = 1e4
POLISH_ITERATIONS = 40
#: PDAS corrections per attempt before a fresh guess (benchmarks/polish.py: cap 5)
POLISH_CAP = 5
#: a robot's verdict: its multipliers > 0, |A_W v - 1| and its margins' violation within POLISH_EQ,
#: the copy's stationarity |P v - y| within POLISH_STAT x max(1, |P v|)
POLISH_EQ = 1e-9
POLISH_STAT = 1e-8
#: a local margin row is in the robot's guess when rows @ v <= 1 + POLISH_ACTIVE at its own iterate
POLISH_ACTIVE = 1e-7
_NONE = 1e300  # "no such row" in a verdict payload (finite: frames carry finite values)


#: issue 10's frame budget for admm: at most this many vectors of M + 1 floats (the relay hub's N <= 16)
FRAME_BUDGET = 16


def polish_max_dim() -> int:
    """The largest M + 1 whose hub frame with the polish payload, 2 d + d (d + 1) / 2 + d floats,
    stays within FRAME_BUDGET d: d <= 2 FRAME_BUDGET - 7 (25: grids of up to 24 points)."""
    return 2 * FRAME_BUDGET - 7


def polish_payload_size(dim: int) -> int:
    """Floats of the polish part of a hub frame: the upper triangle of A_W' A_W and A_W' 1 (the
    verdict rounds reuse its first three entries)."""
    return dim * (dim + 1) // 2 + dim


#: the guard's certificate is evaluated where it decides -- rounds whose rule passed, and the last
#: round of a capped run -- and every round with CERTIFY_EVERY_ROUND (benchmarks/stop_certificate.py
#: --check; the same stops: only the rounds that decide use it). A robot always sends its payload
CERTIFY_EVERY_ROUND = False

#: the guard asks bound <= certify x max(tol, CERTIFY_TOL_FLOOR): the bound is loose by a square root and
#: with piqp's local solves (1e-10) it floors at 3e-4..1.6e-3 where the inexact map stagnates (true error
#: 2e-9..1.3e-6; docs/algorithm.md), so a guard at certify x 1e-6 would never pass; below 1e-3 the rule's
#: own estimate decides the last digits and the guard refuses the far-off stops
CERTIFY_TOL_FLOOR = 1e-3


#: the guard's payload is computed and sent only in "armed" rounds, those whose next round's rule
#: can pass: `cert_armed`'s lower bound on the next round's estimate below CERTIFY_ARM x tol (> 1: a
#: margin for rounding), or the next round a capped run's last; other frames carry PAYLOAD zeros (the
#: same length), from which no certificate and so no stop follows. inf: every round (the guard's
#: first form, benchmarks/stop_certificate.py --check); 0: only a capped run's last round
CERTIFY_ARM = 2.0
_NO_PAYLOAD = np.zeros(cert_math.PAYLOAD)
_NO_PAYLOAD.flags.writeable = False


def cert_armed(residuals: list[float], tol: float, *, plain: bool, next_is_last: bool) -> bool:
    """True when a robot computes and sends its certificate payload for its next frame: there the
    rule may pass. The next round's estimate is the estimate of these residuals (the last
    2 RATE_WINDOW) shifted by one with the next residual appended, and it only grows with that
    residual, so the estimate with a residual of 0 is a lower bound on it: the rule cannot pass
    where this bound is >= tol (the plain map's rule: STALL_STOP_MARGIN x it; a mode switch between
    the rounds at worst moves the stop by a round). A pure function of the fleet residuals, which
    every copy holds alike (the same arming on every copy), computed in the round before."""
    if next_is_last or CERTIFY_ARM == math.inf:
        return True
    ahead = residuals[-(2 * RATE_WINDOW - 1) :] + [0.0]
    bound = STALL_STOP_MARGIN * error_estimate(ahead) if plain else error_estimate(ahead, typical_older=True)
    return bound < CERTIFY_ARM * tol


def certify_threshold(params: ADMMParams) -> float:
    """The certified bound a guarded stop needs (ADMMParams.certify > 0)."""
    return params.certify * max(params.tol, CERTIFY_TOL_FLOOR)


def certify_slot(params: ADMMParams) -> bool:
    """True when hub frames carry the certificate's payload (agents/certificate.py): the guard is
    on and neither end-game, which certifies its own stop, is."""
    return params.certify > 0 and not params.polish and not params.soft_polish


def hub_frame_dim(params: ADMMParams, dim: int) -> int:
    """A hub frame's length: [v; w], and the polish payload when the polish is on (the soft
    end-game's with `soft_polish`), or the certificate's PAYLOAD floats when the certified guard is on."""
    if params.soft_polish:
        from agents.soft_endgame import payload_size

        return 2 * dim + payload_size(dim)
    return 2 * dim + (polish_payload_size(dim) if params.polish else cert_math.PAYLOAD if certify_slot(params) else 0)


def polish_solve(H: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """min 1/2 |x|^2 s.t. H v = b (= {A_W v = 1} when consistent), by the method of multipliers:

        (P + rho H) v = y + rho b,   y <- y - rho (H v - b)        (y = A_W' lam at the end)

    Returns (v, y, the iterates v_1..v_k): a robot's own multipliers are lam_l = -rho sum_k
    (A_l v_k - 1), its own business. Deterministic on any machine (`_spd_factor`, `_dots`: every
    copy gets the same bits from the same sums; K = P + rho H is factored once)."""
    n = len(b)
    P = np.eye(n)
    P[-1, -1] = 0.0
    factor = _spd_factor(P + POLISH_RHO * H)
    y, v = np.zeros(n), np.zeros(n)
    iterates: list[np.ndarray] = []
    for _ in range(POLISH_ITERATIONS):
        v_new = _spd_solve(factor, y + POLISH_RHO * b)
        y = y - POLISH_RHO * (_dots(H, v_new) - b)
        iterates.append(v_new)
        moved = float(np.abs(v_new - v).max())
        v = v_new
        if moved <= 1e-11 * max(1.0, float(np.abs(v).max())):
            break
    return v, y, iterates


#: polish solves taken lately in this process, by the digest of the round's payloads (`_common_solve`
#: is a pure function of them, the same on every copy): computed once per process
_SHARED_POLISH: OrderedDict[bytes, tuple[Any, ...] | None] = OrderedDict()
_TRIU: dict[int, tuple[np.ndarray, np.ndarray]] = {}


def _triu(n: int) -> tuple[np.ndarray, np.ndarray]:
    """np.triu_indices(n), made once per size (the payload's layout of a symmetric matrix)."""
    if n not in _TRIU:
        _TRIU[n] = np.triu_indices(n)
    return _TRIU[n]


def _common_solve(payloads: np.ndarray, n: int) -> tuple[np.ndarray, bool, np.ndarray, int] | None:
    """What every copy computes alike from a sum round's payloads (a row per robot in id order):
    the exactly rounded sums H, b, the polished point v (`polish_solve`), whether it is stationary
    (|P v - y| <= POLISH_STAT max(1, |P v|), y = A_W' lam), and the sum and number of the iterates
    (each robot's multipliers follow from them). None when the sums are not finite or K = P + rho H
    is not positive definite (no row pins gamma). n: the dimension M + 1 (the payload is n(n+1)/2 + n)."""
    t = n * (n + 1) // 2
    sums = _pairwise_sum(payloads)
    if not np.all(np.isfinite(sums)):
        return None
    H = np.zeros((n, n))
    H[_triu(n)] = sums[:t]
    H = H + np.triu(H, 1).T
    try:
        v, y, iterates = polish_solve(H, sums[t:])
    except np.linalg.LinAlgError:
        return None
    pv = v.copy()
    pv[-1] = 0.0
    stationary = float(np.abs(pv - y).max()) <= POLISH_STAT * max(1.0, float(np.abs(pv).max()))
    return v, stationary, np.add.reduce(np.array(iterates), axis=0), len(iterates)


class _Endgame:
    """What both end-games beside the hub share (`_Polish`, agents/soft_endgame.py): the payload of this
    round's frame and the last round's, what the current round carries (`kind`), and the certified optimum
    once the fleet agreed on it (`result`)."""

    kind: str
    payload: np.ndarray
    prev_payload: np.ndarray | None
    result: np.ndarray | None
    attempts: int  # attempts begun (0: none ran)

    def _size(self) -> int:
        """Floats of the payload."""
        raise NotImplementedError

    def _next(self, payload: np.ndarray, kind: str) -> None:
        self.prev_payload, self.payload, self.kind = self.payload, payload, kind

    def stop(self) -> None:
        """No (more) attempts (a margin it does not certify, or a robot dropped): zeros from the next
        round's payload on. This round's frame keeps its payload: a drop comes after the frame went
        out, and a resent copy that differed from it would be rejected as equivocation (the survivors
        of a permanent loss then isolated each other)."""
        self.kind = "off"

    def step(self, payloads: np.ndarray, v_own: np.ndarray) -> np.ndarray | None:
        """Fold in the round's payloads (a row per robot in id order); the certified optimum once
        every robot's verdict was ok, else None (and the next payload is set)."""
        if self.kind in ("off", "done"):  # stopped: zeros from now on; done: the same payload again
            self._next(np.zeros(self._size()) if self.kind == "off" else self.payload, self.kind)
            return self.result
        return self._fold(payloads, v_own)

    def _fold(self, payloads: np.ndarray, v_own: np.ndarray) -> np.ndarray | None:
        """`step` while attempts run."""
        raise NotImplementedError


class _Polish(_Endgame):
    """One robot's part of the exact end-game on a complete graph (docs/algorithm.md, "An exact
    end-game (polish)").

    Attempts run beside the ADMM, in two-round steps, with a payload in every hub frame:
    a *sum* round carries robot l's A_W' A_W (upper triangle) and A_W' 1 over its polish rows W_l;
    every copy adds them in robot-id order, exactly rounded, and solves the equality QP
    (`polish_solve`); robot l checks its own rows -- multipliers > 0, rows in W_l at equality, every
    margin held -- and the next, *verdict* round carries [ok, its smallest multiplier, its most
    violated margin]. All ok: the polished point is the certified optimum, every copy holds it bit
    for bit, and the fleet stops. Otherwise a PDAS correction (the fleet's most negative
    multiplier leaves, or else its most violated row enters; its owner makes the change) and a sum
    round again; after POLISH_CAP corrections, or with no correction left, a fresh guess: each
    robot's locally active rows at its current iterate. Only sums of a robot's rows leave it, as
    in `--algorithm newton`; its multipliers never do."""

    def __init__(self, rows: np.ndarray, ids: tuple[int, ...], me: int) -> None:
        self.rows = rows
        self.ids = ids
        self.me = me
        self.dim = rows.shape[1]
        self.W = np.zeros(0, dtype=int)
        self.kind = "sum"  # what the frame of the current round carries
        self.corrections = 0
        self.payload = np.zeros(polish_payload_size(self.dim))
        self.prev_payload: np.ndarray | None = None
        self.v: np.ndarray | None = None  # the last solve's point (verdict rounds judge it)
        self.lam = np.zeros(0)
        self.result: np.ndarray | None = None  # the certified optimum, once the fleet agreed
        self.attempts = 0

    def guess(self, v_own: np.ndarray) -> None:
        """A fresh attempt: W_l = the rows at equality in the robot's own solve; a sum round next."""
        self.W = np.flatnonzero(self.rows @ v_own <= 1.0 + POLISH_ACTIVE)
        self.corrections = 0
        self.attempts += 1
        self._set_sums()

    def _set_sums(self) -> None:
        A = self.rows[self.W]
        n = self.dim
        out = np.zeros(polish_payload_size(n))
        out[: n * (n + 1) // 2] = (A.T @ A)[_triu(n)]
        out[n * (n + 1) // 2 :] = A.sum(axis=0)
        self._next(out, "sum")

    def _size(self) -> int:
        return polish_payload_size(self.dim)

    def _fold(self, payloads: np.ndarray, v_own: np.ndarray) -> np.ndarray | None:
        if self.kind == "sum":
            self._solve(payloads)
            return None
        ok = payloads[:, 0]
        if bool(np.all(ok == 1.0)):
            assert self.v is not None
            self.result = self.v
            self._next(np.zeros(polish_payload_size(self.dim)), "done")
            return self.result
        worst_lam, worst_slack = payloads[:, 1], payloads[:, 2]
        k = int(np.argmin(worst_lam))  # ties: the lowest id
        move = None
        if worst_lam[k] <= 0.0:
            move = ("drop", k)
        else:
            k = int(np.argmin(worst_slack))
            if worst_slack[k] < -1e-12:
                move = ("add", k)
        if move is None or self.corrections >= POLISH_CAP:
            self.guess(v_own)
            return None
        self.corrections += 1
        if self.ids[move[1]] == self.me and self.v is not None:
            if move[0] == "drop" and len(self.lam):
                self.W = np.delete(self.W, int(np.argmin(self.lam)))
            elif move[0] == "add":
                slack = self.rows @ self.v - 1.0
                slack[self.W] = np.inf
                self.W = np.union1d(self.W, [int(np.argmin(slack))])
        self._set_sums()
        return None

    def _solve(self, payloads: np.ndarray) -> None:
        """The sum round: the fleet's sums, the common solve, this robot's verdict payload."""
        n = self.dim
        common, _ = shared_step(_SHARED_POLISH, _digest(b"polish", np.ascontiguousarray(payloads)),
                                lambda: _common_solve(payloads, n), SHARED_STEPS_KEPT)
        if common is None:  # a bad payload (or no row pins gamma): no verdict, a fresh guess next
            self.v, self.lam = None, np.zeros(0)
            out = np.zeros(polish_payload_size(n))
            out[:3] = [0.0, _NONE, _NONE]  # not ok, and nothing to move
            self._next(out, "verdict")
            return
        v, stationary, xsum, k = common
        A = self.rows[self.W]
        lam = -POLISH_RHO * (A @ xsum - k)  # = -rho sum_k (A v_k - 1): this robot's multipliers
        slack = self.rows @ v - 1.0
        outside = np.delete(slack, self.W)
        ok = (stationary and (len(A) == 0 or (float(lam.min()) > 0.0 and float(np.abs(A @ v - 1.0).max()) <= POLISH_EQ))
              and float(slack.min()) >= -POLISH_EQ)
        self.v, self.lam = v, lam
        out = np.zeros(polish_payload_size(n))
        out[:3] = [1.0 if ok else 0.0, float(lam.min()) if len(A) else _NONE,
                   float(outside.min()) if len(outside) else _NONE]
        self._next(out, "verdict")

    def state(self) -> dict[str, Any]:
        return {"W": [int(i) for i in self.W], "kind": self.kind, "corrections": self.corrections,
                "payload": to_bytes(self.payload), "prev_payload": to_bytes(self.prev_payload),
                "v": to_bytes(self.v), "lam": to_bytes(self.lam), "result": to_bytes(self.result),
                "attempts": self.attempts}

    def load(self, state: dict[str, Any]) -> None:
        self.W = np.array(state["W"], dtype=int)
        self.kind, self.corrections, self.attempts = state["kind"], int(state["corrections"]), int(state["attempts"])
        self.payload, self.prev_payload = from_bytes(state["payload"]), from_bytes(state["prev_payload"])
        self.v, self.result = from_bytes(state["v"]), from_bytes(state["result"])
        lam = from_bytes(state["lam"])
        self.lam = lam if lam is not None else np.zeros(0)


class ConsensusADMM(RoundCore):
    """One robot's decentralized ADMM; drive it with receive / ready / advance."""

    algorithm = "admm"

    def __init__(
        self, share: RobotShare, params: ADMMParams, *, keep_trace: bool = True, hub_frames: bool = True
    ) -> None:
        robot_id = share.robot_id
        super().__init__(
            robot_id, share.neighbours, share.dim, diameter=params.diameter, round_cap=params.max_rounds,
            keep_trace=keep_trace,
        )
        self.params = params
        self._features = share.features
        self._labels = share.labels
        self._C = share.C
        self._n_robots = n_robots = share.n_robots
        degrees = share.degrees
        self._hub: _Hub | None = None
        self._edges: dict[int, _Edge] = {}
        if hub_form(params, n_robots, self.neighbours, degrees):
            self._hub = _Hub(tuple(sorted(self.neighbours + (robot_id,))), self.dim, hub_penalty(params, self.dim), params)
        else:
            self._edges = {
                j: _Edge(self.dim, robot_id < j, edge_penalty(params, self.dim, len(self.neighbours), degrees.get(j, 1)))
                for j in self.neighbours
            }
        self._prev_mean: np.ndarray | None = None
        self._step_q: tuple[np.ndarray | None, np.ndarray] = (None, np.zeros((0, 0)))  # (`_shared_step`)
        # the edge form learns who was dropped for good fleet-wide (agents/rounds.py): its stop flags must
        # reach across the survivors' graph, however wide it became (`_gone_changed`), and a soft margin
        # weighs |x|^2 by 1 / (robots left) (its answer depends on it; a hard margin's does not, so its
        # steps stay as they were). The hub form sees every drop itself. No list is sent before a loss
        self.floods_gone = self._hub is None
        self._qp = self._build_qp()
        self._residuals: list[float] = []  # the last 2 * RATE_WINDOW, for the error estimate
        self._held = 0  # hub form on the plain map: rounds in a row its stop test has passed
        self._cert_slot = False  # (known below, with the frame layout: round 0's step takes no guess)
        self._values = self._local_step()
        # hub form: frames carry [v; w] (see _Hub._map); without `hub_frames` (a frame layout with
        # no room for w) each copy computes every w itself -- exact only while the copies agree
        self._hub_frames = self._hub is not None and hub_frames
        # the exact end-game (params.polish, hard margin): its payload follows [v; w] in every frame
        self._polish: _Polish | SoftEndgame | None = None
        if self._hub_frames:
            self.frame_dim = hub_frame_dim(params, self.dim)
            if params.polish:
                self._polish = _Polish(self._qp._rows, self._hub.ids, robot_id)
                if self._C is None:
                    self._polish.guess(self._values)
                else:  # soft margins: the frame keeps its layout, the polish stays off
                    self._polish.stop()
            elif params.soft_polish:
                from agents.soft_endgame import SoftEndgame  # (it builds on this module's exact sums)

                off = self._C is None and not params.hard_endgame
                C = self._C if self._C is not None else math.inf  # hard margins: C = inf, B stays empty
                self._polish = SoftEndgame(self._qp, self._hub.ids, robot_id, 0.0 if off else C)
                if off:  # hard margins without hard_endgame: the frame keeps its layout, the end-game stays off
                    self._polish.stop()
                else:  # its guesses read the step's multipliers
                    self._qp.keep_multipliers = True
        # the certified guard (params.certify): a payload of PAYLOAD floats follows [v; w]; it decides
        # (beside the rule) on hard margins while no robot was dropped, else the rule alone
        self._cert_slot = self._hub_frames and certify_slot(params)
        self._cert_payload = np.zeros(cert_math.PAYLOAD)
        self._prev_cert_payload = np.zeros(cert_math.PAYLOAD)
        self._certificate: Certificate | None = None  # the last round's fleet certificate
        self._fleet_bound = math.inf  # its bound over the robots' values of that round
        if self._cert_slot:
            self._sides = cert_math.sides(self._qp._rows)
            self._pdiag = cert_math.step_diagonal(self._hub.penalty, n_robots)
        self._w: np.ndarray = self._values.copy()  # round 0: w = v (the start is z = mean v)
        self._prev_w: np.ndarray | None = None
        self._record()
        if not self.neighbours:  # alone: round 0 already solved the whole problem
            self.finished = True
            self.residual = 0.0

    def outgoing(self) -> StateUpdate:
        """v, and in the hub form w beside it: [v; w] (the function and result stay v). One
        message built (its checks run once), from fresh concatenations: no copies of v first."""
        if not self._hub_frames:
            return super().outgoing()
        prev = None if self._prev_values is None or self._prev_w is None else np.concatenate(
            [self._prev_values, self._prev_w, *self._extras(prev=True)])
        now = [self._values, self._w, *self._extras(prev=False)]
        return StateUpdate(sender=self.robot_id, round=self.round, values=np.concatenate(now),
                           flags=self._flags, prev_values=prev, prev_flags=self._prev_flags)

    def divergence(self) -> str | None:
        """`RoundCore.divergence` on v itself (the function: this core's `values` is a copy of it)."""
        return check_iterate(self._values)

    def _extras(self, *, prev: bool) -> list[np.ndarray]:
        """What a hub frame carries after [v; w]: the polish's payload or the certificate's (or nothing)."""
        if self._polish is not None:
            return [self._polish.prev_payload if prev else self._polish.payload]
        if self._cert_slot:
            return [self._prev_cert_payload if prev else self._cert_payload]
        return []

    @property
    def cert_active(self) -> bool:
        """True when the certified guard decides beside the rule: its slot in the frames, a hard
        margin, no robot dropped (the survivors' problem is not the one the dual bounds)."""
        return self._cert_slot and self._C is None and not self.dropped

    def error_bound(self) -> float | None:
        """A proven upper bound on this robot's function error against the exact optimum, from the
        last round's fleet certificate (agents/certificate.py); None where there is none."""
        return cert_math.reported_bound(self._certificate if self.cert_active else None, self._values)

    def endgame(self) -> str | None:
        """How the exact end-game beside the hub ended (`_Polish`, agents/soft_endgame.py), for the result
        row: "certified" -- the run ended on its certified optimum (every robot certified its own rows: the
        exact optimum itself, hence no `error_bound`) --, "not certified" -- attempts ran, but the ADMM's
        own rule or the round cap stopped first, or a drop stopped it --, None: no end-game ran (none
        beside this fleet, or off from the start)."""
        pol = self._polish
        if pol is None or pol.attempts == 0:
            return None
        return "certified" if pol.result is not None else "not certified"

    def result(self) -> dict[str, Any]:
        return {**super().result(), "error_bound": self.error_bound(), "endgame": self.endgame()}

    def status(self) -> dict[str, Any]:
        if self._hub is not None and self._hub.plain:
            return {**super().status(), "error_estimate": STALL_STOP_MARGIN * error_estimate(self._residuals)}
        if self._hub is not None:
            return {**super().status(), "error_estimate": self._hub_estimate()}
        return {**super().status(), "error_estimate": error_estimate(self._residuals)}

    def _hub_estimate(self) -> float:
        """The hub's error estimate (Anderson on): the rate is read only from residuals of one
        stretch of the acceleration (`settled`); inf before. An estimate whose older window ends
        before a restart compared two different extrapolations: castellated's soft phase (held-out 4)
        stopped at error 7.8e-3 for tol 1e-3 when a restart lowered the residual's level by 30 %."""
        hub = self._hub
        assert hub is not None
        if self.params.settled_rate and not settled(hub.age):
            return math.inf
        return error_estimate(self._residuals, typical_older=True)

    # -- one round ----------------------------------------------------------------------------
    def _step(self, mine: np.ndarray, theirs: dict[int, np.ndarray]) -> tuple[np.ndarray, bool]:
        if self._hub is not None:
            return self._hub_step(mine, theirs)
        p = self.params
        # round 0 holds each robot's own solution and no edge history: start z at the midpoint
        relax = p.relax if self.round > 0 else 1.0
        for j, edge in self._edges.items():
            low, high = (mine, theirs[j]) if self.robot_id < j else (theirs[j], mine)
            edge.update(low, high, relax)
        primal = relative_gap(mine, np.array(list(theirs.values()))) if theirs else 0.0
        dual = 0.0 if self._prev_values is None else relative_gap(mine, self._prev_values)
        self.residual = max(primal, dual)
        self._residuals = (self._residuals + [self.residual])[-2 * RATE_WINDOW :]
        below = error_estimate(self._residuals) < p.tol
        return self._primal_step(), below

    def _forget_edge(self, j: int) -> None:
        """Removing the edge with its dual keeps sum_l lambda = 0 over the remaining robots, so
        they converge to the solution of *their* data rather than a biased point (with a soft
        margin once every survivor weighs |x|^2 by 1 / (robots left): `_gone_changed`)."""
        if self._hub is not None:
            self._hub.drop(j)
            if self._polish is not None:  # the polish does not follow a drop: it stops for good
                self._polish.stop()
            if self._weight_matters():  # soft: the survivors' problem weighs |x|^2 by 1 / (robots left)
                self._qp = self._build_qp()
            return
        del self._edges[j]
        self._qp = self._build_qp()

    def _gone_changed(self) -> None:
        """Edge form: the fleet lost robots for good (`gone`): the stop flags reach across the
        survivors' graph, however wide it became; with a soft margin this robot's share of 1/2 |x|^2
        also becomes 1 / (robots left), so the survivors' fixed point is their own problem's (a hard
        margin's answer is the minimum-norm separator whatever the weight: its steps stay unchanged)."""
        if self._weight_matters():
            self._qp = self._build_qp()
        self._widen_stop(self._n_robots - len(self.gone))

    def _hub_step(self, mine: np.ndarray, theirs: dict[int, np.ndarray]) -> tuple[np.ndarray, bool]:
        """A complete graph: everyone's values are here, so run the fleet's accelerated hub ADMM."""
        hub = self._hub
        assert hub is not None
        me = self.robot_id
        # every robot's frame in id order as one (robots x frame) array: one concatenation instead
        # of slicing v and w out of each frame and joining each half (the rows hold the same numbers)
        pol = self._polish
        # (this robot's own frame as its parts, [v; w; payload]: one concatenation in all, not
        # its own first -- the same numbers in the same places)
        own = (mine,) if not self._hub_frames else (mine, self._w, *self._extras(prev=False))
        rows = np.concatenate([x for i in hub.ids for x in (own if i == me else (theirs[i],))]).reshape(
            len(hub.ids), -1)
        frames, certs = rows, None
        if pol is not None:  # the hub steps on [v; w] alone, the polish on the rest (views: the
            frames, payloads = rows[:, : 2 * self.dim], rows[:, 2 * self.dim :]  # arithmetic is elementwise)
        elif self._cert_slot:  # ... and the certificate on its payloads
            frames, certs = rows[:, : 2 * self.dim], rows[:, 2 * self.dim :]
        s_before, mean_before = hub.s, self._prev_mean  # (the step replaces them, never changes them in place)
        self._prev_mean, self.residual = self._shared_step(frames, rows)
        self._residuals = (self._residuals + [self.residual])[-2 * RATE_WINDOW :]
        if hub.plain:  # after the stall switch: the plain map's stop rule, safe on its slow modes
            self._held = plain_stop_held(self._residuals, self._held, self.params.tol)
            below = self._held >= STALL_HOLD
        else:
            self._held = 0
            below = self._hub_estimate() < self.params.tol
        if self.cert_active:  # the guard: the rule's stop also needs the certified bound
            self._fleet_bound = math.inf
            last = self.round + 1 >= self._round_cap  # (a capped run reports a bound too)
            if (below or last or CERTIFY_EVERY_ROUND) and s_before is not None and mean_before is not None:
                self._certify(frames, certs, s_before, mean_before, rows)  # only where it can decide: the rule passed
            below = below and self._fleet_bound <= certify_threshold(self.params)
        if self._cert_slot:  # (decided before the step: its solve keeps its multipliers only when armed)
            armed = self.cert_active and cert_armed(self._residuals, self.params.tol, plain=hub.plain,
                                                     next_is_last=self.round + 2 >= self._round_cap)
            self._qp.keep_multipliers = armed
        new = self._primal_step()
        if self._cert_slot:
            self._prev_cert_payload, self._cert_payload = (
                self._cert_payload, self._own_payload(new) if armed else _NO_PAYLOAD)
        if pol is not None:
            done = pol.step(payloads, new)
            if done is not None:  # certified by every robot: the exact optimum, the same bits everywhere
                new, below = done.copy(), True
        self._prev_w, self._w = self._w, hub.message(me, new)
        return new, below

    def _own_payload(self, v: np.ndarray) -> np.ndarray:
        """This robot's certificate payload for the frame of v (agents/certificate.py): its margins
        at the last mean, its step's multipliers' side sums and KKT residual |A' lam - grad| (x
        part; grad = P v + q as every copy computes it), its largest |phi|. Zeros where there is none."""
        hub, qp, mean = self._hub, self._qp, self._prev_mean
        lam = qp.multipliers
        if not self.cert_active or hub is None or hub.s is None or mean is None or lam is None:
            return np.zeros(cert_math.PAYLOAD)
        grad = self._pdiag * v + (-hub.penalty * hub.center(self.robot_id))  # (the step's q, as solved)
        return cert_math.robot_payload(qp._rows, self._sides, lam, grad, mean)

    def _shared_step(self, frames: np.ndarray, rows: np.ndarray | None = None) -> tuple[np.ndarray, float]:
        """The part of a hub round every copy computes alike -- the hub's step on the robots' v and
        w (a row [v; w] per robot in id order; rows of v alone: no w in the frames, each copy
        computes them), the mean of the v's and the residual -- taken once per process: a copy with
        the same token and inputs adopts the step already taken (`_SHARED_STEPS`). Returns (mean,
        residual). The helpers take the rows as arrays where they took lists of rows: each stacks
        them into a fresh contiguous array first, so the arithmetic and its order are unchanged.
        ``rows``: the whole frames (contiguous) of which ``frames`` may be the first columns (a
        view, no copy): the step's key digests them (payloads included: the same on every copy)."""
        hub = self._hub
        assert hub is not None
        prev = self._prev_mean
        d, with_w = self.dim, frames.shape[1] != self.dim
        # the step's key: the digest of the token, flags, prev and frames, as one stream -- but a copy
        # that adopts checks the frames by comparing them (shared_input_step): only the copy that
        # steps hashes them, for the new token every adopting copy takes (the same digest it would compute)
        inputs = frames if rows is None else rows
        keyed = hashlib.blake2b(digest_size=20)
        for part in (hub.token, b"w" if with_w else b"-", b"p" if prev is not None else b"-", b"" if prev is None else prev):
            keyed.update(part)
        key = keyed.copy().digest()

        def compute() -> tuple[Any, ...]:
            keyed.update(inputs)  # (the new token: the digest of the whole stream, frames included)
            token = keyed.digest()
            values = frames[:, :d]
            if not with_w:
                shares = values if hub.s is None else [hub.message(i, v) for i, v in zip(hub.ids, values)]
                synced = True
            else:
                ws = frames[:, d:]
                shares, synced = ws, hub.s is None or hub.synced(values, ws)
            if hub.s is None:
                hub.start(shares)
            else:
                hub.step(shares, synced)
            mean = hub._mean(values)
            # primal: the v's spread around their mean; dual: the mean's move since last round
            gaps = relative_gaps(mean, values if prev is None else np.concatenate([values, prev[None]]))
            primal = float(_max_reduce(gaps[: len(values)]))  # (np.max without its wrapper)
            dual = 0.0 if prev is None else float(gaps[-1])
            residual = max(primal, dual)
            hub.watch(residual)
            # every robot's step cost q_l = -penalty (z - u_l) at the new state, a row each: the
            # elementwise operations of `_primal_step`'s own, done once for the process
            st = hub.s
            qs = -hub.penalty * (st[:d] - st[d:].reshape(-1, d))
            qs.flags.writeable = False
            return (hub.snapshot(), mean, residual, (st, qs), token)

        done, adopted = shared_input_step(_SHARED_STEPS, key, inputs, compute, SHARED_STEPS_KEPT)
        if adopted:
            hub.adopt(done[0])
        hub.token = done[4]
        self._step_q = done[3]
        return done[1], done[2]

    def _certify(self, frames: np.ndarray, certs: np.ndarray, s: np.ndarray, mean: np.ndarray, rows: np.ndarray) -> None:
        """The fleet's certificate of this round (agents/certificate.py) from the frames' v and
        payloads (views of the whole frames ``rows``), the hub state s at which those v were
        computed and the mean of the round before (where the payloads' margins were taken); its
        bound over the frames' v. The same bits on every copy; computed once per process
        (`_SHARED_CERTS`, as the hub's step)."""
        d = self.dim
        values = frames[:, :d]

        def compute() -> tuple[Certificate | None, float]:
            grads = self._pdiag * values - self._hub.penalty * (s[:d] - s[d:].reshape(len(values), d))
            cert = fleet_certificate(certs, mean[:-1], _pairwise_sum(grads)[:-1])
            return cert, (math.inf if cert is None else cert.fleet_bound(values))

        key = _digest(b"cert", self._hub.token, s, mean, rows)
        (cert, bound), _ = shared_step(_SHARED_CERTS, key, compute, SHARED_STEPS_KEPT)
        self._fleet_bound = bound
        if cert is not None:  # (an older certificate stays a valid proof: P >= P* >= D held then)
            self._certificate = cert

    def _save_state(self) -> dict[str, Any]:
        return {
            "edges": {j: e.state() for j, e in self._edges.items()},
            "hub": None if self._hub is None else self._hub.state(),
            "prev_mean": to_bytes(self._prev_mean),
            "residuals": list(self._residuals),
            "held": self._held,
            "w": to_bytes(self._w),
            "prev_w": to_bytes(self._prev_w),
            **({} if self._polish is None else {"polish": self._polish.state()}),
            **({} if not self._cert_slot else {"cert": {
                "payload": to_bytes(self._cert_payload), "prev_payload": to_bytes(self._prev_cert_payload),
                "certificate": None if self._certificate is None else self._certificate.as_list(),
                "bound": self._fleet_bound}}),
        }

    def _load_state(self, state: dict[str, Any]) -> None:
        for j, edge_state in state["edges"].items():
            self._edges[int(j)].load(edge_state)
        if self._hub is not None:
            self._hub.load(state["hub"])
        self._prev_mean = from_bytes(state["prev_mean"])
        self._residuals = [float(r) for r in state["residuals"]]
        self._held = int(state.get("held", 0))
        self._w, self._prev_w = from_bytes(state["w"]), from_bytes(state["prev_w"])
        if self._polish is not None:
            self._polish.load(state["polish"])
        if self._cert_slot:
            cert = state["cert"]
            self._cert_payload, self._prev_cert_payload = from_bytes(cert["payload"]), from_bytes(cert["prev_payload"])
            c = cert["certificate"]
            self._certificate = None if c is None else Certificate.from_list([float(x) for x in c])
            self._fleet_bound = float(cert["bound"])

    # -- internals ----------------------------------------------------------------------------
    def _build_qp(self) -> MarginQP:
        return MarginQP(
            self._features,
            self._labels,
            # every robot its share of 1/2 |x|^2: of the fleet the hub still holds (a complete graph
            # knows who left; a soft margin's answer depends on it), else of the fleet it started with
            # less the robots it knows to be dropped for good with a soft margin (`_gone_changed`)
            x_weight=1.0 / (len(self._hub.ids) if self._hub is not None else self._n_robots - len(self._weighed_gone())),
            prox_weight=self._prox_weight(),
            C=self._C,
        )

    def _weighed_gone(self) -> tuple[int, ...]:
        """The drops the edge form's |x|^2 weight counts: `gone` with a soft margin; none with a hard
        one (its answer does not depend on the weight, and its steps stay those it took before)."""
        return self.gone if self._weight_matters() else ()

    def _weight_matters(self) -> bool:
        """True when the answer depends on each robot's weight of |x|^2 (1 / robots left): a soft
        margin; a hard margin's minimum-norm separator does not (agents/lsq_admm.py: always)."""
        return self._C is not None

    def _prox_weight(self) -> np.ndarray:
        if self._hub is not None:
            return self._hub.penalty
        return sum((e.rho for e in self._edges.values()), np.zeros(self.dim))

    def _local_step(self) -> np.ndarray:
        """Round 0: the robot's own max-margin solution, a warm start of the right magnitude."""
        self._qp.set_prox(np.zeros(self.dim))
        try:
            return self._primal_step()
        finally:
            self._qp.set_prox(self._prox_weight())

    def _primal_step(self) -> np.ndarray:
        hub = self._hub
        if hub is not None and hub.s is not None:  # (a hub has no edges)
            at, qs = self._step_q  # (the shared step's rows of q, kept for the state they were made at)
            q = qs[hub.ids.index(self.robot_id)] if at is hub.s else -hub.penalty * hub.center(self.robot_id)
            return self._qp.solve_v(q, guess=self._warm_guess())
        q = np.zeros(self.dim)
        for edge in self._edges.values():
            q += edge.sign * edge.lam - edge.rho * edge.z
        return self._qp.solve_v(q, guess=self._warm_guess())

    def _warm_guess(self) -> np.ndarray | None:
        """This robot's v for the step QP's exact warm-started solve where the certified guard decides
        (WARM_QP), else None: piqp answers."""
        return self._values if WARM_QP and self.cert_active else None
