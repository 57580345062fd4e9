"""A certified bound on the hub form's function error, from the duality gap (pure: no I/O, no clock).

Why: the hub's stop rule (r / (1 - rate), agents/admm.py) is a heuristic that Anderson plateaus fool
(docs/algorithm.md, "A certified stop"); this bound is *proven* >= the function error of any point
against the exact optimum, and every copy of the hub computes it from its frames alike, so it can
guard the rule's stop (ADMMParams.certify).

Hard margin, rows a_i = y_i [phi_i; 1], v = (x, gamma), x = K^{1/2} c (the rkhs norm is |x|):

* Primal. At the fleet's mean x_bar, m+ = min of phi_i' x_bar over the positive rows, m- = max over
  the negative rows (each robot sends its own two: a min/max over robots). If m+ > m-, the point
  s (x_bar, g), g = -(m+ + m-)/2, s = 2/(m+ - m-), holds every margin: P = s^2 |x_bar|^2 / 2 >= P*.
* Dual ("hub dual"). Robot l's multipliers lam_l >= 0 of its own step QP satisfy A_l' lam_l = grad_l
  + r_l (grad_l = P_l v_l + q_l, r_l the solver's residual, robot-local); with S+, S- the fleet's
  per-side sums of lam, t = S_small / S_big and W the x part of sum_l grad_l (every hub copy computes
  it from the frames' v_l and its own centres), the balanced, optimally scaled multipliers give
  D = (2 S_small)^2 / (2 B^2) <= P*, B = |W| + sum_l |r_l| + (1 - t) S_big phi_max.
* Gap. 1/2 |x|^2 is 1-strongly convex: e0 = sqrt(2 (P - D)) >= |s x_bar - x*|, and |x*| >= sqrt(2 D);
  gamma* lies within e0 phi_max of s g (both classes have a tight row at the optimum). So any point
  (x, gamma) has function error at most
      (|x - s x_bar| + e0) / sqrt(2 D)  +  (|gamma - s g| + e0 phi_max) / max(1, |s g| - e0 phi_max).

Every reduction over robots is exactly rounded (math.fsum) or a min/max, in robot-id order, so
every copy gets the same bits from the same frames. A robot sends PAYLOAD floats beside [v; w]:
[m+_l, m-_l, S+_l, S-_l, |r_l|, phi_max_l]; a payload that is not finite, or has negative sums, makes
the fleet's certificate absent (no stop by it), never an error.
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
            phi_max: float) -> np.ndarray:
    """A robot's PAYLOAD floats: its margins at the mean, its multipliers' per-side sums (side =
    `sides(rows)`), the norm of its KKT residual, its largest |phi_i|. Zeros (no certificate) when
    anything is not finite."""
    out = [margins[0], margins[1], math.fsum(lam.take(side[0]).tolist()), math.fsum(lam.take(side[1]).tolist()),
           residual, phi_max]
    return np.array(out) if all(map(math.isfinite, out)) else np.zeros(PAYLOAD)


def step_diagonal(prox: np.ndarray, n_robots: int) -> np.ndarray:
    """The diagonal of a robot's step QP, as MarginQP builds it: the proximal weight per variable of
    (x, gamma) plus the objective's |x|^2 / (2 N) on x. grad_l = step_diagonal * v_l + q_l."""
    d = np.array(prox, dtype=float)
    d[:-1] += 1.0 / n_robots
    return d


def robot_payload(rows: np.ndarray, side: tuple[np.ndarray, np.ndarray], lam: np.ndarray, grad: np.ndarray,
                  mean: np.ndarray, phi_max: float) -> np.ndarray:
    """A robot's PAYLOAD for its step: its multipliers lam (clipped at 0: any lam >= 0 gives a valid
    dual, so round-off below 0 goes), its KKT residual |A' lam - grad| on x, its margins at the fleet
    mean `mean` (which every copy holds). Robot-local products: plain BLAS; only the fleet's sums
    over robots must be exactly rounded."""
    lam = np.maximum(lam[: len(rows)], 0.0)
    resid = norm((lam @ rows - grad)[:-1])
    return payload(margin_extremes(rows[:, :-1] @ mean[:-1], side), side, lam, resid, phi_max)


