"""Run the command blocks of docs/deploy.md as they are written (shared by the deployment tests).

A block marked ``<!-- test:NAME -->`` in the doc is run with bash: whole (``run``) or, for a
long-running command, exec'ed in the background (``start``), optionally inside a network namespace.
Stand-ins on ``PATH`` make it runnable on one machine: ``shapefleet`` is this interpreter's
``-m launcher.cli``, and ``scp`` copies ``HOST:PATH`` to and from ``$FAKE_HOSTS/HOST/PATH`` (each
robot "host" is a folder; its robot runs in ``hosts/<host>/shapefleet``).

Every process started here is stopped by its own PID (:func:`stop`).
"""

from __future__ import annotations

import os
import queue
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DOC = ROOT / "docs" / "deploy.md"
SCENARIO = ROOT / "docker" / "scenario.toml"

_BLOCK = re.compile(r"<!--\s*test:([\w-]+)\s*-->\s*\n```[^\n]*\n(.*?)\n```", re.S)

_SCP = r"""#!/usr/bin/env bash
# test stand-in for scp: HOST:PATH is $FAKE_HOSTS/HOST/PATH on this machine
set -euo pipefail
args=()
for a in "$@"; do
    if [[ "$a" =~ ^([A-Za-z0-9._-]+):(.*)$ ]]; then a="$FAKE_HOSTS/${BASH_REMATCH[1]}/${BASH_REMATCH[2]}"; fi
    args+=("$a")
done
mkdir -p "$(dirname "${args[-1]}")"
exec cp "${args[@]}"
"""


def blocks() -> dict[str, str]:
    """NAME -> the text of the block marked ``<!-- test:NAME -->`` in docs/deploy.md."""
    found = _BLOCK.findall(DOC.read_text())
    names = [name for name, _ in found]
    assert len(names) == len(set(names)), f"a test block name is used twice in {DOC}: {names}"
    return dict(found)


def environment(tmp: Path, **variables: str) -> dict[str, str]:
    """Env of the doc's commands: stand-ins first on PATH, the doc's variables (ROUTER_IP, ...)."""
    bin_dir = tmp / "bin"
    bin_dir.mkdir(exist_ok=True)
    shim = bin_dir / "shapefleet"
    shim.write_text(f'#!/bin/sh\nexec "{sys.executable}" -m launcher.cli "$@"\n')
    scp = bin_dir / "scp"
    scp.write_text(_SCP)
    for f in (shim, scp):
        f.chmod(0o755)
    (tmp / "hosts").mkdir(exist_ok=True)
    env = {k: v for k, v in os.environ.items() if not k.startswith("SHAPEFLEET_")}
    env.update(
        PATH=f"{bin_dir}{os.pathsep}{env.get('PATH', '/usr/bin:/bin')}",
        PYTHONPATH=str(ROOT),
        FAKE_HOSTS=str(tmp / "hosts"),
        MPLBACKEND="Agg",
        **variables,
    )
    return env


def host_dir(tmp: Path, host: str) -> Path:
    """Where the doc's ``~/shapefleet`` of a robot host is (the robot's working folder)."""
    return tmp / "hosts" / host / "shapefleet"


def run(name: str, cwd: Path, env: dict[str, str], timeout: float = 120) -> subprocess.CompletedProcess:
    """Run block NAME to completion (bash -euo pipefail); fail the test with its output if it fails."""
    script = blocks()[name]
    proc = subprocess.run(
        ["bash", "-euo", "pipefail", "-c", script], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout
    )
    assert proc.returncode == 0, f"docs/deploy.md block {name!r} failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}"
    return proc


def start(name: str, cwd: Path, env: dict[str, str], *, netns: str | None = None, log: Path | None = None) -> subprocess.Popen:
    """Start the single command of block NAME (exec'ed: the PID is the command's), optionally in a
    network namespace. stdout: a pipe (read it with :class:`Lines`), or with ``log`` stdout and
    stderr go to that file."""
    return spawn(["bash", "-c", "exec " + blocks()[name]], cwd, env, netns=netns, log=log)


def spawn(argv: list[str], cwd: Path, env: dict[str, str], *, netns: str | None = None, log: Path | None = None) -> subprocess.Popen:
    if netns is not None:
        argv = ["ip", "netns", "exec", netns, *argv]
    if log is None:
        return subprocess.Popen(argv, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True)
    with open(log, "wb") as fh:  # the child keeps its own descriptor
        return subprocess.Popen(argv, cwd=cwd, env=env, stdout=fh, stderr=subprocess.STDOUT, start_new_session=True)


def stop(proc: subprocess.Popen, grace: float = 5.0) -> None:
    """SIGTERM, a grace period, SIGKILL; always reaped. Only this PID (never a name)."""
    if proc.poll() is None:
        try:
            os.kill(proc.pid, signal.SIGTERM)
            proc.wait(grace)
        except subprocess.TimeoutExpired:
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait(10)
        except ProcessLookupError:
            pass
    proc.wait(10)
    for stream in (proc.stdout, proc.stderr):
        if stream is not None:
            stream.close()


def wait_all(procs: list[subprocess.Popen], timeout: float) -> list[int | None]:
    """Exit codes of ``procs`` once all have exited, or None for those still running at the bound."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and any(p.poll() is None for p in procs):
        time.sleep(0.1)
    return [p.poll() for p in procs]


class Lines:
    """A thread reading a process's stdout line by line (so its pipe never fills up)."""

    def __init__(self, proc: subprocess.Popen) -> None:
        self.queue: queue.SimpleQueue = queue.SimpleQueue()
        self.seen: list[str] = []
        self.thread = threading.Thread(target=self._read, args=(proc.stdout,), daemon=True)
        self.thread.start()

    def _read(self, stream) -> None:
        try:
            for raw in iter(stream.readline, b""):
                self.queue.put(raw.decode(errors="replace"))
        except (ValueError, OSError):  # closed by stop()
            pass

    def wait_for(self, needle: str, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                line = self.queue.get(timeout=min(0.2, max(0.01, deadline - time.monotonic())))
            except queue.Empty:
                continue
            self.seen.append(line)
            if needle in line:
                return True
        return False
