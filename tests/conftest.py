"""Shared fixtures: small scenarios built through the same code path as the CLI."""

from __future__ import annotations

import contextlib
import functools
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from agents.problem import solve_central
from launcher.world import Options, build_world


#: the paper's setting, which the fixed-grid tests measure (the CLI's default is now autogrid)
PAPER = {"grid": "5x3", "sigma": 1.0, "algorithm": "admm"}


def step_all(cores, deliver=None):
    """One lock-step round: everyone publishes, everyone receives, everyone advances."""
    updates = [c.outgoing() for c in cores]
    for c in cores:
        for u in updates:
            if deliver is None or deliver(u, c):
                c.receive(u)
    for c in cores:
        c.advance()


def run_to_end(cores, limit=5000):
    """Lock-step rounds until every core has finished (at most ``limit``)."""
    for _ in range(limit):
        if all(c.finished for c in cores):
            return
        step_all(cores)
    raise AssertionError("fleet did not finish")


def exchange_until_finished(cores: dict, limit: int) -> None:
    """Drive ``cores`` (id -> core) by a perfect in-memory exchange: each round every core
    publishes, its neighbours receive, the ready ones advance; until all have finished or
    ``limit`` rounds (the reference the networked shells must equal)."""
    for _ in range(limit):
        if all(c.finished for c in cores.values()):
            return
        for update in [c.outgoing() for c in cores.values()]:
            for c in cores.values():
                if update.sender in c.neighbours:
                    c.receive(update)
        for c in cores.values():
            if c.ready():
                c.advance()


def make_run(**kwargs):
    """(world, spec, central) for Options(**kwargs) with a fixed fleet id, on the paper's
    setting (grid 5x3, sigma 1, admm) unless the test passes its own; autogrid runs get no
    paper grid or sigma (they choose their own; central is None then)."""
    kwargs.setdefault("fleet_id", "test")
    kwargs.setdefault("algorithm", PAPER["algorithm"])
    if kwargs["algorithm"] != "autogrid":
        kwargs.setdefault("grid", PAPER["grid"])
        kwargs.setdefault("sigma", PAPER["sigma"])
    world, spec = build_world(Options(**kwargs))
    central = solve_central(spec.basis, world.points, world.labels, spec.C) if spec.fixed_grid else None
    return world, spec, central


@pytest.fixture(scope="session")
def default_run():
    return make_run()


def max_function_error(spec, central, robots) -> float:
    """Largest ||f_l - f*||_H/||f*||_H + |gamma_l - gamma*|/max(1,|gamma*|) over robots."""
    b = spec.basis
    return max(
        b.function_error(b.c_from_x(np.asarray(r["x"])), r["gamma"], central.c, central.gamma) for r in robots
    )


ROOT = Path(__file__).resolve().parent.parent


def cli_exit_and_stderr(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, list[str]]:
    """(exit code, stderr lines) of ``shapefleet argv`` run in this process; never a traceback."""
    from launcher import cli

    try:
        code = cli.main(argv)
    except SystemExit as exc:
        code = int(exc.code or 0)
    err = capsys.readouterr().err.strip().splitlines()
    assert "Traceback" not in "\n".join(err)
    return code, err


def processes_with(marker: str) -> list[int]:
    """PIDs (other than ours) whose command line contains ``marker`` (e.g. a test's tmp_path)."""
    found = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit() or int(entry) == os.getpid():
            continue
        try:
            with open(f"/proc/{entry}/cmdline", "rb") as fh:
                cmdline = fh.read().replace(b"\0", b" ").decode(errors="replace")
        except OSError:  # gone meanwhile
            continue
        if marker in cmdline:
            found.append(int(entry))
    return found


