"""The ADMM step's QP solved exactly through its box-constrained dual by an active-set method.

Why: every ADMM round solves, per robot, min 1/2 v' D v + q' v  s.t.  A v >= 1 (hard margin) or
with slacks of cost C (soft), D DIAGONAL and positive (x_weight + prox on x, prox on gamma). piqp's
interior point grows with dim (1.7-2.9 ms per solve at dim 142 in the default run's hard phase, under
load); this method costs ~7 numpy-level steps whatever dim is (0.3 ms there, 6-10x less), but more
than piqp on the paper preset's 16 variables. MarginQP (agents/problem.py) therefore uses it for
hard-margin steps with fewer rows than variables only (benchmarks/results/round_cost.md). Through the dual
(multipliers lam, one per row of A; v = D^-1 (A' lam - q)) it is

    min 1/2 lam' H lam - b' lam    s.t.  0 <= lam (<= C soft),   H = A D^-1 A',  b = 1 + A D^-1 q

whose gradient g = H lam - b = A v - 1 is the margin excess of each row. The method below is the
dual form of Goldfarb & Idnani (1983): start at lam = 0 (the unconstrained minimiser), add the most
violated margin, move along the direction that keeps the free multipliers' margins tight, and drop a
free multiplier that reaches a bound on the way. H may be singular (more rows than dim); the free
set's block is kept positive definite, a zero-curvature direction is followed to its blocking bound.

It always starts the same way, so a solve is a pure function of its inputs (checkpoint resume bit for
bit). The end point is re-solved on its free set and certified by the KKT conditions (multipliers in
their box, every margin's sign, stationarity by construction); whenever that fails (degenerate or
singular free sets, cycling, an unbounded dual = infeasible hard margin) it returns None and the
caller falls back to piqp, so the answer is always the QP's optimum.
"""

from __future__ import annotations

import math

import numpy as np

#: margins within this of tight count as tight (unitless: g is A v - 1)
KKT_TOL = 1e-9
#: a margin must be violated by more than this to enter (keeps round-off from cycling)
ENTER_TOL = 1e-12
#: Schur complement below this fraction of H_jj: the entering row depends on the free ones
SINGULAR_TOL = 1e-10


def dual_hessian(rows: np.ndarray, d: np.ndarray) -> np.ndarray:
    """H = A D^-1 A' for the margin rows A and the positive diagonal d (computed once per D)."""
    scaled = rows / np.sqrt(d)
    return scaled @ scaled.T


