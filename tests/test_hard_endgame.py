"""The exact end-game on hard margins (agents/soft_endgame.py with C = inf, `AutoGridParams.hard_endgame`):
autogrid's hard answer solve on a complete graph runs the block Krylov end-game with B empty and no upper
bound, and stops when every robot certified its own rows. Checked on a small fleet: the stop is the exact
hard optimum (not a tolerance away), the same bits on every robot, earlier than the ADMM's own stop, and a
restored robot continues bit for bit. The outlines' rounds are measured in benchmarks/, not here."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from agents.autogrid import ADMM
from agents.problem import solve_central

from .test_autogrid import _lockstep, _resume_from_checkpoints, make_cores, robots_of, run_fleet
from .test_autogrid_illcond import _fleets, _params


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
    params = _params(spec, hub_frames=True, validate_divisors=(4.0, 6.0, 8.0, 12.0))
    return robots, params, run_fleet(make_cores(robots, params)), run_fleet(make_cores(robots, dataclasses.replace(
        params, hard_endgame=False)))


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
    """Restarted from checkpoints in a start round and in a round of a solve of the last hard solve's
    end-game, the fleet ends with the same rounds and bits as without the restart."""
    robots, params, ref, _ = hard_fleet
    start = [r for p, r in ref[0].phases if p == ADMM][-1]
    for wanted in ("start", "grow"):
        cores = make_cores(robots, params)
        _lockstep(cores, start + 1)
        for _ in range(200):
            if cores[0]._sub._polish.kind == wanted:
                break
            _lockstep(cores, 1)
        assert cores[0].phase == ADMM and cores[0]._sub._polish.hard and cores[0]._sub._polish.kind == wanted
        resumed = _resume_from_checkpoints(cores, robots, params)
        for a, b in zip(ref, resumed):
            assert a.round == b.round and a.grid_history == b.grid_history
            assert np.array_equal(a.function()[1], b.function()[1]) and a.function()[2] == b.function()[2]

