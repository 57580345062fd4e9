"""Crash injection in both shells: `simulate --crash` on the virtual clock equals a clean run bit
for bit across a restart, and `launch` (SIGKILL) equals `simulate` bit for bit across a restart
and across a permanent loss."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

import numpy as np
import pytest

from agents.problem import solve_central
from agents.spec import Timing
from launcher.fleet import CrashPlan, launch_fleet
from launcher.simulate import simulate_fleet
from tests.conftest import ROOT, bounded_and_clean, make_run, max_function_error

TIMING = Timing(retransmit_s=0.02, dead_after_s=6.0, max_wall_s=40.0, linger_s=1.0)


def same_iterates(robots: list[dict], want: dict[int, dict], *, restarted=()) -> None:
    """Round for round, bit for bit: every recorded iterate, the final x and gamma, the rounds."""
    for r in robots:
        w = want[r["id"]]
        assert r["stopped"] == "finished" and (r["rounds"], r["converged"]) == (w["rounds"], w["converged"])
        rounds = sorted(r["trace"])
        assert rounds == list(range(0 if r["id"] not in restarted else rounds[0], w["rounds"] + 1))
        np.testing.assert_array_equal(np.array([r["trace"][k] for k in rounds]),
                                      np.array([w["trace"][k] for k in rounds]))
        assert r["x"] == w["x"] and r["gamma"] == w["gamma"]


@pytest.fixture(scope="module")
def run():
    return make_run(fleet_id="crash", timing=TIMING)


def test_simulate_crash_and_restart_is_the_clean_run_bit_for_bit(run):
    _, spec, central = run
    clean = {r["id"]: r for r in simulate_fleet(spec).robots}
    out = simulate_fleet(spec, crashes=[CrashPlan(1, 40)], restart=True, restart_after=0.5)
    assert [(c["robot"], c["planned_round"], c["round"], c["fired"]) for c in out.crash_log] == [(1, 40, 40, True)]
    by_id = {r["id"]: r for r in out.robots}
    assert [by_id[i]["restarts"] for i in (0, 1, 2)] == [0, 1, 0]
    assert min(by_id[1]["trace"]) < 40  # resumed from the checkpoint before its last round
    same_iterates(out.robots, clean, restarted=(1,))
    assert all(r["neighbours_dropped"] == [] for r in out.robots)
    assert max_function_error(spec, central, out.robots) < 1e-3


def test_simulate_permanent_loss_survivors_solve_their_data(run):
    world, spec, _ = run
    out = simulate_fleet(spec, crashes=[CrashPlan(1, 40)], restart=False)
    assert [r["id"] for r in out.robots] == [0, 2]  # the dead robot has no row
    r0, r2 = out.robots
    assert r0["neighbours_dropped"] == r2["neighbours_dropped"] == [1]
    assert r0["dropped_at"] == r2["dropped_at"] == {1: 41}  # its round-40 frame got out: stuck at 41
    assert r0["converged"] and r2["converged"] and r0["rounds"] == r2["rounds"]
    kept = [r for r in world.robots if r.id in (0, 2)]
    ref = solve_central(spec.basis, np.vstack([r.points for r in kept]), np.concatenate([r.labels for r in kept]), spec.C)
    assert max_function_error(spec, ref, out.robots) < 1e-3
    # without restarts the survivors wait launch's NO_RESTART_DEAD_AFTER_S (2.5 s), not 6 s
    assert 2.5 <= out.virtual_s < 6.0


@pytest.mark.parametrize("options, params", [
    pytest.param({"C": 10.0}, {}, id="soft"),
    pytest.param({}, {"soft_polish": True, "hard_endgame": True}, id="hard"),
    pytest.param({"polish": True}, {}, id="gram-polish")])
def test_a_permanent_loss_during_an_end_game_leaves_survivors_that_finish(options, params):
    """A drop stops every end-game beside the hub (agents/soft_endgame.py: the soft default of --C on a
    complete graph; the hard one; --polish). It used to rewrite the payload of the round's frame that
    was already out: the survivors rejected each other's resent copies as equivocation (1250 frames)
    and both stopped isolated at round 42. Now they finish on the exact answer of their own data (the
    soft one too: a drop reweighs every survivor's share of |x|^2, which was 0.33 off before)."""
    world, spec, _ = make_run(fleet_id="crash-endgame", timing=TIMING, **options)
    spec = dataclasses.replace(spec, params={**spec.params, **params})
    out = simulate_fleet(spec, crashes=[CrashPlan(1, 40)], restart=False)
    assert [r["id"] for r in out.robots] == [0, 2]
    assert all(r["converged"] and r["stopped"] == "finished" and r["neighbours_dropped"] == [1] for r in out.robots)
    assert all(r["frames_rejected"] == 0 for r in out.robots)
    kept = [r for r in world.robots if r.id in (0, 2)]
    ref = solve_central(spec.basis, np.vstack([r.points for r in kept]), np.concatenate([r.labels for r in kept]), spec.C)
    assert max_function_error(spec, ref, out.robots) < 1e-3


def test_a_sparse_soft_fleet_after_a_permanent_loss_solves_its_survivors_problem():
    """On a sparse graph a robot sees only its neighbours die; the edge form floods the ids dropped for
    good (agents/rounds.py) and every survivor weighs |x|^2 by 1 / (robots left): robot 3, no neighbour
    of the dead robot, learns it from its neighbours. Before, all kept 1 / N and solved C x 4/3: 0.19
    off, NOT converged."""
    world, spec, _ = make_run(fleet_id="crash-ring-soft", timing=TIMING, robots=4, topology="ring", C=10.0)
    out = simulate_fleet(spec, crashes=[CrashPlan(1, 40)], restart=False)
    assert [r["id"] for r in out.robots] == [0, 2, 3]
    assert [r["neighbours_dropped"] for r in out.robots] == [[1], [1], []]
    assert all(r["converged"] and r["frames_rejected"] == 0 for r in out.robots)
    kept = [r for r in world.robots if r.id != 1]
    ref = solve_central(spec.basis, np.vstack([r.points for r in kept]), np.concatenate([r.labels for r in kept]), spec.C)
    assert max_function_error(spec, ref, out.robots) < 1e-3


def test_without_restarts_a_sparse_fleet_runs_the_edge_form_and_its_survivors_finish():
    """The relay hub (sparse fleets' default) cannot drop a robot dead for good: without restarts the
    run gives the robots the edge form (launcher.fleet.spec_for_run, as `launch` does), whose
    survivors of a 4-ring drop the dead one and end on the exact answer of their own data."""
    world, spec, _ = make_run(fleet_id="crash-ring", timing=TIMING, robots=4, topology="ring")
    out = simulate_fleet(spec, crashes=[CrashPlan(1, 40)], restart=False)
    assert [r["id"] for r in out.robots] == [0, 2, 3]
    assert all(r["converged"] and r["neighbours_dropped"] == [1] for r in out.robots if r["id"] in (0, 2))
    assert all(r["converged"] for r in out.robots)
    kept = [r for r in world.robots if r.id != 1]
    ref = solve_central(spec.basis, np.vstack([r.points for r in kept]), np.concatenate([r.labels for r in kept]), spec.C)
    assert max_function_error(spec, ref, out.robots) < 1e-3
    # with restarts (the default) the same fleet runs the relay hub, whose frames relay all four robots
    relayed = simulate_fleet(spec).robots
    per_frame = [r["bytes_sent"] / (r["rounds"] + 1) for r in (relayed[0], out.robots[0])]
    assert all(r["converged"] for r in relayed) and per_frame[0] > 2 * per_frame[1]  # 1164 against 482 B


def test_a_crash_that_cannot_fire_is_reported(run):
    _, spec, _ = run
    out = simulate_fleet(spec, crashes=[CrashPlan(1, 4000)], restart=True)
    assert out.crash_log == [{"robot": 1, "planned_round": 4000, "fired": False}]
    assert len(out.robots) == 3


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "launcher.cli", *args], capture_output=True, text=True,
                          timeout=240, cwd=ROOT)


