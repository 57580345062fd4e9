"""What several benchmarks do the same way: a timed lock-step round of in-process cores, and a
results table shown row by row while it runs and written under benchmarks/results/."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

RESULTS = Path(__file__).resolve().parent / "results"

#: the in-process fleets the round benchmarks measure: (row label, Options keywords)
FLEETS = [
    ("paper setting: 3 robots, blob, complete", {}),
    ("3 robots, bean", {"shape": "bean"}),
    ("3 robots, star", {"shape": "star"}),
    ("3 robots, crescent", {"shape": "crescent"}),
    ("4 robots, ring", {"robots": 4, "topology": "ring"}),
    ("5 robots, line", {"robots": 5, "topology": "line"}),
    ("8 robots, ring", {"robots": 8, "topology": "ring"}),
    ("8 robots, complete", {"robots": 8}),
    ("16 robots, geometric 3.0", {"robots": 16, "topology": "geometric", "comm_range": 3.0}),
    ("16 robots, ring", {"robots": 16, "topology": "ring"}),
    ("16 robots, complete", {"robots": 16}),
]


def lockstep_round(cores: list[Any]) -> tuple[list[Any], float]:
    """One lock-step round: everyone publishes, everyone receives, everyone advances. Returns the
    round's updates and the seconds spent in the cores' `advance` (compute only, no messaging)."""
    updates = [c.outgoing() for c in cores]
    for c in cores:
        for u in updates:
            c.receive(u)
    started = time.perf_counter()
    for c in cores:
        c.advance()
    return updates, time.perf_counter() - started


def add_row(lines: list[str], line: str) -> None:
    """Keep a table row for the file and show it at once (the runs are long)."""
    lines.append(line)
    print(line, flush=True)


def write_results(name: str, text: str) -> Path:
    """Write benchmarks/results/``name`` and say so."""
    out = RESULTS / name
    out.write_text(text)
    print(f"wrote {out}")
    return out
