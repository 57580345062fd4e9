"""The end of a run draws shapes.png in a forked child while result.json and convergence.png are
written (launcher/report.py ``drawn_aside``, issue 14): the same file as drawn in the process, and
the child never outlives the block -- waited for by its PID, or SIGKILLed and reaped when the block
fails; on a machine without an idle core, nothing is forked. Run in a fresh interpreter: a fork needs a process without other threads, which a pytest
process that has run other tests need not be."""

import json
import os
import subprocess
import sys
from pathlib import Path

from launcher.router import child_env

ROOT = Path(__file__).resolve().parent.parent

_SCRIPT = r"""
import json, os, sys
from pathlib import Path
from launcher import report
from tests.conftest import make_run

out = Path(sys.argv[1])
report._core_idle = lambda: True  # fork even when other jobs keep the cores busy (CI)
world, spec, central = make_run()
rows = [{"id": r.id, "c": list(central.c + 0.02 * r.id), "gamma": central.gamma} for r in world.robots]
result = {"robots": rows, "grid": spec.basis.grid.tolist()}
hist = [{"round": k, "function_error": 10.0 ** (-k / 10), "consensus_error": 10.0 ** (-k / 9)} for k in range(60)]
me, said = os.getpid(), {}

def shapes(path):
    def draw():
        (out / (path.name + ".pid")).write_text(str(os.getpid()))
        report.plot_shapes(path, world, spec.basis, result)
    return draw

shapes(out / "here.png")()  # the serial way
with report.drawn_aside(shapes(out / "aside.png")):
    report.plot_convergence(out / "convergence.png", hist)
said["aside_pid"] = int((out / "aside.png.pid").read_text())

def fails_in_child():  # a child that fails: the picture is drawn here after the block
    if os.getpid() != me:
        raise RuntimeError("no")
    shapes(out / "again.png")()
with report.drawn_aside(fails_in_child):
    pass
said["again_pid"] = int((out / "again.png.pid").read_text())

def hangs():
    import time
    time.sleep(60)
try:
    with report.drawn_aside(hangs):
        raise KeyboardInterrupt  # Ctrl-C while result.json is written: the child is stopped, not waited for
except KeyboardInterrupt:
    pass
try:
    os.waitpid(-1, os.WNOHANG)
    said["children_left"] = True
except ChildProcessError:
    said["children_left"] = False
said["me"] = me
print(json.dumps(said))
"""


def test_a_picture_drawn_aside_is_the_file_drawn_here_and_its_child_never_outlives_the_block(tmp_path):
    done = subprocess.run([sys.executable, "-c", _SCRIPT, str(tmp_path)], cwd=ROOT, env=child_env(),
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    said = json.loads(done.stdout.strip().splitlines()[-1])
    assert said["aside_pid"] != said["me"]  # drawn by a forked child ...
    here, aside = (tmp_path / "here.png").read_bytes(), (tmp_path / "aside.png").read_bytes()
    assert len(here) > 10_000 and here == aside  # ... the same bytes as drawn in the process
    assert (tmp_path / "convergence.png").stat().st_size > 10_000
    assert said["again_pid"] == said["me"] and (tmp_path / "again.png").read_bytes() == here
    assert said["children_left"] is False


def test_nothing_is_forked_without_an_idle_core(monkeypatch, tmp_path):
    from launcher import report

    monkeypatch.setattr(report, "_core_idle", lambda: False)
    drawn = []
    with report.drawn_aside(lambda: drawn.append(os.getpid())):
        assert drawn == []  # drawn after the block, here
    assert drawn == [os.getpid()]
