"""Relaxed ADMM for lossy, asynchronous networks (R-ADMM / PDMM), one robot's sans-IO core.

Why it exists: today's consensus ADMM (agents/admm.py) needs the *exact* value of every
neighbour each round; a stale substitute breaks sum(lambda) = 0 and biases the answer. Robots that
never wait (free mode, protocol/free.py) need an algorithm for which a lost or late packet is a
*skipped* update, not a wrong one. This is the relaxed Peaceman-Rachford splitting of the dual
problem of Bastianello, Carli, Schenato & Todescato ("Asynchronous distributed optimization over
lossy networks via relaxed ADMM", arXiv 1809.09887), which is PDMM with relaxation; with the
margin constraints inside f_l it is the inequality-constrained case of arXiv 2309.12897.

State of robot i: one auxiliary vector z_ij per neighbour j (i's end of edge ij). One tick:

    v_i  = argmin_v  f_i(v) - (sum_j z_ij)' v + 1/2 v' diag(sum_j rho_ij) v     (a small QP, piqp)
    y_ij = 2 rho_ij v_i - z_ij                                                   (sent to j)

and when j's packet y_ji arrives at i:   z_ij <- (1 - alpha) z_ij + alpha y_ji.

A lost packet leaves z_ij as it was (a skipped coordinate update of the relaxed PR operator),
which is why loss costs time but never accuracy. At a fixed point z_ij + z_ji = 2 rho_ij v_i =
2 rho_ij v_j (consensus) and sum_i grad f_i = 0 (optimality): the centralized solution.

Old and duplicated packets: every packet carries the sender's tick counter (its sequence number);
a packet no newer than the last one applied from that sender is dropped. Delay: the relaxation
``alpha`` (< 1/2 damps, as ARock's step size) is what keeps the iteration stable when the y's in
flight were computed from old z's.

Stopping (no waiting, so no lockstep flags): a robot is *calm* when it heard every neighbour in
the last ``window`` ticks (a silent or partitioned neighbour is no evidence) and its distance to
the fixed point, estimated as c / (1 - rate) + g from its change per tick c (the contraction
seen over the last two windows sums the changes still to come) plus its gap g to every
neighbour's newest v (`RelaxedADMM.distance_estimate`), is below ``tol``.
A raw residual bound is not enough: measured on a 4-robot fleet after a partition, residuals
of 1e-4 per tick still stood 2.5e-3 from the answer. It publishes a hop count h_i = 0 if not
calm, else 1 + min_j h_j (newest values, capped at D + 1); it stops at h_i >= D + 1
(D = ``diameter``): every robot within D hops was calm too; and it stops when a neighbour
announced its stop (h_j = D + 1), so the decision floods through the fleet and no robot is left
iterating alone against frozen neighbours. The launcher still checks agreement on the final answers (success means agreement).

`NewestValueADMM` is the counter-example kept for measurement: today's edge-form consensus ADMM
(agents/admm.py, no acceleration) fed the newest value each neighbour sent. Both ends of an edge
then update their copies of (z, lambda) from different pairs of vectors, lambda_ij = -lambda_ji
breaks, and the fleet drifts: benchmarks/free.py measures it (it diverges, or stops calm and in
agreement 0.5 away from the answer -- agreement cannot detect that bias).

No I/O, no clock: packets in (`receive`), packets out (`tick`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from agents.admm import ADMMParams, ConsensusADMM, edge_penalty
from agents.admm import error_estimate as admm_error_estimate
from agents.params import check_counts, check_diameter, check_positive
from agents.problem import MarginQP
from agents.rounds import RobotShare, RoundCore, check_iterate, result_row


@dataclass(frozen=True)
class RelaxedADMMParams:
    """Penalty, relaxation and the calm-stop rule (the same on every robot)."""

    # measured (benchmarks/free.py, loss 0.3, 20 ms): alpha 0.9 stops about 20 % sooner than
    # ADMM's 0.5; rho 8 was faster on the default fleet but twice slower on 4 robots, 15 is even
    rho: float = 15.0
    gamma_penalty: float = 3.0
    alpha: float = 0.9  # relaxation in (0, 1): 1/2 is ADMM (Douglas-Rachford); smaller damps delay
    tol: float = 1e-3  # bound on the estimated relative function error at the stop
    window: int = 40  # ticks per window of the contraction estimate (two are needed)
    diameter: int = 1
    max_ticks: int = 20000

    def __post_init__(self) -> None:
        check_positive(self, "rho", "gamma_penalty")
        if not 0 < self.alpha < 1:
            raise ValueError(f"alpha must be in (0, 1), got {self.alpha}")
        check_positive(self, "tol")
        check_counts(self, "window", "max_ticks")
        check_diameter(self.diameter)

    @classmethod
    def from_params(cls, params: dict[str, Any]) -> RelaxedADMMParams:
        """The fleet file's params filtered by this class's fields (other algorithms' keys ignored)."""
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in params.items() if k in names})


