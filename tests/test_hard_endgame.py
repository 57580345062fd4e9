"""The exact end-game on hard margins (agents/soft_endgame.py with C = inf, `AutoGridParams.hard_endgame`):
autogrid's hard answer solve on a complete graph runs the block Krylov end-game with B empty and no upper
bound, and stops when every robot certified its own rows. Checked on a small fleet: the stop is the exact
hard optimum (not a tolerance away), the same bits on every robot, earlier than the ADMM's own stop, and a
restored robot continues bit for bit. The outlines' rounds are measured in benchmarks/, not here."""

from __future__ import annotations

import numpy as np
import pytest

from agents.problem import solve_central

from .test_autogrid_illcond import _fleets
from .test_soft_endgame import assert_endgame_restarts_bit_for_bit, fleets_with_and_without


def _hard_error(core, robots) -> float:
    """The core's agreed function against the exact hard solve on its final grid (all data in one QP)."""
    pts = np.vstack([np.asarray(p) for _, p, _ in robots.values() if len(p)])
    labs = np.concatenate([np.asarray(l) for _, _, l in robots.values() if len(l)])
    grid, c, gamma = core.function()
    central = solve_central(core._basis, pts, labs, None)
    return core._basis.function_error(c, gamma, central.c, central.gamma)


@pytest.fixture(scope="module")
def hard_fleet():
    """The default world (3 robots x 20 points, blob), which ends on a hard margin, with hub frames and
    room for the payload; with and without the hard end-game."""
    spec, robots, _ = _fleets()
    return (robots, *fleets_with_and_without(spec, robots, "hard_endgame"))


def test_autogrid_hard_answer_is_certified_exact_and_earlier(hard_fleet):
    robots, params, cores, plain = hard_fleet
    assert all(c.margin == "hard" and c.converged for c in cores + plain)
    assert all(np.array_equal(c.function()[1], cores[0].function()[1]) for c in cores)  # bit for bit
    assert np.array_equal(cores[0].grid, plain[0].grid)
    last, plain_last = cores[0].grid_history[-1], plain[0].grid_history[-1]
    assert last["status"] == "hard-margin solved" and last["endgame"] == "certified"
    assert "endgame" not in plain_last
    # the end-game's stop is the exact optimum; the ADMM's own stop is a tolerance away
    assert _hard_error(cores[0], robots) < 1e-9 < _hard_error(plain[0], robots)
    assert last["rounds"] < plain_last["rounds"] and cores[0].round < plain[0].round


def test_restart_inside_the_hard_endgame_resumes_bit_for_bit(hard_fleet):
    """Restarted from checkpoints in a start round and in a round of a solve of the hard end-game, the fleet
    ends with the same rounds and bits as without the restart."""
    robots, params, ref, _ = hard_fleet
    assert_endgame_restarts_bit_for_bit(robots, params, ref, hard=True)


def test_plain_admm_eight_robots_hard_endgame_certifies_the_exact_optimum():
    """Plain admm on a complete graph of 8 robots, hard margin, with the end-game: one robot's step leaves
    all its rows off the margin with tiny positive multipliers; guessing them all on the margin (33-42 E
    rows for 16 unknowns) never certified. The guess drops rows off the margin at the robot's own step,
    and the fleet stops at the exact optimum, the same bits on every robot."""
    from agents.spec import build_core
    from launcher.world import Options, build_world

    from .conftest import run_to_end

    world, spec = build_world(Options(fleet_id="test", preset="paper", robots=8, max_rounds=1000))
    spec.params.update({"soft_polish": True, "hard_endgame": True})
    central = solve_central(spec.basis, world.points, world.labels, spec.C)
    cores = [build_core(spec, i, keep_trace=False) for i in spec.robot_ids]
    run_to_end(cores, limit=1000)
    assert all(c.converged for c in cores)
    assert all(c._polish is not None and c._polish.result is not None for c in cores)  # certified
    assert all(np.array_equal(c.values, cores[0].values) for c in cores)
    b = cores[0].values
    error = spec.basis.function_error(spec.basis.c_from_x(b[:-1]), b[-1], central.c, central.gamma)
    assert error < 1e-9