def test_simulate_crash_flags(tmp_path):
    out = tmp_path / "dead"
    proc = _cli("simulate", "--preset", "paper", "--crash", "1@40", "--no-restart", "--dead-after", "3s",
                "--out", str(out))
    assert proc.returncode == 0, proc.stderr
    result = json.loads((out / "result.json").read_text())
    assert result["crashes"][0]["robot"] == 1 and result["crashes"][0]["restarted_at_s"] is None
    assert result["absent"] == [1] and result["participants"] == [0, 2]
    assert result["virtual_s"] >= 2.5 and result["converged"]
    for args, needle in ((["--crash", "7@10"], "--crash: robot 7 is not in the fleet"),
                         (["--crash", "x"], "--crash"), (["--dead-after", "0s"], "--dead-after")):
        proc = _cli("simulate", "--preset", "paper", *args, "--out", str(tmp_path / "bad"))
        assert proc.returncode == 2 and needle in proc.stderr.strip().splitlines()[-1], proc.stderr


@pytest.mark.integration
def test_launch_permanent_loss_equals_simulate_bit_for_bit(run, tmp_path):
    """SIGKILL lands a little after the planned round; the survivors' drop round says where the
    dead robot stopped, and `simulate` with the crash one round before it gives the same iterates."""
    _, spec, _ = run
    with bounded_and_clean(str(tmp_path), 45.0, "launch-permanent-loss"):
        out = launch_fleet(spec, workdir=tmp_path / "fleet", crashes=[CrashPlan(1, 40)], restart_after=0.5,
                           restart=False, zenoh_port=None, progress=False)
    assert not out.timed_out and [r["id"] for r in out.robots] == [0, 2]
    stuck = {r["dropped_at"][1] for r in out.robots}
    assert len(stuck) == 1, f"survivors dropped robot 1 at different rounds: {stuck}"
    want = simulate_fleet(spec, crashes=[CrashPlan(1, stuck.pop() - 1)], restart=False)
    same_iterates(out.robots, {r["id"]: r for r in want.robots})


