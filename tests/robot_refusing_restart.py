"""A robot program for tests (``launch_fleet(robot_argv=("-m", "tests.robot_refusing_restart"))``):
agents.robot, except that a robot whose checkpoint already exists -- a restart -- exits at once with
an error and no result, as a restart that cannot read its files does. What the launcher must then
report: the robot was lost, the run did not converge (tests/test_launch.py)."""

from __future__ import annotations

import sys
from pathlib import Path

from agents import robot


def main(argv: list[str]) -> int:
    solo = "--id" in argv  # (robots sharing a process are never restarted alone: only crash-planned ones)
    workdir = Path(argv[argv.index("--workdir") + 1])
    if solo and (workdir / f"robot-{argv[argv.index('--id') + 1]}.ckpt").exists():
        print("shapefleet robot: this test program refuses every restart", file=sys.stderr)
        return 2
    return robot.main(argv)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
