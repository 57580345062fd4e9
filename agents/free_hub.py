"""Free-running hub ADMM on a complete graph (asynchronous Douglas-Rachford, ARock), sans-IO.

Why it exists: on a complete graph lockstep runs the hub form of consensus ADMM (z = mean, one
dual per robot; agents/admm.py ``_Hub``), which needs fewer iterations than the edge form, and
accelerates it with Anderson. The free relaxed ADMM (agents/pdmm.py) runs the edge form and pays
about three times the iterations. This is the hub form for robots that never wait.

Robot i owns one vector t_i (its proximal centre z - u_i) and P, the hub form's penalty (one
diagonal, the same on every robot). One tick, with the newest a_j it holds from every neighbour:

    m_i = mean_j a_j        (own a_i of the last tick, the newest held a_j of the others)
    t_i <- t_i + eta (m_i - x_i)                                  (eta in (0, 2): relaxation)
    x_i = argmin_v  f_i(v) + 1/2 (v - t_i)' P (v - t_i)          (the robot's QP, piqp)
    a_i = 2 x_i - t_i                                            (published with x_i)

In ADMM's words a_i = x_i + u_i' (the dual after this x step) and m_i is the z the robot would
compute from its newest values; with everyone's newest values equal to their current ones it is
the synchronous over-relaxed Douglas-Rachford / ADMM step (eta 1: plain ADMM).

Exactness under loss and delay (docs/robustness.md, tests/test_free_hub.py): a lost or late packet
is an *old* a_j -- a consistent pair (x_j, t_j) of an earlier state, never a mixed or wrong value --
so it changes which iterate a robot reads, not the operator. At any fixed point (t_i unchanged,
everyone holding everyone's current values): m_i = x_i for all i, so all x_i equal one z; summing
a_j gives sum_j t_j = N z; x_i = prox(t_i) means 0 in df_i(z) + P (z - t_i), and summing over i,
0 in sum_i df_i(z) + P (N z - sum_j t_j) = sum_i df_i(z): z is the centralized optimum. This is
ARock (Peng, Xu, Yan, Yin, arXiv 1506.02396) applied to the Douglas-Rachford operator of the
consensus problem, one block per robot, reads of bounded staleness: it converges for a small
enough eta against the largest staleness (their step 1 / (1 + 2 tau / sqrt(N)) for random
blocks); eta larger than that is a measured choice (benchmarks/free.py), not a theorem.

Acceleration (``hub_anderson`` > 0, the default 35): Anderson on the robot's *view of the whole
fleet*. From the newest packets robot i knows every robot's (x_j, a_j), hence t_j = 2 x_j - a_j:
a point S = (t_1..t_N) of the fleet's state and, exactly, the Douglas-Rachford image of that point,
F(S)_j = t_j + eta (mean_k a_k - x_j) -- each x_j is robot j's own prox of its own t_j. So every
view is an exact evaluation of the one fleet operator at some (mixed-age) point, which is what
type-II Anderson needs: it extrapolates from the last ``hub_anderson`` views (regularised least
squares on the P-weighted residuals, as lockstep's hub) and the robot keeps its own block of the
result as its new t_i. By default it steps only when a packet brought news; ``hub_every_tick``
steps on every tick (its own block of the view is new after every solve). Safeguard: when the
view's residual exceeds ``hub_safeguard`` x the best since the last restart, the history is dropped
and the plain step taken (``restarts`` counts them); ``hub_step_cap`` > 0 also scales the
extrapolation's correction of the whole view (P-weighted) down to at most that many times the
view's residual (mixed-age views can make the least squares propose a far jump). Both options are
off by default: with them and eta 1.6 the 3-robot fleet was faster at 5 ms, but 4-robot fleets
stopped outside the tolerance (benchmarks/results/free.md, docs/robustness.md). In lockstep
(everyone's newest = current) every robot holds the same views and this is lockstep's global
Anderson. At a fixed point the
residual is zero, the least squares returns zero and the extrapolation is the plain step (the
cap scales a zero correction): the fixed point, so the answer, is unchanged (tests/test_free_hub.py).
Convergence of the extrapolated asynchronous iteration is not a theorem (measured:
benchmarks/results/free.md); the answer it stops at is checked against the exact one
in every benchmark and sweep cell. Anderson on the robot's own t_i sequence alone was slower than
no acceleration (664 against 476 iterations without a clock): robots then extrapolate with
unrelated coefficients.

Stop: the relaxed ADMM's calm rule (agents/pdmm.py ``RelaxedADMM.tick``: distance estimate below
``tol``, hop counts over the diameter, the stop floods), its window set by `hub_window` from the
tick period (0.2 s of the robot's clock, 20 to 40 ticks) unless ``params`` names one. No I/O, no clock.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from agents.admm import ANDERSON_REG, complete_graph
from agents.pdmm import Packet, RelaxedADMM, RelaxedADMMParams
from agents.rounds import RobotShare


#: the stop rule's window (RelaxedADMMParams.window) as robot-clock time, clamped to [20, 40] ticks
HUB_WINDOW_S = 0.2


def hub_window(period: float) -> int:
    """The free hub's stop window in ticks for a tick ``period`` (s): 0.2 s of the robot's own clock,
    at least 20 and at most 40 ticks (40 at 5 ms and below, 20 at 10 ms and above). Why by time: the
    window must span the same stretch of the contraction however often a robot ticks; the period is
    the robot's own setting, so this needs nothing it does not know (not the network's delay).
    Measured (benchmarks/results/free.md): at 10 ms the 40-tick window waited 0.4 s longer than the
    20-tick one for errors at the stop that stayed 10 to 100 times below the tolerance."""
    return min(40, max(20, round(HUB_WINDOW_S / period)))


@dataclass(frozen=True)
class FreeHubParams(RelaxedADMMParams):
    """The relaxed ADMM's settings (rho, gamma_penalty, tol, window, diameter, max_ticks; alpha
    unused) plus the hub's relaxation and acceleration."""

    rho: float = 8.0  # measured at loss 0.3, 20 ms, period 5 ms: 5 and 10 slower, 12-20 much slower
    # memory and safeguard chosen on seeds 0-2 at periods 10 and 5 ms (loss 0.3, 20 ms; the largest
    # ratio to lockstep's stop time over the six runs). A candidate eta 1.6 + every-tick steps + step
    # cap 10 (better on 3 robots at 5 ms) stopped 4-robot fleets outside the tolerance (6e-3): not the
    # default (benchmarks/results/free.md, docs/robustness.md)
    hub_relax: float = 1.5  # eta in (0, 2): 1 is plain ADMM; smaller damps staleness (ARock's step)
    hub_anderson: int = 35  # memory of the Anderson acceleration on the robot's view (0: none; 5-25 slower)
    hub_safeguard: float = 10.0  # restart Anderson when the view's residual exceeds this x its best
    hub_every_tick: bool = False  # True: step on ticks without news too (the candidate; see above)
    hub_step_cap: float = 0.0  # >0: extrapolation's correction at most this x the view's residual

    def __post_init__(self) -> None:
        super().__post_init__()
        if not 0 < self.hub_relax < 2:
            raise ValueError(f"hub_relax must be in (0, 2), got {self.hub_relax}")
        if not 0 <= self.hub_anderson <= 50:
            raise ValueError(f"hub_anderson must be in [0, 50], got {self.hub_anderson}")
        if not self.hub_safeguard > 1:
            raise ValueError(f"hub_safeguard must be above 1, got {self.hub_safeguard}")
        if not self.hub_step_cap >= 0:
            raise ValueError(f"hub_step_cap must be 0 (no cap) or positive, got {self.hub_step_cap}")


