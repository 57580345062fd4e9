"""`shapefleet launch` starts its router and its first robot processes before its imports
(launcher/router.py EarlyRouter, EarlyRobots): a launch refused for bad input leaves neither behind
(nor the router's folder), an early router whose launcher is gone ends by itself, and an early robot
runs with the arguments and log its launcher hands it."""

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from launcher.router import EarlyRobots, EarlyRouter, child_env
from protocol.zenoh_config import free_loopback_port

from .conftest import processes_with

ROOT = Path(__file__).resolve().parent.parent


def test_bad_input_stops_the_early_router_and_removes_its_folder(tmp_path):
    env = {**child_env(), "TMPDIR": str(tmp_path)}  # the early router's folder (tempfile.mkdtemp) goes here
    proc = subprocess.run([sys.executable, "-m", "launcher.cli", "launch", "--preset", "paper", "--robots", "0",
                           "--out", str(tmp_path / "run")], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.count("\n") == 1 and "--robots" in proc.stderr
    assert processes_with(str(tmp_path)) == []
    assert not list(tmp_path.glob("shapefleet-router-*")) and not (tmp_path / "run").exists()


@pytest.mark.parametrize("early", [EarlyRouter, EarlyRobots])
def test_an_early_router_or_robot_is_only_for_a_plain_launch(early):
    for args in (["simulate", "--preset", "paper"], ["launch", "--zenoh-port", "7447"], ["launch", "--config=s.toml"],
                 ["launch", "-h"]):
        assert early.for_command_line(["shapefleet", *args]) is None, args


def run_orphaned(args: str, log: Path, *, marker: str, wait_s: float = 20.0) -> list[int]:
    """Start ``python ARGS --parent-pid <a shell>`` from a shell that exits at once (the process is
    orphaned, as when its launcher is SIGKILLed); the PIDs still running ``wait_s`` later (each then
    killed by its PID: never left running, even when the test fails)."""
    script = f"{sys.executable} {args} --parent-pid $$ > {log} 2>&1 &"
    subprocess.run(["sh", "-c", script], cwd=ROOT, env=child_env(), timeout=10, check=True)
    end = time.monotonic() + wait_s
    while processes_with(marker) and time.monotonic() < end:
        time.sleep(0.05)
    left = processes_with(marker)
    for pid in left:
        os.kill(pid, 9)
    return left


def test_a_router_ends_when_its_parent_is_gone(tmp_path):
    """... and removes its early-router folder: a killed launcher leaves no /tmp/shapefleet-router-*."""
    folder = tmp_path / "shapefleet-router-test"
    folder.mkdir()
    ready, log = folder / "ready.json", tmp_path / "router.log"
    assert run_orphaned(f"-m launcher.router --port {free_loopback_port()} --ready-file {ready} --max-wall-s 30 "
                        f"--orphan-folder {folder}", log, marker=str(ready)) == []
    said = log.read_text()
    assert '"router": "ready"' in said and '"router": "closed"' in said, said  # it ran, then ended by itself
    assert not folder.exists()


def test_an_early_router_bound_shorter_than_the_run_is_not_adopted(tmp_path):
    """A launch whose bound outlasts the early router's (a long --max-wall) starts a router of its
    own: the early one would end by itself in the middle of the run, so it is stopped instead."""
    from launcher.fleet import _start_router

    early = EarlyRouter(str(tmp_path))
    early.bound_s = 10.0  # shorter than the run's 60 s below
    router = None
    try:
        router, _ = _start_router(None, tmp_path, 60.0, started=[], early=early)
        assert router.proc.pid != early.proc.pid and not early.adopted
        assert early.proc.poll() is not None and not early.folder.exists()  # stopped by its PID, folder gone
    finally:
        for proc in [early.proc] + ([router.proc] if router is not None else []):
            if proc.poll() is None:
                proc.kill()
                proc.wait(10)
        if router is not None:
            router.stop()


# ----------------------------------------------------------------------------- early robots


def test_no_early_robots_for_a_free_running_fleet():  # another robot program (agents/free_robot.py)
    assert EarlyRobots.for_command_line(["shapefleet", "launch", "--sync", "free"]) is None
    assert EarlyRobots.for_command_line(["shapefleet", "launch", "--sync=free"]) is None


def test_an_early_robot_runs_with_the_arguments_and_log_it_is_handed(tmp_path):
    """The launcher's message gives the forked robot its arguments and its log: a fleet file that
    is not there is the robot's usual one-line refusal (exit 2), written to the log it was handed."""
    early, proc = EarlyRobots(1, str(tmp_path)), None
    try:
        log = tmp_path / "robot-0.log"
        proc = early.take(["--fleet-file", str(tmp_path / "nowhere.json"), "--id", "0", "--connect",
                           "tcp/127.0.0.1:7447", "--workdir", str(tmp_path)], log)
        assert proc is not None and early.take([], log) is None  # capacity 1: handed once
        assert proc.pid != early.proc.pid and proc.wait(30) == 2 and proc.poll() == 2
        assert proc.stdout.read() == b""  # its stdout: the pipe handed with it, at its end
        said = log.read_text()
        assert said.count("\n") == 1 and "nowhere.json" in said, said
    finally:
        zygote = early.proc
        early.close()
        if proc is not None:
            proc.stdout.close()
    assert zygote.returncode == 0 and processes_with(str(tmp_path)) == []


def test_early_robots_not_adopted_are_stopped_by_pid(tmp_path):
    early = EarlyRobots(2, str(tmp_path))
    procs = list(early.procs)
    end = time.monotonic() + 10  # exec'd by now, or soon
    while not processes_with(str(tmp_path)) and time.monotonic() < end:
        time.sleep(0.01)
    assert len(procs) == 1 and processes_with(str(tmp_path)) == [procs[0].pid]  # one zygote, named by its run folder
    early.discard()
    assert all(p.returncode is not None for p in procs) and processes_with(str(tmp_path)) == []


def _fleet_file(tmp_path: Path) -> Path:
    from tests.conftest import make_run

    _, spec, _ = make_run(fleet_id="zygote")
    fleet = tmp_path / "fleet.json"
    spec.save(fleet)
    return fleet


@pytest.mark.parametrize("how", ["sigterm", "sigkill"])
def test_forked_robots_are_stopped_by_their_pid(tmp_path, how):
    """Two robots forked by the zygote (no router: they wait for one) are each a process of their
    own, stopped by its PID as launch_fleet stops any robot (SIGTERM: the robot's own stop, exit
    code as Popen's; SIGKILL: -9); the zygote then ends and nothing is left behind."""
    import signal

    from launcher.fleet import _stop_all

    fleet, early, procs = _fleet_file(tmp_path), EarlyRobots(2, str(tmp_path)), []
    try:
        for i in (0, 1):
            procs.append(early.take(["--fleet-file", str(fleet), "--id", str(i), "--connect",
                                     f"tcp/127.0.0.1:{free_loopback_port()}", "--workdir", str(tmp_path)],
                                    tmp_path / f"robot-{i}.log"))
        assert all(p is not None for p in procs) and len({p.pid for p in procs} | {early.proc.pid}) == 3
        assert all(p.poll() is None for p in procs)
        if how == "sigterm":
            codes = _stop_all(procs, grace_s=10.0)
            assert all(c is not None and c != -signal.SIGKILL for c in codes), codes
        else:
            for p in procs:
                p.kill()
            assert [p.wait(10) for p in procs] == [-signal.SIGKILL] * 2
        procs[0].kill()  # once it ended: nothing (its PID is still a zombie of the zygote's, never another's)
    finally:
        early.close()
        for p in procs:
            if p is not None:
                p.stdout.close()
    assert processes_with(str(tmp_path)) == []


def test_the_zygote_stops_its_robots_when_its_launcher_is_gone(tmp_path):
    """A launcher killed by SIGKILL: its zygote sees its socket end, SIGTERMs the robots it forked
    and ends; nothing is left (robots waiting for a router that will never come)."""
    fleet = _fleet_file(tmp_path)
    script = (f"import sys, time; sys.path.insert(0, {str(ROOT)!r}); from launcher.router import EarlyRobots; "
              f"e = EarlyRobots(2, {str(tmp_path)!r}); "
              f"[e.take(['--fleet-file', {str(fleet)!r}, '--id', str(i), '--connect', "
              f"'tcp/127.0.0.1:{free_loopback_port()}', '--workdir', {str(tmp_path)!r}], "
              f"__import__('pathlib').Path({str(tmp_path)!r}) / f'robot-{{i}}.log') for i in (0, 1)]; "
              "print('forked', flush=True); time.sleep(60)")
    launcher = subprocess.Popen([sys.executable, "-c", script], cwd=ROOT, env=child_env(), stdout=subprocess.PIPE)
    try:
        assert launcher.stdout.readline() == b"forked\n"
        assert len(set(processes_with(str(tmp_path))) - {launcher.pid}) == 3  # the zygote and its two robots
        launcher.kill()
        launcher.wait(10)
        end = time.monotonic() + 20
        while processes_with(str(tmp_path)) and time.monotonic() < end:
            time.sleep(0.05)
    finally:
        if launcher.poll() is None:
            launcher.kill()
            launcher.wait(10)
        launcher.stdout.close()
        left = processes_with(str(tmp_path))
        for pid in left:
            os.kill(pid, 9)
    assert left == []


@pytest.mark.parametrize("program", ["agents.robot", "agents.free_robot"])
def test_a_robot_whose_launcher_is_gone_stops_by_itself(tmp_path, program):
    """A launcher killed by SIGKILL cannot stop its robots; with ``--parent-pid`` (what launch_fleet
    passes) they notice and stop as on SIGTERM, instead of waiting max_wall_s (600 s) for a router
    that died with the launcher."""
    from tests.conftest import make_run

    _, spec, _ = make_run(fleet_id="orphan")
    fleet = tmp_path / "fleet.json"
    spec.save(fleet)
    extra = " --period 0.01" if program == "agents.free_robot" else ""
    log = tmp_path / "robot.log"  # no router: the robot would wait for one
    left = run_orphaned(f"-m {program} --fleet-file {fleet} --id 0 --connect tcp/127.0.0.1:{free_loopback_port()} "
                        f"--workdir {tmp_path}{extra}", log, marker=str(fleet))
    assert left == [], log.read_text()
    assert "gone: stopping" in log.read_text()