def wait_until(predicate, timeout: float):
    """The first truthy value of ``predicate()``, polled every 50 ms for at most ``timeout``
    seconds; None when it never came (the caller says what it waited for)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        value = predicate()
        if value:
            return value
        time.sleep(0.05)
    return None


@contextlib.contextmanager
def bounded_and_clean(marker: str, seconds: float, what: str):
    """A hard wall-clock bound (SIGALRM raises TimeoutError naming `what`) and, afterwards, no
    process whose command line names `marker`: leftovers are killed by PID, then the test fails."""

    def on_alarm(signum, frame):
        raise TimeoutError(f"{what} exceeded its {seconds:g}s bound")

    previous = signal.signal(signal.SIGALRM, on_alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
        left = processes_with(marker)
        for pid in left:  # never leave them running, even when failing
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        assert not left, f"processes left behind: {left}"


def start_router(folder: Path, port: int, *, max_wall_s: float) -> subprocess.Popen:
    """A router subprocess on a loopback port, returned once it listens (bounded wait).

    The caller stops it by its PID (launcher.fleet.stop_process) in a `finally`.
    """
    ready = folder / "ready.json"
    proc = subprocess.Popen(
        [sys.executable, "-m", "launcher.router", "--port", str(port), "--ready-file", str(ready),
         "--max-wall-s", str(max_wall_s)],
        cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=dict(os.environ, PYTHONPATH=str(ROOT)),
    )
    deadline = time.monotonic() + 20
    while not ready.exists():
        if proc.poll() is not None or time.monotonic() > deadline:
            from launcher.fleet import stop_process

            stop_process(proc)
            raise AssertionError(f"router did not become ready: {proc.stderr.read().decode()}")
        time.sleep(0.02)
    return proc


# -- evidence that must not vanish quietly (issue 18) ---------------------------------------------
#: set by .ci/run: a skipped evidence test (TLS, multi-host walk-through, docker files) fails instead
REQUIRE_EVIDENCE_ENV = "SHAPEFLEET_REQUIRE_EVIDENCE"


def evidence_required() -> bool:
    return os.environ.get(REQUIRE_EVIDENCE_ENV, "") not in ("", "0")


def skip_evidence(reason: str, *, allow_module_level: bool = False):
    """Skip an evidence test for ``reason``, or fail it when REQUIRE_EVIDENCE_ENV is set (CI).

    The only TLS and multi-host evidence lives in these tests: on the machines CI runs on their
    tools (openssl, root and ``ip netns``, PyYAML) are there, so a skip there is a broken machine.
    """
    if evidence_required():
        pytest.fail(f"evidence test cannot run: {reason} ({REQUIRE_EVIDENCE_ENV} is set)", pytrace=False)
    pytest.skip(reason, allow_module_level=allow_module_level)


# -- two workers (`make test`: pytest-xdist `-n 2 --dist loadscope`) -----------------------------
#: the xdist work unit of every test file that starts robot or router processes: one worker runs
#: them one after the other, so two multi-process fleets never share the 2 cores (their wall-clock
#: bounds and dead-after timers were written for one fleet at a time) while the other worker runs
#: the in-process files; every other file stays one unit (its module fixtures computed once)
PROCESS_GROUP = "processes"
#: what marks a file as starting processes: the integration and fleet_processes markers and the
#: plugin's router fixture (the controller sees test ids only, not markers: it reads the file)
PROCESS_SIGNS = ("pytest.mark.integration", "pytest.mark.fleet_processes", "zenoh_router")


@functools.lru_cache(maxsize=None)
def starts_processes(path: Path) -> bool:
    """True for a test file that names one of PROCESS_SIGNS."""
    try:
        text = path.read_text(encoding="utf-8")
    except OSError:
        return False
    return any(sign in text for sign in PROCESS_SIGNS)


@pytest.hookimpl(optionalhook=True)  # a hook of pytest-xdist: absent without it
def pytest_xdist_make_scheduler(config: pytest.Config, log):
    """``--dist loadscope`` with every process-starting file in one unit (PROCESS_GROUP)."""
    if config.getvalue("dist") != "loadscope":
        return None  # xdist's own scheduler for the mode asked
    from xdist.scheduler import LoadScopeScheduling

    class ProcessesTogether(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            if starts_processes(config.rootpath / nodeid.split("::", 1)[0]):
                return PROCESS_GROUP
            return super()._split_scope(nodeid)

    return ProcessesTogether(config, log)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    """Safety net: with REQUIRE_EVIDENCE_ENV set, any skip in a module that declares
    ``EVIDENCE = True`` (however it was raised) is reported as a failure."""
    outcome = yield
    report = outcome.get_result()
    if report.skipped and evidence_required() and getattr(item.module, "EVIDENCE", False):
        if not hasattr(report, "wasxfail"):
            report.outcome = "failed"
            report.longrepr = f"evidence test skipped ({report.longrepr}) while {REQUIRE_EVIDENCE_ENV} is set"


def assert_bound_holds_every_round(spec, central, cores, rounds: int, errors, each_round=None) -> int:
    """Step the fleet `rounds` times; every robot's certified `error_bound()` (where it has one) must be
    >= its true error (`errors(spec, central, cores)`, per robot); `each_round(cores)` checks more after
    every step. Returns how many robot-rounds had a bound (callers assert it is not a vacuous loop)."""
    bounded = 0
    for _ in range(rounds):
        step_all(cores)
        if each_round is not None:
            each_round(cores)
        for c, e in zip(cores, errors(spec, central, cores)):
            b = c.error_bound()
            if b is not None:
                bounded += 1
                assert b >= e, (c.round, b, e)
    return bounded
