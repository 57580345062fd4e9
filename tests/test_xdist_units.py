"""`make test` runs two pytest-xdist workers; tests/conftest.py makes every file that starts robot or
router processes one work unit (one worker, one multi-process fleet at a time). The scheduler sees
test ids only and classifies a file by its text: these tests keep that reading in step with the
markers pytest actually sees."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from .conftest import PROCESS_GROUP, ROOT, pytest_xdist_make_scheduler, starts_processes


def test_every_file_with_a_process_test_is_in_the_process_unit(request: pytest.FixtureRequest) -> None:
    """A test marked integration / fleet_processes, or using the router fixture, lives in a file the
    scheduler puts in PROCESS_GROUP (a marker spelled so that the text test misses it fails here)."""
    marked = {
        item.path
        for item in request.session.items
        if item.get_closest_marker("integration") or item.get_closest_marker("fleet_processes")
        or "zenoh_router" in getattr(item, "fixturenames", ())
    }
    if not marked:  # a run of this file alone: the suite's process tests were not collected
        pytest.skip("needs the suite's process tests in the session (make test collects them)")
    assert sorted(str(p.relative_to(ROOT)) for p in marked if not starts_processes(p)) == []


def test_in_process_files_keep_their_own_unit() -> None:
    assert starts_processes(ROOT / "tests/test_launch.py") and starts_processes(ROOT / "tests/test_robot_shell.py")
    assert not starts_processes(ROOT / "tests/test_topology.py") and not starts_processes(ROOT / "tests/test_kernel.py")
    assert not starts_processes(ROOT / "tests/no_such_file.py")


def test_the_scheduler_groups_process_files_and_keeps_others_by_file() -> None:
    pytest.importorskip("xdist")
    config = SimpleNamespace(rootpath=ROOT, getvalue=lambda name: "loadscope")
    sched = pytest_xdist_make_scheduler(config, log=None)
    split = sched._split_scope
    assert split("tests/test_launch.py::test_cli_launch_end_to_end") == PROCESS_GROUP
    assert split("examples/test_fleet_example.py::test_fleet_survives_loss_delay_and_a_crash") == PROCESS_GROUP
    assert split("tests/test_topology.py::test_complete") == "tests/test_topology.py"
    other = SimpleNamespace(rootpath=ROOT, getvalue=lambda name: "load")
    assert pytest_xdist_make_scheduler(other, log=None) is None  # another --dist: xdist's own
