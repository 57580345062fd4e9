"""The LiDAR least-squares model (agents/lsq_model.py) and its fleet (agents/lsq_admm.py):
the exact central solve, the fleet reaching it, crashes, and the shells' checks."""

from __future__ import annotations

import numpy as np
import pytest

from agents.lsq_model import (
    LsqLocalStep,
    design,
    lidar_pairs,
    lsq_rows,
    objective_share,
    solve_central_lsq,
)
from agents.lsq_admm import ConsensusLSQ
from agents.spec import Timing, build_core
from launcher.fleet import CrashPlan, launch_fleet
from launcher.simulate import simulate_fleet
from launcher.world import Options, build_world

from .conftest import bounded_and_clean, cli_exit_and_stderr, max_function_error, run_to_end

TIMING = Timing(retransmit_s=0.02, dead_after_s=6.0, max_wall_s=40.0, linger_s=1.0)


def _world(**kwargs):
    kwargs.setdefault("fleet_id", "test")
    kwargs.setdefault("algorithm", "lsq")
    kwargs.setdefault("grid", "8x6")
    kwargs.setdefault("sigma", 1.0)
    world, spec = build_world(Options(**kwargs))
    return world, spec, spec.central([(r.id, r.points, r.labels) for r in world.robots])


def _stacked_rows(world):
    parts = [lsq_rows(r.points, r.labels) for r in world.robots]
    return np.vstack([p for p, _ in parts]), np.concatenate([t for _, t in parts])


def test_pairs_give_three_rows_and_loose_points_one():
    points = np.array([[0.0, 0.0], [1.0, 0.0], [5.0, 5.0], [2.0, 2.0], [2.0, 4.0], [7.0, 7.0]])
    labels = np.array([1, -1, 1, 1, -1, -1])
    assert lidar_pairs(labels).tolist() == [0, 3]
    rows, targets = lsq_rows(points, labels)
    assert targets.tolist() == [1, 0, -1, 1, 1, 0, -1, -1]
    assert rows[1].tolist() == [0.5, 0.0] and rows[5].tolist() == [2.0, 3.0]  # the midpoints
    assert rows[2].tolist() == [1.0, 0.0] and rows[7].tolist() == [7.0, 7.0]


def test_central_solve_equals_the_stacked_least_squares():
    world, spec, ref = _world()
    basis, lam = spec.basis, spec.algorithm_params.lam
    rows, targets = _stacked_rows(world)
    m = basis.size
    stacked = np.vstack([design(basis.features(rows)), np.hstack([np.sqrt(lam) * np.eye(m), np.zeros((m, 1))])])
    v = np.linalg.lstsq(stacked, np.concatenate([targets, np.zeros(m)]), rcond=None)[0]
    assert np.max(np.abs(v[:-1] - ref.x)) < 1e-10 and abs(v[-1] - ref.gamma) < 1e-10
    assert np.count_nonzero(targets == 0) > 0  # the midpoint rows are in the fit


def test_robot_shares_sum_to_the_central_objective():
    world, spec, ref = _world(robots=4)
    lam, v = spec.algorithm_params.lam, np.append(ref.x, ref.gamma)
    shares = [objective_share(spec.share(i).features, spec.share(i).labels, v, lam, 4) for i in spec.robot_ids]
    rows, targets = _stacked_rows(world)
    central = objective_share(spec.basis.features(rows), targets, v, lam, 1)
    assert sum(shares) == pytest.approx(central, rel=1e-12)


def test_local_step_is_the_minimiser_of_its_share():
    _, spec, _ = _world()
    share = spec.share(0)
    rng = np.random.default_rng(1)
    prox, q = rng.uniform(1, 5, share.dim), rng.normal(size=share.dim)
    step = LsqLocalStep(share.features, share.labels, x_weight=0.03, prox_weight=prox)
    v = step.solve_v(q)
    A = design(share.features)
    grad = 2 * A.T @ (A @ v - share.labels) + q + prox * v
    grad[:-1] += 2 * 0.03 * v[:-1]
    assert np.max(np.abs(grad)) < 1e-9 * max(1.0, np.max(np.abs(q)))


def test_a_pair_split_between_robots_is_not_a_pair():
    world, spec, _ = _world(robots=2)
    a, b = world.robots
    merged = solve_central_lsq(spec.basis, np.vstack([a.points[-1:], b.points[1:2]]), np.array([1, -1]))
    split = solve_central_lsq(spec.basis, np.vstack([a.points[-1:], b.points[1:2]]), np.array([1, -1]),
                              robot_of=np.array([0, 1]))
    assert merged.x.tolist() != split.x.tolist()  # merged holds a midpoint row, split does not


# -- the fleet --------------------------------------------------------------------------------------
@pytest.mark.parametrize(("topology", "robots", "hub"), [("complete", 4, True), ("ring", 5, False)])
def test_fleet_reaches_the_exact_least_squares_fit(topology, robots, hub):
    """Hub form (complete) and edge form (ring) end within 1e-3 of the central solve of the same model."""
    _, spec, ref = _world(topology=topology, robots=robots, tol=1e-5)
    cores = [build_core(spec, i) for i in spec.robot_ids]
    assert all(isinstance(c, ConsensusLSQ) and (c._hub is not None) == hub for c in cores)
    run_to_end(cores)
    results = [c.result() for c in cores]
    assert all(r["converged"] and r["algorithm"] == "lsq" for r in results)
    assert max_function_error(spec, ref, results) < 1e-3


