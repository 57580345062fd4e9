"""The three-machine walk-through of docs/deploy.md, on network namespaces: hub + two robot hosts.

Each "machine" is a network namespace this test creates (and deletes): the hub's has a bridge with
10.213.0.1/24, each robot's a veth into that bridge with 10.213.0.1x/24; those addresses exist only
inside these namespaces. The router runs in the hub's namespace, each robot in its own, with the
doc's commands verbatim (tests/deploy_doc.py); prepare and collect need no network and run on the
host. The result must be the in-process simulator's, bit for bit, and `collect` must write the
result.json `simulate` writes for the same scenario.

Skipped, saying why, where network namespaces cannot be created (not root, no iproute2).
"""

from __future__ import annotations

import json
import os
import secrets
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from tests import deploy_doc as doc
from tests.conftest import skip_evidence

EVIDENCE = True  # with SHAPEFLEET_REQUIRE_EVIDENCE set a skip here fails (tests/conftest.py)

pytestmark = pytest.mark.integration

HUB_IP = "10.213.0.1"
PREFIX = 24
ROBOT_HOSTS = ("robot0", "robot1")  # the doc's two robot hosts
ROUTER_READY_S = 30.0
FLEET_S = 120.0


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, text=True, timeout=20)


def _netns_unavailable() -> str | None:
    if shutil.which("ip") is None:
        return "needs iproute2 ('ip' command) to create network namespaces"
    if os.geteuid() != 0:
        return "needs root to create network namespaces (ip netns add)"
    probe = f"sfprobe{os.getpid()}{secrets.token_hex(2)}"
    try:
        _ip("netns", "add", probe)
    except (subprocess.CalledProcessError, subprocess.TimeoutExpired) as exc:
        return f"cannot create a network namespace here: {getattr(exc, 'stderr', '') or exc}".strip()
    _ip("netns", "del", probe)
    return None


class Machines:
    """Network namespaces for the hub and each robot host, wired by a bridge; deleted on exit."""

    def __init__(self, hosts: tuple[str, ...]) -> None:
        tag = f"sf{os.getpid() % 100000}{secrets.token_hex(2)}"
        self.hub = f"{tag}-hub"
        self.ns = {h: f"{tag}-{h}" for h in hosts}
        self.addr = {h: f"10.213.0.{10 + k}" for k, h in enumerate(hosts)}
        self.created: list[str] = []

    def __enter__(self) -> Machines:
        try:
            for ns in (self.hub, *self.ns.values()):
                _ip("netns", "add", ns)
                self.created.append(ns)
                _ip("-n", ns, "link", "set", "lo", "up")
            _ip("-n", self.hub, "link", "add", "br0", "type", "bridge")
            _ip("-n", self.hub, "addr", "add", f"{HUB_IP}/{PREFIX}", "dev", "br0")
            _ip("-n", self.hub, "link", "set", "br0", "up")
            for k, (host, ns) in enumerate(self.ns.items()):
                # created inside the namespaces: the host's own network is never touched
                _ip("-n", self.hub, "link", "add", f"vh{k}", "type", "veth", "peer", "name", "eth0", "netns", ns)
                _ip("-n", self.hub, "link", "set", f"vh{k}", "master", "br0")
                _ip("-n", self.hub, "link", "set", f"vh{k}", "up")
                _ip("-n", ns, "addr", "add", f"{self.addr[host]}/{PREFIX}", "dev", "eth0")
                _ip("-n", ns, "link", "set", "eth0", "up")
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        for ns in reversed(self.created):  # deleting a namespace deletes its links and bridge
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=20)
        self.created.clear()


@pytest.fixture(scope="module")
def machines_ok():
    reason = _netns_unavailable()
    if reason:
        skip_evidence(reason)


@pytest.fixture(scope="module")
def simulate_result(tmp_path_factory):
    """`shapefleet simulate` on the walk-through's scenario (the doc's prepare flags)."""
    tmp = tmp_path_factory.mktemp("simulate")
    shutil.copy(doc.SCENARIO, tmp / "scenario.toml")
    proc = subprocess.run(
        [sys.executable, "-m", "launcher.cli", "simulate", "--config", "scenario.toml", "--robots", "2", "--out", "sim"],
        cwd=tmp, capture_output=True, text=True, timeout=300, env={**os.environ, "MPLBACKEND": "Agg"},
    )
    assert proc.returncode == 0, proc.stderr
    return json.loads((tmp / "sim" / "result.json").read_text())


