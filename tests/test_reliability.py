"""Issue 11: never a false success, no orphan. One test per row of the issue's table (except the
impostor rows, tests of protocol/), plus the line of 3 robots whose middle robot dies (issue 18).

Each test runs `shapefleet` as a user would (``--preset paper``, short ``--dead-after``), is
bounded in time (SIGALRM), and is followed by a scan of /proc for any process whose command line
holds the test's tmp folder: leftovers are SIGKILLed by PID and the test fails.
Exit codes (launcher/cli.py): 0 converged, 1 not converged / failed, 2 bad input, 128+N signal N.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import networkx as nx
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from tests.conftest import bounded_and_clean, processes_with, wait_until  # noqa: E402

pytestmark = pytest.mark.integration

DEFAULT_BOUND_S = 60.0
PAPER = ("--preset", "paper")


def bound(seconds: float):
    def mark(fn):
        fn._bound_s = seconds
        return fn

    return mark


@pytest.fixture(autouse=True)
def bounded(request, tmp_path):
    limit = getattr(request.function, "_bound_s", DEFAULT_BOUND_S)
    with bounded_and_clean(str(tmp_path), limit, request.node.name):
        yield


def _cli() -> list[str]:
    script = Path(sys.executable).with_name("shapefleet")
    return [str(script)] if script.exists() else [sys.executable, "-m", "launcher.cli"]


def _start(*args: str) -> subprocess.Popen:
    return subprocess.Popen([*_cli(), *args], cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True, env=dict(os.environ, PYTHONPATH=str(ROOT)), start_new_session=True)


def _finish(proc: subprocess.Popen, timeout: float) -> str:
    try:
        _, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.kill(proc.pid, signal.SIGKILL)
        proc.communicate()
        raise
    return err


def _run(*args: str, timeout: float = 50) -> subprocess.CompletedProcess:
    return subprocess.run([*_cli(), *args], cwd=ROOT, capture_output=True, text=True, timeout=timeout,
                          env=dict(os.environ, PYTHONPATH=str(ROOT)))


@contextlib.contextmanager
def _launched(*args: str) -> Iterator[subprocess.Popen]:
    """`_start(*args)`, stopped by its PID (SIGTERM) if it still runs when the block ends."""
    proc = _start(*args)
    try:
        yield proc
    finally:
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGTERM)
            proc.communicate(timeout=15)


def _result(out: Path) -> dict:
    """The run's result.json."""
    return json.loads((out / "result.json").read_text())


def _wait_for(predicate, timeout: float, what: str):
    value = wait_until(predicate, timeout)
    if not value:
        raise AssertionError(f"timed out waiting for {what}")
    return value


def _pid(out: Path, needle: str) -> int | None:
    pids = [p for p in processes_with(str(out)) if needle in Path(f"/proc/{p}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")]
    return pids[0] if pids else None


def _round_of(out: Path, rid: int) -> int:
    """The round robot ``rid`` has checkpointed (0 before its first)."""
    from agents.robot import read_checkpoint

    try:
        return int(read_checkpoint(out / "fleet" / f"robot-{rid}.ckpt")["core"]["round"])
    except (ValueError, OSError, KeyError):
        return 0


def _exact_error(out: Path) -> float:
    """Largest error of any participant against the exact solve of the participants' data,
    recomputed here from the robots' own (c, gamma) and data.csv (not from result.json's metrics)."""
    from agents.kernel import GridBasis
    from agents.problem import solve_central
    from launcher import scenario

    result = _result(out)
    robots = scenario.load_data_csv(out / "data.csv")
    kept = [r for r in robots if r.id in result.get("participants", [r.id for r in robots])]
    basis = GridBasis(np.asarray(result["grid"], dtype=float), float(result["sigma"]))
    ref = solve_central(basis, np.vstack([r.points for r in kept]), np.concatenate([r.labels for r in kept]), result["C"])
    return max(basis.function_error(np.asarray(r["c"]), r["gamma"], ref.c, ref.gamma) for r in result["robots"])


