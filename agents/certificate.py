"""A certified bound on the hub form's function error, from the KKT residual (pure: no I/O, no clock).

Why: the hub's stop rule (r / (1 - rate), agents/admm.py) is a heuristic that Anderson plateaus fool
(docs/algorithm.md, "A certified stop"); this bound is *proven* >= the function error of any point
against the exact optimum, and every copy of the hub computes it from its frames alike, so it can
guard the rule's stop (ADMMParams.certify).

Hard margin, rows a_i = y_i [phi_i; 1], v = (x, gamma), x = K^{1/2} c (the rkhs norm is |x|),
f(v) = |x|^2 / 2, slack_i(v) = a_i' v - 1; the optimum v* has multipliers lam* >= 0 with
(x*, 0) = A' lam* and lam*' slack(v*) = 0.

* Primal point. At a point x_bar every copy holds, m+ = min of phi_i' x_bar over the positive rows,
  m- = max over the negative rows (each robot sends its own two: a min/max over robots). If m+ > m-,
  v0 = s (x_bar, g), g = -(m+ + m-)/2, s = 2/(m+ - m-), holds every margin, with a tight row on each side.
* Multipliers. Robot l's multipliers lam_l >= 0 of its own step QP satisfy A_l' lam_l = grad_l + r_l
  (grad_l = P_l v_l + q_l, r_l the solver's residual, robot-local): the fleet's u = A' lam has x part
  W + r (W the x part of sum_l grad_l, which every hub copy computes from the frames; |r| <= sum_l |r_l|)
  and gamma part dS = S+ - S- exactly (the per-side sums of lam; the gamma column of a row is y).
* Monotonicity (branch certtight). With g = grad f(v0) - u = (x0 - W - r, -dS) and
  c = lam' slack(v0) = u' v0 - S (S = S+ + S-):
      <g, v0 - v*> = |x0 - x*|^2 + lam*' slack(v0) + lam' slack(v*) - c,
  and both middle terms are >= 0 (v0 and v* feasible, lam and lam* >= 0), so with delta = |x0 - x*|
      delta^2 <= |g_x| delta + |dS| |g0 - gamma*| + c.
  Gamma's interval from the multipliers' per-side means: a positive row i holds at v*, so
  gamma* - g0 >= -slack_i(v0) - phi_i' (x* - x0); averaged with weights lam_i / S+,
  gamma* - g0 >= -c / S+ - (u+ / S+)' (x* - x0), u+ = sum of lam_i phi_i over the positive rows; likewise
  gamma* - g0 <= c / S- - (u- / S-)' (x* - x0) with u- = u+ - (W + r). With |u+| <= sum_l |u+_l| (each
  robot sends its own norm):
      |g0 - gamma*| <= slope delta + shift,  slope = max(|u+| / S+, (|u+| + |W| + |r|) / S-),  shift = c / min(S+, S-)
  (near the optimum 0.80-0.85 on the 8-ring against max|phi_i| = 0.9996 of the tight rows' interval
  before; far from it, where |W| / S- is large, it is worse, and a side without multipliers gives no
  certificate). Hence
      delta <= e = (beta + sqrt(beta^2 + 4 c')) / 2,  beta = |x0 - W| + sum_l |r_l| + slope |dS|,  c' = c + |dS| shift,
  c <= W' x0 + dS g0 - S + sum_l |r_l| |x0| (plus a rounding allowance), and |x*| >= |x0| - e. The
  multipliers scaled by any alpha >= 0 are multipliers too (c, dS and u scale with alpha, slope and
  shift do not): e is the smaller of alpha = 1 and alpha = W' x0 / |W|^2.
  Any point (x, gamma) then has function error at most
      (|x - x0| + e) / (|x0| - e)  +  (|gamma - g0| + g_half) / max(1, |g0| - g_half),  g_half = slope e + shift.
  Before (branch guard) the radius was sqrt(2 (P - D)) from strong convexity and a balanced "hub dual"
  D <= P*, and gamma's half-width e max|phi_i|: the gap's first-order part counted twice, the balancing
  term (1 - S_small/S_big) S_big phi_max dominated the dual's loss, and the gamma term (phi_max |x*| /
  |gamma*| = 5.3 x the x term on the 8-ring) dominated the bound; e is ~1.6-2x smaller at the same point
  (the 8-ring at round 596: radius 0.096 against 0.17; docs/algorithm.md).

Every reduction over robots is exactly rounded (math.fsum) or a min/max, in robot-id order, so
every copy gets the same bits from the same frames. A robot sends PAYLOAD floats beside [v; w]:
[m+_l, m-_l, S+_l, S-_l, |r_l|, |u+_l|] (|u+_l| in the slot of max_i |phi_i| before branch certtight); a
payload that is not finite, or has negative sums, makes the fleet's certificate absent (no stop by it),
never an error.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: floats of a robot's certificate payload in a hub frame
PAYLOAD = 6
#: "no row of this label" (finite: frames carry finite values)
NONE = 1e300


def sides(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The indices of a robot's positive and negative rows (rows = y [phi, 1]), made once."""
    pos = rows[:, -1] > 0
    return np.flatnonzero(pos), np.flatnonzero(~pos)


