"""The example algorithm (consensus.py) on both shells, through the pytest plugin's ``fleet``.

What it shows: a user's algorithm plugged in by dotted path runs in ``simulate`` and ``launch``
with the same iterates (bit for bit, round for round), under loss, delay and a crash with a
restart from a checkpoint, and its answer is measured against the exact centralized one.
"""

import numpy as np
import pytest

from launcher import api

AVERAGE = "examples.average_consensus:Average"
NAIVE = "examples.average_consensus:NaiveAverage"
RING = {"robots": 4, "topology": "ring", "tol": 1e-10, "seed": 3}


def centroid(result, ids=None) -> np.ndarray:
    """The exact answer, computed here from the run's data.csv, not by the algorithm."""
    data = np.genfromtxt(result.out / "data.csv", delimiter=",", names=True)
    keep = np.isin(data["robot"], list(ids if ids is not None else result.participants))
    return np.array([data["x"][keep].mean(), data["y"][keep].mean()])


def same_iterates(a, b, *, restarted=()) -> None:
    """Every round both recorded, bit for bit; same rounds; same final vector."""
    assert [r.id for r in a.robots] == [r.id for r in b.robots]
    for ra, rb in zip(a.robots, b.robots):
        assert ra.rounds == rb.rounds and ra.stopped == rb.stopped == "finished"
        common = sorted(set(ra.trace) & set(rb.trace))
        first = 0 if ra.id not in restarted else min(ra.trace)
        assert common == list(range(first, rb.rounds + 1))
        np.testing.assert_array_equal(np.array([ra.trace[k] for k in common]), np.array([rb.trace[k] for k in common]))
        np.testing.assert_array_equal(ra.values, rb.values)


def test_simulate_reaches_the_exact_centroid(fleet):
    r = fleet(mode="simulate", algorithm=AVERAGE, **RING)
    assert r.converged, r.verdict
    for robot in r.robots:
        np.testing.assert_allclose(robot.answer, centroid(r), rtol=0, atol=1e-9)
    assert r.error < 1e-9


@pytest.mark.fleet_processes
def test_launch_same_iterates_as_simulate_under_loss_and_a_crash(fleet):
    want = fleet(mode="simulate", algorithm=AVERAGE, **RING)
    got = fleet(algorithm=AVERAGE, loss=0.3, delay="5ms", jitter="2ms", crash="2@8", restart_after=0.3, **RING)
    assert got.converged, got.verdict
    assert got.robot(2).counters["restarts"] == 1
    same_iterates(got, want, restarted=(2,))
    assert got.error < 1e-9


@pytest.mark.fleet_processes
def test_dead_robot_survivors_reach_their_own_centroid(fleet):
    r = fleet(algorithm=AVERAGE, crash="1@5", no_restart=True, dead_after="1s", **RING)
    assert r.participants == (0, 2, 3) and r.absent == (1,)
    assert r.converged, r.verdict
    for robot in r.robots:  # the centroid of the survivors' data: the flows to robot 1 undone
        np.testing.assert_allclose(robot.answer, centroid(r, (0, 2, 3)), rtol=0, atol=1e-9)


@pytest.mark.fleet_processes
def test_naive_survivors_agree_on_a_biased_answer(fleet):
    """What docs/testing.md's failing test catches: agreement is not correctness."""
    r = fleet(algorithm=NAIVE, crash="1@5", no_restart=True, dead_after="1s", **RING)
    assert r.raw["agreement"]["disagreement"] <= 1e-10  # the survivors agree with each other...
    assert all(robot.converged for robot in r.robots)  # ...and each met its stopping rule,
    bias = max(float(np.linalg.norm(robot.answer - centroid(r, (0, 2, 3)))) for robot in r.robots)
    assert bias > 1e-3, bias  # ...on a point that is not their data's centroid:
    assert r.error > 1e-3 and not r.converged and "biased point" in r.verdict  # the verdict says so


def test_bad_dotted_path_is_one_usage_error(fleet):
    with pytest.raises(api.UsageError, match=r"--algorithm: 'examples.average_consensus:Nope': module .* has no 'Nope'"):
        fleet(mode="simulate", algorithm="examples.average_consensus:Nope")


def test_in_process_crash_survivors_exact_naive_biased(fleet):
    """simulate injects crashes on its virtual clock: fast, deterministic, no process."""
    r = fleet(mode="simulate", algorithm=AVERAGE, crash="1@5", no_restart=True, dead_after="1s", **RING)
    assert r.participants == (0, 2, 3) and r.absent == (1,) and r.converged, r.verdict
    for robot in r.robots:
        np.testing.assert_allclose(robot.answer, centroid(r, (0, 2, 3)), rtol=0, atol=1e-9)
    naive = fleet(mode="simulate", algorithm=NAIVE, crash="1@5", no_restart=True, dead_after="1s", **RING)
    assert not naive.converged and naive.error > 1e-3 and "biased point" in naive.verdict