def test_crash_and_restart_ends_on_the_clean_runs_exact_answer():
    _, spec, ref = _world(fleet_id="lsq-crash", timing=TIMING, topology="ring", robots=4)
    clean = {r["id"]: r for r in simulate_fleet(spec).robots}
    out = simulate_fleet(spec, crashes=[CrashPlan(1, 40)], restart=True, restart_after=0.5)
    assert [c["fired"] for c in out.crash_log] == [True]
    assert {r["id"]: r["restarts"] for r in out.robots} == {0: 0, 1: 1, 2: 0, 3: 0}
    for r in out.robots:
        assert (r["x"], r["gamma"], r["rounds"]) == (clean[r["id"]]["x"], clean[r["id"]]["gamma"], clean[r["id"]]["rounds"])
    assert max_function_error(spec, ref, out.robots) < 1e-3


def test_survivors_of_a_permanent_loss_fit_their_own_data():
    """A dead robot's rows leave the fit and lam / N follows the robots left: the survivors' answer is
    the central fit of their data (not of everyone's)."""
    world, spec, _ = _world(fleet_id="lsq-loss", timing=TIMING, topology="complete", robots=4, tol=1e-5)
    out = simulate_fleet(spec, crashes=[CrashPlan(1, 20)], restart=False)
    assert [r["id"] for r in out.robots] == [0, 2, 3]
    ref = spec.central([(r.id, r.points, r.labels) for r in world.robots if r.id != 1])
    assert max_function_error(spec, ref, out.robots) < 1e-3


# -- the shells -------------------------------------------------------------------------------------
@pytest.mark.parametrize("value", ["0", "-1", "nan", "inf"])
def test_bad_lsq_lambda_exits_2_naming_the_flag(value, tmp_path, capsys):
    code, err = cli_exit_and_stderr(["simulate", "--algorithm", "lsq", "--grid", "5x3", "--sigma", "1",
                                     "--lsq-lambda", value, "--out", str(tmp_path / "x")], capsys)
    assert code == 2 and "--lsq-lambda" in err[-1]


@pytest.mark.parametrize("words", [["--algorithm", "lsq", "--preset", "paper"],
                                   ["--algorithm", "autogrid", "--model", "lsq"], []],
                         ids=["fixed grid", "autogrid", "default"])
def test_lsq_refuses_a_margin_and_data_without_pairs(words, tmp_path, capsys):
    """The fixed-grid fleet and autogrid's least-squares model (tests/test_autogrid_lsq.py), the default run's
    model, alike; autogrid's refusals say how to get the margin model instead (--model svm)."""
    autogrid = "--preset" not in words
    code, err = cli_exit_and_stderr(["simulate", *words, "--C", "10", "--out", str(tmp_path / "c")], capsys)
    assert code == 2 and "--C" in err[-1] and ("--model svm" in err[-1]) == autogrid
    data = tmp_path / "nopairs.csv"  # inside before outside: no (+1, -1) pair in any robot's rows
    data.write_text("robot,x,y,label\n0,0,0,-1\n0,3,3,1\n1,0.5,0,-1\n1,3,-3,1\n")
    code, err = cli_exit_and_stderr(["simulate", *words, "--data", str(data), "--out", str(tmp_path / "d")], capsys)
    assert code == 2 and str(data) in err[-1] and "LiDAR pair" in err[-1] and ("--model svm" in err[-1]) == autogrid
    if autogrid:  # the same data with the margin model: label-only data is what it fits
        code, err = cli_exit_and_stderr(["simulate", *words, "--model", "svm", "--data", str(data), "--C", "10",
                                         "--out", str(tmp_path / "s")], capsys)
        assert code == 0, err


def test_simulate_reports_the_model_and_measures_against_its_own_reference(tmp_path, capsys):
    import json

    code, _ = cli_exit_and_stderr(["simulate", "--algorithm", "lsq", "--grid", "8x6", "--sigma", "1",
                                   "--lsq-lambda", "0.5", "--out", str(tmp_path / "r")], capsys)
    result = json.loads((tmp_path / "r" / "result.json").read_text())
    assert code == 0 and result["algorithm"] == "lsq" and "least squares" in result["model"] and "0.5" in result["model"]
    _, spec, ref = _world(lsq_lambda=0.5)
    assert result["central"]["c"] == ref.c.tolist()  # the run's reference is the least-squares fit
    assert result["metrics"]["function_error"] < 1e-2


@pytest.mark.integration
@pytest.mark.parametrize(("topology", "crashes"), [("complete", []), ("ring", [CrashPlan(1, 40)])])
def test_launch_equals_simulate_bit_for_bit(topology, crashes, tmp_path):
    """Real robot processes over Zenoh give `simulate`'s iterates bit for bit: the hub form, and the edge
    form with robot 1 SIGKILLed at round 40 and restarted from its checkpoint."""
    _, spec, ref = _world(fleet_id=f"lsq-launch-{topology}", timing=TIMING, topology=topology, robots=4)
    want = {r["id"]: r for r in simulate_fleet(spec).robots}
    with bounded_and_clean(str(tmp_path), 45.0, "lsq-launch"):
        out = launch_fleet(spec, workdir=tmp_path / "fleet", crashes=crashes, restart_after=0.5, restart=True,
                           zenoh_port=None, progress=False)
    assert not out.timed_out and sorted(r["id"] for r in out.robots) == [0, 1, 2, 3]
    assert [r["restarts"] for r in sorted(out.robots, key=lambda r: r["id"])] == [0, len(crashes), 0, 0]
    for r in out.robots:
        w = want[r["id"]]
        assert r["stopped"] == "finished" and (r["rounds"], r["converged"]) == (w["rounds"], True)
        rounds = sorted(r["trace"])
        assert rounds[-1] == w["rounds"]
        np.testing.assert_array_equal(np.array([r["trace"][k] for k in rounds]), np.array([w["trace"][k] for k in rounds]))
        assert r["x"] == w["x"] and r["gamma"] == w["gamma"]
    assert max_function_error(spec, ref, out.robots) < 1e-3
