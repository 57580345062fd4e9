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