# ----------------------------------------------------------------------------- the verdict (unit)


def _row(i: int, neighbours, value: float, **kw) -> dict:
    return {"id": i, "neighbours": list(neighbours), "converged": True, "v": value, **kw}


def _gap(a: dict, b: dict) -> float:
    return abs(a["v"] - b["v"])


def test_verdict_needs_agreement_connectivity_and_every_stopping_rule():
    from launcher.report import agreement_verdict

    line = [_row(0, [1], 1.0), _row(1, [0, 2], 1.0), _row(2, [1], 1.0 + 5e-4)]
    assert agreement_verdict(line, _gap, tol=1e-3)["converged"] is True
    # one link disagrees beyond tol: not converged, and the pair is named
    far = [_row(0, [1], 1.0), _row(1, [0, 2], 1.0), _row(2, [1], 1.01)]
    v = agreement_verdict(far, _gap, tol=1e-3)
    assert v["converged"] is False and "robots 1 and 2 disagree by 0.01" in v["verdict"]
    # the middle robot is gone for good: the survivors do not talk, whatever their values
    split = [_row(0, [], 1.0, dropped_at={"1": 24}), _row(2, [], 1.0, dropped_at={"1": 25})]
    v = agreement_verdict(split, _gap, tol=1e-3, absent=[1])
    assert v["converged"] is False and v["agreement"]["components"] == [[0], [2]]
    assert v["agreement"]["partition_since_round"] == 24 and "since round 24" in v["verdict"]
    # a one-sided drop breaks the link too (robot 1 still lists 2, robot 2 dropped 1)
    one_sided = [_row(0, [1], 1.0), _row(1, [0, 2], 1.0), _row(2, [], 1.0)]
    assert agreement_verdict(one_sided, _gap, tol=1e-3)["agreement"]["components"] == [[0, 1], [2]]
    # a robot that failed or did not meet its stopping rule
    failed = [_row(0, [1], 1.0), _row(1, [0], 1.0, converged=False, stopped="diverged", error="robot 1: diverged")]
    v = agreement_verdict(failed, _gap, tol=1e-3)
    assert v["converged"] is False and v["agreement"]["failed"] == [1] and "robot 1: diverged" in v["verdict"]
    assert agreement_verdict([], _gap, tol=1e-3)["converged"] is False
    # the verdict's graph is networkx's idea of connected (a random check against it)
    g = nx.gnp_random_graph(7, 0.3, seed=4)
    rows = [_row(i, list(g.neighbors(i)), 1.0) for i in g.nodes]
    assert agreement_verdict(rows, _gap, tol=1e-3)["agreement"]["connected"] == nx.is_connected(g)


def test_verdict_refuses_agreement_on_a_biased_answer():
    """Robots that agree with each other but not with the exact answer of their data (a lost dual
    after a crash) have not converged; unknown references (None) are not held against them."""
    from launcher.report import WRONG_ANSWER_FACTOR, agreement_verdict

    rows = [_row(0, [1], 1.19), _row(1, [0], 1.19)]
    exact = 1.0
    v = agreement_verdict(rows, _gap, tol=1e-3, exact_error=lambda r: abs(r["v"] - exact))
    assert v["converged"] is False and v["agreement"]["error_vs_exact"] == pytest.approx(0.19)
    assert "from the exact answer of the participants' data" in v["verdict"]
    close = [_row(0, [1], 1.0 + 0.9 * WRONG_ANSWER_FACTOR * 1e-3), _row(1, [0], 1.0 + 0.9 * WRONG_ANSWER_FACTOR * 1e-3)]
    assert agreement_verdict(close, _gap, tol=1e-3, exact_error=lambda r: abs(r["v"] - exact))["converged"] is True
    v = agreement_verdict(rows, _gap, tol=1e-3, exact_error=lambda r: None)
    assert v["converged"] is True and v["agreement"]["error_vs_exact"] is None


