"""The hub form's exact end-game (ADMMParams.polish, agents/admm.py `_Polish`): attempts beside the
ADMM solve the equality QP on a guessed active set from exactly rounded fleet sums, and stop the fleet
only when every robot certified its own rows. Checked here on the paper fleet (cheap): the stop is the
certified exact optimum, the same bits on every robot, earlier than without the polish; a restored
robot continues the polish bit for bit; the flag off changes no frame; a bad payload does not crash a
robot. The rounds of the large fleets are measured in benchmarks/polish.py, not here."""

from __future__ import annotations

import numpy as np
import pytest

from agents.admm import _Polish, hub_frame_dim, polish_payload_size, polish_solve
from agents.certificate import PAYLOAD
from agents.problem import certify_hard_margin, margin_rows
from agents.spec import build_core

from .conftest import make_run, run_to_end, step_all
from .test_admm import restored_twin, step_with_twin


def _fleet(polish: bool, **kwargs):
    world, spec, central = make_run(**kwargs)
    spec.params["polish"] = polish
    if not polish:  # the certified guard, as asked (silent, a complete hard fleet runs agents/soft_endgame.py)
        spec.params["certify"] = 10.0
    return world, spec, central, [build_core(spec, i) for i in spec.robot_ids]


def _error(spec, central, v: np.ndarray) -> float:
    b = spec.basis
    return b.function_error(b.c_from_x(v[:-1]), v[-1], central.c, central.gamma)


def test_the_polish_stops_at_the_certified_optimum_with_identical_copies():
    _w, spec, central, plain = _fleet(False)
    run_to_end(plain)
    _w, spec, central, cores = _fleet(True)
    run_to_end(cores)
    assert central.certified
    assert all(c.converged for c in cores)
    first = cores[0].values
    assert all(c.values.tobytes() == first.tobytes() for c in cores)  # one point, bit for bit
    assert _error(spec, central, first) < 1e-9  # the exact optimum, not a tolerance away
    assert cores[0].round < plain[0].round  # the end-game ends the run before the ADMM's own stop
    assert any(c._polish.attempts > 1 for c in cores)  # (here after a failed attempt: the loop ran)


def test_other_shapes_stop_exact_too():
    for shape in ("star", "crescent"):
        _w, spec, central, cores = _fleet(True, shape=shape)
        run_to_end(cores)
        assert all(c.converged for c in cores), shape
        assert all(c.values.tobytes() == cores[0].values.tobytes() for c in cores), shape
        assert _error(spec, central, cores[0].values) < 1e-9, shape


def test_a_restored_robot_continues_the_polish_bit_for_bit():
    """Restarted from its checkpoint in a sum round and in a verdict round, a robot sends exactly
    what the original sends until the fleet stops."""
    restored_in = set()
    for at in (6, 7):
        _w, spec, _c, cores = _fleet(True)
        for _ in range(at):
            step_all(cores)
        original = cores[1]
        restored_in.add(original._polish.kind)
        twin = restored_twin(spec, original)
        while not all(c.finished for c in cores):
            step_with_twin(cores, twin, original)
        assert twin.converged and twin.values.tobytes() == original.values.tobytes()
    assert restored_in == {"sum", "verdict"}


def test_the_flag_off_leaves_the_frames_as_they_were():
    _w, spec, _c, cores = _fleet(False)
    dim = spec.basis.size + 1
    # (without the polish the certified guard's payload follows [v; w]: agents/certificate.py)
    assert spec.dim == 2 * dim + PAYLOAD == cores[0].frame_dim == len(cores[0].outgoing().values)
    assert getattr(cores[0], "_polish") is None
    _w, spec, _c, cores = _fleet(True)
    assert spec.dim == 2 * dim + polish_payload_size(dim) == cores[0].frame_dim == len(cores[0].outgoing().values)
    assert hub_frame_dim(cores[0].params, dim) == spec.dim


def test_the_solve_on_the_optimal_set_is_the_kkt_solution():
    """polish_solve on the Gram sums of the optimum's active rows gives certify_hard_margin's point,
    and y = A_W' lam with positive multipliers (what the robots check)."""
    world, spec, central = make_run()
    rows = margin_rows(spec.basis.features(world.points), world.labels)
    exact = np.append(central.x, central.gamma)
    A = rows[rows @ exact - 1.0 < 1e-6]
    v, y, iterates = polish_solve(A.T @ A, A.sum(axis=0))
    assert np.abs(v - certify_hard_margin(rows, exact)).max() < 1e-9
    lam = -1e4 * np.sum([A @ x - 1.0 for x in iterates], axis=0)
    assert lam.min() > 0 and np.abs(A.T @ lam - y).max() < 1e-6 * np.abs(y).max()


