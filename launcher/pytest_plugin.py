"""pytest plugin of shapefleet: a loopback Zenoh router and a fleet factory as fixtures (issue 17).

Registered through the ``pytest11`` entry point (pyproject.toml): installing shapefleet makes the
fixtures available in any test suite, nothing to import.

* ``zenoh_router``: a router on 127.0.0.1 on a free port (multicast scouting off, as every
  shapefleet session), yields its endpoint ``"tcp/127.0.0.1:PORT"`` (a str with ``.port`` and
  ``.pid``); stopped by its PID after the test, which fails if the process is still there.
* ``fleet``: a factory ``fleet(robots=4, loss=0.3, delay="20ms", crash="1@40")`` returning a
  :class:`launcher.api.Result`. Keywords are the CLI's options (launcher/api.py); ``mode`` is
  ``"launch"`` (default: one process per robot over Zenoh) or ``"simulate"`` (in process);
  ``router=zenoh_router`` connects a launch to that router instead of one of its own. Each run
  writes under the test's ``tmp_path`` and gets ``max_wall="60s"`` unless told otherwise.
  ``await fleet.run_async(...)`` does the same inside an event loop (pytest-asyncio).
  After the test every process any run started is checked by PID: one still running is killed
  (by that PID) and the test fails.
* marker ``fleet_processes``: the test starts processes (router, robots). ``pytest
  --shapefleet-no-processes`` skips such tests (and any test using ``zenoh_router``, or
  ``fleet`` in launch mode, fails fast with that reason instead of starting one).
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

MARKER = "fleet_processes"
NO_PROCESSES = "--shapefleet-no-processes"
#: the wall-clock bound each run gets from the fixture unless the test passes max_wall
DEFAULT_MAX_WALL = "60s"
ROUTER_READY_S = 20.0


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(NO_PROCESSES, action="store_true", default=False,
                     help=f"shapefleet: skip tests marked {MARKER} (they start router and robot processes)")


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", f"{MARKER}: starts shapefleet processes (a Zenoh router, robot processes)")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if not config.getoption(NO_PROCESSES):
        return
    skip = pytest.mark.skip(reason=f"{NO_PROCESSES}: this test starts processes")
    for item in items:
        if item.get_closest_marker(MARKER) is not None:
            item.add_marker(skip)


def _no_processes(request: pytest.FixtureRequest) -> None:
    if request.config.getoption(NO_PROCESSES):
        pytest.skip(f"{NO_PROCESSES}: this test starts processes")


def alive(pid: int) -> bool:
    """True while ``pid`` is a running (not zombie) process."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as fh:
            state = fh.read().rsplit(b")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return state not in (b"Z", b"X")


def _cmdline(pid: int) -> bytes:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as fh:
            return fh.read()
    except OSError:
        return b""


def _kill_left(pids: list[int], mark: Path) -> list[int]:
    """The PIDs still running *and* naming ``mark`` in their command line (a reaped PID reused
    by someone else's process is not ours), each killed (SIGKILL, by that PID)."""
    left = [pid for pid in pids if alive(pid) and str(mark).encode() in _cmdline(pid)]
    for pid in left:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
    return left


def _processes_naming(folder: Path) -> list[int]:
    """PIDs (not ours) whose command line names ``folder``: what a run started under it."""
    found, mark = [], str(folder).encode()
    for entry in os.listdir("/proc"):
        if not entry.isdigit() or int(entry) == os.getpid():
            continue
        if mark in _cmdline(int(entry)):
            found.append(int(entry))
    return found


class RouterEndpoint(str):
    """The router's endpoint (a str, ``"tcp/127.0.0.1:PORT"``) with its ``port`` and ``pid``."""

    port: int
    pid: int

    def __new__(cls, endpoint: str, port: int, pid: int) -> RouterEndpoint:
        self = super().__new__(cls, endpoint)
        self.port, self.pid = port, pid
        return self


@pytest.fixture
def zenoh_router(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """A loopback Zenoh router on a free port; yields its endpoint; stopped by PID afterwards."""
    from launcher.fleet import stop_process
    from protocol.zenoh_config import free_loopback_port, router_endpoint

    _no_processes(request)
    folder = tmp_path_factory.mktemp("zenoh-router")
    port, ready = free_loopback_port(), folder / "ready.json"
    root = Path(__file__).resolve().parent.parent
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (str(root), os.environ.get("PYTHONPATH", "")) if p))
    proc = subprocess.Popen(
        [sys.executable, "-m", "launcher.router", "--port", str(port), "--ready-file", str(ready),
         "--max-wall-s", "600"],
        cwd=root, env=env, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
        start_new_session=True,
    )
    try:
        deadline = time.monotonic() + ROUTER_READY_S
        while not ready.exists():
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"zenoh_router: the router on port {port} did not become ready")
            time.sleep(0.02)
        yield RouterEndpoint(router_endpoint(port), port, proc.pid)
    finally:
        stop_process(proc)
        if proc.stderr is not None:
            proc.stderr.close()
        left = _kill_left([proc.pid], folder)
    assert not left, f"zenoh_router: router process {proc.pid} was still running after stop"


class FleetFactory:
    """``fleet(...)``: run a fleet with the CLI's options under the test's folder (module doc)."""

    def __init__(self, folder: Path, request: pytest.FixtureRequest) -> None:
        self._folder = folder
        self._request = request
        self.results: list[Any] = []
        self.folders: list[Path] = []

    def _prepare(self, robots: int | None, mode: str, options: dict[str, Any]) -> dict[str, Any]:
        if mode == "launch":
            _no_processes(self._request)
            options.setdefault("max_wall", DEFAULT_MAX_WALL)
        if robots is not None:
            options["robots"] = robots
        out = Path(options.get("out") or self._folder / f"fleet-{len(self.folders)}")
        self.folders.append(out)
        options["out"] = out
        return options

    def __call__(self, robots: int | None = None, *, mode: str = "launch", **options: Any) -> Any:
        """Run it and return its :class:`launcher.api.Result` (UsageError on bad options)."""
        from launcher import api

        result = api.run(mode, **self._prepare(robots, mode, options))
        self.results.append(result)
        return result

    async def run_async(self, robots: int | None = None, *, mode: str = "launch", **options: Any) -> Any:
        """The same, awaited: the run goes to a worker thread; the loop stays free."""
        from launcher import api

        result = await api.run_async(mode, **self._prepare(robots, mode, options))
        self.results.append(result)
        return result

    def leftovers(self) -> list[int]:
        """PIDs still running of any run: those the results list, and any other naming its folder
        (every process a launch starts names its run folder on its command line)."""
        found: set[int] = set()
        for folder in self.folders:
            mine = [pid for r in self.results for pid in r.pids] + _processes_naming(folder.resolve())
            found |= {pid for pid in mine if alive(pid) and str(folder.resolve()).encode() in _cmdline(pid)}
        return sorted(found)


@pytest.fixture
def fleet(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[FleetFactory]:
    """Fleet factory (module doc); afterwards no process of its runs is left, checked by PID."""
    factory = FleetFactory(tmp_path, request)
    yield factory
    left = factory.leftovers()  # ours: each names its run folder
    for pid in left:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
    assert not left, f"fleet: processes left behind (killed by PID): {left}"
