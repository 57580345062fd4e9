"""A test file to copy into your own suite: a fleet over Zenoh with loss and a crash.

Nothing to import from shapefleet's tests: `pip install shapefleet` registers the pytest plugin
(launcher/pytest_plugin.py) and with it the fixture ``fleet``. Each call launches a Zenoh router
and the robot processes (one or several robots each) on 127.0.0.1 (multicast scouting off), injects the faults on every
directed link, kills and restarts robots as told, and returns a typed result
(launcher/api.py ``Result``). After the test the fixture checks by PID that no process is left.
"""

import pytest

from launcher.pytest_plugin import alive


@pytest.mark.fleet_processes
def test_fleet_survives_loss_delay_and_a_crash(fleet):
    r = fleet(robots=3, preset="paper", loss=0.3, delay="20ms", crash="1@40", restart_after=0.3)

    assert r.converged, r.verdict  # every robot agrees with its neighbours, one connected fleet
    assert r.participants == (0, 1, 2) and r.absent == ()
    assert r.error < 1e-3  # each robot's function against the exact centralized solve
    assert r.robot(1).counters["restarts"] == 1  # robot 1 was killed at round 40 and resumed
    assert sum(x.counters["frames_lost"] for x in r.robots) > 0  # the loss really happened
    assert r.pids and not any(alive(pid) for pid in r.pids)  # every process it started is gone
