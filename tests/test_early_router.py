"""`shapefleet launch` starts its router before its imports (launcher/router.py EarlyRouter) and
forks its robot processes from itself (launcher/fleet.py fork_robot): a launch refused for bad input
leaves no router behind (nor its folder), an early router whose launcher is gone ends by itself, and
a forked robot runs with the arguments and log it is given, is stopped by its PID, and stops by
itself when its launcher is gone."""

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from launcher.router import EarlyRouter, child_env
from protocol.zenoh_config import free_loopback_port

from .conftest import processes_with

ROOT = Path(__file__).resolve().parent.parent
pytestmark = pytest.mark.integration  # routers and forked robots: real processes


def test_bad_input_stops_the_early_router_and_removes_its_folder(tmp_path):
    env = {**child_env(), "TMPDIR": str(tmp_path)}  # the early router's folder (tempfile.mkdtemp) goes here
    proc = subprocess.run([sys.executable, "-m", "launcher.cli", "launch", "--preset", "paper", "--robots", "0",
                           "--out", str(tmp_path / "run")], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.count("\n") == 1 and "--robots" in proc.stderr
    assert processes_with(str(tmp_path)) == []
    assert not list(tmp_path.glob("shapefleet-router-*")) and not (tmp_path / "run").exists()


def test_an_early_router_is_only_for_a_plain_launch():
    for args in (["simulate", "--preset", "paper"], ["launch", "--zenoh-port", "7447"], ["launch", "--config=s.toml"],
                 ["launch", "-h"]):
        assert EarlyRouter.for_command_line(["shapefleet", *args]) is None, args


def run_orphaned(args: str, log: Path, *, marker: str, wait_s: float = 20.0) -> list[int]:
    """Start ``python ARGS --parent-pid <a shell>`` from a shell that exits at once (the process is
    orphaned, as when its launcher is SIGKILLed); the PIDs still running ``wait_s`` later (each then
    killed by its PID: never left running, even when the test fails)."""
    script = f"{sys.executable} {args} --parent-pid $$ > {log} 2>&1 & echo $!"
    said = subprocess.run(["sh", "-c", script], cwd=ROOT, env=child_env(), timeout=10, check=True,
                          capture_output=True, text=True).stdout
    started = int(said.split()[-1])
    end = time.monotonic() + wait_s
    # the started PID itself, not only a command-line scan: a scan that runs while the process is
    # between fork and exec can read an empty command line and miss it (once in CI: the test then
    # found the router "gone" before it had printed anything)
    while (_running(started) or processes_with(marker)) and time.monotonic() < end:
        time.sleep(0.05)
    left = sorted(set(processes_with(marker)) | ({started} if _running(started) else set()))
    for pid in left:
        os.kill(pid, 9)
    return left


def _running(pid: int) -> bool:
    """``pid`` exists and is not a zombie (an orphan whose new parent has not reaped it yet)."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return False


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


# ----------------------------------------------------------------------------- forked robots

_FORKER = r"""
import json, sys, time
from pathlib import Path
from launcher.fleet import fork_robot
folder, fleet, port, then = Path(sys.argv[1]), sys.argv[2], sys.argv[3], sys.argv[4]
args = lambda i: ["--fleet-file", fleet, "--id", str(i), "--connect", f"tcp/127.0.0.1:{port}", "--workdir", str(folder),
                  "--parent-pid", str(__import__("os").getpid())]
robots = [fork_robot(args(i), open(folder / f"robot-{i}.log", "ab")) for i in (0, 1)]
print(json.dumps([r.pid for r in robots]), flush=True)
if then == "stop":  # as launch_fleet stops its robots: by PID, SIGTERM then SIGKILL, reaped
    from launcher.fleet import _stop_all
    time.sleep(1.0)
    print(json.dumps(_stop_all(robots, grace_s=10.0)), flush=True)
else:  # wait to be SIGKILLed, as a launcher can be
    time.sleep(60)
"""


@pytest.fixture
def router_port(tmp_path):
    """A router for the forked robots (without one, a robot's Zenoh session takes ~9 s to give up)."""
    from launcher.fleet import stop_process
    from tests.conftest import start_router

    port = free_loopback_port()
    router = start_router(tmp_path, port, max_wall_s=60)
    yield port
    stop_process(router)


def _forker(tmp_path: Path, port: int, then: str) -> subprocess.Popen:
    from tests.conftest import make_run

    _, spec, _ = make_run(fleet_id="forked")
    fleet = tmp_path / "fleet.json"
    spec.save(fleet)  # robots 0 and 1 of 3: they wait for robot 2
    return subprocess.Popen([sys.executable, "-c", _FORKER, str(tmp_path), str(fleet), str(port), then],
                            cwd=ROOT, env=child_env(), stdout=subprocess.PIPE, text=True)


def _leftovers(pids: list[int], wait_s: float = 20.0) -> list[int]:
    """Those of ``pids`` still running (not zombies) after up to ``wait_s``; each then SIGKILLed."""
    def running(pid: int) -> bool:
        try:
            with open(f"/proc/{pid}/stat") as fh:
                return fh.read().rsplit(")", 1)[1].split()[0] != "Z"
        except OSError:
            return False

    end = time.monotonic() + wait_s
    while any(running(p) for p in pids) and time.monotonic() < end:
        time.sleep(0.05)
    left = [p for p in pids if running(p)]
    for pid in left:
        os.kill(pid, 9)
    return left


def test_forked_robots_are_stopped_by_their_pid(tmp_path, router_port):
    """Two robots forked from one process (no router: they wait for one) are each a process of
    their own in a session of its own, and stop on their launcher's SIGTERM as robots do (code 0
    or 1 as Popen's, not SIGKILL's -9), their stderr in the log each was given."""
    proc = _forker(tmp_path, router_port, "stop")
    try:
        pids = json.loads(proc.stdout.readline())
        assert len(set(pids) | {proc.pid}) == 3
        end = time.monotonic() + 10  # each calls setsid first thing after the fork
        while not all(os.getsid(p) == p for p in pids) and time.monotonic() < end:
            time.sleep(0.01)
        assert all(os.getsid(p) == p for p in pids)
        codes = json.loads(proc.stdout.readline())
        assert proc.wait(30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
        proc.stdout.close()
    assert all(c in (0, 1) for c in codes), codes
    assert all(json.loads((tmp_path / f"robot-{i}.json").read_text())["stopped"] == "signal" for i in (0, 1))
    assert _leftovers(pids, 0.0) == []
    assert all("Traceback" not in (tmp_path / f"robot-{i}.log").read_text() for i in (0, 1))


def test_forked_robots_stop_by_themselves_when_their_launcher_is_gone(tmp_path, router_port):
    """A launcher killed by SIGKILL cannot stop its robots: forked ones, too, see it gone
    (``--parent-pid``) and stop as on SIGTERM."""
    proc = _forker(tmp_path, router_port, "wait")
    try:
        pids = json.loads(proc.stdout.readline())
        proc.kill()
        proc.wait(10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
        proc.stdout.close()
    assert _leftovers(pids) == []
    assert all("gone: stopping" in (tmp_path / f"robot-{i}.log").read_text() for i in (0, 1))


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
