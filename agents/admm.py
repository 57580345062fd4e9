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

No I/O, no clock: frames in (`receive`), frames out (`outgoing`, `advance`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from agents.problem import MarginQP
from agents.rounds import RoundCore, from_bytes, relative_gap, to_bytes


@dataclass(frozen=True)
class ADMMParams:
    """Penalty, over-relaxation and stopping rule (the same on every robot)."""

    rho: float = 15.0
    gamma_penalty: float = 3.0  # the offset's consensus penalty relative to x's (see edge_penalty)
    relax: float = 1.95
    tol: float = 1e-3  # bound on the estimated relative function error at the stop
    max_rounds: int = 5000
    diameter: int = 1

    def __post_init__(self) -> None:
        if not self.rho > 0:
            raise ValueError(f"rho must be positive, got {self.rho}")
        if not self.gamma_penalty > 0:
            raise ValueError(f"gamma_penalty must be positive, got {self.gamma_penalty}")
        if not 0 < self.relax < 2:
            raise ValueError(f"over-relaxation must be in (0, 2), got {self.relax}")
        if not self.tol > 0:
            raise ValueError(f"tol must be positive, got {self.tol}")
        if self.max_rounds < 1:
            raise ValueError(f"max_rounds must be at least 1, got {self.max_rounds}")
        if not 0 <= self.diameter <= 62:
            raise ValueError(f"diameter must be in [0, 62] (flag bits), got {self.diameter}")


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


#: rounds per window of the contraction estimate; the estimate needs two full windows
RATE_WINDOW = 20


def error_estimate(residuals: list[float]) -> float:
    """Distance to the fixed point implied by recent residuals: r / (1 - observed rate).

    ADMM's residuals oscillate, so the rate compares the largest residual of the last window
    with that of the window before (a per-round geometric rate), which is robust to the swings.
    Infinite until two windows exist or while the residual is not shrinking.
    """
    if len(residuals) < 2 * RATE_WINDOW:
        return float("inf")
    recent = max(residuals[-RATE_WINDOW:])
    older = max(residuals[-2 * RATE_WINDOW : -RATE_WINDOW])
    if not older > 0:
        return 0.0 if recent == 0 else float("inf")
    rate = (recent / older) ** (1.0 / RATE_WINDOW)
    if rate >= 1.0:
        return float("inf")
    return recent / (1.0 - rate)


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


class ConsensusADMM(RoundCore):
    """One robot's decentralized ADMM; drive it with receive / ready / advance."""

    algorithm = "admm"

    def __init__(
        self,
        robot_id: int,
        neighbours: tuple[int, ...],
        features: np.ndarray,
        labels: np.ndarray,
        *,
        n_robots: int,
        params: ADMMParams,
        C: float | None = None,
        neighbour_degrees: dict[int, int] | None = None,
        keep_trace: bool = True,
    ) -> None:
        super().__init__(
            robot_id,
            neighbours,
            features.shape[1] + 1,
            diameter=params.diameter,
            round_cap=params.max_rounds,
            keep_trace=keep_trace,
        )
        self.params = params
        self._features = features
        self._labels = labels
        self._C = C
        self._n_robots = n_robots
        degrees = neighbour_degrees or {}
        self._edges = {
            j: _Edge(self.dim, robot_id < j, edge_penalty(params, self.dim, len(self.neighbours), degrees.get(j, 1)))
            for j in self.neighbours
        }
        self._qp = self._build_qp()
        self._residuals: list[float] = []  # the last 2 * RATE_WINDOW, for the error estimate
        self._values = self._local_step()
        self._record()
        if not self.neighbours:  # alone: round 0 already solved the whole problem
            self.finished = True
            self.residual = 0.0

    def status(self) -> dict[str, Any]:
        return {**super().status(), "error_estimate": error_estimate(self._residuals)}

    # -- one round ----------------------------------------------------------------------------
    def _step(self, mine: np.ndarray, theirs: dict[int, np.ndarray]) -> tuple[np.ndarray, bool]:
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
        they converge to the solution of *their* data rather than a biased point."""
        del self._edges[j]
        self._qp = self._build_qp()

    def _save_state(self) -> dict[str, Any]:
        return {"edges": {j: e.state() for j, e in self._edges.items()}, "residuals": list(self._residuals)}

    def _load_state(self, state: dict[str, Any]) -> None:
        for j, edge_state in state["edges"].items():
            self._edges[int(j)].load(edge_state)
        self._residuals = [float(r) for r in state["residuals"]]

    # -- internals ----------------------------------------------------------------------------
    def _build_qp(self) -> MarginQP:
        return MarginQP(
            self._features,
            self._labels,
            x_weight=1.0 / self._n_robots,
            prox_weight=self._prox_weight(),
            C=self._C,
        )

    def _prox_weight(self) -> np.ndarray:
        return sum((e.rho for e in self._edges.values()), np.zeros(self.dim))

    def _local_step(self) -> np.ndarray:
        """Round 0: the robot's own max-margin solution, a warm start of the right magnitude."""
        self._qp.set_prox(np.zeros(self.dim))
        try:
            return self._primal_step()
        finally:
            self._qp.set_prox(self._prox_weight())

    def _primal_step(self) -> np.ndarray:
        q = np.zeros(self.dim)
        for edge in self._edges.values():
            q += edge.sign * edge.lam - edge.rho * edge.z
        sol = self._qp.solve(q)
        return np.append(sol.x, sol.gamma)
