"""The Zenoh fleet on this machine: one router process and one process per robot.

``launch_fleet(spec, ...)`` is what ``shapefleet launch`` runs:

1. write the fleet file ``workdir/fleet.json`` (timing adjusted to the crash plan, see below);
2. start the router (``python -m launcher.router --port P --ready-file ...``) on a loopback port and
   wait, bounded, until it listens;
3. start one ``python -m launcher.cli robot --fleet-file ... --id I --connect tcp/127.0.0.1:P
   --checkpoint workdir/robot-I.ckpt --result workdir/robot-I.json`` per robot; stdout is a pipe
   (one JSON status line per round, read by one thread per process), stderr goes to
   ``workdir/robot-I.log``;
4. follow the status lines: live table (rich) of round, residual, frame counters and state;
   carry out the crash plan: when robot I reports round >= R it is SIGKILLed; with restarts it is
   started again after ``restart_after`` seconds with the same arguments and resumes from its
   checkpoint, without restarts it stays dead and its neighbours drop it after ``dead_after_s``;
5. when every robot process has exited (or the overall time bound is over: then every robot is
   asked to stop, SIGTERM, and writes a result saying so), stop the router and collect the result
   files. A robot that is dead for good wrote none and is absent from the outcome.

A router that dies during the run is started again on the same endpoint (at most
``ROUTER_RESTARTS`` times); the robots' Zenoh clients reconnect to it by themselves and the
fleet resumes from the agreed round (robots do not drop neighbours while they have no router).
SIGTERM, SIGHUP and SIGINT (Ctrl-C) received while the fleet runs stop it the same way: every
robot is asked to stop (SIGTERM: it writes a result saying ``stopped = "signal"``), the router is
stopped, and the outcome says which signal (``interrupted``) so the caller writes a partial result.

Every process started here is stopped by its own PID (SIGTERM, a grace period, SIGKILL, reaped) in
a ``finally``: on success, on error, on the time bound and on Ctrl-C. Children run in their own
session, so a terminal's Ctrl-C reaches only the launcher, which then stops them in order. As a
last line of defence against a launcher that is itself SIGKILLed, the router is given a
``--max-wall-s`` and every robot its ``timing.max_wall_s``: nothing outlives its bound.

Loopback only; multicast scouting is off in every configuration (protocol/zenoh_config.py).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import queue
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from agents.spec import FleetSpec
from launcher.cores import runs_alone, usable_cores
from launcher.router import EarlyRouter
from launcher.router import spawn as _spawn
from launcher.simulate import FleetOutcome
from protocol.zenoh_config import free_loopback_port, parse_endpoint, router_endpoint, validate_endpoint
from protocol.session import row_from_file

__all__ = [
    "CrashPlan",
    "CrashEvent",
    "LaunchError",
    "LaunchOutcome",
    "parse_crash",
    "launch_fleet",
    "fleet_timing",
    "time_bound_s",
    "stop_process",
    "max_robots",
    "choose_robots_per_process",
]

log = logging.getLogger("shapefleet.launch")

HOST = "127.0.0.1"

ROUTER_START_TIMEOUT_S = 20.0  # router process up and listening
ROUTER_PORT_ATTEMPTS = 3  # a port picked for us may be taken between the pick and the bind
STOP_GRACE_S = 3.0  # SIGTERM -> SIGKILL
START_ALLOWANCE_S = 5.0  # a robot process: interpreter, imports, session, core (2 loaded cores)
NO_RESTART_DEAD_AFTER_S = 2.5  # --no-restart: neighbours give a crashed robot up this soon
WALL_MARGIN_S = 15.0  # on top of max_wall_s + start + restarts + linger
ROUTER_RESTARTS = 5  # a router that keeps dying is a machine problem: give up after this many
# --robots bound on this machine: robot processes per core, and memory per robot process (an
# interpreter with numpy, scipy, piqp and a Zenoh session: about 25 MB resident measured with
# 129 robots, counted double for the launcher's pipes, logs and the router's share)
ROBOTS_PER_CORE = 8
ROBOT_MEMORY_MB = 50.0
REFRESH_PER_S = 4  # the live table's redraws per second
# robots per process (robots_per_process "auto"): one process per robot while they spread evenly
# over the cores, up to this many per core, else one process per core
AUTO_SOLO_PER_CORE = 2
# ... but a fleet of more robots than cores and at most this many runs in one process (measured on
# 2 cores, results/round_cost.md, branch shellcost: 3 and 4 robots faster and ~45 % less CPU so; 8 not)
ONE_PROCESS_MAX = 4
# one status line per robot per refresh of the live table at most (was 0.05 s: at 32 robots, 30-130 ms a round,
# a line every round -- 0.11-0.13 ms of a robot's CPU each, and the launcher parses 32 a round)
STATUS_INTERVAL_S = 1.0 / REFRESH_PER_S
# robots sharing a process share one Zenoh session (own publisher, key, subscriptions, token each)
SHARED_SESSION = os.environ.get("SHAPEFLEET_SESSION_PER_ROBOT", "") == ""
# how long the launcher waits for a robot process whose stdout just ended to exit
EXIT_AFTER_EOF_S = 0.2
SHARED_ROBOT_MEMORY_MB = 10.0  # a robot as a task of a shared process: its session, core, buffers
# the default --max-robots per core when robots share processes (64 on 2 cores; 32 robots, admm, paper preset:
# 2310 rounds in 79-94 s there -- not under a minute, docs/scaling.md)
SHARED_ROBOTS_PER_CORE = 32
STOP_SIGNALS = ("SIGTERM", "SIGHUP", "SIGINT")

STATES = ("starting", "running", "crashed", "restarted", "dead", "finished", "stopped")


class LaunchError(RuntimeError):
    """The fleet could not be run (e.g. the router did not come up); the message says why."""


@dataclass(frozen=True)
class CrashEvent:
    """A crash the launcher carried out."""

    robot: int
    planned_round: int
    round: int  # the round the robot had reported when it was killed
    pid: int
    at_s: float  # seconds since launch
    restarted_at_s: float | None = None


@dataclass
class LaunchOutcome(FleetOutcome):
    """FleetOutcome plus what only a process fleet has: states, crashes, the router port."""

    states: dict[int, str] = field(default_factory=dict)
    crashes: list[CrashEvent] = field(default_factory=list)
    crashes_not_fired: list[CrashPlan] = field(default_factory=list)
    port: int = 0
    workdir: Path | None = None
    timed_out: bool = False
    pids: list[int] = field(default_factory=list)  # every process started (router first)
    interrupted: str | None = None  # the signal that stopped the launcher (SIGTERM, SIGHUP, SIGINT)
    router_restarts: list[float] = field(default_factory=list)  # seconds since launch
    # monotonic-clock marks of the run (launch, router_ready, robots_started, robots_exited,
    # stopped): start-up and shut-down costs, compared with the robots' own marks by benchmarks
    timeline: dict[str, float] = field(default_factory=dict)
    # robots whose process ended without a result and not by the crash plan (a restart that failed,
    # a robot that died of an error): what happened, in one line each -- the run failed for them
    lost_unexpectedly: dict[int, str] = field(default_factory=dict)


@dataclass(frozen=True)
class CrashPlan:
    """SIGKILL robot ``robot`` as soon as it reports round ``round`` or later."""

    robot: int
    round: int


_CRASH_RE = re.compile(r"\s*(\d+)\s*@\s*(\d+)\s*")


def parse_crash(text: str) -> CrashPlan:
    """``"1@40"`` -> ``CrashPlan(robot=1, round=40)``; ValueError naming --crash otherwise."""
    m = _CRASH_RE.fullmatch(text) if isinstance(text, str) else None
    if m is None:
        raise ValueError(f"--crash: {text!r} is not ID@ROUND, e.g. 1@40")
    robot, rnd = int(m.group(1)), int(m.group(2))
    if rnd < 1:
        raise ValueError(f"--crash: {text!r} is not ID@ROUND with ROUND >= 1, e.g. 1@40")
    return CrashPlan(robot, rnd)


def _available_memory_mb() -> float | None:
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return None


def max_robots(per_process: int | str | None = "auto") -> tuple[int, str]:
    """How many robots this machine runs at once, and why (cores, memory).

    One process per robot (``per_process`` 1): past a few per core the rounds crawl and the
    robots' time-outs fire (measured: 129 processes on 2 cores, load 180). Several robots per
    process ("auto" or a number > 1: see :func:`robots_per_process`): bounded by memory only.
    The caller may override it.
    """
    cores = os.cpu_count() or 1
    mem = _available_memory_mb()
    if per_process not in (None, "auto") and int(per_process) == 1:
        by_cores = ROBOTS_PER_CORE * cores
        by_memory = int(0.5 * mem / ROBOT_MEMORY_MB) if mem is not None else by_cores
        bound = max(1, min(by_cores, by_memory))
        why = (f"{cores} cores x {ROBOTS_PER_CORE}"
               + ("" if mem is None else f", half of {mem:.0f} MB available memory / {ROBOT_MEMORY_MB:g} MB per robot"))
        return bound, why
    by_cores = SHARED_ROBOTS_PER_CORE * cores
    by_memory = int(0.5 * mem / SHARED_ROBOT_MEMORY_MB) if mem is not None else by_cores
    why = (f"{cores} cores x {SHARED_ROBOTS_PER_CORE} robots sharing processes"
           + ("" if mem is None else f", half of {mem:.0f} MB available memory / {SHARED_ROBOT_MEMORY_MB:g} MB "
                                     "per robot"))
    return max(1, min(by_cores, by_memory)), why


def fleet_timing(spec: FleetSpec, crashes: list[CrashPlan], *, restart: bool, restart_after: float) -> Any:
    """The timing the robots are given: ``dead_after_s`` fitted to the crash plan.

    With restarts, a neighbour must not give a crashed robot up before it is back:
    ``dead_after_s >= restart_after + START_ALLOWANCE_S``. Without restarts, the survivors should
    not wait the default 6 s: ``dead_after_s <= NO_RESTART_DEAD_AFTER_S`` (still well above the
    spread of the robots' start-up times on a small fleet).
    """
    timing = spec.timing
    if not crashes:
        return timing
    if restart:
        dead = max(timing.dead_after_s, restart_after + START_ALLOWANCE_S)
    else:
        dead = min(timing.dead_after_s, NO_RESTART_DEAD_AFTER_S)
    return dataclasses.replace(timing, dead_after_s=dead)


def spec_for_run(spec: FleetSpec, crashes: list[CrashPlan], *, restart: bool, restart_after: float) -> FleetSpec:
    """The spec the robots of a run are given (the same in `simulate` and `launch`): the timing of
    `fleet_timing`, and without restarts the edge form on sparse fleets.

    Why: a robot that dies for good cannot be dropped by the relay hub (agents/relay_hub.py: its
    relays are gone), so its survivors would stop without an answer; the edge form's survivors drop
    it and finish on their own data, which is what ``--no-restart`` promises. A fleet file's explicit
    ``relay`` wins; complete graphs (the hub form drops the dead) are unaffected."""
    timing = fleet_timing(spec, crashes, restart=restart, restart_after=restart_after)
    if timing is not spec.timing:
        spec = dataclasses.replace(spec, timing=timing)
    if not restart and spec.algorithm == "admm" and "relay" not in spec.params:
        spec = dataclasses.replace(spec, params={**spec.params, "relay": False})
    return spec


def time_bound_s(timing: Any, restarts: int, restart_after: float) -> float:
    """The launcher's overall bound: every robot's own ``max_wall_s`` plus start-up, restarts,
    linger and a margin. Past it every robot still running is stopped (SIGTERM: it writes a
    result saying ``stopped = "signal"``)."""
    return (timing.max_wall_s + START_ALLOWANCE_S + float(getattr(timing, "linger_s", 1.0))
            + restarts * (restart_after + START_ALLOWANCE_S) + WALL_MARGIN_S)


# --------------------------------------------------------------------------- processes


def _signal(proc: subprocess.Popen, sig: int) -> None:
    if proc.poll() is None:
        try:
            os.kill(proc.pid, sig)
        except ProcessLookupError:
            pass


def stop_process(proc: subprocess.Popen, grace_s: float = STOP_GRACE_S) -> int | None:
    """SIGTERM ``proc`` by its PID, wait ``grace_s``, SIGKILL, reap. Returns its exit code."""
    return _stop_all([proc], grace_s)[0]


def _stop_all(procs: list[subprocess.Popen], grace_s: float = STOP_GRACE_S) -> list[int | None]:
    """Stop several processes at once: SIGTERM each, wait up to ``grace_s`` in total, SIGKILL the
    rest, reap all. A Ctrl-C while waiting skips to SIGKILL (and is re-raised afterwards)."""
    interrupted: BaseException | None = None
    for p in procs:
        _signal(p, signal.SIGTERM)
    end = time.monotonic() + grace_s
    try:
        for p in procs:
            try:
                p.wait(max(0.0, end - time.monotonic()))
            except subprocess.TimeoutExpired:
                pass
    except KeyboardInterrupt as exc:
        interrupted = exc
    for p in procs:
        _signal(p, signal.SIGKILL)
    for p in procs:
        try:
            p.wait(10)
        except subprocess.TimeoutExpired:  # unkillable (D state): nothing more we can do
            log.error("process %d did not die after SIGKILL", p.pid)
    if interrupted is not None:
        raise interrupted
    return [p.returncode for p in procs]


def _cpu_seconds(pid: int) -> float | None:
    """User + system CPU seconds a running process has used so far (/proc; None elsewhere)."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as fh:
            fields = fh.read().rsplit(b")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None


def _port_in_use(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as a listener would
        try:
            s.bind((HOST, port))
        except OSError:
            return True
    return False


class _Router:
    """The router subprocess, started on ``port`` and waited for (bounded)."""

    def __init__(self, port: int, workdir: Path, lifetime_s: float) -> None:
        self.port = port
        self.endpoint = router_endpoint(port, HOST)
        self.ready_file = workdir / "router.ready.json"
        self.log_path = workdir / "router.log"
        try:
            self.ready_file.unlink()
        except FileNotFoundError:
            pass
        self._log = open(self.log_path, "ab")  # a restarted router appends
        argv = [sys.executable, "-m", "launcher.router", "--port", str(port), "--host", HOST,
                "--ready-file", str(self.ready_file), "--max-wall-s", f"{lifetime_s:.0f}"]
        try:
            self.proc = _spawn(argv, stdout=self._log, stderr=subprocess.STDOUT)
        except BaseException:
            self._log.close()
            raise

    @classmethod
    def adopt(cls, early: EarlyRouter, workdir: Path) -> _Router:
        """The router the CLI started before its imports (launcher/router.py EarlyRouter): its
        log goes to ``workdir/router.log`` when it stops."""
        router = cls.__new__(cls)
        router.port, router.endpoint, router.proc = early.port, early.endpoint, early.proc
        router.ready_file, router.log_path, router._log = early.ready_file, early.log_path, early.log
        router._early, router._final_log = early, workdir / "router.log"
        early.adopted = True
        return router

    def wait_ready(self, timeout_s: float) -> None:
        """Return once the router listens; LaunchError (port in use, exited, too slow) otherwise."""
        end = time.monotonic() + timeout_s
        while not self.ready_file.exists():
            if self.proc.poll() is not None:
                text = self.log_path.read_text(errors="replace")
                if "Address already in use" in text or "os error 98" in text:
                    raise _PortInUse(self.port)
                last = text.strip().splitlines()[-1] if text.strip() else "no output"
                raise LaunchError(f"the Zenoh router exited with code {self.proc.returncode}: {last} "
                                  f"(log: {self.log_path})")
            if time.monotonic() > end:
                raise LaunchError(f"the Zenoh router on port {self.port} did not come up within "
                                  f"{timeout_s:g}s (log: {self.log_path})")
            time.sleep(0.02)

    def stop(self) -> None:
        try:
            stop_process(self.proc)
        finally:
            self._log.close()
            early = getattr(self, "_early", None)
            if early is not None:  # an adopted early router: its log joins the run's
                early.take_log(self._final_log)
                early.adopted = False
                early.discard()
                self.log_path = self._final_log


class _PortInUse(LaunchError):
    def __init__(self, port: int) -> None:
        super().__init__(f"port {port} is in use")
        self.port = port


def _start_router(zenoh_port: int | None, workdir: Path, lifetime_s: float, started: list[int],
                  meanwhile: Callable[[str], Any] | None = None,
                  early: EarlyRouter | None = None) -> tuple[_Router, Any]:
    """Start the router on ``zenoh_port`` (ValueError if taken) or on a free port (retried);
    ``early``: a router already started (free port, long enough bound) is taken as the first try.

    ``meanwhile(endpoint)`` runs as soon as the router process is spawned, before it listens: the
    robots start then, and import while the router starts (their Zenoh clients retry until it
    listens). What it returns is handed back; if this port fails, its ``abandon()`` is called.
    """
    if early is not None and early.bound_s < lifetime_s:  # it would end by itself mid-run (--max-wall)
        early.discard()
        early = None
    attempts = 1 if zenoh_port is not None else ROUTER_PORT_ATTEMPTS
    for attempt in range(attempts):
        if attempt == 0 and early is not None:
            router = _Router.adopt(early, workdir)
            port = router.port
        else:
            port = zenoh_port if zenoh_port is not None else free_loopback_port(HOST)
            if zenoh_port is not None and _port_in_use(port):
                raise ValueError(f"--zenoh-port {port} is in use")
            router = _Router(port, workdir, lifetime_s)
        started.append(router.proc.pid)
        extra = None
        try:
            extra = None if meanwhile is None else meanwhile(router.endpoint)
            router.wait_ready(ROUTER_START_TIMEOUT_S)
            return router, extra
        except _PortInUse:
            if extra is not None:
                extra.abandon()
            router.stop()
            if zenoh_port is not None:
                raise ValueError(f"--zenoh-port {port} is in use") from None
            log.info("port %d was taken before the router bound it (attempt %d)", port, attempt + 1)
        except BaseException:
            try:
                if extra is not None:
                    extra.abandon()
            finally:
                router.stop()
            raise
    raise LaunchError(f"no free loopback port for the Zenoh router after {attempts} attempts")


# --------------------------------------------------------------------------- robots

#: robot processes forked from the launcher (after its imports, before any thread of its own) instead
#: of each starting an interpreter and importing numpy, the algorithms and Zenoh (~0.3 s of CPU each,
#: issue 14); SHAPEFLEET_SPAWN_ROBOTS=1 spawns them (A/B comparisons)
FORK_ROBOTS = os.environ.get("SHAPEFLEET_SPAWN_ROBOTS", "") == "" and hasattr(os, "fork")
#: at most this many robot processes forked (two is what `auto` starts for 5+ robots on 2 cores;
#: 3-4 robots run as one process, two with a crash plan): a forked process keeps the launcher's
#: command line, so a fleet whose robots are found by their ``--id`` (ps, tests/test_reliability.py's
#: pause of robot 2 of 4) is spawned
FORK_MAX_PROCESSES = 2


def can_fork() -> bool:
    """This process runs no other thread (a fork beside one can copy a lock it holds) and no event
    loop (a robot's own ``asyncio.run`` would refuse to start inside a copy of it)."""
    asyncio = sys.modules.get("asyncio")
    if asyncio is not None and asyncio._get_running_loop() is not None:
        return False
    return runs_alone()


class ForkedChild:
    """A robot process forked from the launcher: what launch_fleet uses of a ``subprocess.Popen``
    (pid, stdout, poll, wait, signals). It is our child: reaped by waitpid, so its PID is never
    another process's while we may signal it."""

    stdin = None

    def __init__(self, pid: int, stdout: IO[bytes]) -> None:
        self.pid, self.stdout = pid, stdout
        self.returncode: int | None = None
        self.args = ["agents.robot", str(pid)]

    def poll(self) -> int | None:
        if self.returncode is None:
            try:
                pid, status = os.waitpid(self.pid, os.WNOHANG)
            except ChildProcessError:  # reaped by someone else (a SIGCHLD handler): it has ended
                self.returncode = 1
                return self.returncode
            if pid:
                self.returncode = os.waitstatus_to_exitcode(status)
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        import select

        if self.poll() is None:
            fd = os.pidfd_open(self.pid)
            try:
                select.select([fd], [], [], timeout)
            finally:
                os.close(fd)
        code = self.poll()
        if code is None:
            raise subprocess.TimeoutExpired(self.args, timeout)
        return code

    def send_signal(self, sig: int) -> None:
        if self.poll() is None:
            os.kill(self.pid, sig)

    def terminate(self) -> None:
        self.send_signal(signal.SIGTERM)

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)


def _fresh_stdio() -> None:
    """sys.stdout and sys.stderr on file descriptors 1 and 2, as an interpreter starts them (the
    launcher's may be something else: pytest's capture, a terminal's line buffering)."""
    import faulthandler
    import io

    sys.stdout = io.TextIOWrapper(io.FileIO(1, "w", closefd=False), encoding="utf-8")
    sys.stderr = io.TextIOWrapper(io.FileIO(2, "w", closefd=False), encoding="utf-8", errors="backslashreplace",
                                  line_buffering=True)
    if faulthandler.is_enabled():
        faulthandler.enable(sys.stderr)


def fork_robot(args: list[str], log: IO[bytes]) -> ForkedChild | None:
    """A robot process forked from this one running ``agents.robot.main(args)``, its stdout a pipe
    to us and its stderr ``log`` (None when the fork fails: spawn one)."""
    import concurrent.futures.thread  # noqa: F401 -- what a robot imports before its first round:
    import gc

    import zenoh  # noqa: F401 -- once here, not in each child

    from agents import robot

    for stream in (sys.stdout, sys.stderr):  # nothing of ours printed twice by the child
        stream.flush()
    frozen = gc.get_freeze_count()
    gc.freeze()  # the child's collections skip (and do not copy) what we imported; ours, as before
    read_end, write_end = os.pipe()
    try:
        pid = os.fork()
    except OSError:
        pid = -1
    if pid:
        if not frozen:
            gc.unfreeze()
        os.close(write_end)
        if pid < 0:
            os.close(read_end)
            return None
        return ForkedChild(pid, os.fdopen(read_end, "rb"))
    code = 1
    try:
        os.setsid()  # a session (and scheduler autogroup) of its own, as a spawned robot's
        for sig in (signal.SIGTERM, signal.SIGHUP):
            signal.signal(sig, signal.SIG_DFL)
        signal.signal(signal.SIGINT, signal.default_int_handler)
        os.dup2(os.open(os.devnull, os.O_RDONLY), 0)  # as a spawned robot's stdin
        os.dup2(write_end, 1)
        os.dup2(log.fileno(), 2)
        os.closerange(3, 1 << 16)  # none of the launcher's files (pipes of other robots, the router's log)
        _fresh_stdio()
        logging.root.handlers.clear()  # the robot's own logging.basicConfig
        code = robot.run_forked(args)
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    except BaseException:  # noqa: BLE001 -- said in its log, as an interpreter would
        import traceback

        traceback.print_exc()
    finally:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except Exception:  # noqa: BLE001
                pass
        os._exit(code)



@dataclass
class _Proc:
    """One robot process: it runs the robots ``ids`` (one, or several as asyncio tasks)."""

    ids: tuple[int, ...]
    argv: list[str]
    log_path: Path
    proc: subprocess.Popen | None = None
    log_fh: IO[bytes] | None = None
    reader: threading.Thread | None = None
    generation: int = -1
    restart_at: float | None = None
    killed: bool = False  # the current process was SIGKILLed by us
    exit_code: int | None = None


@dataclass
class _Robot:
    id: int
    p: _Proc  # the process it runs in
    result_path: Path
    crashes: list[CrashPlan]  # still to carry out, by round
    state: str = "starting"
    status: dict[str, Any] = field(default_factory=dict)
    restarts: int = 0

    @property
    def log_path(self) -> Path:
        return self.p.log_path


def _lost_why(r: _Robot, *, interrupted: bool) -> str | None:
    """Why robot r has no result when the crash plan did not mean it to be gone (its process killed
    by the plan with no restart to follow, or a run stopped by a signal or the time bound), else None."""
    p = r.p
    if interrupted or p.killed:  # stopped by a signal or the bound, or SIGKILLed by the plan: gone as asked
        return None
    code = p.exit_code if p.exit_code is not None else (p.proc.poll() if p.proc is not None else None)
    try:
        lines = [ln for ln in p.log_path.read_text(errors="replace").splitlines() if ln.strip()]
    except OSError:
        lines = []
    last = f": {lines[-1].strip()}" if lines else ""
    after = " after its restart" if r.restarts else ""
    return f"robot {r.id}'s process ended{after} without a result (exit code {code}){last} (log {p.log_path})"


def _read_lines(stream: IO[bytes], key: int, gen: int, events: queue.SimpleQueue) -> None:
    try:
        for line in iter(stream.readline, b""):
            events.put((key, gen, line))
    except (OSError, ValueError):  # stream closed under us while shutting down
        pass
    events.put((key, gen, None))


def choose_robots_per_process(n_robots: int, setting: int | str | None = "auto", cores: int | None = None) -> int:
    """How many robots share one process: ``setting`` if a number, else chosen from the cores.

    One process per robot while every core gets the same number of them, at most
    ``AUTO_SOLO_PER_CORE`` (n <= cores, or n a multiple of the cores up to 2 per core: process
    isolation, and the rounds are fastest so); otherwise one process per core. A lockstep round
    waits for the slowest robot, so processes spread unevenly (3 on 2 cores: one core time-slices
    two robots while the other runs one) make every round wait on the doubled core, and each extra
    interpreter costs ~0.3 s of start-up CPU and ~25 MB. Measured (results/round_cost.md, issue
    14): 3 robots on 2 cores as 2 + 1 robots per process, against 3 processes, fleet CPU per round
    -30 %, launch -0.4 s, rounds no slower; 16 processes on 2 cores 115 ms/round against 12 ms
    for 2 processes of 8. A fleet of more robots than cores but at most ``ONE_PROCESS_MAX`` runs
    in one process (branch shellcost, 2 cores: 3 robots 3.7-4.0 ms/round as 1 x 3 against
    5.3-6.4 as 2 + 1 and 6.8-7.3 as 3 x 1; 4 robots 3.8-5.9 as 1 x 4 against 4.3-9.2 as 2 x 2;
    robot processes' CPU -40 to -50 %; 8 robots: 2 x 4 is faster): the robots' loop thread is
    busy while the second core runs Zenoh's threads and the router, and the robots of one process
    share a hub step and a Zenoh session.
    """
    if setting not in (None, "auto"):
        k = int(setting)
        if k < 1:
            raise ValueError(f"--robots-per-process: {setting!r} must be at least 1 or 'auto'")
        return k
    cores = cores or usable_cores()
    if cores < n_robots <= ONE_PROCESS_MAX:
        return n_robots
    if n_robots <= cores or (n_robots <= AUTO_SOLO_PER_CORE * cores and n_robots % cores == 0):
        return 1
    return -(-n_robots // cores)


def _groups(ids: list[int], per_process: int, solo: set[int]) -> list[tuple[int, ...]]:
    """Robots in processes of ``per_process`` (consecutive ids); robots in ``solo`` (a crash is
    planned for them: a SIGKILL takes their process) each in a process of their own."""
    shared = [i for i in ids if i not in solo]
    out = [tuple(shared[k:k + per_process]) for k in range(0, len(shared), per_process)]
    return sorted(out + [(i,) for i in ids if i in solo])


class _Fleet:
    """The robot processes and what the launcher knows about them."""

    def __init__(self, spec: FleetSpec, workdir: Path, fleet_file: Path, endpoint: str,
                 crashes: list[CrashPlan], restart: bool, restart_after: float,
                 started: list[int], console: Any | None, per_process: int = 1,
                 robot_argv: tuple[str, ...] = ("-m", "agents.robot")) -> None:
        self.spec = spec
        self.fork = FORK_ROBOTS and tuple(robot_argv) == ("-m", "agents.robot")
        self.restart = restart
        self.restart_after = restart_after
        self.events: queue.SimpleQueue = queue.SimpleQueue()
        self.started = started
        self.console = console
        self.t0 = time.monotonic()
        self.crash_events: list[CrashEvent] = []
        self.robots: dict[int, _Robot] = {}
        self.procs: list[_Proc] = []
        for i in spec.robot_ids:
            ck, res = workdir / f"robot-{i}.ckpt", workdir / f"robot-{i}.json"
            for stale in (ck, ck.with_name(ck.name + ".tmp"), res):  # never resume a previous run
                try:
                    stale.unlink()
                except FileNotFoundError:
                    pass
        solo = {c.robot for c in crashes}
        for ids in _groups(list(spec.robot_ids), per_process, solo):
            # every status line (one per robot per round, or fewer: STATUS_INTERVAL_S) says which
            # robot it is for; a robot with a crash plan reports every round so it dies on time
            interval = 0.0 if solo & set(ids) else STATUS_INTERVAL_S
            argv = [sys.executable, *robot_argv[:2], "--fleet-file", str(fleet_file), *robot_argv[2:],
                    "--id" if len(ids) == 1 else "--ids", ",".join(map(str, ids)), "--connect", endpoint,
                    "--workdir", str(workdir),
                    "--status-interval", f"{interval:g}", "--parent-pid", str(os.getpid())]
            if len(ids) > 1 and SHARED_SESSION:
                argv.append("--shared-session")
            name = f"robot-{ids[0]}" if len(ids) == 1 else f"robots-{ids[0]}-{ids[-1]}"
            proc = _Proc(ids, argv, workdir / f"{name}.log")
            self.procs.append(proc)
            for i in ids:
                plans = sorted((c for c in crashes if c.robot == i), key=lambda c: c.round)
                self.robots[i] = _Robot(i, proc, workdir / f"robot-{i}.json", plans)
                if len(ids) > 1:  # robot-I.log names every robot's log, as with one per process
                    link = workdir / f"robot-{i}.log"
                    try:
                        link.unlink()
                    except FileNotFoundError:
                        pass
                    link.symlink_to(proc.log_path.name)

    # -- process life ------------------------------------------------------------------------
    def start(self, p: _Proc, read: bool = True) -> None:
        if p.log_fh is None:
            p.log_fh = open(p.log_path, "ab")
        if p.proc is not None:  # a restart: the killed process's pipe has reached its end
            if p.reader is not None:
                p.reader.join(2)
            if p.proc.stdout is not None:
                p.proc.stdout.close()
        p.generation += 1
        argv = list(p.argv)
        plans = self.robots[p.ids[0]].crashes if len(p.ids) == 1 and p.ids[0] in self.robots else []
        if plans:  # the robot dies at the planned round itself; the launcher restarts it
            argv += ["--crash-at", str(plans[0].round)]
        adopted = None
        forked = None
        if p.proc is None and self.fork:  # a first start, no thread running: forked from us
            forked = fork_robot(argv[3:], p.log_fh)  # after [python, -m, agents.robot]
        p.proc = forked or _spawn(argv, stdout=subprocess.PIPE, stderr=p.log_fh)
        self.started.append(p.proc.pid)
        p.killed = False
        p.exit_code = None
        p.restart_at = None
        if read:
            self.read(p)

    def read(self, p: _Proc) -> None:
        """Follow the status lines of ``p``'s process (a thread)."""
        assert p.proc is not None
        key = self.procs.index(p)
        p.reader = threading.Thread(target=_read_lines, args=(p.proc.stdout, key, p.generation, self.events),
                                    name=f"robots-{p.ids[0]}-stdout", daemon=True)
        p.reader.start()

    def start_all(self) -> None:
        # forked from this process when it runs no other thread (then each is forked before any
        # reader thread starts), else spawned; a restart is always spawned
        self.fork = self.fork and len(self.procs) <= FORK_MAX_PROCESSES and can_fork()
        try:
            for p in self.procs:
                self.start(p, read=not self.fork)
        finally:
            if self.fork:
                self.fork = False
                for p in self.procs:
                    if p.proc is not None:
                        self.read(p)

    def live(self) -> list[subprocess.Popen]:
        return [p.proc for p in self.procs if p.proc is not None and p.proc.poll() is None]

    def busy(self) -> bool:
        """Some robot process runs, or one is due to be restarted."""
        return bool(self.live()) or any(p.restart_at is not None for p in self.procs)

    def _say(self, text: str) -> None:
        log.info("%s", text)
        if self.console is not None:
            self.console.log(text)

    def crash(self, r: _Robot, plan: CrashPlan, reported: int) -> None:
        p = r.p  # a robot with a crash plan runs alone in its process (see _groups)
        assert p.proc is not None and p.ids == (r.id,)
        # usually it has already killed itself at the planned round (--crash-at); _signal never
        # signals a process already reaped (its PID may belong to someone else by now)
        _signal(p.proc, signal.SIGKILL)
        p.proc.wait(10)
        p.killed = True
        p.exit_code = p.proc.returncode
        now = time.monotonic() - self.t0
        self.crash_events.append(CrashEvent(r.id, plan.round, reported, p.proc.pid, now))
        if self.restart:
            r.state = "crashed"
            p.restart_at = time.monotonic() + self.restart_after
            self._say(f"robot {r.id} SIGKILLed at round {reported} (plan {r.id}@{plan.round}); "
                      f"restart in {self.restart_after:g}s")
        else:
            r.state = "dead"
            self._say(f"robot {r.id} SIGKILLed at round {reported} (plan {r.id}@{plan.round}); stays dead")

    def restart_due(self, now: float) -> None:
        for p in self.procs:
            if p.restart_at is not None and now >= p.restart_at:
                self.start(p)
                for rid in p.ids:
                    r = self.robots[rid]
                    r.restarts += 1
                    r.state = "restarted"
                    ev = next(e for e in reversed(self.crash_events) if e.robot == r.id)
                    self.crash_events[self.crash_events.index(ev)] = dataclasses.replace(
                        ev, restarted_at_s=now - self.t0)
                    self._say(f"robot {r.id} restarted (pid {p.proc.pid}), resuming from its checkpoint")

    def next_restart(self) -> float | None:
        due = [p.restart_at for p in self.procs if p.restart_at is not None]
        return min(due) if due else None

    # -- status lines ------------------------------------------------------------------------
    def on_line(self, key: int, gen: int, line: bytes | None) -> None:
        p = self.procs[key]
        if line is None and gen == p.generation and p.proc is not None:
            # its stdout ends as it exits: wait for that now (reap() sees it at once) rather
            # than notice it at the next poll of the launcher's loop, up to 0.25 s later
            try:
                p.proc.wait(EXIT_AFTER_EOF_S)
            except subprocess.TimeoutExpired:
                pass
        if line is None or gen != p.generation:
            return  # end of a stream, or a line a killed process had written before it died
        try:
            st = json.loads(line)
        except ValueError:
            log.debug("robots %s: not a status line: %r", p.ids, line[:200])
            return
        if not isinstance(st, dict) or "round" not in st:
            return
        rid = st.get("robot", p.ids[0]) if len(p.ids) > 1 else p.ids[0]
        if rid not in p.ids:
            return
        r = self.robots[rid]
        r.status = st
        if r.state == "starting":
            r.state = "running"
        if r.crashes and not st.get("finished") and "stopped" not in st:
            plan = r.crashes[0]
            if int(st["round"]) >= plan.round and p.proc is not None and p.proc.poll() is None:
                r.crashes.pop(0)
                self.crash(r, plan, int(st["round"]))

    def reap(self) -> None:
        """Notice processes that exited on their own."""
        for p in self.procs:
            if p.proc is None or p.killed or p.exit_code is not None:
                continue
            rc = p.proc.poll()
            if rc is None:
                continue
            r0 = self.robots[p.ids[0]]
            if rc == -signal.SIGKILL and len(p.ids) == 1 and r0.crashes:
                # its planned crash (--crash-at), noticed before its last status line was read
                plan = r0.crashes.pop(0)
                self.crash(r0, plan, max(int(r0.status.get("round", 0)), plan.round))
                continue
            p.exit_code = rc
            for rid in p.ids:
                r = self.robots[rid]
                stopped = r.status.get("stopped")
                if rc == 0 or (len(p.ids) > 1 and stopped == "finished"):
                    r.state = "finished"
                elif stopped is not None or r.result_path.exists():
                    r.state = "stopped"  # max_wall / signal: a result, not converged
                else:
                    r.state = "dead"
                    self._say(f"robot {r.id} exited with code {rc} (see {p.log_path})")

    def abandon(self) -> None:
        """Stop every robot process started so far (the router they were given failed)."""
        try:
            _stop_all(self.live())
        finally:
            self.close()

    def close(self) -> None:
        for p in self.procs:
            if p.reader is not None:
                p.reader.join(5)
            if p.proc is not None and p.proc.stdout is not None:
                p.proc.stdout.close()
            if p.log_fh is not None:
                p.log_fh.close()

    # -- display -----------------------------------------------------------------------------
    def table(self, title: str) -> Any:
        from rich import box
        from rich.table import Table

        t = Table(title=title, title_justify="left", box=box.SIMPLE_HEAD, pad_edge=False)
        for col in ("robot", "state", "round", "residual", "sent", "recv", "lost", "rejected", "restarts"):
            t.add_column(col, justify="left" if col == "state" else "right", no_wrap=True)
        colour = {"running": "green", "restarted": "green", "crashed": "yellow", "dead": "red",
                  "finished": "cyan", "stopped": "magenta", "starting": "dim"}
        for r in self.robots.values():
            st = r.status
            res = st.get("residual")
            t.add_row(
                str(r.id), f"[{colour.get(r.state, '')}]{r.state}", str(st.get("round", "-")),
                "-" if res is None else f"{res:.1e}",
                *(str(st.get(k, "-")) for k in ("sent", "received", "lost", "rejected")),
                str(r.restarts),
            )
        return t


def _normalise(res: dict[str, Any]) -> dict[str, Any]:
    """A robot's result file -> the FleetOutcome row: the very row simulate_fleet gives
    (``protocol.session.row_from_file``, the inverse of what the robot wrote)."""
    return row_from_file(res)


def _collect(fleet: _Fleet) -> list[dict[str, Any]]:
    results = []
    for r in fleet.robots.values():
        try:
            data = json.loads(r.result_path.read_text())
        except FileNotFoundError:
            continue
        except ValueError as exc:  # never half-written (atomic), so this is a bug: say it
            log.error("robot %d: unreadable result %s: %s", r.id, r.result_path, exc)
            continue
        results.append(_normalise(data))
    return sorted(results, key=lambda res: res["id"])


# --------------------------------------------------------------------------- entry point


def launch_fleet(
    spec: FleetSpec,
    *,
    workdir: Path,
    crashes: list[CrashPlan],
    restart_after: float,
    restart: bool,
    zenoh_port: int | None,
    progress: bool = True,
    router: str | None = None,
    on_running: Callable[[str], None] | None = None,
    robots_per_process: int | str | None = "auto",
    robot_argv: tuple[str, ...] = ("-m", "agents.robot"),
    early_router: EarlyRouter | None = None,
) -> LaunchOutcome:
    """Run ``spec`` as one process per robot plus a router on 127.0.0.1; see the module doc.

    ``crashes``: robots to SIGKILL at a round (``parse_crash``); ``restart``: start them again
    after ``restart_after`` seconds (they resume from their checkpoint), else they stay dead.
    ``zenoh_port``: the router's port (ValueError if taken), None for a free one.
    ``progress``: live table on a terminal (never when stdout is not a TTY).
    ``router``: the endpoint of a router that already runs (loopback): connect the robots to it
    instead of starting one (several fleets can share a router; ``zenoh_port`` must be None).
    ``on_running(endpoint)``: called once the router is up and the robots were started.
    ``robots_per_process``: robots run as asyncio tasks of one process (sharing one Zenoh
    session unless SHAPEFLEET_SESSION_PER_ROBOT is set, each with its own key and files), a number
    or "auto" (:func:`choose_robots_per_process`); a robot with a crash plan always runs alone, so
    that its SIGKILL takes only it.
    ``robot_argv``: the robot program (``-m module``) and its extra arguments (free sync:
    ``("-m", "agents.free_robot", "--period", "0.01")``).
    ``early_router``: a router the CLI started before its imports (launcher/router.py): used
    instead of starting one when it fits (no ``zenoh_port``/``router``, its bound long enough),
    else stopped.

    Returns a :class:`LaunchOutcome` (a ``FleetOutcome``): ``robots`` holds the result of every
    robot that wrote one, sorted by id; a robot dead for good is absent.
    """
    router = _check_launch_args(spec, crashes, restart_after, zenoh_port, router)
    per_process = choose_robots_per_process(spec.n_robots, robots_per_process)
    # absolute: a restarted robot is spawned in the project's root (launcher/router.py spawn), where a
    # relative fleet file, checkpoint or result path would name nothing (its restart then failed)
    workdir = Path(workdir).resolve()
    workdir.mkdir(parents=True, exist_ok=True)
    run_spec = spec_for_run(spec, crashes, restart=restart, restart_after=restart_after)
    timing = run_spec.timing
    fleet_file = workdir / "fleet.json"
    run_spec.save(fleet_file)
    run = _LaunchRun(spec, workdir, time_bound_s(timing, len(crashes) if restart else 0, restart_after),
                     progress and sys.stdout.isatty())
    run.catch_stop_signals()

    def start_robots(endpoint: str) -> _Fleet:
        return run.start_robots(_Fleet(run_spec, workdir, fleet_file, endpoint, crashes, restart, restart_after,
                                       run.started, run.console, per_process, robot_argv))

    try:  # also when the router or a robot fails to start: our signal handlers are put back
        run.start(zenoh_port, router, start_robots, early_router)
        if on_running is not None:
            on_running(run.endpoint)
        run.supervise()
    finally:
        run.shut_down()
    return run.outcome()


def _check_launch_args(spec: FleetSpec, crashes: list[CrashPlan], restart_after: float,
                       zenoh_port: int | None, router: str | None) -> str | None:
    """ValueError for arguments that cannot make a run; the router endpoint, checked (loopback)."""
    unknown = sorted({c.robot for c in crashes} - set(spec.robot_ids))
    if unknown:
        raise ValueError(f"--crash: robot {unknown[0]} is not in the fleet (robots {list(spec.robot_ids)})")
    if restart_after < 0:
        raise ValueError("--restart-after: must be a non-negative number of seconds")
    if router is None:
        return None
    if zenoh_port is not None:
        raise ValueError("launch_fleet: give zenoh_port or router, not both")
    return validate_endpoint(router)  # loopback only


class _LaunchRun:
    """One launch from the router's start to the outcome, in named steps (see `launch_fleet`)."""

    def __init__(self, spec: FleetSpec, workdir: Path, bound_s: float, show: bool) -> None:
        self.spec, self.workdir, self.bound_s = spec, workdir, bound_s
        self.console = None
        if show:
            from rich.console import Console

            self.console = Console()
        self.started: list[int] = []
        self.t0 = time.monotonic()
        self.interrupted: list[str] = []
        self.previous_handlers: dict[int, Any] = {}
        self.router_restarts: list[float] = []
        self.timeline = {"launch": self.t0}
        self.timed_out = False
        self.live_display: Any = None
        self.own_router: _Router | None = None
        self.fleet: _Fleet | None = None
        self.endpoint = ""
        self.port = 0

    def catch_stop_signals(self) -> None:
        """SIGTERM/SIGHUP/SIGINT end the run in order (robots write their results), not the launcher."""
        if threading.current_thread() is not threading.main_thread():
            return

        def on_signal(signum: int, _frame: Any) -> None:
            if not self.interrupted:
                self.interrupted.append(signal.Signals(signum).name)
                log.warning("launcher: %s received; stopping every robot", self.interrupted[0])

        for name in STOP_SIGNALS:
            sig = getattr(signal, name)
            self.previous_handlers[sig] = signal.signal(sig, on_signal)

    def start_robots(self, robots: _Fleet) -> _Fleet:
        """Start every robot process of ``robots``; on failure stop those already started."""
        try:
            robots.start_all()
        except BaseException:
            robots.abandon()
            raise
        self.timeline["robots_started"] = time.monotonic()
        return robots

    def start(self, zenoh_port: int | None, router: str | None, start_robots: Callable[[str], _Fleet],
              early: EarlyRouter | None = None) -> None:
        """Our own router (the robots start while it comes up) or the given one, then the robots."""
        if early is not None and (router is not None or zenoh_port is not None or early.proc.poll() is not None
                                  or early.bound_s < self._router_lifetime_s()):
            early.discard()
            early = None
        if router is None:
            self.own_router, self.fleet = _start_router(zenoh_port, self.workdir, self._router_lifetime_s(),
                                                        self.started, meanwhile=start_robots, early=early)
            self.endpoint, self.port = self.own_router.endpoint, self.own_router.port
        else:
            self.endpoint, self.port = router, parse_endpoint(router)[2]
            self.fleet = start_robots(self.endpoint)
        self.timeline["router_ready"] = time.monotonic()

    def _router_lifetime_s(self) -> float:
        return self.bound_s + 2 * WALL_MARGIN_S

    def supervise(self) -> None:
        """Watch the fleet until every robot is done, a stop signal, or the time bound."""
        fleet = self.fleet
        assert fleet is not None
        title = f"fleet {self.spec.fleet}: {self.spec.n_robots} robots on {self.endpoint}"
        if self.console is not None:
            from rich.live import Live

            self.live_display = Live(fleet.table(title), console=self.console, refresh_per_second=REFRESH_PER_S,
                                     transient=True)
            self.live_display.start()
        deadline = self.t0 + self.bound_s
        next_draw = 0.0
        while True:
            now = time.monotonic()
            if self.interrupted:
                break
            if self._router_died():
                self._restart_router()
                continue
            fleet.restart_due(now)
            fleet.reap()
            if not fleet.busy():
                break
            if now >= deadline:
                self.timed_out = True
                log.warning("fleet %s: time bound %.0fs reached; stopping every robot", self.spec.fleet, self.bound_s)
                if self.console is not None:
                    self.console.log(f"time bound {self.bound_s:.0f}s reached: stopping every robot")
                break
            wait = min(0.25, deadline - now)
            nxt = fleet.next_restart()
            if nxt is not None:
                wait = max(0.0, min(wait, nxt - now))
            self._pump_events(wait)
            if self.live_display is not None and now >= next_draw:
                self.live_display.update(fleet.table(title))
                next_draw = now + 1.0 / REFRESH_PER_S

    def _router_died(self) -> bool:
        assert self.fleet is not None
        return self.own_router is not None and self.own_router.proc.poll() is not None and bool(self.fleet.live())

    def _restart_router(self) -> None:
        """Start our router again on its port (LaunchError after ROUTER_RESTARTS)."""
        assert self.own_router is not None and self.fleet is not None
        if len(self.router_restarts) >= ROUTER_RESTARTS:
            raise LaunchError(f"the Zenoh router died {len(self.router_restarts) + 1} times "
                              f"(log: {self.own_router.log_path})")
        code = self.own_router.proc.returncode
        self.own_router.stop()
        self.own_router = _Router(self.port, self.workdir, self._router_lifetime_s())
        self.started.append(self.own_router.proc.pid)
        self.own_router.wait_ready(ROUTER_START_TIMEOUT_S)
        self.router_restarts.append(time.monotonic() - self.t0)
        self.fleet._say(f"the router exited (code {code}); restarted on {self.endpoint} "
                        f"(pid {self.own_router.proc.pid})")

    def _pump_events(self, wait: float) -> None:
        """Handle the robots' status lines: the first waited for up to ``wait`` s, then all queued."""
        assert self.fleet is not None
        try:
            item = self.fleet.events.get(timeout=wait)
        except queue.Empty:
            item = None
        while item is not None:
            self.fleet.on_line(*item)
            try:
                item = self.fleet.events.get_nowait()
            except queue.Empty:
                item = None

    def shut_down(self) -> None:
        """Stop every robot (SIGTERM: a robot still running writes its result), then the router,
        the live table and our signal handlers -- each step even when one before it failed."""
        self.timeline["robots_exited"] = time.monotonic()
        try:
            if self.fleet is not None:
                _stop_all(self.fleet.live())
        finally:
            try:
                if self.own_router is not None:
                    cpu = _cpu_seconds(self.own_router.proc.pid)
                    if cpu is not None:  # the router's CPU over the run: fan-out cost (docs/scaling.md)
                        self.timeline["router_cpu_s"] = cpu
                    self.own_router.stop()
            finally:
                if self.live_display is not None:
                    self.live_display.stop()
                if self.fleet is not None:
                    self.fleet.close()
                for sig, handler in self.previous_handlers.items():
                    signal.signal(sig, handler)

    def outcome(self) -> LaunchOutcome:
        """The result files (the final word on each robot's state) and the run's counters."""
        fleet = self.fleet
        assert fleet is not None
        while True:  # status lines written just before the end
            try:
                fleet.on_line(*fleet.events.get_nowait())
            except queue.Empty:
                break
        fleet.reap()
        robots = _collect(fleet)
        have = {res["id"]: res for res in robots}
        lost: dict[int, str] = {}
        for i, r in fleet.robots.items():
            if i in have:
                r.state = "finished" if have[i].get("stopped") == "finished" else "stopped"
            else:
                r.state = "dead"
                why = _lost_why(r, interrupted=bool(self.interrupted or self.timed_out))
                if why is not None:
                    lost[i] = why
        totals = {
            k: sum(int(r.get(f"frames_{k}", 0) or 0) for r in robots)
            for k in ("sent", "received", "lost", "duplicated", "accepted", "rejected")
        }
        self.timeline["stopped"] = time.monotonic()
        wall = time.monotonic() - self.t0
        if self.console is not None:
            self.console.print(fleet.table(f"fleet {self.spec.fleet}: {len(robots)}/{self.spec.n_robots} results, "
                                           f"{wall:.1f}s"))
        return LaunchOutcome(
            robots=robots,
            wall_s=wall,
            virtual_s=wall,  # a process fleet runs in real time
            link_stats=totals,
            states={i: r.state for i, r in fleet.robots.items()},
            crashes=list(fleet.crash_events),
            crashes_not_fired=[c for r in fleet.robots.values() for c in r.crashes],
            port=self.port,
            workdir=self.workdir,
            timed_out=self.timed_out,
            pids=list(self.started),
            interrupted=self.interrupted[0] if self.interrupted else None,
            router_restarts=self.router_restarts,
            timeline=self.timeline,
            lost_unexpectedly=lost,
        )
