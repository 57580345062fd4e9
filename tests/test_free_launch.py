"""`shapefleet launch --sync free` (issue 13): free-running robot processes over Zenoh.

Each robot process (agents/free_robot.py) ticks on its own clock with the newest values it holds,
through the project's fault links, and never waits. What is checked across processes: a small
lossy run ends within its tolerance of the exact answer and says converged; a partition that never
heals is never reported converged; every process the launcher started is gone afterwards (stopped
by its PID; a hard wall-clock bound and a /proc scan for the test's folder catch leftovers).
Loopback only, multicast scouting off (the launcher's configs).
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest

from launcher import api
from launcher.cli import main
from launcher.fleet import choose_robots_per_process
from tests.conftest import bounded_and_clean

pytestmark = pytest.mark.integration


@pytest.fixture(autouse=True)
def bounded(request, tmp_path):
    with bounded_and_clean(str(tmp_path), 120.0, request.node.name):
        yield


def _assert_gone(pids: tuple[int, ...], marker: str) -> None:
    """Every PID the launch started is gone (or, after PID reuse, is not one of this test's)."""
    assert pids
    for pid in pids:
        try:
            cmdline = Path(f"/proc/{pid}/cmdline").read_bytes()
        except OSError:
            continue
        assert marker.encode() not in cmdline, f"process {pid} is still there: {cmdline!r}"


def test_a_lossy_free_run_over_zenoh_ends_within_tolerance_of_the_exact_answer(tmp_path):
    out = tmp_path / "run"
    r = api.launch(sync="free", preset="paper", loss=0.3, delay="10ms", max_wall="60s", out=str(out))
    _assert_gone(r.pids, str(tmp_path))
    per_process = choose_robots_per_process(3)  # `auto`: 3 robots on 2 cores run in one process
    assert len(r.pids) == 1 + -(-3 // per_process)  # the router and the robot processes
    assert r.converged and r.exit_code == 0, r.verdict
    assert r.error is not None and r.error < 1e-3  # the relaxed ADMM's tolerance, against the exact solve
    result = json.loads((out / "result.json").read_text())
    assert result["sync"] == "free" and result["period_s"] == 0.01
    for robot in r.robots:
        assert robot.stopped == "finished" and robot.converged
        assert robot.counters["frames_lost"] > 0  # the fault links did drop frames: nothing was resent
        assert robot.rounds > 50  # ticks of its own clock
    logs = (out / "fleet" / "robot-0.log").read_text()
    assert "Traceback" not in logs


def test_a_partition_that_never_heals_is_not_reported_converged(tmp_path):
    out = tmp_path / "cut"
    r = api.launch(sync="free", preset="paper", partition="0/1,2@0s-1000s", max_wall="5s", out=str(out))
    _assert_gone(r.pids, str(tmp_path))
    assert not r.converged and r.exit_code == 1
    assert all(not robot.converged and robot.stopped == "max_wall" for robot in r.robots)
    # robot 0 heard nobody: everything sent to it was cut
    zero = r.robot(0).counters
    assert zero["frames_lost"] == zero["frames_received"] > 0


def test_free_launch_refuses_what_it_cannot_run(tmp_path):
    with pytest.raises(api.UsageError, match="--crash"):
        api.launch(sync="free", preset="paper", crash="1@40", out=str(tmp_path / "crash"))
    with pytest.raises(api.UsageError, match="--sync free"):
        api.launch(sync="free", out=str(tmp_path / "autogrid"))
    with pytest.raises(api.UsageError, match="--free-algorithm hub"):
        api.launch(sync="free", preset="paper", robots=4, topology="ring", free_algorithm="hub", out=str(tmp_path / "ring"))


def test_a_sweep_over_zenoh_runs_real_processes_and_writes_the_same_columns_plus_over(tmp_path):
    out = tmp_path / "sweep"
    code = main(["sweep", "--over", "zenoh", "--delays", "0ms", "--losses", "0.2", "--out", str(out)])
    rows = list(csv.DictReader(open(out / "sweep.csv")))
    assert code == 0 and [(r["sync"], r["over"]) for r in rows] == [("free", "zenoh"), ("lockstep", "zenoh")]
    for r in rows:
        assert r["converged"] == "True" and float(r["error"]) < 1e-3
        assert 0 < float(r["time_to_claim_s"]) <= float(r["stop_s"]) < 30  # each robot's wall-clock seconds
        assert int(r["bytes_sent"]) > 0 and int(r["frames_sent"]) > 0
    assert (out / "robustness.png").exists()
