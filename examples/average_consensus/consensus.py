"""Average consensus as a shapefleet fleet algorithm: the example of agents/extension.py.

Every robot starts from the sums of its own data, s_i = (sum of x, sum of y, number of points),
and the fleet runs linear average consensus with Metropolis weights of the communication graph,

    s_i <- s_i + sum_j w_ij (s_j - s_i),      w_ij = 1 / (1 + max(deg_i, deg_j)),

which keeps the fleet's sum of s fixed (w_ij = w_ji) and converges to its mean. Each robot's
answer is the centroid of *all* data, mean(s)[:2] / mean(s)[2]: the exact answer is the
centralized np.mean of every point (``reference``).

A robot that dies for good takes with it what it exchanged: the survivors' sum is no longer the
sum of *their* data. ``Average`` keeps, per edge, the total it has moved over that edge and
undoes it when the neighbour is dropped (in its next update, so both ends of every live edge
always use the same published values): the survivors then converge to the centroid of their own
data, exactly. ``NaiveAverage`` just forgets the edge: it converges -- the robots agree -- to a
biased point (docs/testing.md shows the test that catches it).

The module does no I/O, reads no clock and opens no socket: the shells do.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from agents.extension import FleetAlgorithm
from agents.rounds import from_bytes, to_bytes


class Average(FleetAlgorithm):
    """Average consensus of the data sums; exact for the survivors when a robot dies."""

    algorithm = "average-consensus"
    #: undo the flows over an edge whose neighbour died for good (NaiveAverage: no)
    undo_dead_edges = True
    #: nothing in this update can fail like a QP can
    solve_errors = (FloatingPointError,)

    def __init__(self, robot_id: int, neighbours: tuple[int, ...], points: np.ndarray, *,
                 graph: dict[int, tuple[int, ...]], tol: float, diameter: int, max_rounds: int,
                 keep_trace: bool = True) -> None:
        super().__init__(robot_id, neighbours, 3, diameter=diameter, round_cap=max_rounds, keep_trace=keep_trace)
        pts = np.asarray(points, dtype=float).reshape(-1, 2)
        deg = {i: len(n) for i, n in graph.items()}
        # weights of the fleet's *initial* graph: both ends of an edge use the same one, always
        self._weights = {j: 1.0 / (1 + max(deg[robot_id], deg[j])) for j in self.neighbours}
        self._flow = {j: np.zeros(3) for j in self.neighbours}
        self._pending = np.zeros(3)  # flows of dropped edges, undone in the next update
        self._tol = float(tol)
        self._values = np.array([pts[:, 0].sum(), pts[:, 1].sum(), float(len(pts))])
        self._record()

    # -- the four hooks of agents/extension.py ----------------------------------------------
    @classmethod
    def from_spec(cls, spec: Any, robot_id: int, *, keep_trace: bool = True) -> Average:
        """Robot ``robot_id``: its points, its neighbours, the whole graph (for the weights) and
        the run's tol, round cap and graph diameter."""
        me = spec.robots[robot_id]
        p = spec.algorithm_params  # agents.extension.FleetParams: tol, max_rounds, diameter
        return cls(robot_id, me.neighbours, me.points, graph=spec.graph, tol=p.tol, diameter=p.diameter,
                   max_rounds=p.max_rounds, keep_trace=keep_trace)

    @classmethod
    def frame_dim(cls, spec: Any) -> int:
        return 3

    @classmethod
    def reference(cls, spec: Any) -> np.ndarray:
        """The centroid of every point of the robots in ``spec``, computed in one place."""
        return np.vstack([r.points for r in spec.robots.values()]).mean(axis=0)

    def answer(self) -> np.ndarray:
        return self._values[:2] / self._values[2]

    # -- RoundCore -------------------------------------------------------------------------
    def _step(self, mine: np.ndarray, theirs: dict[int, np.ndarray]) -> tuple[np.ndarray, bool]:
        new = mine - self._pending
        self._pending = np.zeros(3)
        gap = 0.0
        for j, v in theirs.items():
            moved = self._weights[j] * (v - mine)
            self._flow[j] += moved
            new = new + moved
            gap = max(gap, float(np.max(np.abs(v - mine))) / max(1.0, float(np.max(np.abs(mine)))))
        self.residual = gap
        return new, gap < self._tol

    def _forget_edge(self, j: int) -> None:
        flow = self._flow.pop(j, np.zeros(3))
        if self.undo_dead_edges:
            self._pending = self._pending + flow

    def _save_state(self) -> dict[str, Any]:
        return {"flow": [[j, to_bytes(f)] for j, f in self._flow.items()], "pending": to_bytes(self._pending)}

    def _load_state(self, state: dict[str, Any]) -> None:
        self._flow = {int(j): from_bytes(f) for j, f in state["flow"]}
        self._pending = from_bytes(state["pending"])


class NaiveAverage(Average):
    """The same update, but a dead neighbour's edge is just forgotten: biased survivors."""

    algorithm = "naive-average-consensus"
    undo_dead_edges = False