@dataclass(frozen=True)
class Packet:
    """What robot ``sender`` tells neighbour ``dest`` at tick ``seq``: its v and the edge's y."""

    sender: int
    seq: int
    values: np.ndarray  # v_sender = (x, gamma): for the neighbour's gap test and the answer
    edge: np.ndarray  # y_{sender -> dest}
    hops: int


def _gap(v: np.ndarray, others: list[np.ndarray]) -> float:
    """agents.rounds.relative_gap's metric (largest over ``others``), without its einsum: a tick
    calls it twice and the einsum on a 16-vector was a sixth of a free run's time (profiled)."""
    nx = max(math.sqrt(float(v[:-1] @ v[:-1])), 1e-12)
    ng = max(1.0, abs(float(v[-1])))
    worst = 0.0
    for w in others:
        d = w - v
        worst = max(worst, math.sqrt(float(d[:-1] @ d[:-1])) / nx + abs(float(d[-1])) / ng)
    return worst


def error_estimate(residuals: list[float], window: int) -> float:
    """Distance to the fixed point implied by the last two windows of residuals: admm's windowed
    r / (1 - rate) (the windows' largest residuals: robust to loss's noisy residuals); infinite while
    a kept residual is not finite."""
    if not all(map(math.isfinite, residuals)):
        return math.inf
    return admm_error_estimate(residuals, window=window)


