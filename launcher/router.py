"""The fleet's Zenoh router: one session in router mode on a loopback port, nothing else.

``run_router(port)`` blocks until SIGTERM or SIGINT, then closes the session and returns.
Readiness (the port is listening) is announced twice: a line ``{"router": "ready", ...}`` on stdout
and, if ``ready_file`` is given, an atomically written JSON file with the same content; the
launcher waits for either before starting robots.

``python -m launcher.router --port 7447`` runs it without the CLI.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from protocol.zenoh_config import TLSFiles, free_loopback_port, router_config, router_endpoint

__all__ = ["run_router", "write_json_atomic", "main", "EarlyRouter", "EarlyRobots", "ForkedRobot", "spawn", "child_env", "ROOT"]

ROOT = Path(__file__).resolve().parent.parent
HOST = "127.0.0.1"
#: an early router's own lifetime bound (it also ends when the launcher that started it is gone);
#: a launch that needs a longer-lived router starts its own instead
EARLY_ROUTER_BOUND_S = 3600.0
#: early robot processes: one per core, at most this many; launch_fleet adopts them only when they
#: are all its robot processes (else robots would start a second apart). An adopted process keeps its
#: ``--early`` command line (its robots' ids are only in its stdin): a fleet whose robots are found
#: by their ``--id`` (ps, tests/test_reliability.py's pause of robot 2 of 4) has more processes than
#: this and starts them the usual way; two is what `auto` starts for 3 or 5+ robots on 2 cores
EARLY_ROBOTS_MAX = 2


def child_env() -> dict[str, str]:
    """The environment of a process the launcher starts: the project importable from ROOT."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH", "")) if p)
    return env


def spawn(argv: list[str], *, stdout: Any, stderr: Any, stdin: Any = subprocess.DEVNULL) -> subprocess.Popen:
    """Start a router or robot process of the launcher."""
    return subprocess.Popen(
        argv,
        cwd=ROOT,
        env=child_env(),
        stdin=stdin,
        stdout=stdout,
        stderr=stderr,
        start_new_session=True,  # a terminal Ctrl-C reaches the launcher only; it stops them
    )