def phi_max(rows: np.ndarray) -> float:
    """The largest |phi_i| of a robot's rows (rows = y [phi, 1])."""
    return max((math.sqrt(math.fsum((r * r).tolist())) for r in rows[:, :-1]), default=0.0)


def norm(v: np.ndarray) -> float:
    """|v|, exactly rounded sum of squares (the same bits on every copy); inf where the squares or
    their sum overflow (an exploding iterate: no certificate, and no warning on the robot's stderr)."""
    with np.errstate(over="ignore", invalid="ignore"):
        squares = (v * v).tolist()
    try:
        return math.sqrt(math.fsum(squares))
    except OverflowError:  # fsum's intermediate overflow of finite squares
        return math.inf


@dataclass(frozen=True)
class Certificate:
    """The fleet's certificate of one round: the rescaled mean s (x_bar, g), e0 and the two
    denominators; `bound` turns it into a proven bound on any point's function error."""

    center: np.ndarray  # s (x_bar, g)
    e0: float  # >= |s x_bar - x*|
    den_x: float  # sqrt(2 D) <= |x*|
    den_g: float  # max(1, |s g| - e0 phi_max) <= max(1, |gamma*|)
    phi_max: float

    def bound(self, v: np.ndarray) -> float:
        """A proven upper bound on the function error of v = (x, gamma) against the exact optimum
        (inf where it overflows)."""
        c = self.center
        with np.errstate(over="ignore", invalid="ignore"):
            dx = v[:-1] - c[:-1]
        return ((norm(dx) + self.e0) / self.den_x
                + (abs(float(v[-1]) - float(c[-1])) + self.e0 * self.phi_max) / self.den_g)

    def fleet_bound(self, values: np.ndarray) -> float:
        """The largest `bound` over rows of values (a robot per row, id order)."""
        return max(self.bound(v) for v in values)

    def as_list(self) -> list[float]:
        """Checkpoint form (`from_list` inverts it)."""
        return [self.e0, self.den_x, self.den_g, self.phi_max, *self.center.tolist()]

    @classmethod
    def from_list(cls, xs: list[float]) -> Certificate:
        return cls(np.array(xs[4:], dtype=float), float(xs[0]), float(xs[1]), float(xs[2]), float(xs[3]))


def fleet_certificate(payloads: np.ndarray, x_bar: np.ndarray, w_x: np.ndarray) -> Certificate | None:
    """The fleet's certificate from every robot's payload (a row per robot, id order), the mean
    x_bar at which the margins were taken and w_x, the x part of sum_l grad_l; None where none
    exists (no balanced dual, the mean not separating, a bad payload). Finite but huge numbers (a
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
    resid, phi = math.fsum(cols[4]), max(cols[5])
    small, big = min(s_pos, s_neg), max(s_pos, s_neg)
    if not small > 0:
        return None
    b = norm(w_x) + resid + (1.0 - small / big) * big * phi
    dual = (2.0 * small) ** 2 / (2.0 * b * b) if b > 0 else math.inf
    s = 2.0 / (m_pos - m_neg)
    g = -(m_pos + m_neg) / 2.0
    primal = s * s * math.fsum((x_bar * x_bar).tolist()) / 2.0
    if not (0 < dual < math.inf and math.isfinite(primal)):
        return None
    e0 = math.sqrt(2.0 * max(primal - dual, 0.0))
    cert = Certificate(np.append(s * x_bar, s * g), e0, math.sqrt(2.0 * dual), max(1.0, abs(s * g) - e0 * phi), phi)
    return cert if all(map(math.isfinite, cert.as_list())) else None


def reported_bound(certificate: Certificate | None, values: np.ndarray) -> float | None:
    """What a robot reports as its `error_bound`: the fleet's last certificate applied to its own
    values (the bound holds for any point, so it is proven for what the robot returns); None where
    there is no certificate or the bound overflows."""
    if certificate is None:
        return None
    b = certificate.bound(values)
    return b if math.isfinite(b) else None