def _walk_through(tmp: Path, tls: bool, machines: Machines) -> dict[str, float]:
    """The doc's steps 1-6; returns nothing but leaves hub/run and the hosts' results."""
    hub = tmp / "hub"
    hub.mkdir()
    shutil.copy(doc.SCENARIO, hub / "scenario.toml")
    env = doc.environment(tmp, ROUTER_IP=HUB_IP, ROUTER_PORT="7447")
    if tls:
        doc.run("certs", hub, env)
    doc.run("prepare", hub, env)
    doc.run("copy-fleet", hub, env)
    if tls:
        doc.run("copy-certs", hub, env)
    started: list[subprocess.Popen] = []
    try:
        router = doc.start("router-tls" if tls else "router", hub, env, netns=machines.hub)
        started.append(router)
        lines = doc.Lines(router)
        assert lines.wait_for('"ready"', ROUTER_READY_S), f"router not ready: {lines.seen}"
        robots = []
        for host in ROBOT_HOSTS:
            cwd = doc.host_dir(tmp, host)
            robots.append(doc.start("robot-tls" if tls else "robot", cwd, env, netns=machines.ns[host], log=cwd / "robot.log"))
            started.append(robots[-1])
        codes = doc.wait_all(robots, FLEET_S)
        logs = {h: (doc.host_dir(tmp, h) / "robot.log").read_text()[-2000:] for h in ROBOT_HOSTS}
        assert codes == [0] * len(robots), f"robot exit codes {codes}; logs: {logs}"
    finally:
        for proc in reversed(started):
            doc.stop(proc)
    doc.run("fetch", hub, env)
    doc.run("collect", hub, env)
    return {}


@pytest.mark.parametrize("tls", [False, True], ids=["tcp", "tls"])
def test_walk_through_on_three_machines(tmp_path, machines_ok, simulate_result, tls):
    from agents.spec import FleetSpec
    from launcher.simulate import simulate_fleet

    with Machines(ROBOT_HOSTS) as machines:
        _walk_through(tmp_path, tls, machines)

    hub = tmp_path / "hub"
    # every robot host got its own data and nothing of the others'
    full = FleetSpec.load(hub / "fleet" / "fleet.json")
    for k, host in enumerate(ROBOT_HOSTS):
        own = FleetSpec.load(doc.host_dir(tmp_path, host) / "fleet.json")
        assert own.owner == k and own.config_tag == full.config_tag
        assert all(len(r.points) == 0 for i, r in own.robots.items() if i != k)

    # the networked run computes the in-process simulator's iterates, bit for bit
    want = {r["id"]: r for r in simulate_fleet(full).robots}
    for k, host in enumerate(ROBOT_HOSTS):
        got = json.loads((doc.host_dir(tmp_path, host) / "result.json").read_text())
        assert got["stopped"] == "finished" and got["converged"]
        assert (got["id"], got["rounds"]) == (k, want[k]["rounds"])
        assert got["x"] == list(want[k]["x"]) and got["gamma"] == want[k]["gamma"]
        assert {int(r): v for r, v in got["trace"].items()} == {r: list(v) for r, v in want[k]["trace"].items()}
        assert got["frames_rejected"]["total"] == 0

    # collect writes what simulate writes for the same scenario
    result = json.loads((hub / "run" / "result.json").read_text())
    for name in ("result.json", "data.csv", "shapes.png", "convergence.png"):
        assert (hub / "run" / name).stat().st_size > 0
    assert result["converged"] and result["rounds"] == simulate_result["rounds"]
    assert result["absent"] == [] and result["participants"] == [0, 1]
    assert result["central"] == simulate_result["central"]
    for got, want_row in zip(result["robots"], simulate_result["robots"], strict=True):
        assert got["id"] == want_row["id"]
        assert np.max(np.abs(np.subtract(got["c"], want_row["c"]))) <= 1e-9
        assert abs(got["gamma"] - want_row["gamma"]) <= 1e-9
    for key in ("function_error", "consensus_error", "train_accuracy", "iou"):
        assert result["metrics"][key] == pytest.approx(simulate_result["metrics"][key], abs=1e-9)
    assert [h["round"] for h in result["history"]] == [h["round"] for h in simulate_result["history"]]