def _terminate(proc: subprocess.Popen) -> None:
    """SIGTERM a process of ours by its PID, SIGKILL after 3 s; reaped either way."""
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(3.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(10)


class EarlyRouter:
    """The router of a `shapefleet launch`, started before the launcher's own imports.

    The command line says at once that a router will be needed; started first, its interpreter
    and ``import zenoh`` (~0.2 s of CPU) run on the core the launcher's single-threaded imports
    and world leave free, instead of beside the robots' start (issue 14). Its log and ready file
    wait in a temporary folder until launch_fleet adopts it (launcher/fleet.py ``_Router.adopt``);
    a run that ends before (bad input, --help) stops it by its PID and removes the folder.
    It ends by itself when its launcher is gone (``--parent-pid``) or after EARLY_ROUTER_BOUND_S.
    """

    def __init__(self, run_folder: str | None = None) -> None:
        self.port = free_loopback_port(HOST)
        self.endpoint = router_endpoint(self.port, HOST)
        self.bound_s = EARLY_ROUTER_BOUND_S
        self.folder = Path(tempfile.mkdtemp(prefix="shapefleet-router-"))
        self.ready_file = self.folder / "router.ready.json"
        self.log_path = self.folder / "router.log"
        self.adopted = False
        self.log = open(self.log_path, "ab")
        argv = [sys.executable, "-m", "launcher.router", "--port", str(self.port), "--host", HOST,
                "--ready-file", str(self.ready_file), "--max-wall-s", f"{self.bound_s:.0f}",
                "--parent-pid", str(os.getpid()), "--orphan-folder", str(self.folder)]
        if run_folder:  # in its command line, as a router started by launch_fleet has (ps, tests)
            argv += ["--run-folder", run_folder]
        try:
            self.proc = spawn(argv, stdout=self.log, stderr=subprocess.STDOUT)
        except BaseException:
            self.discard()
            raise

    @classmethod
    def for_command_line(cls, argv: Sequence[str]) -> EarlyRouter | None:
        """An early router when ``argv`` (the program's) is a plain ``launch`` that starts its own
        router on a free port: not with --zenoh-port or --config (they may name the port), not
        for --help."""
        out = _launch_out(argv)
        if out is False:
            return None
        try:
            return cls(out)
        except OSError:  # no port, no temporary folder: launch_fleet starts its router as always
            return None

    def take_log(self, into: Path) -> None:
        """Append what the router wrote so far to ``into`` (the run's router.log); later output
        follows in the same file."""
        if not self.log.closed:
            self.log.flush()
        with open(into, "ab") as out, open(self.log_path, "rb") as early:
            shutil.copyfileobj(early, out)

    def discard(self) -> None:
        """Stop the router by its PID if nobody adopted it, and remove its folder."""
        proc = getattr(self, "proc", None)
        if proc is not None and not self.adopted:
            _terminate(proc)
        if not self.adopted:
            self.log.close()
            shutil.rmtree(self.folder, ignore_errors=True)


def _launch_out(argv: Sequence[str]) -> str | None | bool:
    """A plain ``launch`` command line's ``--out`` (None: no output folder given), or False when it
    is not a plain launch (another command, --help, --zenoh-port or --config naming the port)."""
    args = list(argv[1:])
    if not args or args[0] != "launch":
        return False
    if any(a in ("-h", "--help") or a.split("=")[0] in ("--zenoh-port", "--config") for a in args):
        return False
    out = None
    for i, a in enumerate(args):
        if a == "--out" and i + 1 < len(args):
            out = args[i + 1]
        elif a.startswith("--out="):
            out = a.split("=", 1)[1]
    return out


class EarlyRobots:
    """The robot processes of a `shapefleet launch`, forked from one "zygote" started with its early
    router, before the launcher's own imports (issue 14: launch wall time).

    The zygote (agents/robot.py ``serve_forks``) imports what a robot needs (numpy, the algorithms,
    Zenoh: ~0.3 s of CPU, the longest step of a robot's start) once, while the launcher imports and
    builds the world; then each robot process the launcher hands over (:meth:`take`) is forked from
    it, single-threaded and before any Zenoh session exists, instead of starting an interpreter of
    its own. launch_fleet adopts them as its first robot processes (launcher/fleet.py
    ``_Fleet.start_all``) when there are at most ``capacity`` (one per core, at most
    EARLY_ROBOTS_MAX), else none. Each child is a :class:`ForkedRobot`: stopped by its PID like any
    process of the launcher (a pidfd: never another process), its exit code reported by the zygote.
    A zygote not used (a smaller fleet, bad input, a user algorithm) or no longer needed is stopped
    by its PID (``discard``, ``close``); one whose launcher is gone stops its children and exits.
    """

    def __init__(self, count: int, run_folder: str | None = None) -> None:
        import socket

        self.capacity = count
        self.forked: list[ForkedRobot] = []
        self.exits: dict[int, int] = {}
        self._lock = threading.Lock()
        self._sock, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        argv = [sys.executable, "-m", "agents.robot", "--early", "--parent-pid", str(os.getpid())]
        if run_folder:  # in its command line (and its children's), as its router has (ps, tests)
            argv += ["--run-folder", run_folder]
        try:
            with theirs:
                self.proc: subprocess.Popen | None = spawn(argv, stdin=theirs.fileno(), stdout=subprocess.DEVNULL,
                                                           stderr=subprocess.DEVNULL)
        except BaseException:
            self._sock.close()
            raise

    @property
    def procs(self) -> list[subprocess.Popen]:
        """The zygote while it can still fork (for ps-like checks and tests)."""
        return [self.proc] if self.proc is not None and self.proc.poll() is None else []

    @classmethod
    def for_command_line(cls, argv: Sequence[str]) -> EarlyRobots | None:
        """A zygote for a plain ``launch`` (as :meth:`EarlyRouter.for_command_line`), not with
        ``--sync free`` (another robot program)."""
        out = _launch_out(argv)
        args = list(argv[1:])
        if os.environ.get("SHAPEFLEET_NO_EARLY_ROBOTS") or not hasattr(os, "pidfd_open"):  # A/B; Linux only
            return None
        if out is False or any(a == "free" and b in ("--sync",) for b, a in zip(args, args[1:])) \
                or "--sync=free" in args:
            return None
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
        try:
            return cls(min(cores, EARLY_ROBOTS_MAX), out)
        except OSError:  # launch_fleet starts its robots as always
            return None

    def take(self, args: list[str], log_path: Path, timeout_s: float = 30.0) -> ForkedRobot | None:
        """A robot process forked with ``args`` (agents/robot.py's, after ``-m agents.robot``) and
        its log; None when the zygote cannot (gone, or ``capacity`` used): start one as usual."""
        import socket

        if self.proc is None or len(self.forked) >= self.capacity:
            return None
        read_end, write_end = os.pipe()
        try:
            with self._lock:
                socket.send_fds(self._sock, [json.dumps({"argv": args, "log": str(log_path)}).encode()], [write_end])
            os.close(write_end)
            write_end = -1
            end = time.monotonic() + timeout_s  # the zygote may still be importing
            pid = None
            while pid is None and time.monotonic() < end and self.proc.poll() is None:
                pid = self._pump(min(0.5, max(0.0, end - time.monotonic())), want_pid=True)
            if pid is None:
                raise OSError("the robot zygote did not fork")
        except OSError:  # it died or hangs: stop it; the launcher starts its robots as usual
            os.close(read_end)
            if write_end >= 0:
                os.close(write_end)
            self.close()
            return None
        child = ForkedRobot(self, pid, os.fdopen(read_end, "rb"))
        self.forked.append(child)
        return child

    def _pump(self, timeout_s: float, want_pid: bool = False) -> int | None:
        """Read the zygote's reports for up to ``timeout_s`` (exit codes into ``exits``); with
        ``want_pid``, return as soon as a ``{"pid": N}`` arrives."""
        import select

        end = time.monotonic() + timeout_s
        with self._lock:
            while True:
                if self._sock.fileno() < 0 or not select.select([self._sock], [], [], max(0.0, end - time.monotonic()))[0]:
                    return None
                try:
                    msg = self._sock.recv(1 << 16)
                except OSError:
                    msg = b""
                if not msg:  # the zygote is gone: its children's ends are seen by their pidfds
                    self._sock.close()
                    return None
                got = json.loads(msg)
                if "exit" in got:
                    self.exits[int(got["exit"])] = int(got["code"])
                elif want_pid and "pid" in got:
                    return int(got["pid"])
                if not want_pid:
                    end = time.monotonic()  # drain what is there, do not wait again

    def discard(self) -> None:
        """No more robot processes will be asked for: stop the zygote now if it forked none
        (else it stays, to report its children's ends, until :meth:`close`)."""
        if not self.forked:
            self.close()

    def close(self) -> None:
        """Stop the zygote by its PID: closing its socket ends it (it SIGTERMs and reaps any child
        still running); SIGTERM, then SIGKILL, when it does not end within STOP bounds."""
        proc, self.proc = self.proc, None
        with self._lock:
            self._sock.close()
        for child in self.forked:
            child.release()
        if proc is not None:
            try:
                proc.wait(5.0)  # its children had ZYGOTE_STOP_GRACE_S (3 s) after SIGTERM
            except subprocess.TimeoutExpired:
                pass
            _terminate(proc)


class ForkedRobot:
    """A robot process forked by the zygote of :class:`EarlyRobots`: what launch_fleet uses of a
    ``subprocess.Popen`` (pid, stdout, poll, wait, signals). Signals go through a pidfd (the zygote
    keeps the child a zombie until it ends, so the pidfd is opened on the right process); its exit
    code is the zygote's report (1 if the zygote vanished before saying it)."""

    stdin = None

    def __init__(self, owner: EarlyRobots, pid: int, stdout: Any) -> None:
        self.owner, self.pid, self.stdout = owner, pid, stdout
        self.returncode: int | None = None
        self.args = ["agents.robot", "--early", str(pid)]
        self._pidfd: int | None = os.pidfd_open(pid)

    def _ended(self, timeout_s: float) -> bool:
        import select

        if self._pidfd is None:
            return True
        return bool(select.select([self._pidfd], [], [], max(0.0, timeout_s))[0])

    def poll(self) -> int | None:
        """Its exit code once it ended (as Popen's), else None."""
        if self.returncode is None and self._ended(0.0):
            end = time.monotonic() + 2.0  # the zygote says the code as soon as it sees the end
            while self.pid not in self.owner.exits and time.monotonic() < end and self.owner._sock.fileno() >= 0:
                self.owner._pump(0.05)
            self.returncode = self.owner.exits.get(self.pid, 1)
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        """Wait for its end (subprocess.TimeoutExpired after ``timeout`` s)."""
        if self.returncode is None and not self._ended(1e9 if timeout is None else timeout):
            raise subprocess.TimeoutExpired(self.args, timeout)
        return self.poll()  # type: ignore[return-value]

    def send_signal(self, sig: int) -> None:
        """Signal it by its pidfd (nothing once it ended)."""
        if self.poll() is None and self._pidfd is not None:
            try:
                signal.pidfd_send_signal(self._pidfd, sig)
            except ProcessLookupError:
                pass

    def terminate(self) -> None:
        self.send_signal(signal.SIGTERM)

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)

    def release(self) -> None:
        """Close its pidfd (the zygote is being stopped; it reaps the child)."""
        if self.returncode is None and self._pidfd is not None and self._ended(0.0):
            self.returncode = self.owner.exits.get(self.pid, 1)
        if self._pidfd is not None:
            os.close(self._pidfd)
            self._pidfd = None