def margin_extremes(products: np.ndarray, side: tuple[np.ndarray, np.ndarray]) -> tuple[float, float]:
    """(m+_l, m-_l) of one robot: products = rows[:, :-1] @ x_bar (= y_i phi_i' x_bar; robot-local,
    so any deterministic product will do), side = `sides(rows)`. NONE / -NONE for a label the robot
    has no row of. (Plain floats: a min of 20 values costs less outside numpy.)"""
    p, n = products.take(side[0]).tolist(), products.take(side[1]).tolist()
    return (min(p) if p else NONE), (-min(n) if n else -NONE)


def payload(margins: tuple[float, float], side: tuple[np.ndarray, np.ndarray], lam: np.ndarray, residual: float,
            spread: float) -> np.ndarray:
    """A robot's PAYLOAD floats: its margins at the mean, its multipliers' per-side sums (side =
    `sides(rows)`), the norm of its KKT residual, `spread` = |sum of lam_i phi_i over its positive rows|
    (the gamma interval's slope, see the module). Zeros (no certificate) when anything is not finite."""
    out = [margins[0], margins[1], math.fsum(lam.take(side[0]).tolist()), math.fsum(lam.take(side[1]).tolist()),
           residual, spread]
    return np.array(out) if all(map(math.isfinite, out)) else np.zeros(PAYLOAD)


def step_diagonal(prox: np.ndarray, n_robots: int) -> np.ndarray:
    """The diagonal of a robot's step QP, as MarginQP builds it: the proximal weight per variable of
    (x, gamma) plus the objective's |x|^2 / (2 N) on x. grad_l = step_diagonal * v_l + q_l."""
    d = np.array(prox, dtype=float)
    d[:-1] += 1.0 / n_robots
    return d


def robot_payload(rows: np.ndarray, side: tuple[np.ndarray, np.ndarray], lam: np.ndarray, grad: np.ndarray,
                  mean: np.ndarray) -> np.ndarray:
    """A robot's PAYLOAD for its step: its multipliers lam (clipped at 0: any lam >= 0 gives a valid
    dual, so round-off below 0 goes), its KKT residual |A' lam - grad| on x, its margins at the point
    `mean` (which every copy holds), |u+_l| (its positive rows' lam_i phi_i summed). Robot-local
    products: plain BLAS; only the fleet's sums over robots must be exactly rounded."""
    lam = np.maximum(lam[: len(rows)], 0.0)
    resid = norm((lam @ rows - grad)[:-1])
    pos = side[0]
    spread = norm(lam.take(pos) @ rows.take(pos, axis=0)[:, :-1]) if len(pos) else 0.0
    return payload(margin_extremes(rows[:, :-1] @ mean[:-1], side), side, lam, resid, spread)


def norm(v: np.ndarray) -> float:
    """|v|, exactly rounded sum of squares (the same bits on every copy); inf where the squares or
    their sum overflow (an exploding iterate: no certificate, and no warning on the robot's stderr)."""
    with np.errstate(over="ignore", invalid="ignore"):
        squares = (v * v).tolist()
    try:
        return math.sqrt(math.fsum(squares))
    except OverflowError:  # fsum's intermediate overflow of finite squares
        return math.inf


#: relative allowance for the rounding of c's sum (its terms are exactly rounded products and sums: a
#: few units of 2^-53 each; far below any bound the guard could use)
ROUNDING = 1e-13


@dataclass(frozen=True)
class Certificate:
    """The fleet's certificate of one round: the feasible point v0 = s (x_bar, g), e0 >= |x0 - x*|
    and the two denominators; `bound` turns it into a proven bound on any point's function error."""

    center: np.ndarray  # v0 = s (x_bar, g)
    e0: float  # >= |x0 - x*| (the module's e)
    den_x: float  # |x0| - e0 <= |x*|
    den_g: float  # max(1, |g0| - g_half) <= max(1, |gamma*|)
    g_half: float  # >= |g0 - gamma*|

    def bound(self, v: np.ndarray) -> float:
        """A proven upper bound on the function error of v = (x, gamma) against the exact optimum
        (inf where it overflows)."""
        c = self.center
        with np.errstate(over="ignore", invalid="ignore"):
            dx = v[:-1] - c[:-1]
        return ((norm(dx) + self.e0) / self.den_x
                + (abs(float(v[-1]) - float(c[-1])) + self.g_half) / self.den_g)

    def fleet_bound(self, values: np.ndarray) -> float:
        """The largest `bound` over rows of values (a robot per row, id order)."""
        return max(self.bound(v) for v in values)

    def as_list(self) -> list[float]:
        """Checkpoint form (`from_list` inverts it)."""
        return [self.e0, self.den_x, self.den_g, self.g_half, *self.center.tolist()]

    @classmethod
    def from_list(cls, xs: list[float]) -> Certificate:
        return cls(np.array(xs[4:], dtype=float), float(xs[0]), float(xs[1]), float(xs[2]), float(xs[3]))