def launch_loss_equals_simulate(tmp_path, world, spec, survivors: list[int], label: str) -> list[dict]:
    """Launch ``spec`` over Zenoh losing robot 1 for good at round 40; its survivors must give
    `simulate`'s iterates (crash one round before their drop round) bit for bit, all converged on the
    exact answer of their own data. Returns the launched robots' rows."""
    with bounded_and_clean(str(tmp_path), 60.0, label):
        out = launch_fleet(spec, workdir=tmp_path / "fleet", crashes=[CrashPlan(1, 40)], restart_after=0.5,
                           restart=False, zenoh_port=None, progress=False)
    assert not out.timed_out and [r["id"] for r in out.robots] == survivors
    stuck = {r["dropped_at"][1] for r in out.robots if r["neighbours_dropped"]}
    assert len(stuck) == 1, f"survivors dropped robot 1 at different rounds: {stuck}"
    want = simulate_fleet(spec, crashes=[CrashPlan(1, stuck.pop() - 1)], restart=False)
    same_iterates(out.robots, {r["id"]: r for r in want.robots})
    kept = [r for r in world.robots if r.id != 1]
    ref = solve_central(spec.basis, np.vstack([r.points for r in kept]), np.concatenate([r.labels for r in kept]), spec.C)
    assert all(r["converged"] for r in out.robots) and max_function_error(spec, ref, out.robots) < 1e-3
    return out.robots


@pytest.mark.integration
def test_launch_of_a_sparse_soft_fleet_losing_a_robot_equals_simulate_bit_for_bit(tmp_path):
    """Over Zenoh the ids dropped for good travel in the frames as in `simulate` (they are part of the
    rounds, never of arrival times): the survivors of a 4-ring with a soft margin give the same iterates
    bit for bit and end on the exact answer of their own data."""
    world, spec, _ = make_run(fleet_id="crash-ring-launch", timing=TIMING, robots=4, topology="ring", C=10.0)
    launch_loss_equals_simulate(tmp_path, world, spec, [0, 2, 3], "launch-sparse-soft-loss")


@pytest.mark.integration
def test_launch_of_a_sparse_hard_fleet_losing_a_robot_equals_simulate_bit_for_bit(tmp_path):
    """A hard margin's lists only widen the stop, which is part of the rounds too: over Zenoh the
    survivors of a 6-ring (a path of diameter 4 once robot 1 is gone, the flags sized for 3) give
    `simulate`'s iterates bit for bit and stop together on the exact answer of their own data."""
    world, spec, _ = make_run(fleet_id="crash-ring-hard-launch", timing=TIMING, robots=6, topology="ring")
    robots = launch_loss_equals_simulate(tmp_path, world, spec, [0, 2, 3, 4, 5], "launch-sparse-hard-loss")
    assert len({r["rounds"] for r in robots}) == 1  # one stop (before: the path's ends 600 rounds apart)
