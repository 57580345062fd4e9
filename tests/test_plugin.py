"""launcher/pytest_plugin.py: loaded by its pytest11 entry point; its fixtures clean up by PID.

The inner test runs (pytester) are user test files in a fresh folder: the plugin reaches them only
through the installed entry point, as it reaches any user's suite.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest

from launcher.pytest_plugin import NO_PROCESSES, alive

pytest_plugins = ["pytester"]


def test_registered_through_pytest11():
    from importlib.metadata import entry_points

    (ep,) = [ep for ep in entry_points(group="pytest11") if ep.name == "shapefleet"]
    assert ep.value == "launcher.pytest_plugin"


def _pids_file(pytester: pytest.Pytester) -> str:
    return str(pytester.path / "pids.json")


@pytest.mark.fleet_processes
def test_router_and_fleet_leave_no_process(pytester: pytest.Pytester):
    """A user's test: a launch on the fixture's router, one in process; PIDs recorded, then gone."""
    pytester.makepyfile(test_user=f"""
        import json
        import pytest

        @pytest.mark.fleet_processes
        def test_launch_on_my_router(zenoh_router, fleet):
            assert zenoh_router.startswith("tcp/127.0.0.1:")
            r = fleet(robots=3, preset="paper", tol=1e-3, loss=0.2, router=zenoh_router)
            s = fleet(robots=3, preset="paper", tol=1e-3, loss=0.2, mode="simulate")
            assert r.converged and s.converged, (r.verdict, s.verdict)
            assert [x.rounds for x in r.robots] == [x.rounds for x in s.robots]
            assert zenoh_router.endswith(str(zenoh_router.port))
            json.dump({{"robots": list(r.pids), "router": [zenoh_router.pid]}}, open({_pids_file(pytester)!r}, "w"))
    """)
    result = pytester.runpytest_subprocess("-q", "-p", "no:cacheprovider")
    result.assert_outcomes(passed=1)
    pids = json.loads((pytester.path / "pids.json").read_text())
    assert pids["robots"] and len(pids["router"]) == 1  # the launch's robots; the fixture's router
    assert not [pid for pid in pids["robots"] + pids["router"] if alive(pid)]


def test_leftover_process_fails_the_test_and_is_killed(pytester: pytest.Pytester):
    """A process a run left behind (here: started by the test itself, naming the run folder) is
    killed by its PID at teardown, and the test fails saying so."""
    pytester.makepyfile(test_user=f"""
        import json, subprocess, sys, time
        from launcher.pytest_plugin import _cmdline

        def test_leaves_one(fleet, tmp_path):
            r = fleet(mode="simulate", preset="paper", tol=1e-3)
            proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)", str(r.out)])
            json.dump(proc.pid, open({_pids_file(pytester)!r}, "w"))
            deadline = time.monotonic() + 10  # until its command line is readable (it names the run)
            while str(r.out).encode() not in _cmdline(proc.pid) and time.monotonic() < deadline:
                time.sleep(0.01)
    """)
    result = pytester.runpytest_subprocess("-q", "-p", "no:cacheprovider")
    result.assert_outcomes(passed=1, errors=1)
    result.stdout.fnmatch_lines(["*fleet: processes left behind (killed by PID)*"])
    pid = json.loads((pytester.path / "pids.json").read_text())
    deadline = time.monotonic() + 5
    while alive(pid) and time.monotonic() < deadline:
        time.sleep(0.05)
    if alive(pid):  # never leave it, even when failing
        os.kill(pid, signal.SIGKILL)
        pytest.fail(f"the plugin did not kill {pid}")


def test_no_processes_option_skips_marked_tests_and_launches(pytester: pytest.Pytester):
    pytester.makepyfile(test_user="""
        import pytest

        @pytest.mark.fleet_processes
        def test_marked():
            raise AssertionError("must be skipped")

        def test_launch_refused(fleet):
            fleet(robots=2)

        def test_router_refused(zenoh_router):
            raise AssertionError("must be skipped")

        def test_simulate_still_runs(fleet):
            assert fleet(mode="simulate", preset="paper", tol=1e-3).converged
    """)
    result = pytester.runpytest_subprocess("-q", "-p", "no:cacheprovider", NO_PROCESSES)
    result.assert_outcomes(passed=1, skipped=3)


async def test_fleet_run_async_in_an_event_loop(fleet):
    """pytest-asyncio: the factory awaited inside the test's loop."""
    r = await fleet.run_async(mode="simulate", preset="paper", tol=1e-3)
    assert r.converged and r.out.parent == fleet.folders[0].parent


def test_marker_registered():
    out = subprocess.run([sys.executable, "-m", "pytest", "--markers", "-p", "no:cacheprovider"],
                         capture_output=True, text=True, timeout=60)
    assert "@pytest.mark.fleet_processes" in out.stdout