def test_verdict_tells_an_unfinished_fleet_from_a_biased_one():
    """Far from the exact answer at the round cap is "not converged yet", not "settled on a bias"."""
    from launcher.report import agreement_verdict

    biased = [_row(0, [1], 1.19), _row(1, [0], 1.19)]
    unfinished = [{**r, "converged": False, "rounds": 5000} for r in biased]
    exact = lambda r: abs(r["v"] - 1.0)  # noqa: E731
    v = agreement_verdict(unfinished, _gap, tol=1e-3, exact_error=exact)["verdict"]
    assert v.startswith("robot 0's answer is 0.19 from the exact answer") and "had not converged when it stopped" in v
    assert "did not meet their stopping rule within 5000 rounds" in v and "biased" not in v
    assert "settled on a biased point" in agreement_verdict(biased, _gap, tol=1e-3, exact_error=exact)["verdict"]


def test_a_run_agreeing_on_a_shifted_answer_is_not_converged(tmp_path):
    """End to end through build_result: every robot reports the exact answer scaled by 1.2."""
    from agents.problem import solve_central
    from launcher.report import build_result
    from launcher.world import Options, build_world

    world, spec = build_world(Options(robots=3, preset="paper", algorithm="admm"))
    central = solve_central(spec.basis, world.points, world.labels, None)
    rows = [
        {"id": i, "neighbours": [j for j in spec.robot_ids if j != i], "converged": True, "rounds": 50,
         "x": (1.2 * central.x).tolist(), "gamma": 1.2 * central.gamma}
        for i in spec.robot_ids
    ]
    out = build_result(world, spec.basis, central, rows, algorithm="admm", C=None, wall_s=0.0)
    assert out["agreement"]["disagreement"] == 0.0 and out["converged"] is False
    assert out["agreement"]["error_vs_exact"] == pytest.approx(out["metrics"]["function_error"])
    rows_ok = [dict(r, x=central.x.tolist(), gamma=central.gamma) for r in rows]
    assert build_result(world, spec.basis, central, rows_ok, algorithm="admm", C=None, wall_s=0.0)["converged"] is True


# ----------------------------------------------------------------------------- table rows


@bound(60)
def test_pause_longer_than_dead_after_heals_on_the_exact_answer(tmp_path):
    """Row 1: SIGSTOP one of 4 robots for longer than --dead-after, then SIGCONT: nobody drops
    anybody (its liveliness token stays), the fleet resumes and ends on the exact answer."""
    out = tmp_path / "run"
    # one process per robot: SIGSTOP pauses robot 2 alone (`auto` runs 4 robots on 2 cores in one process)
    with _launched("launch", *PAPER, "--robots", "4", "--robots-per-process", "1", "--dead-after", "1.5s",
                   "--out", str(out)) as proc:
        pid = _wait_for(lambda: _round_of(out, 2) >= 5 and _pid(out, "--id 2"), 30, "robot 2 at round 5")
        os.kill(pid, signal.SIGSTOP)
        paused_at = _round_of(out, 2)
        time.sleep(4.0)  # > 2 x dead_after
        others = [_round_of(out, i) for i in (0, 1, 3)]
        os.kill(pid, signal.SIGCONT)
        err = _finish(proc, 45)
    assert all(r <= paused_at + 2 for r in others), (paused_at, others)  # they waited for it
    assert proc.returncode == 0, err
    result = _result(out)
    assert result["converged"] is True and result["absent"] == [] and result["participants"] == [0, 1, 2, 3]
    assert all(r["neighbours_dropped"] == [] for r in result["robots"])
    assert _exact_error(out) < 1e-3


