"""What the launcher asks of its own process before it forks (robots, a picture) or sizes its
robot processes: the cores it may use, and whether it runs a thread besides the main one."""

from __future__ import annotations

import os


def usable_cores() -> int:
    """The cores this process may run on (its affinity mask where the OS has one)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def runs_alone() -> bool:
    """This process runs no thread but the main one (ours or a library's): only then is a fork
    safe, since a fork beside a running thread can copy a lock that thread holds. False when it
    cannot tell (no /proc)."""
    try:
        return len(os.listdir("/proc/self/task")) == 1
    except OSError:
        return False
