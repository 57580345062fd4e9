"""Exact all-reduce over the communication graph, as a per-robot sans-IO schedule.

Every robot knows the whole graph (the fleet file lists every robot's neighbours), so every
robot computes the same plan without talking. Two schedules:

* gather (the default): flooding by distance shells. At offset r a robot publishes the
  contributions of the robots exactly r hops away (r = 0: its own); a neighbour learns from these
  the robots r + 1 hops from *it*. After D rounds (D = the diameter) every robot holds an exact
  copy of every contribution and combines them in robot-id order. A complete graph is D = 1:
  one round, one contribution per frame. Frames carry `slots` contributions, the largest shell
  of any robot (2 on a ring); with `max_slots` a larger shell is sent over several rounds.
* tree: BFS tree from the centre (least eccentricity, ties -> lowest id), neighbours visited
  in id order. Convergecast up (a robot at depth d publishes its subtree's partial sum at
  offset h - d, h the tree height), broadcast down (it publishes the total at offset h + d):
  2h >= D rounds, one contribution per frame, and only partial sums travel.

gather needs D rounds where the tree needs 2h (on a ring D = h: half the rounds) for the same
bytes on a ring (2 slots x D rounds = 1 slot x 2h); on star-like graphs its frames are larger.

Why the results are bit-identical everywhere: under gather every robot adds the same vectors
(exact copies) in the same order; under the tree the total is computed once (at the centre) and
copied. Floating-point addition is not associative, so "the same sum" would not be enough.

The combine is element-wise: the first ``n_min`` entries take the minimum, the rest the sum.
No I/O, no clock: the caller feeds every neighbour's frame of the current round to `step`.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np


def combine(a: np.ndarray, b: np.ndarray, n_min: int) -> np.ndarray:
    """a (+) b: minimum over the first n_min entries, sum over the rest."""
    out = a + b
    if n_min:
        out[:n_min] = np.minimum(a[:n_min], b[:n_min])
    return out


def reduce_in_order(parts: Sequence[np.ndarray], n_min: int) -> np.ndarray:
    """Left fold of `combine` over `parts` in the order given (the order fixes the bits)."""
    acc = np.array(parts[0], dtype=float, copy=True)
    for p in parts[1:]:
        acc = combine(acc, p, n_min)
    return acc


def _bfs(graph: Mapping[int, Sequence[int]], root: int) -> tuple[dict[int, int], dict[int, int | None]]:
    """Hop distance from root to every reachable robot, and each one's parent in the breadth-first
    tree (neighbours visited in sorted order: every robot builds the same tree)."""
    dist = {root: 0}
    parent: dict[int, int | None] = {root: None}
    queue = deque([root])
    while queue:
        i = queue.popleft()
        for j in sorted(graph[i]):
            if j not in dist:
                dist[j] = dist[i] + 1
                parent[j] = i
                queue.append(j)
    return dist, parent


def check_graph(graph: Mapping[int, Sequence[int]]) -> None:
    """ValueError unless the graph is undirected, loop-free and connected."""
    ids = set(graph)
    for i, nbrs in graph.items():
        for j in nbrs:
            if j == i or j not in ids or i not in graph[j]:
                raise ValueError(f"communication graph: link {i}-{j} is not a link between two distinct robots both list")
    if ids and len(_bfs(graph, min(ids))[0]) != len(ids):
        raise ValueError("communication graph is not connected: no exact fleet-wide sum exists")


#: schedules: "gather" floods contributions (diameter rounds), "tree" reduces along a spanning tree
SCHEDULES = ("gather", "tree")


@dataclass(frozen=True)
class ReducePlan:
    """One robot's part of the fleet's reduction schedule (the same computation on every robot).

    gather: at offset r (0 <= r < D, D the diameter) a robot publishes the contributions of the
    robots at exactly r hops from it (its "sphere", in id order, zero-padded to `slots`); from
    its neighbours' spheres it learns its own sphere r + 1. After D rounds every robot holds
    every contribution, an exact copy, and combines them in id order. A complete graph is the
    case D = 1 (each robot publishes its own contribution once).
    tree: convergecast to the centre and broadcast back along a BFS tree (2h rounds, 1 slot).
    """

    robot: int
    ids: tuple[int, ...]  # every robot, ascending
    schedule: str  # "gather" | "tree"
    slots: int  # contributions per frame (the same for every robot)
    rounds: int  # rounds per reduction
    # gather: sends[r] = robots whose contributions this robot publishes at offset r;
    # learns[r] = (robot k, neighbour i, slot in i's frame) of what it reads at offset r
    sends: tuple[tuple[int, ...], ...] = ()
    learns: tuple[tuple[tuple[int, int, int], ...], ...] = ()
    # tree
    root: int = 0
    parent: int | None = None
    children: tuple[int, ...] = ()
    depth: int = 0
    height: int = 0

    @property
    def period(self) -> int:
        """Rounds per reduction."""
        return self.rounds

    @property
    def complete(self) -> bool:
        return self.schedule == "gather" and self.rounds == 1

    def describe(self) -> str:
        if self.schedule == "tree":
            return f"tree (root {self.root}, height {self.height}, {self.rounds} rounds)"
        if self.complete:
            return "complete (1 round)"
        return f"gather ({self.rounds} rounds, {self.slots} contributions per frame)"

    @classmethod
    def build(cls, graph: Mapping[int, Sequence[int]], robot: int, schedule: str = "gather",
              max_slots: int | None = None) -> ReducePlan:
        """The plan of `robot`, from every robot's neighbour list. `max_slots` (gather): at most that many
        contributions per frame -- a shell larger than that (on any robot) is sent over several rounds,
        `max_slots` at a time in id order (the relay hub's end-game: frames within the frame budget).

        The fleet-wide part (hop distances, spheres) is computed once per graph and shared by
        every robot's plan built in the same process (:func:`_layout`): per robot it was all-pairs
        breadth-first search and spheres found by scanning every robot per hop count, O(N^2 D)
        per robot, a minute for a 200-robot ring (benchmarks/results/simulate_cost.md)."""
        if schedule not in SCHEDULES:
            raise ValueError(f"all-reduce schedule must be gather or tree, got {schedule!r}")
        lay = _layout(_graph_key(graph))
        if robot not in lay.index:
            raise ValueError(f"robot {robot} is not in the communication graph")
        ids, me = lay.ids, lay.index[robot]
        if schedule == "gather" or lay.diameter <= 1:
            shells = max(lay.diameter, 1)
            widest = int(lay.counts[:, :shells].max())
            cap = widest if max_slots is None else max(1, min(int(max_slots), widest))
            parts = [-(-int(lay.counts[:, r].max()) // cap) for r in range(shells)]  # rounds per shell (>= 1)
            ranked = np.asarray(ids)
            mine = lay.dist[me]
            sends, learns = [], []
            for r in range(shells):
                shell = ranked[mine == r].tolist()  # in id order
                sends += [tuple(shell[p * cap : (p + 1) * cap]) for p in range(parts[r])]
                ks = np.flatnonzero(mine == r + 1)  # in id order
                part_learns: list[list[tuple[int, int, int]]] = [[] for _ in range(parts[r])]
                if len(ks):
                    # the lowest-id neighbour i with k at r hops from it (neighbours in id order), and k's place
                    # among the robots r hops from i, in id order: round place // cap of the shell, slot place % cap
                    via = near_of(lay, robot)[np.argmax(lay.dist[np.ix_(near_of(lay, robot), ks)] == r, axis=0)]
                    for k, i, place in zip(ranked[ks].tolist(), ranked[via].tolist(), lay.rank[via, ks].tolist()):
                        part_learns[place // cap].append((k, i, place % cap))
                learns += [tuple(part) for part in part_learns]
            return cls(robot, ids, "gather", cap, len(sends), sends=tuple(sends), learns=tuple(learns))
        graph = lay.graph
        ecc = lay.dist.max(axis=1)
        root = ids[int(np.argmin(ecc))]  # least eccentricity, ties -> lowest id (ids ascending)
        depth, parent = _bfs(graph, root)
        height = max(depth.values())
        children = tuple(sorted(j for j, p in parent.items() if p == robot))
        return cls(
            robot, ids, "tree", 1, 2 * height,
            root=root, parent=parent[robot], children=children, depth=depth[robot], height=height,
        )


@dataclass(frozen=True)
class _Layout:
    """What every robot's plan shares: the graph, robots by index (ids ascending), hop distances."""

    graph: dict[int, tuple[int, ...]]
    ids: tuple[int, ...]
    index: dict[int, int]
    dist: np.ndarray  # dist[a, b]: hops between robots ids[a] and ids[b]
    rank: np.ndarray  # rank[a, b]: ids[b]'s place among the robots dist[a, b] hops from ids[a], in id order
    counts: np.ndarray  # counts[a, r]: robots r hops from ids[a]
    diameter: int


def near_of(lay: _Layout, robot: int) -> np.ndarray:
    """A robot's neighbours as layout indices, ascending."""
    return np.asarray(sorted(lay.index[int(j)] for j in lay.graph[robot]), dtype=np.intp)


def _graph_key(graph: Mapping[int, Sequence[int]]) -> tuple[tuple[int, tuple[int, ...]], ...]:
    """The graph as a hashable key (neighbour tuples are kept as given: no per-robot copy of E entries)."""
    return tuple(sorted((int(i), n if isinstance(n, tuple) else tuple(n)) for i, n in graph.items()))


def hop_rows(graph: Mapping[int, Sequence[int]]) -> Iterator[tuple[int, np.ndarray]]:
    """(robot, its hops to every robot in ascending id order, -1 where unreachable), robot by robot
    in ascending id order: one breadth-first search each, vectorized over each shell (numpy)."""
    ids = sorted(int(i) for i in graph)
    index = {r: a for a, r in enumerate(ids)}
    n = len(ids)
    near = [np.fromiter((index[int(j)] for j in graph[i]), dtype=np.intp, count=len(graph[i])) for i in ids]
    degree = np.fromiter((len(x) for x in near), dtype=np.intp, count=n)
    starts = np.concatenate(([0], np.cumsum(degree)))
    flat = np.concatenate(near) if n else np.zeros(0, dtype=np.intp)
    for a in range(n):
        row = np.full(n, -1, dtype=np.int32)
        row[a] = 0
        shell, hops = np.array([a]), 0
        while len(shell):
            hops += 1
            lengths = degree[shell]
            offsets = np.repeat(starts[shell] - np.concatenate(([0], np.cumsum(lengths)[:-1])), lengths)
            fresh = np.zeros(n, dtype=bool)
            fresh[flat[offsets + np.arange(int(lengths.sum()))]] = True
            fresh &= row < 0
            shell = np.flatnonzero(fresh)
            row[shell] = hops
        yield ids[a], row


@lru_cache(maxsize=2)
def _layout(key: tuple[tuple[int, tuple[int, ...]], ...]) -> _Layout:
    """Hop distances between all robots (:func:`hop_rows`) and each robot's spheres in id order;
    ValueError as :func:`check_graph`."""
    graph = {i: tuple(int(j) for j in n) for i, n in key}
    check_graph(graph)
    ids = tuple(i for i, _ in key)
    index = {r: a for a, r in enumerate(ids)}
    n = len(ids)
    dist = np.stack([row for _, row in hop_rows(graph)]) if n else np.zeros((0, 0), dtype=np.int32)
    diameter = int(dist.max()) if n else 0
    order = np.argsort(dist, axis=1, kind="stable")  # by hops, then by id (ids ascending)
    counts = np.stack([np.bincount(row, minlength=diameter + 1) for row in dist]) if n else np.zeros((0, 1), int)
    first = np.concatenate((np.zeros((n, 1), dtype=np.intp), np.cumsum(counts, axis=1)[:, :-1]), axis=1)
    rank = np.empty((n, n), dtype=np.int32)
    rows = np.arange(n)[:, None]
    rank[rows, order] = np.arange(n)[None, :] - np.take_along_axis(first, np.take_along_axis(dist, order, 1), 1)
    return _Layout(graph, ids, index, dist, rank, counts, diameter)


def frame_slots(graph: Mapping[int, Sequence[int]], schedule: str = "gather", max_slots: int | None = None) -> int:
    """Contributions per frame of `schedule` on this graph (the fleet's frame length / payload)."""
    return ReducePlan.build(graph, min(graph), schedule, max_slots).slots


class AllReduce:
    """One robot's side of repeated reductions: `begin` a reduction, `step` once per round.

    The frame a robot publishes in each round of a reduction is what `begin` / `step` return
    (`plan.slots * size` floats); slots where the robot has nothing to say are zeros. After the
    reduction's last round `done` is True and `total` is the fleet's combined value, bit for bit
    the same on every robot.
    """

    def __init__(self, plan: ReducePlan, size: int, n_min: int = 0) -> None:
        if not 0 <= n_min <= size:
            raise ValueError(f"n_min must be in [0, {size}], got {n_min}")
        self.plan = plan
        self.size = size
        self.n_min = n_min
        self.offset = 0  # offset of the frame last returned, within the reduction
        self.own: np.ndarray = np.zeros(size)
        self.known: dict[int, np.ndarray] = {}  # gather: the contributions received so far
        self.total: np.ndarray | None = None

    @property
    def frame_size(self) -> int:
        return self.plan.slots * self.size

    @property
    def done(self) -> bool:
        return self.total is not None and self.offset == self.plan.period

    def begin(self, contribution: np.ndarray) -> np.ndarray:
        """Start a reduction with this robot's contribution; the frame of offset 0."""
        contribution = np.asarray(contribution, dtype=float)
        if contribution.shape != (self.size,):
            raise ValueError(f"contribution has shape {contribution.shape}, expected ({self.size},)")
        self.own = contribution.copy()
        self.known = {self.plan.robot: self.own}
        self.offset = 0
        self.total = None
        return self._frame(0, {})

    def step(self, theirs: Mapping[int, np.ndarray]) -> np.ndarray:
        """Consume the neighbours' frames of the current offset; the frame of the next one."""
        if self.offset >= self.plan.period:
            raise RuntimeError("the reduction is complete; begin the next one")
        if self.plan.schedule == "gather":
            n = self.size
            for k, i, slot in self.plan.learns[self.offset]:
                self.known[k] = np.array(theirs[i][slot * n : (slot + 1) * n], dtype=float, copy=True)
        self.offset += 1
        return self._frame(self.offset, theirs)

    def contributions(self) -> np.ndarray:
        """Gather, once done: every robot's contribution, a row each in id order (exact copies, the same
        on every robot) -- for a caller that needs more than their combination (the relay's end-game)."""
        if self.plan.schedule != "gather" or not self.done:
            raise RuntimeError("contributions are known after a completed gather")
        return np.array([self.known[k] for k in self.plan.ids])

    def _pad(self, parts: Sequence[np.ndarray]) -> np.ndarray:
        out = np.zeros(self.frame_size)
        for slot, part in enumerate(parts):
            out[slot * self.size : (slot + 1) * self.size] = part
        return out

    def _frame(self, offset: int, theirs: Mapping[int, np.ndarray]) -> np.ndarray:
        p = self.plan
        if p.schedule == "gather":
            if offset == p.period:
                self.total = reduce_in_order([self.known[k] for k in p.ids], self.n_min)
                return self._pad([self.total]) if p.slots == 1 else np.zeros(self.frame_size)
            return self._pad([self.known[k] for k in p.sends[offset]])
        up, down = p.height - p.depth, p.height + p.depth
        if offset == up:  # the subtree's partial sum: own first, then children in id order
            partial = reduce_in_order([self.own, *(theirs[c] for c in p.children)], self.n_min)
            if p.parent is None:
                self.total = partial
            return partial.copy()
        if offset == down:  # the parent's total, passed on
            self.total = np.array(theirs[p.parent], dtype=float, copy=True)
            return self.total.copy()
        return np.zeros(self.size)

    # -- checkpoint --------------------------------------------------------------------------
    def save(self) -> dict[str, Any]:
        return {
            "offset": self.offset,
            "own": np.asarray(self.own, "<f8").tobytes(),
            "known": [[int(k), np.asarray(v, "<f8").tobytes()] for k, v in sorted(self.known.items())],
            "total": None if self.total is None else np.asarray(self.total, "<f8").tobytes(),
        }

    def load(self, state: Mapping[str, Any]) -> None:
        self.offset = int(state["offset"])
        self.own = np.frombuffer(state["own"], "<f8").copy()
        self.known = {int(k): np.frombuffer(v, "<f8").copy() for k, v in state["known"]}
        self.total = None if state["total"] is None else np.frombuffer(state["total"], "<f8").copy()