@bound(60)
def test_router_killed_mid_run_is_restarted_and_the_fleet_heals(tmp_path):
    """Row 2: SIGKILL the router mid-run: the launcher restarts it on the same endpoint, the
    robots reconnect and the fleet ends on the exact answer of all its robots."""
    out = tmp_path / "run"
    # 20 ms links: the run lasts seconds, so the router dies mid-run (the accelerated ADMM needs
    # only ~120 rounds, well under a second on clean loopback)
    with _launched("launch", *PAPER, "--robots", "4", "--dead-after", "1.5s", "--delay", "20ms", "--out", str(out)) as proc:
        router = _wait_for(lambda: _round_of(out, 0) >= 5 and _pid(out, "launcher.router"), 30, "round 5")
        os.kill(router, signal.SIGKILL)
        err = _finish(proc, 45)
    assert proc.returncode == 0, err
    result = _result(out)
    assert len(result["router_restarts"]) == 1
    assert result["converged"] is True and result["absent"] == [] and len(result["robots"]) == 4
    assert all(r["neighbours_dropped"] == [] for r in result["robots"])
    assert _exact_error(out) < 1e-3


@bound(40)
@pytest.mark.parametrize("sig", ["SIGTERM", "SIGHUP", "SIGINT"])
def test_sigterm_and_sighup_stop_every_child_and_write_a_partial_result(tmp_path, sig):
    """Row 5: SIGTERM (timeout, systemd, docker stop) and SIGHUP clean up like Ctrl-C (SIGINT):
    every child stopped by PID, a partial result, and where the per-robot results are."""
    out = tmp_path / "run"
    # still running when signalled; robots in 2 processes (2 + 1), so that several robot processes are stopped
    proc = _start("launch", *PAPER, "--delay", "20ms", "--robots-per-process", "2", "--out", str(out))
    try:
        _wait_for(lambda: _round_of(out, 0) >= 5, 30, "round 5")
        children = [p for p in processes_with(str(out)) if p != proc.pid]
        assert len(children) >= 3  # router + the robot processes (3 robots, 2 per process: 2 processes)
        os.kill(proc.pid, getattr(signal, sig))
        err = _finish(proc, 20)
    finally:
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGKILL)
            proc.communicate()
    assert proc.returncode == 128 + getattr(signal, sig), err
    assert [p for p in processes_with(str(out))] == []  # no orphan
    result = _result(out)
    assert result["interrupted"] == sig and result["converged"] is False
    assert f"stopped by {sig}" in err and "robot-<id>.json" in err and "Traceback" not in err
    assert {r["stopped"] for r in result["robots"]} <= {"signal", "finished"}


@bound(20)
def test_robots_bound_by_the_machine(tmp_path):
    """Row 6: --robots 1000 is refused in one line naming the bound; nothing is started."""
    out = tmp_path / "run"
    proc = _run("launch", *PAPER, "--robots", "1000", "--out", str(out), timeout=15)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    assert "--robots: 1000" in lines[0] and "cores" in lines[0] and "--max-robots" in lines[0]
    assert not out.exists()


@bound(20)
@pytest.mark.parametrize("form", [["--delay", "-5ms"], ["--delay=-5ms"]], ids=["space", "equals"])
def test_negative_delay_is_one_line(tmp_path, form):
    """Row 7: --delay -5ms (which argparse reads as an option) and --delay=-5ms: one line."""
    proc = _run("launch", *PAPER, *form, "--out", str(tmp_path / "run"), timeout=15)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    assert lines[0] == ("shapefleet: error: --delay: '-5ms' is negative; a duration is >= 0 (use e.g. 20ms or 0.5s)"
                        " (see shapefleet launch --help)")
    assert "usage" not in proc.stderr


@bound(20)
@pytest.mark.parametrize(
    "args", [["--crash", "7@10"], ["--crash", "1@5000"], ["--loss", "2"]], ids=["unknown-robot", "past-cap", "loss"]
)
def test_refused_run_leaves_nothing_behind(tmp_path, args):
    """Row 8: a run refused with exit 2 writes no run folder (no data.csv, no fleet/)."""
    out = tmp_path / "run"
    proc = _run("launch", *PAPER, *args, "--out", str(out), timeout=15)
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert args[0] in proc.stderr
    assert not out.exists()