def solve_box_dual(
    rows: np.ndarray, d: np.ndarray, hessian: np.ndarray, q: np.ndarray, upper: float
) -> tuple[np.ndarray, np.ndarray] | None:
    """(v, lam) at the exact optimum, or None when the active-set method cannot certify it.

    rows: A (n x dim); d: D's positive diagonal; hessian: dual_hessian(rows, d); q: linear term (dim);
    upper: C for a soft margin, np.inf for a hard one. The free block's inverse is carried by
    bordering / deletion updates (the steps only need directions); the end point is re-solved exactly.
    Written for numpy's per-call overhead (n is 15-40): preallocated buffers, few calls per step.
    """
    n = rows.shape[0]
    qd = q / d
    b = rows @ qd
    b += 1.0
    lam = np.zeros(n)
    if n == 0:
        return -qd, lam
    soft = upper < math.inf
    order = np.zeros(n, dtype=np.intp)  # order[:k]: the free multipliers, in the order they entered
    k = 0
    inv_buf = np.empty((n, n))  # inv_buf[:k, :k]: the inverse of the free block of H
    # sign of an admissible move per multiplier: -1 at the lower bound, +1 at the upper, 0 when free
    side = np.full(n, -1.0)
    entering, sigma, g_j = -1, 0.0, 0.0
    for _ in range(6 * n + 20):
        if entering < 0:
            g = hessian @ lam
            g -= b
            score = g * side  # > 0: the bound is violated (first index on ties: pure)
            entering = int(score.argmax())
            if score[entering] <= ENTER_TOL:
                return _certify(rows, d, hessian, b, qd, order[:k], side, upper)
            sigma = -float(side[entering])
            g_j = float(g[entering])
        j = entering
        h_jj = float(hessian[j, j])
        fidx = order[:k]
        if k:
            inv = inv_buf[:k, :k]
            h = hessian[j][fidx]
            w = inv @ h
            schur = h_jj - float(h @ w)
            direction = w * -sigma
            lam_f = lam[fidx]
        else:
            schur = h_jj
        # full step to the minimum along the direction (g_j -> 0), unless the curvature is zero
        step = -sigma * g_j / schur if schur > SINGULAR_TOL * h_jj else math.inf
        kind, blocking, going_up = 0, -1, False  # kind 0: j joins the free set, 1: j hits its box, 2: a drop
        own = upper - float(lam[j]) if sigma > 0 else float(lam[j])  # j's opposite bound (soft margin)
        if own < step:
            step, kind = own, 1
        if k:
            for pos, (li, di) in enumerate(zip(lam_f.tolist(), direction.tolist())):
                if di < 0.0:
                    t = -li / di
                    if t < step:
                        step, kind, blocking, going_up = t, 2, pos, False
                elif soft and di > 0.0:
                    t = (upper - li) / di
                    if t < step:
                        step, kind, blocking, going_up = t, 2, pos, True
        if step == math.inf:
            return None  # unbounded dual: the hard margin is infeasible; piqp says so
        if k:
            lam[fidx] = lam_f + step * direction
        lam[j] += sigma * step
        if kind == 0:  # j joins the free set: border the inverse
            if k:
                ws = w / schur
                inv += w[:, None] * ws
                inv_buf[:k, k] = -ws
                inv_buf[k, :k] = -ws
            inv_buf[k, k] = 1.0 / schur
            order[k] = j
            k += 1
            side[j] = 0.0
            entering = -1
        elif kind == 1:  # j crossed its box: fixed at the other bound
            lam[j] = upper if sigma > 0 else 0.0
            side[j] = 1.0 if sigma > 0 else -1.0
            entering = -1
        else:
            # a free multiplier reached its bound: it leaves (deleted from the inverse); j keeps
            # entering on the smaller set
            i = int(order[blocking])
            lam[i] = upper if going_up else 0.0
            side[i] = 1.0 if going_up else -1.0
            pivot = float(inv[blocking, blocking])
            col = np.delete(inv[:, blocking], blocking)
            shrunk = np.delete(np.delete(inv, blocking, 0), blocking, 1) - col[:, None] * (col / pivot)
            k -= 1
            inv_buf[:k, :k] = shrunk
            order[blocking:k] = order[blocking + 1 : k + 1].copy()
            g_j = float(hessian[j] @ lam - b[j])
    return None


def _certify(
    rows: np.ndarray,
    d: np.ndarray,
    hessian: np.ndarray,
    b: np.ndarray,
    qd: np.ndarray,
    free: np.ndarray,
    side: np.ndarray,
    upper: float,
) -> tuple[np.ndarray, np.ndarray] | None:
    """Re-solve the free multipliers exactly with the others at their bounds and check the KKT point."""
    high = side > 0
    any_high = bool(high.any())
    lam = np.where(high, upper, 0.0) if any_high else np.zeros(len(b))
    if len(free):
        free = np.sort(free)  # the re-solve depends on the set only, not on the path to it
        rhs = b[free]
        if any_high:
            rhs = rhs - hessian[free] @ lam
        # imported here, not at the top: scipy.linalg's import is ~0.15-0.2 s of every robot process's
        # and the launcher's start (agents.spec imports this module), and most runs never get here
        from scipy.linalg.lapack import dposv

        _, lam_f, info = dposv(hessian[free][:, free], rhs)
        if info != 0 or not np.isfinite(lam_f).all() or lam_f.min() < 0.0 or lam_f.max() > upper:
            return None
        lam[free] = lam_f
    v = rows.T @ lam
    v /= d
    v -= qd  # stationarity holds by construction
    g = rows @ v
    g -= 1.0
    # KKT: g >= 0 at the lower bound, g <= 0 at the upper, g = 0 where free (complementarity)
    worst = float((g * side).max())
    if len(free):
        worst = max(worst, float(np.abs(g[free]).max()))
    if worst > KKT_TOL:
        return None
    return v, lam