class FreeHubADMM(RelaxedADMM):
    """One robot's free hub ADMM; the relaxed ADMM's interface, packets and stop rule.

    A packet's ``edge`` is the robot's a_i (the same for every neighbour)."""

    algorithm = "hub"

    def __init__(self, share: RobotShare, params: FreeHubParams) -> None:
        if not isinstance(params, FreeHubParams):
            raise TypeError("FreeHubADMM takes FreeHubParams")
        if not complete_graph(share.n_robots, tuple(share.neighbours), dict(share.degrees)):
            raise ValueError("the free hub ADMM needs a complete graph (every robot a neighbour of every other)")
        super().__init__(share, params)
        self._P = sum(self._rho.values(), np.zeros(self.dim))  # the QP's proximal weight: rho, 3 rho on gamma
        self._t = np.zeros(self.dim)
        self._a = np.zeros(self.dim)  # a_i = 2 x_i - t_i of the last solve
        self._held: dict[int, np.ndarray] = {}  # newest a_j per neighbour
        self.hub_residual = math.inf  # |m_i - x_i| of the last step (P-weighted)
        self._hist_t: list[np.ndarray] = []
        self._hist_f: list[np.ndarray] = []
        self._best = math.inf
        self.restarts = 0  # rejected extrapolations
        self._news: set[int] = set()  # neighbours with a new packet since the last step

    def _apply_edge(self, j: int, edge: np.ndarray) -> None:
        """Hold neighbour j's newest a_j as sent (an old packet was dropped before: an old value)."""
        self._held[j] = edge
        self._news.add(j)

    def _solve(self) -> np.ndarray:
        """Move t_i (every tick, or only on news; see the module), then x_i = prox(t_i), a_i = 2 x_i - t_i."""
        heard_all = len(self._held) == len(self.neighbours)  # until all were heard, t waits
        if self.ticks and (self._news or self.params.hub_every_tick) and heard_all:
            self._t = self._view_step()
        self._news = set()
        sol = self._qp.solve(-self._P * self._t)
        x = np.append(sol.x, sol.gamma)
        self._a = 2.0 * x - self._t
        return x

    def _view_step(self) -> np.ndarray:
        """Anderson on this robot's view of the whole fleet's state (see the module): the view
        S = (t_j) with t_j = 2 x_j - a_j of the newest packet of j (its own: current), its image
        F = S + eta (mean_j a_j - x_j); the extrapolation's own block is the new t_i (with no
        memory, F's own block: the plain relaxed step t_i + eta (m_i - x_i))."""
        me = self.robot_id
        xs = {j: self._their_v[j] for j in self.neighbours}
        As = dict(self._held)
        xs[me], As[me] = self._values, self._a
        ids = sorted(xs)
        S = np.concatenate([2.0 * xs[j] - As[j] for j in ids])
        m = sum((As[j] for j in ids), np.zeros(self.dim)) / len(ids)
        G = np.concatenate([self.params.hub_relax * (m - xs[j]) for j in ids])
        F = S + G
        w = np.tile(np.sqrt(self._P), len(ids))
        res = float(np.linalg.norm(G * w))
        self.hub_residual = res
        if res > self.params.hub_safeguard * self._best:
            self._hist_t, self._hist_f, self._best = [], [], math.inf
            self.restarts += 1
        self._best = min(self._best, res)
        memory = self.params.hub_anderson
        self._hist_t = (self._hist_t + [S])[-(memory + 1):]
        self._hist_f = (self._hist_f + [F])[-(memory + 1):]
        k = ids.index(me)
        own = slice(k * self.dim, (k + 1) * self.dim)
        if len(self._hist_t) < 2:
            return F[own]
        gs = np.array([b - a for a, b in zip(self._hist_t, self._hist_f)]) * w
        dg = np.diff(gs, axis=0)
        dF = np.diff(np.array(self._hist_f), axis=0)
        H = dg @ dg.T
        H[np.diag_indices_from(H)] += ANDERSON_REG * max(float(np.trace(H)) / len(H), 1e-300)
        try:
            coef = np.linalg.solve(H, dg @ (G * w))
        except np.linalg.LinAlgError:
            return F[own]
        cap = self.params.hub_step_cap
        if cap:  # a far jump from an ill-posed least squares: shortened (the view's norm only then)
            step = float(np.linalg.norm((coef @ dF) * w))
            if step > cap * res:
                coef = coef * (cap * res / step)
        return F[own] - coef @ dF[:, own]

    def final_packets(self) -> list[Packet]:
        """The current (x_i, a_i) to every neighbour (what a finished robot repeats too)."""
        return [Packet(self.robot_id, self.ticks, self._values.copy(), self._a.copy(), self.hops) for _ in self.neighbours]

    def result(self) -> dict[str, Any]:
        """The relaxed ADMM's row plus the count of rejected extrapolations."""
        return {**super().result(), "anderson_restarts": self.restarts}

