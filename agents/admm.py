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
early on a small per-round change. Each round carries D+1 flag bits. Bit 0 says "my estimate is below tol"; bit t of
round k+1 is the AND of bit t-1 of round k over the robot and its neighbours. Bit D (D >= graph
diameter) is therefore the AND over *all* robots of bit 0 from D rounds earlier: every robot
sees the same value in the same round, so all stop together with the same iterates.

No I/O, no clock: frames in (`receive`), frames out (`outgoing`, `advance`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from agents.problem import MarginQP
from protocol.frames import StateUpdate

_TINY = 1e-12


@dataclass(frozen=True)
class ADMMParams:
    """Penalty, over-relaxation and stopping rule (the same on every robot)."""

    rho: float = 15.0
    relax: float = 1.8
    tol: float = 1e-3  # bound on the estimated relative function error at the stop
    max_rounds: int = 1000
    diameter: int = 1

    def __post_init__(self) -> None:
        if not self.rho > 0:
            raise ValueError(f"rho must be positive, got {self.rho}")
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

    def __init__(self, dim: int, mine_is_low: bool, rho: float) -> None:
        self.sign = 1.0 if mine_is_low else -1.0
        self.rho = rho  # fixed for the run: both ends must always use the same value
        self.z = np.zeros(dim)  # the edge's consensus value
        self.lam = np.zeros(dim)  # the low end's multiplier

    def update(self, v_low: np.ndarray, v_high: np.ndarray, relax: float) -> None:
        """z and lambda after both ends' primal steps (over-relaxed by `relax`)."""
        h_low = relax * v_low + (1.0 - relax) * self.z
        h_high = relax * v_high + (1.0 - relax) * self.z
        self.z = 0.5 * (h_low + h_high)
        self.lam = self.lam + self.rho * (h_low - self.z)

    def state(self) -> list[bytes | None]:
        return [_raw(self.z), _raw(self.lam)]

    def load(self, state: list[bytes]) -> None:
        self.z, self.lam = _arr(state[0]), _arr(state[1])


def _raw(a: np.ndarray | None) -> bytes | None:
    return None if a is None else np.asarray(a, "<f8").tobytes()


def _arr(b: bytes | None) -> np.ndarray | None:
    return None if b is None else np.frombuffer(b, "<f8").copy()


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


@dataclass
class _Inbox:
    """Neighbour values for the current round and the next (a neighbour may be one ahead)."""

    values: dict[int, dict[int, np.ndarray]] = field(default_factory=dict)
    flags: dict[int, dict[int, int]] = field(default_factory=dict)

    def put(self, rnd: int, sender: int, values: np.ndarray, flags: int) -> None:
        self.values.setdefault(rnd, {})[sender] = values
        self.flags.setdefault(rnd, {})[sender] = flags

    def forget_before(self, rnd: int) -> None:
        for table in (self.values, self.flags):
            for old in [r for r in table if r < rnd]:
                del table[old]


def edge_penalty(rho: float, my_degree: int, their_degree: int) -> float:
    """The ADMM penalty of one edge, the same at both ends.

    Dividing by the larger of the two degrees (Metropolis-style) keeps the value symmetric and a
    robot's total proximal weight sum_j rho_lj at most `rho`, whatever the graph; measured over
    3 to 16 robots and several topologies, the best `rho` then hardly moves (benchmarks/).
    """
    return rho / max(my_degree, their_degree, 1)


def _relative_gap(v: np.ndarray, w: np.ndarray) -> float:
    """Distance of two (x, gamma) measured like the fleet's function error, relative to v."""
    dx = float(np.linalg.norm(v[:-1] - w[:-1])) / max(float(np.linalg.norm(v[:-1])), _TINY)
    return dx + abs(float(v[-1] - w[-1])) / max(1.0, abs(float(v[-1])))


class ConsensusADMM:
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
        if robot_id in neighbours:
            raise ValueError(f"robot {robot_id} lists itself as a neighbour")
        self.robot_id = robot_id
        self.neighbours = tuple(sorted(neighbours))
        self.params = params
        self.dim = features.shape[1] + 1
        self._features = features
        self._labels = labels
        self._C = C
        self._n_robots = n_robots
        degrees = neighbour_degrees or {}
        self._edges = {
            j: _Edge(self.dim, robot_id < j, edge_penalty(params.rho, len(self.neighbours), degrees.get(j, 1)))
            for j in self.neighbours
        }
        self._qp = self._build_qp()
        self._inbox = _Inbox()
        self.dropped: list[int] = []
        self.round = 0
        self.finished = False
        self.residual = float("inf")
        self._residuals: list[float] = []  # the last 2 * RATE_WINDOW, for the error estimate
        self._flags = 0
        self._prev_flags = 0
        self._prev_values: np.ndarray | None = None
        self._keep_trace = keep_trace
        self.trace: dict[int, np.ndarray] = {}
        self._values = self._local_step()
        self._record()
        if not self.neighbours:  # alone: round 0 already solved the whole problem
            self.finished = True
            self.residual = 0.0

    # -- the interface the shells drive -------------------------------------------------------
    def outgoing(self) -> StateUpdate:
        """What to publish now: this round's values, last round's piggybacked for recovery."""
        return StateUpdate(
            sender=self.robot_id,
            round=self.round,
            values=self._values.copy(),
            flags=self._flags,
            prev_values=None if self._prev_values is None else self._prev_values.copy(),
            prev_flags=self._prev_flags,
        )

    def receive(self, update: StateUpdate) -> None:
        """Keep a neighbour's exact values for the rounds still needed; ignore the rest."""
        j = update.sender
        if j not in self._edges:
            return
        if update.round in (self.round, self.round + 1):
            self._inbox.put(update.round, j, update.values, update.flags)
        if update.prev_values is not None and update.round - 1 in (self.round, self.round + 1):
            self._inbox.put(update.round - 1, j, update.prev_values, update.prev_flags)

    def missing(self) -> tuple[int, ...]:
        """Neighbours whose value for the current round has not arrived."""
        have = self._inbox.values.get(self.round, {})
        return tuple(j for j in self.neighbours if j not in have)

    def ready(self) -> bool:
        """True when the next round can be computed."""
        return not self.finished and not self.missing()

    def advance(self) -> StateUpdate:
        """Consume every neighbour's round-k values; compute round k+1."""
        if self.finished:
            raise RuntimeError(f"robot {self.robot_id} has finished; nothing to advance")
        missing = self.missing()
        if missing:
            raise RuntimeError(f"robot {self.robot_id} round {self.round}: waiting for {missing}")
        p = self.params
        theirs = self._inbox.values[self.round]
        their_flags = self._inbox.flags[self.round]
        mine = self._values
        primal = 0.0
        # round 0 holds each robot's own solution and no edge history: start z at the midpoint
        relax = p.relax if self.round > 0 else 1.0
        for j, edge in self._edges.items():
            vj = theirs[j]
            low, high = (mine, vj) if self.robot_id < j else (vj, mine)
            edge.update(low, high, relax)
            primal = max(primal, _relative_gap(mine, vj))
        dual = 0.0 if self._prev_values is None else _relative_gap(mine, self._prev_values)
        self.residual = max(primal, dual)
        self._residuals = (self._residuals + [self.residual])[-2 * RATE_WINDOW :]
        self._flags, self._prev_flags = self._next_flags(their_flags), self._flags
        self._prev_values = mine
        self._values = self._primal_step()
        self.round += 1
        self._inbox.forget_before(self.round)
        self._record()
        if self._flags >> p.diameter & 1 or self.round >= p.max_rounds:
            self.finished = True
        return self.outgoing()

    def drop_neighbour(self, j: int) -> None:
        """Continue without a neighbour that died for good.

        Removing the edge with its dual keeps sum_l lambda = 0 over the remaining robots, so
        they converge to the solution of *their* data rather than a biased point.
        """
        if j not in self._edges:
            return
        del self._edges[j]
        self.neighbours = tuple(n for n in self.neighbours if n != j)
        self.dropped.append(j)
        for table in (self._inbox.values, self._inbox.flags):
            for per_round in table.values():
                per_round.pop(j, None)
        self._qp = self._build_qp()

    @property
    def converged(self) -> bool:
        """Stopped by the residual rule (not by the round cap)."""
        return self.finished and bool(self._flags >> self.params.diameter & 1)

    @property
    def values(self) -> np.ndarray:
        """The current (x, gamma)."""
        return self._values.copy()

    def status(self) -> dict[str, Any]:
        return {
            "robot": self.robot_id,
            "round": self.round,
            "residual": self.residual,
            "error_estimate": error_estimate(self._residuals),
            "finished": self.finished,
            "converged": self.converged,
        }

    def result(self) -> dict[str, Any]:
        """x and gamma of this robot; the shell adds its counters, the launcher the c's."""
        return {
            "id": self.robot_id,
            "algorithm": self.algorithm,
            "x": self._values[:-1].tolist(),
            "gamma": float(self._values[-1]),
            "rounds": self.round,
            "converged": self.converged,
            "residual": self.residual,
            "neighbours": list(self.neighbours),
            "dropped": list(self.dropped),
        }

    # -- checkpoint ---------------------------------------------------------------------------
    def checkpoint(self) -> dict[str, Any]:
        """Everything needed to resume exactly (msgpack-able: floats as raw '<f8' bytes)."""
        return {
            "algorithm": self.algorithm,
            "robot": self.robot_id,
            "round": self.round,
            "finished": self.finished,
            "residual": self.residual,
            "residuals": list(self._residuals),
            "flags": self._flags,
            "prev_flags": self._prev_flags,
            "values": _raw(self._values),
            "prev_values": _raw(self._prev_values),
            "edges": {j: e.state() for j, e in self._edges.items()},
            "dropped": list(self.dropped),
            "inbox": [
                [rnd, j, _raw(v), self._inbox.flags[rnd][j]]
                for rnd, per in self._inbox.values.items()
                for j, v in per.items()
            ],
        }

    def restore(self, state: dict[str, Any]) -> None:
        """Resume from `checkpoint()` output (the same robot, data and parameters)."""
        if state.get("algorithm") != self.algorithm or state.get("robot") != self.robot_id:
            raise ValueError("checkpoint belongs to another robot or algorithm")
        for j in state["dropped"]:
            self.drop_neighbour(int(j))
        self.round = int(state["round"])
        self.finished = bool(state["finished"])
        self.residual = float(state["residual"])
        self._residuals = [float(r) for r in state["residuals"]]
        self._flags = int(state["flags"])
        self._prev_flags = int(state["prev_flags"])
        self._values = _arr(state["values"])
        self._prev_values = _arr(state["prev_values"])
        for j, edge_state in state["edges"].items():
            self._edges[int(j)].load(edge_state)
        self._inbox = _Inbox()
        for rnd, j, v, flags in state["inbox"]:
            self._inbox.put(int(rnd), int(j), _arr(v), int(flags))
        self.trace = {}
        self._record()

    # -- internals ----------------------------------------------------------------------------
    def _build_qp(self) -> MarginQP:
        return MarginQP(
            self._features,
            self._labels,
            x_weight=1.0 / self._n_robots,
            prox_weight=self._prox_weight(),
            C=self._C,
        )

    def _prox_weight(self) -> float:
        return float(sum(e.rho for e in self._edges.values()))

    def _local_step(self) -> np.ndarray:
        """Round 0: the robot's own max-margin solution, a warm start of the right magnitude."""
        self._qp.set_prox(0.0)
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

    def _next_flags(self, their_flags: dict[int, int]) -> int:
        below = error_estimate(self._residuals) < self.params.tol
        combined = self._flags
        for f in their_flags.values():
            combined &= f
        mask = (1 << (self.params.diameter + 1)) - 1
        return ((combined << 1) | int(below)) & mask

    def _record(self) -> None:
        if self._keep_trace:
            self.trace[self.round] = self._values.copy()