class RelaxedADMM:
    """One robot's R-ADMM; drive it with `receive(packet)` and `tick()` at any pace."""

    algorithm = "radmm"
    #: what a tick may raise when its local solve fails (the session stops the robot with the reason)
    solve_errors = RoundCore.solve_errors

    def __init__(self, share: RobotShare, params: RelaxedADMMParams) -> None:
        self.robot_id = share.robot_id
        self.neighbours = share.neighbours
        self.dim = share.dim
        self.params = params
        degrees = share.degrees
        pen = ADMMParams(rho=params.rho, gamma_penalty=params.gamma_penalty)
        self._rho = {j: edge_penalty(pen, self.dim, len(self.neighbours), degrees.get(j, 1)) for j in self.neighbours}
        self._z = {j: np.zeros(self.dim) for j in self.neighbours}
        self._last_seq = {j: -1 for j in self.neighbours}
        self._their_v: dict[int, np.ndarray] = {}
        self._their_hops = {j: 0 for j in self.neighbours}
        prox = sum(self._rho.values(), np.zeros(self.dim))
        self._qp = MarginQP(share.features, share.labels, x_weight=1.0 / share.n_robots, prox_weight=prox, C=share.C)
        self._values = np.zeros(self.dim)
        self._changes: list[float] = []
        self._gaps: list[float] = []
        self._heard = {j: -(10**9) for j in self.neighbours}
        self.hops = 0
        self.ticks = 0
        self.residual = math.inf
        self.applied = 0
        self.stale = 0  # packets dropped as old or duplicated
        self.finished = not self.neighbours
        if self.finished:  # alone: the whole problem is its own
            self._values = self._solve()
            self.residual = 0.0

    @property
    def values(self) -> np.ndarray:
        """The current (x, gamma)."""
        return self._values.copy()

    @property
    def converged(self) -> bool:
        """Stopped by the calm-stop rule (not by the tick cap)."""
        return self.finished and (self.hops > self.params.diameter or not self.neighbours)

    def _fresh(self, p: Packet) -> bool:
        """p comes from a neighbour and is newer than its last packet (an older one is counted stale)."""
        if p.sender not in self._z:
            return False
        if p.seq <= self._last_seq[p.sender]:
            self.stale += 1
            return False
        return True

    def receive(self, p: Packet) -> bool:
        """Apply neighbour p.sender's edge update if it is newer than the last one; else drop it."""
        if not self._fresh(p):
            return False
        j = p.sender
        if p.edge.shape != (self.dim,) or p.values.shape != (self.dim,):
            raise ValueError(f"robot {j} sent vectors of the wrong length, expected {self.dim}")
        self._last_seq[j] = p.seq
        self._apply_edge(j, p.edge)
        self._their_v[j] = p.values
        self._their_hops[j] = p.hops
        self._heard[j] = self.ticks
        self.applied += 1
        return True

    def _apply_edge(self, j: int, edge: np.ndarray) -> None:
        """The relaxed update of z_ij from neighbour j's y_ji (the free hub ADMM holds a_j instead)."""
        a = self.params.alpha
        self._z[j] = (1.0 - a) * self._z[j] + a * edge

    def tick(self) -> list[Packet]:
        """One local update from the newest z's: the packets to send (one per neighbour)."""
        if self.finished:
            return self.final_packets()
        new = self._solve()
        change = _gap(new, [self._values]) if self.ticks else math.inf
        theirs = [self._their_v[j] for j in self.neighbours if j in self._their_v]
        gap = _gap(new, theirs) if len(theirs) == len(self.neighbours) else math.inf
        self._values = new
        self.ticks += 1
        self.residual = max(change, gap)
        w = self.params.window
        self._changes = (self._changes + [change])[-2 * w :]
        self._gaps = (self._gaps + [gap])[-w:]
        cap = self.params.diameter + 1
        # a neighbour that finished (hop count at the cap) is final, not silent
        fresh = all(self.ticks - self._heard[j] <= w or self._their_hops[j] >= cap for j in self.neighbours)
        calm = fresh and self.distance_estimate() < self.params.tol
        self.hops = min(cap, 1 + min(self._their_hops.values())) if calm else 0
        if max(self._their_hops.values()) >= cap:  # a neighbour stopped: the decision floods on
            self.hops = cap
        if self.hops >= cap or self.ticks >= self.params.max_ticks:
            self.finished = True
        return self.final_packets()

    def distance_estimate(self) -> float:
        """How far this robot's v may still be from the fixed point: the changes still to come
        (the last window's largest change per tick summed as a geometric series at the rate of
        the last two windows, :func:`error_estimate`) plus its largest gap to a neighbour's newest
        v in the last window. The two are kept apart because only the change is a per-tick
        quantity: the gap does not shrink with the period, and summing it as a series (the rule
        before) inflated the estimate by 1 / (1 - rate per tick), the more so the shorter the
        period (measured in benchmarks/results/free.md, "stop rule")."""
        w = self.params.window
        if len(self._gaps) < w:
            return math.inf
        return error_estimate(self._changes, w) + max(self._gaps)

    def final_packets(self) -> list[Packet]:
        """The packets of the current state (also what a finished robot repeats while lingering)."""
        return [
            Packet(self.robot_id, self.ticks, self._values.copy(), 2.0 * self._rho[j] * self._values - self._z[j], self.hops)
            for j in self.neighbours
        ]

    def divergence(self) -> str | None:
        """Why the current function cannot be a result, or None."""
        return check_iterate(self._values)

    def result(self) -> dict[str, Any]:
        """x and gamma of this robot; the shell adds its counters."""
        return {
            **result_row(self, self._values, rounds=self.ticks, dropped=[]),
            "packets_applied": self.applied,
            "packets_stale": self.stale,
        }

    def _solve(self) -> np.ndarray:
        q = -sum(self._z.values(), np.zeros(self.dim))
        sol = self._qp.solve(q)
        return np.append(sol.x, sol.gamma)


class _NewestValues(RelaxedADMM):
    """A free core that keeps the newest v of each neighbour and ignores the edge vector."""

    def _apply_edge(self, j: int, edge: np.ndarray) -> None:
        """The edge vector is not used: only the newest v (kept by ``receive``) counts."""

