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

__all__ = ["run_router", "write_json_atomic", "main", "EarlyRouter", "spawn", "child_env", "ROOT"]

ROOT = Path(__file__).resolve().parent.parent
HOST = "127.0.0.1"
#: an early router's own lifetime bound (it also ends when the launcher that started it is gone);
#: a launch that needs a longer-lived router starts its own instead
EARLY_ROUTER_BOUND_S = 3600.0


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
