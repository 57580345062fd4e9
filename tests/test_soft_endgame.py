"""The soft margin's exact end-game (agents/soft_endgame.py): beside a soft hub ADMM every robot guesses its
own rows' active sets, the fleet solves the reduced problem by a block Krylov method with one all-reduce of
function-space vectors a round, and stops only when every robot certified its own rows. Checked on small
fleets: the stop is the exact soft optimum (not a tolerance away), the same bits on every robot, earlier than
the ADMM's own stop; a restored robot continues bit for bit; frames stay within issue 10's budget and the
flag off leaves them as they were. The held-out outlines' rounds are measured in benchmarks/, not here."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from agents.admm import FRAME_BUDGET, hub_frame_dim
from agents.autogrid import ADMM
from agents.soft_endgame import BLOCK, payload_size
from agents.spec import build_core

from .conftest import make_run, run_to_end, step_all
from .test_autogrid import _lockstep, _resume_from_checkpoints, make_cores, run_fleet
from .test_autogrid_illcond import _fleets, _params
from .test_autogrid_softstart import _soft_error


def _admm_fleet(soft_polish: bool, **kwargs):
    world, spec, central = make_run(C=10.0, **kwargs)
    spec.params["soft_polish"] = soft_polish
    return spec, central, [build_core(spec, i) for i in spec.robot_ids]


def _error(spec, central, v: np.ndarray) -> float:
    b = spec.basis
    return b.function_error(b.c_from_x(v[:-1]), v[-1], central.c, central.gamma)


@pytest.mark.parametrize("shape", ["crescent", "star"])
def test_admm_soft_endgame_stops_at_the_certified_optimum_with_identical_copies(shape):
    spec, central, plain = _admm_fleet(False, shape=shape)
    run_to_end(plain)
    spec, central, cores = _admm_fleet(True, shape=shape)
    run_to_end(cores)
    assert all(c.converged for c in cores)
    assert all(c.values.tobytes() == cores[0].values.tobytes() for c in cores)  # one point, bit for bit
    assert cores[0]._polish.result is not None  # every robot certified its own rows
    assert np.array_equal(cores[0].values, cores[0]._polish.result)
    assert _error(spec, central, cores[0].values) < 1e-6  # (piqp's reference itself: ~1e-7 on the star)
    assert cores[0].round < plain[0].round  # the end-game ends the run before the ADMM's own stop
    if shape == "crescent":  # the ADMM's own stop is a tolerance away, the end-game's is the optimum
        assert _error(spec, central, cores[0].values) < 1e-9 < 1e-7 < _error(spec, central, plain[0].values)


def test_frames_stay_within_the_budget_and_the_flag_off_leaves_them():
    spec, _c, cores = _admm_fleet(True)
    d = spec.basis.size + 1
    assert spec.dim == hub_frame_dim(spec.algorithm_params, d) == 2 * d + payload_size(d) == len(cores[0].outgoing().values)
    assert spec.dim <= FRAME_BUDGET * d  # BLOCK + 1 vectors of M + 1 floats and a few scalars beside [v; w]
    spec, _c, cores = _admm_fleet(False)
    assert getattr(cores[0], "_polish") is None and len(cores[0].outgoing().values) == spec.dim != 2 * d + payload_size(d)


def test_complete_graphs_keep_the_block_of_3_and_its_narrow_start():
    """The relay fleets' wide start block (agents/relay_hub.py RELAY_ENDGAME_BLOCK) stays off the complete graphs:
    their end-game has the default block and starts from the preconditioned 1 and t alone -- the start round's
    third scalar and image slots stay 0 -- so their frames and bits are those before it."""
    spec, _c, cores = _admm_fleet(True)
    d = spec.basis.size + 1
    for _ in range(2000):
        if cores[0]._polish.kind == "start":
            break
        step_all(cores)
    ends = [c._polish for c in cores]
    assert all(e.kind == "start" and e.block == BLOCK == 3 and not e.wide_start for e in ends)
    assert all(e.U.shape[1] == 2 == e.sent and len(e.payload) == payload_size(d) for e in ends)
    assert any(np.any(e.payload[3:5]) for e in ends)  # the 1' U of the two start vectors...
    assert not any(np.any(e.payload[5]) or np.any(e.payload[6 + 2 * d : 6 + 3 * d]) for e in ends)  # ...no third


@pytest.fixture(scope="module")
def soft_fleet():
    """tests/test_autogrid_illcond.py's fleet that ends soft, with hub frames and room for the payload (four
    sigma candidates widen the frame: the end-game runs only where its payload fits, `_endgame_fits`)."""
    spec, _, ill = _fleets(same_robot=True)
    return (ill, *fleets_with_and_without(spec, ill, "soft_polish"))


def fleets_with_and_without(spec, robots, flag: str):
    """Params with hub frames and room for the end-game's payload (four sigma candidates widen the frame),
    and the fleet run with them and with `flag` off."""
    params = _params(spec, hub_frames=True, validate_divisors=(4.0, 6.0, 8.0, 12.0))
    off = dataclasses.replace(params, **{flag: False})
    return params, run_fleet(make_cores(robots, params)), run_fleet(make_cores(robots, off))


def test_autogrid_soft_answer_is_certified_and_earlier(soft_fleet):
    ill, params, cores, plain = soft_fleet
    assert all(c.margin == "soft" and c.converged for c in cores + plain)
    assert all(np.array_equal(c.function()[1], cores[0].function()[1]) for c in cores)
    assert np.array_equal(cores[0].grid, plain[0].grid)
    assert cores[0].grid_history[-1]["endgame"] == "certified" and "endgame" not in plain[0].grid_history[-1]
    assert _soft_error(cores[0], ill) < 1e-7  # (piqp's reference itself: ~1e-8 here)
    soft_rounds = [h["rounds"] for h in cores[0].grid_history if h["margin"] == "soft"]
    plain_rounds = [h["rounds"] for h in plain[0].grid_history if h["margin"] == "soft"]
    assert soft_rounds[-1] < plain_rounds[-1] and cores[0].round < plain[0].round


def test_restart_inside_the_endgame_resumes_bit_for_bit(soft_fleet):
    """Restarted from checkpoints in a start round and in a round of a solve, the fleet ends with the same
    rounds and bits as without the restart."""
    ill, params, ref, _ = soft_fleet
    assert_endgame_restarts_bit_for_bit(ill, params, ref, hard=False)


def assert_endgame_restarts_bit_for_bit(robots, params, ref, *, hard: bool) -> None:
    """Restart the fleet from checkpoints taken in a start round and in a round of a solve of the last answer
    solve's end-game (a hard one when `hard`); it must end with `ref`'s rounds, history and bits."""
    start = [r for p, r in ref[0].phases if p == ADMM][-1]
    for wanted in ("start", "grow"):
        cores = make_cores(robots, params)
        _lockstep(cores, start + 1)
        for _ in range(200):
            if cores[0]._sub._polish.kind == wanted:
                break
            _lockstep(cores, 1)
        pol = cores[0]._sub._polish
        assert cores[0].phase == ADMM and pol.kind == wanted and pol.hard == hard
        resumed = _resume_from_checkpoints(cores, robots, params)
        for a, b in zip(ref, resumed):
            assert a.round == b.round and a.grid_history == b.grid_history
            assert np.array_equal(a.function()[1], b.function()[1]) and a.function()[2] == b.function()[2]
