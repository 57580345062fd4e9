"""Autogrid on a sparse graph losing a robot for good: its frames flood who was dropped (agents/rounds.py
`floods_gone`), its edge-form sub-machines (the answer's ADMM, the sigma sweep's tasks) take every
neighbour's list with its values, weigh |x|^2 by 1 / (robots left) in their soft solves and widen their
stop, and its counted phases cover the survivors' graph (`AdaptiveGridCore._reach`). Before, the soft
phases kept 1 / N: the 4-ring without robot 1 settled 0.31 from its survivors' answer, NOT converged."""

from __future__ import annotations

import numpy as np
import pytest

from agents.autogrid_rules import AutoGridParams
from agents.kernel import GridBasis
from agents.problem import solve_central
from launcher.fleet import CrashPlan, spec_for_run
from launcher.simulate import simulate_fleet
from tests.conftest import PAPER, make_run
from tests.test_crash import TIMING
from tests.test_survivors import _lockstep


def autogrid_fleet(robots: int, topology: str, *, C: float | None, dead: int = 1):
    """(world, spec) of an autogrid fleet on a sparse graph, as a run losing ``dead`` for good gives it
    (the paper's sigma and start grid, as `--preset paper`: no sigma sweep, a fast test)."""
    world, spec, _ = make_run(fleet_id=f"survivors-autogrid-{topology}", timing=TIMING, robots=robots,
                              topology=topology, C=C, algorithm="autogrid", model="svm", grid=PAPER["grid"],
                              sigma=PAPER["sigma"])
    return world, spec_for_run(spec, [CrashPlan(dead, 40)], restart=False, restart_after=0.5)


def survivors_error(world, rows: list[dict], dead: int, C: float | None) -> float:
    """Largest relative function error of the robots' answers against the exact central solve of the
    survivors' data on the grid and sigma the fleet agreed on."""
    kept = [r for r in world.robots if r.id != dead]
    points, labels = np.vstack([r.points for r in kept]), np.concatenate([r.labels for r in kept])
    grid = np.asarray(rows[0]["grid"])
    assert all(np.array_equal(np.asarray(r["grid"]), grid) and r["sigma"] == rows[0]["sigma"] for r in rows)
    basis = GridBasis(grid, rows[0]["sigma"])
    central = solve_central(basis, points, labels, C)
    return max(basis.function_error(np.asarray(r["c"]), r["gamma"], central.c, central.gamma) for r in rows)


@pytest.fixture(scope="module")
def soft_ring():
    return autogrid_fleet(4, "ring", C=10.0)


def test_a_sparse_soft_autogrid_fleet_losing_a_robot_ends_on_its_survivors_exact_answer(soft_ring):
    world, spec = soft_ring
    out = simulate_fleet(spec, crashes=[CrashPlan(1, 40)], restart=False)
    assert [r["id"] for r in out.robots] == [0, 2, 3]
    assert all(r["converged"] and r["stopped"] == "finished" and r["frames_rejected"] == 0 for r in out.robots)
    assert len({r["rounds"] for r in out.robots}) == 1
    assert survivors_error(world, out.robots, dead=1, C=10.0) < 1e-3  # before: 0.31


def test_a_hard_autogrid_six_ring_falling_back_to_soft_after_a_loss_converges():
    """Its hard solves turn ill-conditioned and fall back to the soft margin (C = soft_C) in a round an
    alarm's max-consensus sets: on the survivors' path (diameter 4 > D = 3) that consensus must reach
    5 hops. Before: split, NOT converged; with the lists but D-hop phases: one end switched 3 rounds
    late, and the fleet settled 0.28 from the answer."""
    world, spec = autogrid_fleet(6, "ring", C=None)
    out = simulate_fleet(spec, crashes=[CrashPlan(1, 40)], restart=False)
    assert [r["id"] for r in out.robots] == [0, 2, 3, 4, 5]
    assert all(r["converged"] and r["stopped"] == "finished" for r in out.robots)
    assert len({r["rounds"] for r in out.robots}) == 1 and len({tuple(map(tuple, r["phases"])) for r in out.robots}) == 1
    C = None if out.robots[0]["margin"] == "hard" else AutoGridParams(model="svm").soft_C
    assert survivors_error(world, out.robots, dead=1, C=C) < 1e-3


def test_a_sparse_autogrid_fleet_without_a_loss_sends_no_list_and_keeps_its_bits(soft_ring):
    """No loss, no list: the run with the lists on is the run with them off, bit for bit."""
    _, spec = soft_ring
    on, heard = _lockstep(spec, dead=-1, at=0, rounds=3000)
    off, _ = _lockstep(spec, dead=-1, at=0, rounds=3000, floods=False)
    assert all(g == () for per in heard.values() for g in per.values())
    assert all(c.converged for c in on.values())
    for i, c in on.items():
        assert c.round == off[i].round and c.outgoing() == off[i].outgoing()
        np.testing.assert_array_equal(c.values, off[i].values)


def test_an_autogrid_survivor_restarted_after_the_news_goes_on_bit_for_bit(soft_ring):
    """Robot 3 (two hops from the loss) rebuilt from its round-45 checkpoint, inside the answer's ADMM:
    its sub-machine's list and weights come back, and every robot ends on the same bits."""
    _, spec = soft_ring
    clean, _ = _lockstep(spec, dead=1, at=40, rounds=3000)
    frames: list = []
    again, _ = _lockstep(spec, dead=1, at=40, rounds=3000, restart=(3, 45), frames=frames)
    before, after = frames
    assert before == after and after.gone == (1,)
    for i, c in clean.items():
        assert c.converged and again[i].round == c.round and again[i].gone == c.gone == (1,)
        np.testing.assert_array_equal(again[i].values, c.values)


def test_a_complete_soft_autogrid_fleet_losing_a_robot_ends_on_its_survivors_exact_answer():
    """A complete graph floods no lists (every survivor sees the drop itself), so a sub-machine autogrid
    builds after the loss (here its grid refinements) was handed none and weighed |x|^2 by 1 / N: the
    survivors settled 0.19-0.26 from their answer, NOT converged. It is now handed the robots dropped."""
    world, spec, _ = make_run(fleet_id="survivors-autogrid-complete", timing=TIMING, robots=4, C=10.0,
                              algorithm="autogrid", model="svm", grid=PAPER["grid"], sigma=PAPER["sigma"])
    spec = spec_for_run(spec, [CrashPlan(1, 40)], restart=False, restart_after=0.5)
    out = simulate_fleet(spec, crashes=[CrashPlan(1, 40)], restart=False)
    assert [r["id"] for r in out.robots] == [0, 2, 3]
    assert all(r["converged"] and r["stopped"] == "finished" for r in out.robots)
    assert survivors_error(world, out.robots, dead=1, C=10.0) < 1e-3