def fleet_certificate(payloads: np.ndarray, x_bar: np.ndarray, w_x: np.ndarray) -> Certificate | None:
    """The fleet's certificate from every robot's payload (a row per robot, id order), the
    point x_bar at which the margins were taken and w_x, the x part of sum_l grad_l; None where none
    exists (x_bar not separating, the radius e0 not below |x0|, a bad payload). Finite but huge numbers (a
    forged or garbled frame, an exploding iterate) overflow to no certificate, never to an error."""
    try:
        with np.errstate(over="ignore", invalid="ignore"):
            return _fleet_certificate(payloads, x_bar, w_x)
    except (OverflowError, ZeroDivisionError):  # float ** and fsum raise where numpy would give inf
        return None


def _fleet_certificate(payloads: np.ndarray, x_bar: np.ndarray, w_x: np.ndarray) -> Certificate | None:
    p = np.asarray(payloads, dtype=float)
    if p.ndim != 2 or p.shape[1] != PAYLOAD or not len(p):
        return None
    cols = list(zip(*p.tolist()))  # (plain floats: these few scalars cost less outside numpy)
    if not all(map(math.isfinite, [x for col in cols for x in col])) or min(min(col) for col in cols[2:]) < 0:
        return None
    m_pos, m_neg = min(cols[0]), max(cols[1])
    if not (m_pos > m_neg and m_pos < NONE and m_neg > -NONE):
        return None
    s_pos, s_neg = math.fsum(cols[2]), math.fsum(cols[3])
    resid, spread = math.fsum(cols[4]), math.fsum(cols[5]) * (1.0 + ROUNDING)  # spread >= |u+|
    if not (s_pos > 0 and s_neg > 0):  # (a side without multipliers: no gamma interval)
        return None
    total, imbalance = math.fsum([s_pos, s_neg]), math.fsum([s_pos, -s_neg])  # S and dS, exactly rounded
    s = 2.0 / (m_pos - m_neg)
    x0, g0 = s * x_bar, s * (-(m_pos + m_neg) / 2.0)
    x0_norm, w_norm = norm(x0), norm(w_x)
    # c >= lam' slack(v0) = u' v0 - S, u = (W + r, dS): the exactly rounded sum of its terms, |r| |x0| for
    # the unknown residual and an allowance for the rounding of the products
    terms = (w_x * x0).tolist() + [imbalance * g0, -total]
    c = max(math.fsum(terms) + resid * x0_norm + ROUNDING * (math.fsum(map(abs, terms)) + total * abs(g0)), 0.0)
    # gamma's interval: |g0 - gamma*| <= slope delta + shift (u- = u+ - (W + r))
    slope = max(spread / s_pos, (spread + w_norm + resid) / s_neg) * (1.0 + ROUNDING)
    shift = c / min(s_pos, s_neg) * (1.0 + ROUNDING)
    # the multipliers scaled by alpha >= 0 are multipliers too (c and u scale with alpha): alpha = 1, and
    # the alpha that brings alpha W nearest x0 (it helps where the multipliers are far off)
    ww = w_norm * w_norm
    alphas = (1.0,) if not ww > 0 else (1.0, max(math.fsum(terms[:-2]) / ww, 0.0))
    e0 = min(_radius(norm(x0 - a * w_x) + a * (resid + slope * abs(imbalance)), a * (c + abs(imbalance) * shift))
             for a in alphas)
    if not (x0_norm - e0 > 0 and math.isfinite(e0)):
        return None
    g_half = (slope * e0 + shift) * (1.0 + ROUNDING)
    cert = Certificate(np.append(x0, g0), e0, x0_norm - e0, max(1.0, abs(g0) - g_half), g_half)
    return cert if all(map(math.isfinite, cert.as_list())) else None


def _radius(beta: float, c: float) -> float:
    """The largest delta >= 0 with delta^2 <= beta delta + c (the module's e), rounded up a little."""
    beta = beta * (1.0 + ROUNDING)
    return (beta + math.sqrt(beta * beta + 4.0 * max(c, 0.0))) / 2.0 * (1.0 + ROUNDING)


def reported_bound(certificate: Certificate | None, values: np.ndarray) -> float | None:
    """What a robot reports as its `error_bound`: the fleet's last certificate applied to its own
    values (the bound holds for any point, so it is proven for what the robot returns); None where
    there is no certificate or the bound overflows."""
    if certificate is None:
        return None
    b = certificate.bound(values)
    return b if math.isfinite(b) else None