@bound(40)
def test_crash_that_never_fires_is_reported(tmp_path):
    """Row 9: a crash planned after the run's end (it stops by its rule long before the cap)
    is named on stderr and in result.json; a crash past the cap is refused (test above)."""
    out = tmp_path / "run"
    proc = _run("launch", *PAPER, "--crash", "2@4000", "--out", str(out), timeout=35)
    assert proc.returncode == 0, proc.stderr
    result = _result(out)
    assert result["rounds"] < 4000 and result["crashes"] == []
    assert result["crashes_not_fired"] == [{"robot": 2, "round": 4000}]
    assert "--crash 2@4000 never fired" in proc.stderr


@bound(30)
def test_one_robot_reports_its_exact_answer_as_converged(tmp_path):
    """Row 10: --robots 1 holds all the data: its round-0 solve is the exact answer."""
    out = tmp_path / "run"
    proc = _run("simulate", *PAPER, "--robots", "1", "--out", str(out), timeout=25)
    assert proc.returncode == 0, proc.stderr
    result = _result(out)
    assert result["converged"] is True and result["rounds"] == 0
    assert result["metrics"]["function_error"] < 1e-9
    assert _exact_error(out) < 1e-9


@bound(40)
def test_line_of_three_whose_middle_robot_dies_is_not_converged(tmp_path):
    """Issue 18: a line 0-1-2 whose middle robot dies for good leaves two robots that cannot
    talk: each stops "isolated", the result names the partition, the exit code is 1. Robot 1 SIGKILLs
    itself right after queueing its round-20 frame: when that frame leaves the process first its
    neighbours advance once more and drop it in round 21, when it does not they drop it in round 20,
    and in 19 when the round-19 frame was still queued too (all three seen on this 2-core machine)."""
    out = tmp_path / "run"
    proc = _run("launch", *PAPER, "--topology", "line", "--crash", "1@20", "--no-restart", "--out", str(out), timeout=35)
    assert proc.returncode == 1, proc.stderr
    result = _result(out)
    assert result["converged"] is False and result["absent"] == [1]
    assert result["agreement"]["components"] == [[0], [2]] and result["agreement"]["connected"] is False
    assert 19 <= result["agreement"]["partition_since_round"] <= 21
    assert {r["stopped"] for r in result["robots"]} == {"isolated"}
    assert "split into [0] | [2]" in result["verdict"] and "NOT converged" in proc.stderr


@bound(40)
def test_solver_failure_is_one_line_and_never_converged(tmp_path):
    """Divergence is an error: a local solve piqp cannot finish (a penalty of 1e300) ends the run
    with one line and exit 1, in process and over Zenoh, without a traceback in any log."""
    proc = _run("simulate", *PAPER, "--rho", "1e300", "--out", str(tmp_path / "sim"), timeout=25)
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    # (which robot and round meets piqp's failure first depends on the path: the guard's exact warm QP
    # answers some steps piqp cannot)
    (line,) = proc.stderr.strip().splitlines()
    assert re.fullmatch(r"shapefleet: the run failed: robot \d+ round \d+: local solver failed: "
                        r"piqp returned Status\.PIQP_MAX_ITER_REACHED", line), line
    out = tmp_path / "launch"
    proc = _run("launch", *PAPER, "--rho", "1e300", "--dead-after", "1s", "--out", str(out), timeout=35)
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    assert "local solver failed" in proc.stderr
    result = _result(out)
    assert result["converged"] is False and result["agreement"]["failed"]
    for log in (out / "fleet").glob("robot-*.log"):
        assert "Traceback" not in log.read_text()


def test_exploding_iterate_is_divergence():
    from agents.robot import check_iterate

    assert check_iterate(np.array([1.0, -2.0, 3.0])) is None
    assert "non-finite" in check_iterate(np.array([1.0, np.nan]))
    assert "exploding" in check_iterate(np.array([1.0, -2.4e77]))