class NewestValueADMM(_NewestValues):
    """Today's edge-form ADMM on whatever neighbour value arrived last (biased; for measurement).

    Same packets, sequence numbers and calm-stop rule as the relaxed ADMM, so the two differ only
    in the mathematics; the edge vector of a packet is ignored."""

    algorithm = "admm-newest"

    def __init__(self, share: RobotShare, params: RelaxedADMMParams, *, relax: float = 1.95) -> None:
        super().__init__(share, params)
        admm = ADMMParams(rho=params.rho, gamma_penalty=params.gamma_penalty, relax=relax, anderson=0)
        self._admm = ConsensusADMM(share, admm, keep_trace=False)
        self._started = False

    def _solve(self) -> np.ndarray:
        core = self._admm
        if not self._started:  # tick 0: the robot's own solution (the lockstep core's round 0)
            self._started = True
            return core.values
        relax = core.params.relax
        mine = self._values
        for j, edge in core._edges.items():
            theirs = self._their_v.get(j)
            if theirs is None:
                continue
            low, high = (mine, theirs) if self.robot_id < j else (theirs, mine)
            edge.update(low, high, relax)
        return core._primal_step()


class FreeCTADMM(_NewestValues):
    """The paper's CT-ADMM on the robot's own clock: each tick integrates one period T_sp of the
    flow (agents/ct_admm.py) with the newest neighbour samples held -- stale by the network's delay
    and by lost packets, so delay enters the feedback loop (measured: benchmarks/free.py).
    A neighbour not heard yet is held at the robot's own value. The tick period must be T_sp."""

    algorithm = "ct-admm-free"

    def __init__(self, share: RobotShare, params: RelaxedADMMParams, *, ct_params: Any) -> None:
        from agents.ct_admm import ContinuousTimeADMM

        self._ct = ContinuousTimeADMM(share, ct_params, keep_trace=False)
        super().__init__(share, params)

    def _solve(self) -> np.ndarray:
        ct = self._ct
        mine = ct._values
        theirs = {j: self._their_v.get(j, mine) for j in ct.neighbours}
        new, _ = ct._step(mine, theirs)
        ct._prev_values, ct._values = mine, new
        ct.round += 1
        return new


FREE_ALGORITHMS = ("auto", "radmm", "hub", "admm-newest", "ct-admm-free")


def free_algorithm_for(spec: Any, algorithm: str = "auto") -> str:
    """``auto``: the free hub ADMM (agents/free_hub.py, Anderson-accelerated) on a complete graph,
    where every robot hears every robot, the relaxed ADMM on any other graph; a named one as is."""
    if algorithm != "auto":
        return algorithm
    complete = all(len(n) == spec.n_robots - 1 for n in spec.graph.values())
    return "hub" if spec.n_robots > 1 and complete else "radmm"


def build_free_core(spec: Any, rid: int, params: dict[str, Any] | None = None, algorithm: str = "auto",
                    period: float = 0.01) -> Any:
    """Robot ``rid``'s free-mode core on the spec's grid (a FleetSpec): ``auto`` (`free_algorithm_for`),
    the free hub ADMM, the relaxed ADMM, or (for
    measurement) today's ADMM fed the newest values (``admm-newest``) or the paper's CT-ADMM
    integrating one ``period`` per tick with held samples (``ct-admm-free``). Here, not in the
    launcher, because the robot process (agents/free_robot.py) builds it too."""
    from agents.ct_admm import CTADMMParams
    from agents.free_hub import FreeHubADMM, FreeHubParams, hub_window

    if algorithm not in FREE_ALGORITHMS:
        raise ValueError(f"free sync runs {', '.join(FREE_ALGORITHMS)}, not {algorithm!r}")
    if not spec.fixed_grid:
        raise ValueError("free sync needs a fixed grid and sigma (--grid and --sigma, or --preset paper)")
    algorithm = free_algorithm_for(spec, algorithm)
    # the fleet file's tol and diameter hold for every algorithm; its rho and relax are lockstep
    # ADMM's (tuned for it), so the free core keeps its own unless ``params`` names them
    given = {"tol": spec.params.get("tol", 1e-3), "diameter": spec.params.get("diameter", 1), **(params or {})}
    kw: dict[str, Any] = {}
    if algorithm == "hub":
        given.setdefault("window", hub_window(period))
    if algorithm == "admm-newest":
        kw["relax"] = float(given.get("relax", spec.params.get("relax", 1.95)))
    if algorithm == "ct-admm-free":
        kw["ct_params"] = CTADMMParams(period=period)
    cls = {"radmm": RelaxedADMM, "hub": FreeHubADMM, "admm-newest": NewestValueADMM, "ct-admm-free": FreeCTADMM}[algorithm]
    typed = (FreeHubParams if algorithm == "hub" else RelaxedADMMParams).from_params(given)
    return cls(spec.share(rid), typed, **kw)
