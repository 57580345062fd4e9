"""Wall milliseconds per fleet round of the in-process fleet (session + shell + cores), best and
median of N runs, on three scenarios. Used to check that a change to the shell or the options
(issue 12) does not make rounds dearer: run it on two checkouts, interleaved, and compare.

    .venv/bin/python benchmarks/simulate_cost.py 3
    (cd /tmp/base && PYTHONPATH=/tmp/base /path/to/.venv/bin/python /path/to/benchmarks/simulate_cost.py 3)
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from launcher.simulate import simulate_fleet  # noqa: E402
from launcher.world import Options, build_world  # noqa: E402

CASES = {
    "paper setting, 3 robots, complete": {"preset": "paper"},
    "paper grid, 8 robots, ring": {"preset": "paper", "robots": 8, "topology": "ring"},
    "autogrid, 3 robots x 15 points, budget 60": {"points": 15, "max_grid_points": 60},
}


def main(repeats: int) -> None:
    print("| scenario | rounds | best ms/round | median ms/round |")
    print("|---|---:|---:|---:|")
    for name, kw in CASES.items():
        _, spec = build_world(Options(fleet_id="bench", **kw))
        times = []
        for _ in range(repeats):
            t = time.perf_counter()
            out = simulate_fleet(spec)
            times.append(time.perf_counter() - t)
        rounds = max(r["rounds"] for r in out.robots)
        print(f"| {name} | {rounds} | {1e3 * min(times) / rounds:.2f} | {1e3 * statistics.median(times) / rounds:.2f} |",
              flush=True)


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 3)