def test_a_bad_payload_fails_the_attempt_not_the_robot():
    """Non-finite sums (a forged frame) give no verdict: the attempt fails on every copy alike
    and a fresh guess follows; a verdict round with a NaN moves nothing."""
    world, spec, _c = make_run()
    rows = margin_rows(spec.basis.features(world.points), world.labels)
    pol = _Polish(rows, (0, 1, 2), 0)
    pol.guess(np.zeros(rows.shape[1]))
    bad = np.tile(pol.payload, (3, 1))
    bad[2, 0] = np.nan
    assert pol.step(bad, np.zeros(rows.shape[1])) is None
    assert pol.kind == "verdict" and pol.payload[0] == 0.0
    verdicts = np.tile(pol.payload, (3, 1))
    verdicts[1, 1] = np.nan
    assert pol.step(verdicts, np.zeros(rows.shape[1])) is None
    assert pol.kind == "sum" and pol.corrections == 0 and pol.attempts == 2  # a fresh guess


# -- over Zenoh: the process fleet equals `simulate` bit for bit, a crash mid-polish included -------

from launcher.fleet import CrashPlan  # noqa: E402
from tests.test_launch import _assert_same_iterates, _launch, _run, _simulate, bounded, bound  # noqa: E402,F401


@pytest.mark.integration
@bound(60)
def test_launch_with_the_polish_equals_simulate_across_a_crash(tmp_path):
    """3 robots as processes over a router, robot 1 SIGKILLed at round 8 (mid-attempt) and restarted
    from its checkpoint: every iterate, the polished result and the rounds equal simulate's."""
    _world, spec, central = _run(fleet_id="launch-polish")
    spec.params["polish"] = True
    want = _simulate(spec)
    assert all(w["converged"] for w in want.values())
    out = _launch(spec, tmp_path, crashes=[CrashPlan(1, 8)], restart=True, restart_after=0.5)
    assert [(c.robot, c.planned_round) for c in out.crashes] == [(1, 8)]
    _assert_same_iterates(out.robots, want, restarted=(1,))
    assert max(_error(spec, central, np.append(r["x"], r["gamma"])) for r in out.robots) < 1e-9


# -- the command line: --polish where it exists, a clear error elsewhere ----------------------------

from launcher.options import Options  # noqa: E402
from launcher.scenario import ScenarioError  # noqa: E402
from launcher.world import build_world  # noqa: E402


def test_the_polish_flag_reaches_the_fleet_file_only_when_given():
    _w, spec = build_world(Options(fleet_id="p", preset="paper", polish=True))
    assert spec.params["polish"] is True and spec.algorithm_params.polish
    _w, spec = build_world(Options(fleet_id="p", preset="paper"))
    assert "polish" not in spec.params  # other fleets' files (and config tags) stay as they were


@pytest.mark.parametrize("kwargs, says", [
    ({}, "--algorithm admm only (this run: autogrid)"),
    ({"preset": "paper", "C": 10.0}, "needs a hard margin"),
    ({"preset": "paper", "topology": "ring", "robots": 6}, "needs a complete graph"),
    ({"grid": "6x5", "sigma": 1.0, "algorithm": "admm"}, "the grid has 30 points"),
    ({"preset": "paper", "algorithm": "newton"}, "--algorithm admm only (this run: newton)"),
])
def test_the_polish_flag_refuses_what_it_cannot_do(kwargs, says):
    with pytest.raises(ScenarioError, match="--polish: ") as err:
        build_world(Options(fleet_id="p", polish=True, **kwargs))
    assert says in str(err.value)


def test_the_budget_bound_is_the_largest_grid_whose_polish_frames_fit():
    """polish_max_dim is exact: its frame fits 16 (M + 1) floats, one more does not; a 24-point grid runs."""
    from agents.admm import FRAME_BUDGET, ADMMParams, polish_max_dim

    on = ADMMParams(polish=True)
    d = polish_max_dim()
    assert hub_frame_dim(on, d) <= FRAME_BUDGET * d < hub_frame_dim(on, d + 1) - FRAME_BUDGET
    _w, spec = build_world(Options(fleet_id="p", grid="6x4", sigma=1.0, algorithm="admm", polish=True))
    assert len(spec.grid) == d - 1 and spec.polish_refusal() is None and spec.dim <= FRAME_BUDGET * d
