"""Who talks to whom: the fleet's communication graph.

Nodes are robot ids. Consensus ADMM only reaches the common solution on a connected graph, so
a disconnected one is refused here, with the flag to change, rather than discovered later as
a fleet that never agrees.

The graph is kept as plain adjacency (``links``: each robot's neighbours) on the launch path:
importing networkx took 0.13-0.14 s of the launcher's start (issue 14); ``build_topology`` and
``as_graph`` give the networkx graph to whoever wants one, and import it then.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import networkx as nx

TOPOLOGIES = ("complete", "ring", "line", "geometric")


class TopologyError(ValueError):
    """A graph that cannot be built or would not let the fleet agree; names the flag to change."""


def build_topology(
    kind: str,
    robot_ids: Sequence[int],
    *,
    positions: np.ndarray | None = None,
    comm_range: float | None = None,
) -> nx.Graph:
    """The communication graph of `kind` over `robot_ids` as a networkx graph (see ``links``).
    When positions are given they are stored as the node attribute "pos" (for plots)."""
    adjacency, xy = _adjacency(kind, robot_ids, positions, comm_range)
    return as_graph(adjacency, None if xy is None else dict(zip(adjacency, xy)))


def links(
    kind: str,
    robot_ids: Sequence[int],
    *,
    positions: np.ndarray | None = None,
    comm_range: float | None = None,
) -> dict[int, tuple[int, ...]]:
    """Each robot's neighbours (both sorted) in the graph of `kind` over `robot_ids`.

    ring and line follow the order of `robot_ids` (a ring of 2 is one edge, of 3 a triangle);
    geometric links robots at most `comm_range` apart, `positions[i]` belonging to
    `robot_ids[i]` (TopologyError if that leaves the fleet disconnected). `positions` and
    `comm_range` are ignored by the other kinds."""
    return neighbours(_adjacency(kind, robot_ids, positions, comm_range)[0])


def as_graph(adjacency: Mapping[int, Iterable[int]], positions: Mapping[int, np.ndarray] | None = None) -> nx.Graph:
    """The networkx graph of an adjacency (node attribute "pos": each robot's position).
    networkx is imported here, off the launch path."""
    import networkx as nx

    graph = nx.Graph()
    graph.add_nodes_from(adjacency)
    graph.add_edges_from((a, b) for a, near in adjacency.items() for b in near)
    if positions is not None:
        nx.set_node_attributes(graph, dict(positions), "pos")
    return graph


def _adjacency(
    kind: str, robot_ids: Sequence[int], positions: np.ndarray | None, comm_range: float | None
) -> tuple[dict[int, dict[int, None]], np.ndarray | None]:
    """The graph as adjacency dicts (insertion-ordered, as networkx keeps them) and the checked
    positions (None when not given and not needed)."""
    if kind not in TOPOLOGIES:
        raise TopologyError(f"--topology: {kind!r} is not one of {', '.join(TOPOLOGIES)}")
    ids = _check_ids(robot_ids)
    adjacency: dict[int, dict[int, None]] = {robot: {} for robot in ids}

    def link(a: int, b: int) -> None:
        adjacency[a][b] = None
        adjacency[b][a] = None

    if kind == "complete":
        for i, a in enumerate(ids):
            for b in ids[i + 1 :]:
                link(a, b)
    elif kind in ("ring", "line"):
        for a, b in zip(ids, ids[1:]):
            link(a, b)
        if kind == "ring" and len(ids) > 2:
            link(ids[-1], ids[0])
    xy = None
    if positions is not None or kind == "geometric":
        xy = _check_positions(kind, ids, positions)
    if kind == "geometric":
        comm_range = _check_range(comm_range)
        gaps = np.hypot(*(xy[:, None, :] - xy[None, :, :]).transpose(2, 0, 1))
        rows, cols = np.nonzero(np.triu(gaps <= comm_range, k=1))
        for i, j in zip(rows.tolist(), cols.tolist(), strict=True):
            link(ids[i], ids[j])
        if len(components(adjacency)) > 1:
            raise TopologyError(_disconnected_message(adjacency, ids, gaps, comm_range))
    return adjacency, xy


def components(adjacency: Mapping[int, Iterable[int]]) -> list[list[int]]:
    """The connected groups of robots, each sorted, ordered by their smallest id."""
    near = {int(a): [int(b) for b in bs] for a, bs in adjacency.items()}
    seen: set[int] = set()
    groups = []
    for start in near:
        if start in seen:
            continue
        seen.add(start)
        group, frontier = [start], [start]
        while frontier:
            for b in near[frontier.pop()]:
                if b not in seen:
                    seen.add(b)
                    group.append(b)
                    frontier.append(b)
        groups.append(sorted(group))
    return sorted(groups, key=lambda g: g[0])


def _check_ids(robot_ids: Sequence[int]) -> list[int]:
    ids = list(robot_ids)
    if not ids:
        raise TopologyError("a fleet needs at least one robot")
    for robot in ids:
        if isinstance(robot, bool) or not isinstance(robot, (int, np.integer)) or robot < 0:
            raise TopologyError(f"robot id {robot!r} is not a non-negative integer")
    ids = [int(robot) for robot in ids]
    if len(set(ids)) != len(ids):
        duplicates = sorted({robot for robot in ids if ids.count(robot) > 1})
        raise TopologyError(f"robot ids {duplicates} appear more than once")
    return ids


def _check_positions(kind: str, ids: list[int], positions: np.ndarray | None) -> np.ndarray:
    if positions is None:
        raise TopologyError(f"--topology {kind} needs the robots' positions")
    xy = np.asarray(positions, dtype=float)
    if xy.shape != (len(ids), 2) or not np.all(np.isfinite(xy)):
        raise TopologyError(
            f"--topology {kind}: positions must be {len(ids)} finite (x, y) rows, one per robot, "
            f"got shape {xy.shape}"
        )
    return xy


def _check_range(comm_range: float | None) -> float:
    if comm_range is None:
        raise TopologyError("--topology geometric needs --comm-range (the radio range)")
    if not (math.isfinite(comm_range) and comm_range > 0):
        raise TopologyError(f"--comm-range: {comm_range!r} must be a positive distance")
    return float(comm_range)


def _disconnected_message(
    adjacency: Mapping[int, Iterable[int]], ids: list[int], gaps: np.ndarray, comm_range: float
) -> str:
    """Name the groups that cannot hear each other and the smallest range that joins them.

    That range is the longest edge of the minimum spanning tree: below it some group is cut
    off, at it the fleet is connected.
    """
    import networkx as nx  # a refused fleet only: off the launch path

    groups = sorted(components(adjacency))
    complete = nx.Graph()
    complete.add_weighted_edges_from(
        (ids[i], ids[j], gaps[i, j]) for i in range(len(ids)) for j in range(i + 1, len(ids))
    )
    needed = max(w for _, _, w in nx.minimum_spanning_tree(complete).edges(data="weight"))
    listed = " and ".join(str(group) for group in groups)
    return (
        f"--topology geometric --comm-range {comm_range:g} leaves robots {listed} disconnected; "
        f"raise --comm-range to at least {_round_up(needed):g} "
        "(the widest gap the fleet must bridge)"
    )


def _round_up(value: float, digits: int = 3) -> float:
    """value rounded up to `digits` significant digits, so the advised range really suffices."""
    scale = 10.0 ** (digits - 1 - math.floor(math.log10(value)))
    return math.ceil(value * scale) / scale


def _adjacency_of(graph: nx.Graph | Mapping[int, Iterable[int]]) -> dict[int, list[int]]:
    """A networkx graph's or an adjacency mapping's neighbour lists."""
    if hasattr(graph, "adj"):
        return {node: list(graph.adj[node]) for node in graph.nodes}
    return {int(a): [int(b) for b in bs] for a, bs in graph.items()}


def neighbours(graph: nx.Graph | Mapping[int, Iterable[int]]) -> dict[int, tuple[int, ...]]:
    """Each robot's neighbours, both sorted: the lists robots are handed."""
    adjacency = _adjacency_of(graph)
    return {int(node): tuple(sorted(int(n) for n in adjacency[node])) for node in sorted(adjacency)}


def diameter(graph: nx.Graph | Mapping[int, Iterable[int]], *, beyond: int | None = None) -> int:
    """Most hops between any two robots: how many rounds information needs to cross the fleet.

    ``beyond``: stop at the first robot whose eccentricity exceeds it and return that eccentricity
    (then only "more than ``beyond``" is exact): a check against a limit refuses a wide sparse
    graph after one breadth-first search instead of one per robot (N of them: minutes at 10^4)."""
    from agents.allreduce import hop_rows  # one vectorized search per robot (geometric 400: 5.5 s -> 0.3 s)

    adjacency = _adjacency_of(graph)
    if not adjacency or len(components(adjacency)) > 1:
        raise TopologyError("the diameter of a disconnected graph is unbounded")
    widest = 0
    for _, hops in hop_rows(adjacency):
        widest = max(widest, int(hops.max()))
        if beyond is not None and widest > beyond:
            break
    return widest


def known_diameter(kind: str, n_robots: int) -> int | None:
    """The diameter of `kind` over n robots where it needs no search (complete, ring, line), else None."""
    if n_robots <= 1:
        return 0
    return {"complete": 1, "ring": n_robots // 2, "line": n_robots - 1}.get(kind)
