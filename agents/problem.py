"""The SVM on the grid basis as quadratic programs solved with piqp.

Variables are v = (x, gamma) with x = K_G^{1/2} c (see kernel.py); soft margins add one slack
per data point. Hard margin (the paper):     min 1/2 |x|^2          s.t. theta_i (phi_i' x + gamma) >= 1
Soft margin (penalty C):                     min 1/2 |x|^2 + C sum xi  s.t. theta_i (phi_i' x + gamma) + xi_i >= 1, xi >= 0

Hard-margin ADMM steps with fewer margin rows than variables are solved exactly through their dual
by an active-set method (agents/qp_dual.py); everything else, and every step the dual does not
certify, by piqp.

piqp >= 0.7 writes inequalities as h_l <= G z <= h_u (older versions had G z <= h); every
constraint here is a lower bound with h_u = +inf.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

import numpy as np
import piqp

from agents.kernel import GridBasis
from agents.qp_dual import KKT_TOL, dual_hessian, solve_box_dual

INFEASIBLE_ADVICE = (
    "the hard-margin problem is infeasible: no function on this grid separates the data "
    "(the paper's Fig. 5). Use a finer grid (--grid), bounds that cover the data "
    "(--grid-bounds), a smaller --sigma, or a soft margin (--C 100)"
)


class InfeasibleError(ValueError):
    """The hard-margin problem has no solution on this grid."""


class SolverError(RuntimeError):
    """piqp failed for a reason other than infeasibility."""


def _settings(solver: piqp.DenseSolver) -> None:
    settings = solver.settings
    settings.verbose = False
    settings.eps_abs = 1e-10
    settings.eps_rel = 1e-10
    settings.max_iter = 500


def _new_solver() -> piqp.DenseSolver:
    solver = piqp.DenseSolver()
    _settings(solver)
    return solver


def _piqp_solve(solver: piqp.DenseSolver, qp: MarginQP, full_q: np.ndarray) -> np.ndarray:
    """Set ``solver`` up on ``qp`` with cost ``full_q`` (a full set-up: nothing of an earlier
    solve survives it) and solve; the solution as a fresh array, or the QP's errors. The margin
    rows' multipliers (piqp's z_l: G' z_l = P z + q) are kept in ``qp.multipliers``."""
    solver.setup(qp._P, full_q, None, None, qp._G, qp._h_l, qp._h_u, qp._x_l, qp._x_u)
    status = solver.solve()
    if status == piqp.PIQP_PRIMAL_INFEASIBLE:
        raise InfeasibleError(INFEASIBLE_ADVICE)
    if status != piqp.PIQP_SOLVED:
        raise SolverError(f"piqp returned {status}")
    qp.multipliers = np.array(solver.result.z_l, dtype=float) if qp.keep_multipliers else None
    return np.array(solver.result.x, dtype=float)