def write_json_atomic(path: Path, obj: object) -> None:
    """Write JSON to ``path`` via a temporary file in the same folder and ``os.replace``."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "w", encoding="utf-8") as fh:
        json.dump(obj, fh)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


def run_router(
    port: int,
    *,
    host: str = "127.0.0.1",
    ready_file: Path | None = None,
    max_wall_s: float | None = None,
    stream=sys.stdout,
    loopback_only: bool = True,
    tls: TLSFiles | None = None,
    peers: list[str] | None = None,
    parent_pid: int | None = None,
    orphan_folder: Path | None = None,
) -> None:
    """Open a Zenoh router listening on ``tcp/host:port``; run until SIGTERM/SIGINT; close.

    ``max_wall_s`` (optional) bounds the lifetime, for tests and benchmarks. Must be called from
    the main thread (it installs signal handlers; previous handlers are restored on return).
    ``loopback_only=False`` lets ``host`` be a LAN address (multi-host deployments); ``tls``
    listens on ``tls/host:port`` instead (see protocol.zenoh_config.TLSFiles). ``peers``: other
    routers to link to (``tcp/host:port``), e.g. one router per host with the robots split between
    them (docs/scaling.md, "Beyond one host"). ``parent_pid``: end when that process is no
    longer this one's parent (the launcher that started it is gone); ``orphan_folder`` (an early
    router's temporary folder, named ``shapefleet-router-*``) is then removed, as nobody else will.
    """
    import zenoh

    config = router_config(port, host, loopback_only=loopback_only, tls=tls, peers=peers or ())  # validates
    stop = threading.Event()

    def on_signal(signum, _frame):
        stop.set()

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGTERM, signal.SIGINT)}
    session = None
    orphaned = False
    try:
        session = zenoh.open(config)
        info = {
            "router": "ready",
            "endpoint": router_endpoint(port, host, "tls" if tls else "tcp"),
            "pid": os.getpid(),
            "zid": str(session.zid()),
        }
        if ready_file is not None:
            write_json_atomic(Path(ready_file), info)
        print(json.dumps(info), file=stream, flush=True)
        deadline = None if max_wall_s is None else time.monotonic() + max_wall_s
        while not stop.is_set():
            if parent_pid is not None and os.getppid() != parent_pid:
                orphaned = True
                break
            timeout = 0.5 if deadline is None else min(0.5, deadline - time.monotonic())
            if timeout <= 0:
                break
            stop.wait(timeout)
    finally:
        if session is not None:
            session.close()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        if ready_file is not None:
            try:
                Path(ready_file).unlink()
            except FileNotFoundError:
                pass
    print(json.dumps({"router": "closed", "pid": os.getpid()}), file=stream, flush=True)
    if orphaned and orphan_folder is not None and Path(orphan_folder).name.startswith("shapefleet-router-"):
        shutil.rmtree(orphan_folder, ignore_errors=True)  # its launcher was killed: nobody adopts it


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m launcher.router", description=__doc__.splitlines()[0])
    ap.add_argument("--port", type=int, required=True)
    ap.add_argument("--host", default="127.0.0.1")
    ap.add_argument("--ready-file", type=Path, default=None)
    ap.add_argument("--max-wall-s", type=float, default=None)
    ap.add_argument("--connect", action="append", default=[], help="another router to link to (repeatable)")
    ap.add_argument("--allow-remote", action="store_true", help="listen / connect beyond loopback")
    ap.add_argument("--parent-pid", type=int, default=None, help="end when this process is no longer the parent")
    ap.add_argument("--run-folder", default=None, help="the run this router serves (for ps; not read)")
    ap.add_argument("--orphan-folder", type=Path, default=None,
                    help="with --parent-pid: remove this shapefleet-router-* folder when the parent is gone")
    args = ap.parse_args(argv)
    try:
        run_router(args.port, host=args.host, ready_file=args.ready_file, max_wall_s=args.max_wall_s,
                   loopback_only=not args.allow_remote, peers=args.connect, parent_pid=args.parent_pid,
                   orphan_folder=args.orphan_folder)
    except ValueError as exc:
        print(f"router: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    code = main()
    # the process ends next: objects in the permanent generation are not walked by the
    # interpreter's last collections (0.06-0.09 s -> 0.02 s of exit, see launcher.cli.freeze_before_exit)
    __import__("gc").freeze()
    raise SystemExit(code)
