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
import signal
import sys
import threading
import time
from pathlib import Path

from protocol.zenoh_config import TLSFiles, router_config, router_endpoint

__all__ = ["run_router", "write_json_atomic", "main"]


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
) -> None:
    """Open a Zenoh router listening on ``tcp/host:port``; run until SIGTERM/SIGINT; close.

    ``max_wall_s`` (optional) bounds the lifetime, for tests and benchmarks. Must be called from
    the main thread (it installs signal handlers; previous handlers are restored on return).
    ``loopback_only=False`` lets ``host`` be a LAN address (multi-host deployments); ``tls``
    listens on ``tls/host:port`` instead (see protocol.zenoh_config.TLSFiles). ``peers``: other
    routers to link to (``tcp/host:port``), e.g. one router per host with the robots split between
    them (docs/scaling.md, "Beyond one host").
    """
    import zenoh

    config = router_config(port, host, loopback_only=loopback_only, tls=tls, peers=peers or ())  # validates
    stop = threading.Event()

    def on_signal(signum, _frame):
        stop.set()

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGTERM, signal.SIGINT)}
    session = None
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


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m launcher.router", description=__doc__.splitlines()[0])
    ap.add_argument("--port", type=int, required=True)
    ap.add_argument("--host", default="127.0.0.1")
    ap.add_argument("--ready-file", type=Path, default=None)
    ap.add_argument("--max-wall-s", type=float, default=None)
    ap.add_argument("--connect", action="append", default=[], help="another router to link to (repeatable)")
    ap.add_argument("--allow-remote", action="store_true", help="listen / connect beyond loopback")
    args = ap.parse_args(argv)
    try:
        run_router(args.port, host=args.host, ready_file=args.ready_file, max_wall_s=args.max_wall_s,
                   loopback_only=not args.allow_remote, peers=args.connect)
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
