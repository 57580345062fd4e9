"""The run's pictures are drawn side by side (launcher/report.py ``draw_pictures``): the first in
the launcher, the others in forked children; a child that fails or hangs is stopped by its PID and
its picture drawn in the launcher, so nothing is lost and drawing errors still surface."""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

from launcher import report

pytestmark = pytest.mark.skipif(not hasattr(os, "fork"), reason="pictures are drawn in parallel only with fork")


def _writer(path: Path, *, fail_in_child: bool = False, hang_in_child: bool = False, parent: int | None = None):
    def job() -> None:
        in_child = os.getpid() != parent
        if in_child and fail_in_child:
            raise RuntimeError("child failure")
        if in_child and hang_in_child:
            (path.parent / "hung.pid").write_text(str(os.getpid()))
            time.sleep(30)
        path.write_text(str(os.getpid()))

    return job


def test_the_other_pictures_are_drawn_by_a_child_process(tmp_path: Path) -> None:
    me = os.getpid()
    jobs = [_writer(tmp_path / f"{k}.txt", parent=me) for k in range(3)]
    report.draw_pictures(jobs)
    pids = [int((tmp_path / f"{k}.txt").read_text()) for k in range(3)]
    assert pids[0] == me
    assert pids[1] != me and pids[2] != me and pids[1] != pids[2]


def test_a_picture_whose_child_failed_is_drawn_by_the_launcher(tmp_path: Path) -> None:
    me = os.getpid()
    report.draw_pictures([_writer(tmp_path / "a.txt", parent=me),
                          _writer(tmp_path / "b.txt", fail_in_child=True, parent=me)])
    assert int((tmp_path / "b.txt").read_text()) == me


def test_a_drawing_error_still_reaches_the_caller(tmp_path: Path) -> None:
    def broken() -> None:
        raise ValueError("cannot draw")

    with pytest.raises(ValueError, match="cannot draw"):
        report.draw_pictures([_writer(tmp_path / "a.txt", parent=os.getpid()), broken])


def test_a_hung_child_is_stopped_by_its_pid_and_its_picture_drawn_here(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setattr(report, "PICTURE_CHILD_TIMEOUT_S", 0.5)
    me = os.getpid()
    t0 = time.monotonic()
    report.draw_pictures([_writer(tmp_path / "a.txt", parent=me),
                          _writer(tmp_path / "b.txt", hang_in_child=True, parent=me)])
    assert time.monotonic() - t0 < 10
    assert int((tmp_path / "b.txt").read_text()) == me
    hung = int((tmp_path / "hung.pid").read_text())
    with pytest.raises(ProcessLookupError):
        os.kill(hung, 0)  # stopped and reaped