def test_every_marked_block_of_the_doc_is_run_by_these_tests():
    """A block added to docs/deploy.md with a test marker must be run here or in test_tls.py."""
    run_here = {"certs", "prepare", "copy-fleet", "copy-certs", "router", "router-tls", "robot", "robot-tls", "fetch", "collect"}
    assert set(doc.blocks()) == run_here
    for name, text in doc.blocks().items():
        if name.startswith(("router", "robot")):  # started in the background: one command, exec'ed
            assert text.lstrip().startswith("shapefleet ") and "\n" not in text.replace("\\\n", ""), name


# ----------------------------------------------------------------------------- two linked routers

SITES = ("siteA", "siteB")  # two hosts, each with its own router and half of the robots
ROUTER_PORT = 7447


def test_two_linked_routers_robots_split_between_hosts(tmp_path, machines_ok):
    """Issue 14, beyond one host: a router on each of two hosts, the second linked to the first
    (``--connect``); robots 0-1 on host A (client of router A), 2-3 on host B (client of router B),
    each pair as tasks of one process. Frames between the sites cross both routers; the run is the
    in-process simulator's, bit for bit."""
    from launcher.simulate import simulate_fleet
    from launcher.world import Options, build_world

    _world, spec = build_world(Options(robots=4, preset="paper", max_rounds=80, fleet_id="two-routers"))
    want = {r["id"]: r for r in simulate_fleet(spec).robots}
    spec.save(tmp_path / "fleet.json")
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parent.parent)}
    py = sys.executable
    started: list[subprocess.Popen] = []
    with Machines(SITES) as machines:
        addr = machines.addr
        try:
            for site, peer in zip(SITES, (None, addr[SITES[0]])):
                argv = [py, "-m", "launcher.router", "--port", str(ROUTER_PORT), "--host", addr[site],
                        "--allow-remote", "--ready-file", str(tmp_path / f"{site}.ready"), "--max-wall-s", "120"]
                if peer is not None:
                    argv += ["--connect", f"tcp/{peer}:{ROUTER_PORT}"]
                started.append(doc.spawn(argv, tmp_path, env, netns=machines.ns[site], log=tmp_path / f"{site}-router.log"))
            for site in SITES:
                end = time.monotonic() + ROUTER_READY_S
                while not (tmp_path / f"{site}.ready").exists():
                    assert time.monotonic() < end, (tmp_path / f"{site}-router.log").read_text()
                    time.sleep(0.05)
            robots = []
            for site, ids in zip(SITES, ("0,1", "2,3")):
                (tmp_path / site).mkdir()
                argv = [py, "-m", "agents.robot", "--fleet-file", str(tmp_path / "fleet.json"), "--ids", ids,
                        "--connect", f"tcp/{addr[site]}:{ROUTER_PORT}", "--allow-remote",
                        "--workdir", str(tmp_path / site), "--status-interval", "1"]
                robots.append(doc.spawn(argv, tmp_path, env, netns=machines.ns[site], log=tmp_path / f"{site}-robots.log"))
            started += robots
            codes = doc.wait_all(robots, FLEET_S)
            assert None not in codes, "robots still running at the bound"
        finally:
            for proc in reversed(started):
                doc.stop(proc)
    for site, ids in zip(SITES, ((0, 1), (2, 3))):
        for i in ids:
            got = json.loads((tmp_path / site / f"robot-{i}.json").read_text())
            assert got["stopped"] == "finished" and got["rounds"] == want[i]["rounds"], (tmp_path / f"{site}-robots.log").read_text()
            assert got["neighbours_dropped"] == [] and got["frames_rejected"]["total"] == 0
            assert {int(r): v for r, v in got["trace"].items()} == {r: list(v) for r, v in want[i]["trace"].items()}
            assert got["x"] == list(want[i]["x"]) and got["gamma"] == want[i]["gamma"]
