"""Communication graphs: each kind's edges, the connectivity refusal, neighbour lists, diameter."""

from __future__ import annotations

import networkx as nx
import numpy as np
import pytest

from launcher import scenario as sc
from launcher.topology import TOPOLOGIES, TopologyError, build_topology, diameter, known_diameter, neighbours


def edges(graph: nx.Graph) -> set[frozenset[int]]:
    return {frozenset(edge) for edge in graph.edges}


def test_complete() -> None:
    graph = build_topology("complete", range(5))
    assert graph.number_of_edges() == 10 and diameter(graph) == 1
    assert neighbours(graph)[3] == (0, 1, 2, 4)


@pytest.mark.parametrize(
    ("n", "expected"),
    [
        (1, set()),
        (2, {(0, 1)}),
        (3, {(0, 1), (1, 2), (0, 2)}),
        (5, {(0, 1), (1, 2), (2, 3), (3, 4), (0, 4)}),
    ],
)
def test_ring(n: int, expected: set[tuple[int, int]]) -> None:
    graph = build_topology("ring", range(n))
    assert sorted(graph.nodes) == list(range(n))
    assert edges(graph) == {frozenset(e) for e in expected}


@pytest.mark.parametrize("n", [1, 2, 3, 6])
def test_line(n: int) -> None:
    graph = build_topology("line", range(n))
    assert edges(graph) == {frozenset((i, i + 1)) for i in range(n - 1)}
    assert diameter(graph) == n - 1


def test_ring_and_line_follow_the_given_order() -> None:
    graph = build_topology("ring", [7, 2, 5, 0])
    assert edges(graph) == {frozenset(e) for e in [(7, 2), (2, 5), (5, 0), (0, 7)]}
    assert neighbours(graph) == {0: (5, 7), 2: (5, 7), 5: (0, 2), 7: (0, 2)}
    assert list(neighbours(graph)) == [0, 2, 5, 7]


@pytest.mark.parametrize("kind", ["complete", "ring", "line"])
def test_known_diameter_is_the_searched_one(kind: str) -> None:
    """build_world checks ring, line and complete fleets by their closed-form diameter (no graph, no
    search): it is networkx's diameter of the graph built, for every size up to 40."""
    for n in range(1, 41):
        graph = build_topology(kind, range(n))
        assert known_diameter(kind, n) == (nx.diameter(graph) if n > 1 else 0) == diameter(graph)
    assert known_diameter("geometric", 10) is None


def test_diameter_beyond_a_limit_stops_at_the_first_robot_past_it() -> None:
    """``beyond``: the first eccentricity past the limit (a lower bound of the diameter, past the limit)
    instead of the diameter; within the limit, the diameter itself."""
    path = build_topology("line", [5, 0, 1, 2, 3, 4])  # robot 0 is second along the path: eccentricity 4
    assert diameter(path) == 5 and diameter(path, beyond=10) == 5
    assert diameter(path, beyond=3) == 4


def test_diameter() -> None:
    assert diameter(build_topology("ring", range(6))) == 3
    assert diameter(build_topology("ring", range(7))) == 3
    assert diameter(build_topology("complete", [4])) == 0
    split = nx.Graph()
    split.add_nodes_from([0, 1])
    with pytest.raises(TopologyError, match="disconnected"):
        diameter(split)


def test_geometric_links_robots_within_range() -> None:
    positions = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [2.0, 1.5]])
    graph = build_topology("geometric", [0, 1, 2, 3], positions=positions, comm_range=1.5)
    assert edges(graph) == {frozenset(e) for e in [(0, 1), (1, 2), (2, 3)]}
    graph = build_topology("geometric", [0, 1, 2, 3], positions=positions, comm_range=2.0)
    assert edges(graph) == {frozenset(e) for e in [(0, 1), (1, 2), (2, 3), (0, 2), (1, 3)]}
    np.testing.assert_array_equal(graph.nodes[3]["pos"], [2.0, 1.5])


def test_geometric_refuses_a_split_fleet_and_says_how_far_to_reach() -> None:
    positions = np.array([[0.0, 0.0], [1.0, 0.0], [4.4449, 0.0]])
    with pytest.raises(TopologyError) as info:
        build_topology("geometric", [0, 1, 2], positions=positions, comm_range=2.0)
    message = str(info.value)
    assert message.startswith(
        "--topology geometric --comm-range 2 leaves robots [0, 1] and [2] disconnected"
    )
    assert "raise --comm-range to at least 3.45" in message
    graph = build_topology("geometric", [0, 1, 2], positions=positions, comm_range=3.45)
    assert nx.is_connected(graph)


def test_geometric_on_placed_robots() -> None:
    shape = sc.SHAPES[sc.DEFAULT_SHAPE]()
    poses = sc.place_robots(shape, 6)
    graph = build_topology("geometric", range(6), positions=poses, comm_range=5.0)
    assert nx.is_connected(graph)
    assert {frozenset((i, (i + 1) % 6)) for i in range(6)} <= edges(graph)


@pytest.mark.parametrize(
    ("kwargs", "expected"),
    [
        ({}, "needs the robots' positions"),
        ({"positions": np.zeros((2, 2))}, "needs --comm-range"),
        (
            {"positions": np.zeros((3, 2)), "comm_range": 1.0},
            "must be 2 finite (x, y) rows, one per robot, got shape (3, 2)",
        ),
        (
            {"positions": np.zeros((2, 2)), "comm_range": 0.0},
            "--comm-range: 0.0 must be a positive",
        ),
        ({"positions": np.zeros((2, 2)), "comm_range": float("nan")}, "--comm-range"),
    ],
)
def test_geometric_needs_positions_and_a_range(kwargs: dict, expected: str) -> None:
    with pytest.raises(TopologyError) as info:
        build_topology("geometric", [0, 1], **kwargs)
    assert expected in str(info.value)


def test_bad_kinds_and_ids() -> None:
    with pytest.raises(
        TopologyError, match="--topology: 'star' is not one of complete, ring, line, geometric"
    ):
        build_topology("star", [0, 1])
    assert TOPOLOGIES == ("complete", "ring", "line", "geometric")
    with pytest.raises(TopologyError, match="at least one robot"):
        build_topology("ring", [])
    with pytest.raises(TopologyError, match=r"robot ids \[1\] appear more than once"):
        build_topology("line", [0, 1, 1])
    with pytest.raises(TopologyError, match="not a non-negative integer"):
        build_topology("complete", [0, -1])