def margin_rows(features: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Rows of theta_i [phi_i', 1]: the margin constraints are rows @ v >= 1."""
    labels = np.asarray(labels, dtype=float)
    return labels[:, None] * np.hstack([features, np.ones((len(features), 1))])


@dataclass(frozen=True)
class QPSolution:
    """(x, gamma) and, for soft margins, the slacks."""

    x: np.ndarray
    gamma: float
    slack: np.ndarray
    status: str


class MarginQP:
    """One quadratic program over v = (x, gamma[, xi]) with the margin constraints of some data.

    Every solve sets piqp up afresh: a round must be a pure function of its inputs so that a
    robot restored from a checkpoint continues bit for bit. `setup` resets piqp's whole state (the
    same bits as a new solver whatever it solved before: checked on every solve of the paper
    preset, a 16-robot ring and the default run, in run order, shuffled, and with one solver for
    all; tests/test_problem.py), so the solver object and its settings are made once per QP and
    only `setup` + `solve` run per round. piqp's `update(c=...)` is NOT used: it rescales the new
    cost in another order than `setup` and moves the last bits of ~98 % of the solutions.
    Hard-margin steps with fewer rows than variables go through the exact active-set dual instead
    (agents/qp_dual.py: always started at lam = 0, so it is pure as well), piqp answering
    whenever that does not certify its point.
    """

    def __init__(
        self,
        features: np.ndarray,
        labels: np.ndarray,
        *,
        x_weight: float,
        prox_weight: float | np.ndarray,
        C: float | None,
    ) -> None:
        self.dim = features.shape[1] + 1
        rows = margin_rows(features, labels)
        n = len(rows)
        self.soft = C is not None
        self.n_slack = n if self.soft else 0
        size = self.dim + self.n_slack
        self._x_weight = x_weight
        self._size = size
        self._rows = rows
        self._upper = float(C) if self.soft else np.inf
        self._set_weights(prox_weight)
        self._q_slack = np.full(self.n_slack, float(C) if self.soft else 0.0)
        G = np.hstack([rows, np.eye(n)]) if self.soft else rows
        self._G = np.asfortranarray(G)
        self._h_l = np.ones(n)
        self._h_u = np.full(n, np.inf)
        self._x_l = self._x_u = None
        if self.soft:
            self._x_l = np.concatenate([np.full(self.dim, -np.inf), np.zeros(n)])
            self._x_u = np.full(size, np.inf)
        # piqp's solver, made (and its settings set) on the first piqp solve and set up afresh on
        # every one; the lock only guards against two threads sharing one QP (a QP belongs to one
        # core, which one thread drives): a second caller gets a solver of its own
        self._solver: piqp.DenseSolver | None = None
        self._solver_lock = threading.Lock()
        #: the last solve's margin multipliers lam >= 0 (A' lam = P v + q up to the solver's
        #: residual): what the certified stop's dual is built from (agents/certificate.py)
        self.multipliers: np.ndarray | None = None
        #: kept only when asked (the hub core asks in its guard's armed rounds): piqp's solves skip
        #: the copy otherwise
        self.keep_multipliers = False

    def _set_weights(self, prox: float | np.ndarray) -> None:
        """P = x_weight on x, plus a proximal weight per variable of (x, gamma) (a scalar for all),
        and with it the dual's diagonal and Hessian where the exact dual answers (below)."""
        p_diag = np.zeros(self._size)
        p_diag[: self.dim] = prox
        p_diag[: self.dim - 1] += self._x_weight
        d = p_diag[: self.dim].copy()
        # The exact active-set dual (agents/qp_dual.py) answers the HARD-margin steps where it is the
        # smaller problem: every variable weighted (gamma's prox > 0: ADMM steps, not own solves) and
        # fewer margin rows n than variables dim, so H = A D^-1 A' has full rank. Measured per solve
        # on the default run's hard phase (dim 142, n 16-20): ~6-10x cheaper than piqp; the paper
        # preset's steps (n 20 >= dim 16) stay on piqp, ~3x cheaper there than this numpy loop.
        # Soft margins stay on piqp too: the dual solves them exactly (tests/test_qp_dual.py) but
        # moved the chaotic Anderson sweep (default run 357 -> 424 rounds, a sweep task's hinge
        # 8.7e-5 apart between data and data x1000: tests/test_autogrid.py::test_sigma_sweep_is_scale_free).
        weighted = not self.soft and bool(np.all(d > 0))
        self._d = d if weighted and len(self._rows) < self.dim else None
        self._hessian = dual_hessian(self._rows, d) if self._d is not None else None
        # The other hard-margin steps (n >= dim: the paper preset's 20 rows on 16 variables) try the
        # exact KKT solve on the active set of a guess first (`_warm_solve`); piqp when it fails
        self._warm = _WarmKKT(self._rows, d) if weighted and self._d is None else None
        self._P = np.asfortranarray(np.diag(p_diag))

    def set_prox(self, prox: float | np.ndarray) -> None:
        """Change the proximal weights (e.g. 0 for a robot's own solve); the constraints stay."""
        self._set_weights(prox)

    def solve(self, q: np.ndarray, guess: np.ndarray | None = None) -> QPSolution:
        """Minimise 1/2 v' P v + q' v over the margin constraints; q has length dim.

        With every variable weighted the exact active-set dual answers (agents/qp_dual.py), or
        with n >= dim the exact solve on the active rows of ``guess`` (a v whose tight margins are
        the guess: the caller's previous solution, so that the answer stays a pure function of the
        caller's state); piqp answers when neither certifies its point, and for a weightless gamma.
        """
        z, by_dual = self._solve_z(np.asarray(q, dtype=float), guess)
        if not by_dual:
            return self._solution(z)
        slack = np.maximum(0.0, 1.0 - self._rows @ z) if self.soft else np.zeros(0)
        return QPSolution(x=z[:-1].copy(), gamma=float(z[-1]), slack=slack, status="solved")

    def solve_v(self, q: np.ndarray, guess: np.ndarray | None = None) -> np.ndarray:
        """`solve`'s v = (x, gamma) as one fresh vector (the same bits as
        ``np.append(sol.x, sol.gamma)``), without the QPSolution's copies: an ADMM round's call."""
        z, by_dual = self._solve_z(np.asarray(q, dtype=float), guess)
        return z if by_dual or not self.soft else z[: self.dim].copy()

    def _solve_z(self, q: np.ndarray, guess: np.ndarray | None = None) -> tuple[np.ndarray, bool]:
        """(z, True): v = (x, gamma) from the exact dual or the guess's active set when it certifies
        its point (a fresh array); else (z, False): piqp's (x, gamma[, xi])."""
        if self._hessian is not None:
            exact = solve_box_dual(self._rows, self._d, self._hessian, q, self._upper)
            if exact is not None:
                self.multipliers = exact[1] if self.keep_multipliers else None
                return exact[0], True
        elif guess is not None and self._warm is not None:
            v = self._warm.solve(q, guess)
            if v is not None:
                self.multipliers = self._warm.multipliers() if self.keep_multipliers else None
                return v, True
        return self._piqp(q), False

    def solve_piqp(self, q: np.ndarray) -> QPSolution:
        """The same QP by piqp's interior point (to 1e-10): the fallback, and the reference in tests."""
        return self._solution(self._piqp(np.asarray(q, dtype=float)))

    def _solution(self, z: np.ndarray) -> QPSolution:
        """piqp's z = (x, gamma[, xi]) as a QPSolution."""
        return QPSolution(
            x=z[: self.dim - 1].copy(),
            gamma=float(z[self.dim - 1]),
            slack=z[self.dim :].copy(),
            status="solved",
        )

    def _piqp(self, q: np.ndarray) -> np.ndarray:
        """piqp's solution z = (x, gamma[, xi]) as a fresh array (piqp's own result is a view of
        the solver's memory, overwritten by its next solve)."""
        full_q = np.concatenate([q, self._q_slack]) if self.soft else q
        lock = self._solver_lock
        if not lock.acquire(blocking=False):  # another thread is in this QP: a solver of its own
            return _piqp_solve(_new_solver(), self, full_q)
        try:
            solver = self._solver
            if solver is None:
                solver = self._solver = _new_solver()
            return _piqp_solve(solver, self, full_q)
        finally:
            lock.release()


#: a guess's margin counts as active when within this of tight (piqp's answers: ~1e-10)
WARM_ACTIVE = 1e-7
#: primal-dual active-set corrections of the guess before piqp answers
WARM_TRIES = 3


#: active sets whose sub-systems a `_WarmKKT` keeps (a robot's W moves among a few sets near the end)
WARM_SUBSETS = 16

_min = np.minimum.reduce  # (np.min without its Python wrapper)
_nonnegative = (0.0).__le__  # x >= 0.0 (False for a NaN)
#: the LAPACK gesv gufunc np.linalg.solve calls for a vector right-hand side (its wrapper's type
#: checks and error-state set-up cost ~2 us more than the solve on the <= 16 rows here; the same
#: routine, the same bits: tests/test_problem.py compares the two)
try:  # numpy's private module: where a numpy lacks it, the public wrapper (same routine, ~2 us slower)
    from numpy.linalg import _umath_linalg

    _gesv = _umath_linalg.solve1
except (ImportError, AttributeError):  # pragma: no cover - depends on the numpy installed
    def _gesv(a: np.ndarray, b: np.ndarray, signature: str = "dd->d") -> np.ndarray:
        return np.linalg.solve(a, b)


class _WarmKKT:
    """The hard-margin step QP's exact optimum from the active set of a guess (`solve`).

    Why: piqp's interior point costs ~70 us per solve on the paper preset's 16 variables and 20
    rows, every round, per robot; between ADMM rounds the active margins rarely change, so the KKT
    system on the guess's tight rows W (the dual's H_WW lam = b_W, H = A D^-1 A', b = 1 + A D^-1 q:
    one LAPACK solve of <= dim rows) mostly gives the optimum at once -- certified like the exact
    dual (agents/qp_dual.py): lam >= 0, every margin within KKT_TOL of held and W's tight
    (stationarity holds by construction). Otherwise up to WARM_TRIES primal-dual active-set
    corrections (drop the most negative multiplier, or add the most violated margin), then None
    and the caller asks piqp. W is a pure function of the guess (its margins within WARM_ACTIVE of
    tight): a robot resumed from its checkpoint solves alike. Written for numpy's per-call cost.
    """

    def __init__(self, rows: np.ndarray, d: np.ndarray) -> None:
        self.rows = rows
        self.d = d
        self.rows_d = rows / d  # A D^-1
        self.hessian = dual_hessian(rows, d)
        # the last answer and its margins A v (as Python floats): the next round's guess is that
        # answer (identity), so its margins need not be computed again (the same product, the same bits)
        self._last: tuple[np.ndarray, list[float]] | None = None
        self._lam: tuple[list[int], np.ndarray] = ([], np.zeros(0))  # (W, lam_W)
        # per active set W (its indices): A_W D^-1 and H_WW, the same rows `take` gives every time,
        # |W| ones, and whether W's solve ran once without a NaN (W rarely changes between rounds; at most
        # WARM_SUBSETS kept, the oldest dropped)
        self._subs: dict[tuple[int, ...], tuple[np.ndarray, np.ndarray, np.ndarray, bool]] = {}

    def multipliers(self) -> np.ndarray:
        """The last certified solve's multipliers, one per row (zero off its set W)."""
        lam = np.zeros(len(self.rows))
        lam[self._lam[0]] = self._lam[1]
        return lam

    def solve(self, q: np.ndarray, guess: np.ndarray) -> np.ndarray | None:
        # The tests on the margins and multipliers run on Python floats (`tolist`, then comparisons):
        # the same IEEE comparisons as numpy's (a NaN compares False in both), no arithmetic, so the
        # same decisions (tests/test_qp_dual.py::test_warm_solve_decides_as_numpys_reductions_did) with
        # 6 small numpy calls fewer a solve (compare, nonzero, 3 reduces, take: ~1 us each, more when
        # cold between the hub's steps) for 2 `tolist`s (0.1-0.3 us). The products and the LU solve
        # are numpy's, as before.
        rows = self.rows
        last = self._last
        margins = last[1] if last is not None and last[0] is guess else (rows @ guess).tolist()
        # W: the rows within WARM_ACTIVE of tight, ascending (as `(margins <= 1 + WARM_ACTIVE).nonzero()`)
        limit = 1.0 + WARM_ACTIVE
        free = [i for i, m in enumerate(margins) if m <= limit]
        q_d = q / self.d  # (D^-1 q: the same bits wherever the loop below needs it)
        held, tight = 1.0 - KKT_TOL, 1.0 + KKT_TOL
        for _ in range(WARM_TRIES + 1):
            if free:
                key = tuple(free)
                a_wd, h_ww, ones, clean = self._subs.get(key) or self._sub(free, key)
                b_w = a_wd @ q
                b_w += ones  # (+ 1.0 elementwise: an array operand skips the scalar's conversion, ~0.3 us)
                # numpy's LU (not scipy's dposv: importing scipy.linalg costs a robot ~0.15 s), the gufunc
                # of np.linalg.solve without its wrapper; a singular H_WW (W's rows dependent) gives NaN.
                # Its floating-point flags are silenced (as np.linalg.solve does) until this W has been
                # solved once without a NaN: the LU of a W depends on W alone, so from then on only an
                # overflow of b_w's solve could raise one (a warning then, the same answer)
                if clean:
                    lam_f = _gesv(h_ww, b_w, signature="dd->d")
                else:
                    with np.errstate(all="ignore"):
                        lam_f = _gesv(h_ww, b_w, signature="dd->d")
                negative = not all(map(_nonnegative, lam_f.tolist()))  # a multiplier < 0 or NaN (rare)
                if negative and math.isnan(_min(lam_f)):  # a NaN (minimum propagates it): singular, give up
                    return None
                if not clean:  # W solved without a NaN
                    self._subs[key] = (a_wd, h_ww, ones, True)
                if negative:
                    del free[int(lam_f.argmin())]  # the most negative multiplier leaves
                    continue
                v = a_wd.T @ lam_f  # D^-1 (A_W' lam - q)
                v -= q_d
            else:
                v = -q_d
            g = rows @ v
            margins = g.tolist()
            if all(map(held.__le__, margins)):  # every margin held; W's tight (else: ill-conditioned)
                # (W's margins are among those just held: only their upper side is left to check)
                if free and not all(map(tight.__ge__, map(margins.__getitem__, free))):
                    return None
                self._last = (v, margins)
                self._lam = (free, lam_f) if free else (free, np.zeros(0))
                return v
            worst = int(g.argmin())  # the most violated margin joins (ascending, as np.union1d)
            if worst not in free:
                free = sorted([*free, worst])
        return None

    def _sub(self, free: list[int], key: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
        """(A_W D^-1, H_WW, ones, solved once without a NaN) for a new active set ``free`` (``key``:
        its tuple), kept per set: copies of the same rows (`solve` looks a kept set up itself)."""
        if len(self._subs) >= WARM_SUBSETS:
            del self._subs[next(iter(self._subs))]
        sub = self._subs[key] = (
            self.rows_d.take(free, 0), self.hessian.take(free, 0).take(free, 1), np.ones(len(free)), False,
        )
        return sub


@dataclass(frozen=True)
class CentralSolution:
    """The reference every robot is measured against."""

    c: np.ndarray
    x: np.ndarray
    gamma: float
    status: str  # "solved" | "infeasible"
    message: str = ""
    #: True when the optimum is certified by its KKT conditions (hard margin: the active-set
    #: system solved directly, every multiplier positive, every margin held), not just piqp's tolerance
    certified: bool = False

    @property
    def solved(self) -> bool:
        return self.status == "solved"


def solve_central(
    basis: GridBasis, points: np.ndarray, labels: np.ndarray, C: float | None = None
) -> CentralSolution:
    """All data in one QP: the solution the decentralized fleet must reach."""
    features = basis.features(points)
    # P is only positive semi-definite (gamma is free of cost); piqp's proximal interior
    # point handles that directly.
    qp = MarginQP(features, labels, x_weight=1.0, prox_weight=0.0, C=C)
    try:
        sol = qp.solve(np.zeros(qp.dim))
    except InfeasibleError as exc:
        m = basis.size
        return CentralSolution(np.full(m, np.nan), np.full(m, np.nan), float("nan"), "infeasible", str(exc))
    v = np.append(sol.x, sol.gamma)
    exact = None if C is not None else certify_hard_margin(margin_rows(features, labels), v)
    if exact is not None:
        v = exact
    return CentralSolution(basis.c_from_x(v[:-1]), v[:-1], float(v[-1]), "solved", certified=exact is not None)


def certify_hard_margin(rows: np.ndarray, guess: np.ndarray, active_tol: float = 1e-6) -> np.ndarray | None:
    """The hard-margin optimum from the KKT system on the constraints active at `guess`, or None.

    piqp stops at its tolerance; on ill-conditioned grids that is measurably off the optimum
    (1.6e-5 in function error on a 4-robot ring). Solving P v = A_act' lam, A_act v = 1 directly
    and checking lam > 0 and rows v >= 1 certifies the exact optimum (strict convexity in x and the
    active margins pin gamma); None when the check fails (degenerate active set), and the caller
    keeps the solver's point.
    """
    active = rows[rows @ guess - 1.0 < active_tol]
    n, k = len(guess), len(active)
    if k == 0:
        return None
    p = np.eye(n)
    p[-1, -1] = 0.0
    kkt = np.block([[p, -active.T], [active, np.zeros((k, k))]])
    rhs = np.concatenate([np.zeros(n), np.ones(k)])
    sol = np.linalg.lstsq(kkt, rhs, rcond=None)[0]
    v, lam = sol[:n], sol[n:]
    residual = float(np.abs(kkt @ sol - rhs).max())
    if residual < 1e-10 and lam.min() > 0 and (rows @ v).min() > 1.0 - 1e-12:
        return v
    return None
