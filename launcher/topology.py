"""Who talks to whom: the fleet's communication graph.

Nodes are robot ids. Consensus ADMM only reaches the common solution on a connected graph, so
a disconnected one is refused here, with the flag to change, rather than discovered later as
a fleet that never agrees.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import networkx as nx
import numpy as np

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
    """The communication graph of `kind` over `robot_ids`.

    ring and line follow the order of `robot_ids` (a ring of 2 is one edge, of 3 a triangle);
    geometric links robots at most `comm_range` apart, `positions[i]` belonging to
    `robot_ids[i]`. `positions` and `comm_range` are ignored by the other kinds. When
    positions are given they are stored as the node attribute "pos" (for plots).
    """
    if kind not in TOPOLOGIES:
        raise TopologyError(f"--topology: {kind!r} is not one of {', '.join(TOPOLOGIES)}")
    ids = _check_ids(robot_ids)
    graph = nx.Graph()
    graph.add_nodes_from(ids)
    if kind == "complete":
        graph.add_edges_from((a, b) for i, a in enumerate(ids) for b in ids[i + 1 :])
    elif kind in ("ring", "line"):
        nx.add_path(graph, ids)
        if kind == "ring" and len(ids) > 2:
            graph.add_edge(ids[-1], ids[0])
    if positions is not None or kind == "geometric":
        xy = _check_positions(kind, ids, positions)
        nx.set_node_attributes(graph, {robot: xy[i] for i, robot in enumerate(ids)}, "pos")
    if kind == "geometric":
        comm_range = _check_range(comm_range)
        gaps = np.hypot(*(xy[:, None, :] - xy[None, :, :]).transpose(2, 0, 1))
        rows, cols = np.nonzero(np.triu(gaps <= comm_range, k=1))
        graph.add_edges_from(
            (ids[i], ids[j]) for i, j in zip(rows.tolist(), cols.tolist(), strict=True)
        )
        if not nx.is_connected(graph):
            raise TopologyError(_disconnected_message(graph, ids, gaps, comm_range))
    return graph


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
    graph: nx.Graph, ids: list[int], gaps: np.ndarray, comm_range: float
) -> str:
    """Name the groups that cannot hear each other and the smallest range that joins them.

    That range is the longest edge of the minimum spanning tree: below it some group is cut
    off, at it the fleet is connected.
    """
    groups = sorted(sorted(group) for group in nx.connected_components(graph))
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


def neighbours(graph: nx.Graph) -> dict[int, tuple[int, ...]]:
    """Each robot's neighbours, both sorted: the lists robots are handed."""
    return {
        int(node): tuple(sorted(int(n) for n in graph.neighbors(node)))
        for node in sorted(graph.nodes)
    }


def diameter(graph: nx.Graph) -> int:
    """Most hops between any two robots: how many rounds information needs to cross the fleet."""
    if graph.number_of_nodes() == 0 or not nx.is_connected(graph):
        raise TopologyError("the diameter of a disconnected graph is unbounded")
    return int(nx.diameter(graph))
