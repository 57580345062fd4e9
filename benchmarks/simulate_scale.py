"""Peak memory and time of `shapefleet simulate` per fleet size, topology and algorithm: what the
in-process fleet's robot bound (launcher/cli.py ``simulate_bound``) is derived from.

Each case runs `shapefleet simulate ... --max-rounds R` (the real command, quiet) in a child
process under an address-space limit (``--limit-mb``, default 3000: a case that would pass it dies
of MemoryError instead of taking the machine) and a wall-clock limit, stopped by its PID. The child
records, at each phase's end, the wall time and its own peak RSS: the world (build_world), the exact
reference (solve_central), the robots' sessions (set-up), the rounds, the report; the parent reads
the child's peak RSS from wait4.

    .venv/bin/python benchmarks/simulate_scale.py                      # the table of results/simulate_cost.md
    .venv/bin/python benchmarks/simulate_scale.py --cases admm:complete:50,100 newton:ring:25,50,100
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

DEFAULT_CASES = [
    "admm:complete:25,50,100,200,400",
    "admm:ring:25,50,100,124",
    "admm:line:25,50,63",
    "admm:geometric:25,50,100,200,400",
    "ct-admm:complete:25,50,100,200",
    "ct-admm:ring:25,50,100",
    "newton:complete:25,50,100,200",
    "newton:ring:25,50,100,124",
    "newton:geometric:25,50,100,200",
    "autogrid:complete:25,50,100,200",
    "autogrid:ring:25,50,100",
]


def _child(argv: list[str]) -> None:
    """Run the command with each phase timed; print one JSON line of the marks on stdout's last line."""
    sys.path.insert(0, str(ROOT))
    marks: list[tuple[str, float, float]] = []
    t0 = time.perf_counter()

    def mark(name: str) -> None:
        marks.append((name, time.perf_counter() - t0, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
                      resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0))

    from launcher import cli, simulate, world
    from agents import problem

    def timed(module: object, name: str, label: str) -> None:
        inner = getattr(module, name)

        def wrapper(*a: object, **k: object) -> object:
            mark(f"before {label}")
            try:
                return inner(*a, **k)
            finally:
                mark(label)

        setattr(module, name, wrapper)

    mark("imports")
    timed(cli, "build_world", "world")
    timed(problem, "solve_central", "central")
    timed(simulate, "_sessions", "setup")
    timed(simulate, "simulate_fleet", "rounds")
    timed(cli, "_finish", "report")
    report = cli.run_simulate(cli.parse_args(argv), quiet=True)
    mark("end")
    rounds = max((int(r.get("rounds") or 0) for r in report.robots), default=0)
    print(json.dumps({"code": report.code, "marks": marks, "rounds": rounds}))


def _phase_times(marks: list[list]) -> dict[str, float]:
    """Seconds spent in each phase (from its 'before' mark to its end mark)."""
    out: dict[str, float] = {}
    start: dict[str, float] = {}
    for name, t, *_ in marks:
        if name.startswith("before "):
            start[name[7:]] = t
        elif name in start:
            out[name] = out.get(name, 0.0) + t - start.pop(name)
    if "rounds" in out and "setup" in out:
        out["rounds"] -= out["setup"]  # simulate_fleet builds the sessions first
    return out


def _override(robots: int) -> list[str]:
    """--max-robots N where simulate has it (the bound would refuse the larger cases)."""
    sys.path.insert(0, str(ROOT))
    from launcher.options import OPTIONS

    return ["--max-robots", str(robots)] if any(o.name == "max-robots" and "simulate" in o.commands
                                                for o in OPTIONS) else []


def run_case(algorithm: str, topology: str, robots: int, *, rounds: int, limit_mb: int, timeout_s: float,
             extra: list[str] = ()) -> dict:
    """One child run; its figures (or why it has none). ``rounds`` 0: the algorithm's own cap."""
    args = ["simulate", "--robots", str(robots), "--topology", topology, *extra]
    if rounds:
        args += ["--max-rounds", str(rounds)]
    if algorithm != "autogrid":
        args += ["--preset", "paper", "--algorithm", algorithm]
    else:
        args += ["--algorithm", "autogrid"]
    with tempfile.TemporaryDirectory(prefix="simscale-") as tmp:
        args += ["--out", tmp, *_override(robots)]

        def limits() -> None:
            limit = limit_mb * 1024 * 1024
            resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
            os.nice(15)

        t = time.perf_counter()
        proc = subprocess.Popen([sys.executable, __file__, "--child", *args], stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, preexec_fn=limits, text=True)
        try:
            out, err = proc.communicate(timeout=timeout_s)
            timed_out = False
        except subprocess.TimeoutExpired:
            os.kill(proc.pid, signal.SIGKILL)
            out, err = proc.communicate()
            timed_out = True
        finally:  # Ctrl-C or SIGTERM (main turns it into SystemExit): the child goes too, by its PID
            if proc.poll() is None:
                os.kill(proc.pid, signal.SIGKILL)
                proc.wait()
        wall = time.perf_counter() - t
    row = {"algorithm": algorithm, "topology": topology, "robots": robots, "flags": " ".join(extra),
           "wall_s": round(wall, 2)}
    try:
        data = json.loads(out.strip().splitlines()[-1])
        peak = max(m[2] for m in data["marks"])
        rss = {m[0]: m[2] for m in data["marks"] if not m[0].startswith("before ")}
        # the report may draw shapes.png in a forked child (launcher/report.py drawn_aside): it shares the
        # pages it does not write, so what it adds is its peak above the RSS it was forked with
        drawing = max(m[3] for m in data["marks"])
        machine = peak + max(0.0, drawing - rss.get("rounds", peak))
        row.update(code=data["code"], rounds=data["rounds"], peak_mb=round(peak), drawing_mb=round(drawing), machine_mb=round(machine), phases={k: round(v, 2) for k, v in _phase_times(data["marks"]).items()},
                   rss_after={k: round(v) for k, v in rss.items()})
    except (IndexError, ValueError, KeyError):
        last = (err.strip().splitlines() or ["?"])[-1]
        row.update(code=proc.returncode, failed="timed out" if timed_out else last[:160])
    return row


HEADER = ("| algorithm | topology | robots | rounds | wall s | world s | central s | set-up s | rounds s | report s | "
          "MB after set-up | MB after rounds | peak MB | fit MB |\n"
          "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")


def fitted_mb(row: dict) -> float:
    """launcher/simulate.py's fitted peak for this case at the rounds it ran (what the bound uses,
    there with the round cap): at or above the measured peak where the fit holds."""
    sys.path.insert(0, str(ROOT))
    from launcher import cli
    from launcher.simulate import simulate_memory_mb
    from launcher.world import resolve_options

    argv = ["simulate", "--robots", str(row["robots"]), "--topology", row["topology"], *row["flags"].split()]
    argv += ["--algorithm", row["algorithm"]] + ([] if row["algorithm"] == "autogrid" else ["--preset", "paper"])
    options = resolve_options(cli._options(cli.parse_args(argv)))
    _, grid_points = cli._rounds_and_grid(options)
    return simulate_memory_mb(row["robots"], row["topology"], options.algorithm, rounds=row["rounds"],
                              grid_points=grid_points)


def table_line(row: dict) -> str:
    """One row of the results table (peak MB: with a forked drawing's own pages, if any)."""
    name = f"{row['algorithm']} {row.get('flags', '')}".strip()
    head = f"| {name} | {row['topology']} | {row['robots']} |"
    if "failed" in row:
        return f"{head} - | {row['wall_s']:.1f} | {row['failed']} |"
    ph = row["phases"]
    cells = " | ".join(f"{ph[k]:.2f}" if k in ph else "-" for k in ("world", "central", "setup", "rounds", "report"))
    after = row["rss_after"]
    return (f"{head} {row['rounds']} | {row['wall_s']:.1f} | {cells} | {after.get('setup', '-')} | "
            f"{after.get('rounds', '-')} | {row['machine_mb']} | {fitted_mb(row):.0f} |")


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        _child(sys.argv[2:])
        return
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # so run_case's finally stops its child
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cases", nargs="*", default=DEFAULT_CASES,
                   help="ALGORITHM:TOPOLOGY:N,N,...[:--flag=value,...] (e.g. admm:ring:50:--grid=10x5)")
    p.add_argument("--rounds", type=int, default=2, help="--max-rounds of every case (0: the algorithm's own cap)")
    p.add_argument("--limit-mb", type=int, default=3000)
    p.add_argument("--timeout", type=float, default=150.0)
    p.add_argument("--json", type=Path, help="append every row as a JSON line here")
    p.add_argument("--table", type=Path, help="only print the table of the rows stored in this JSON-lines file")
    a = p.parse_args()
    print(HEADER)
    if a.table:
        for line in a.table.read_text().splitlines():
            print(table_line(json.loads(line)))
        return
    for case in a.cases:
        algorithm, topology, sizes, *flags = case.split(":")
        extra = [w for f in (flags[0].split(",") if flags else []) for w in f.split("=", 1)]
        for n in (int(s) for s in sizes.split(",")):
            row = run_case(algorithm, topology, n, rounds=a.rounds, limit_mb=a.limit_mb, timeout_s=a.timeout,
                           extra=extra)
            if a.json:
                with open(a.json, "a") as fh:
                    fh.write(json.dumps(row) + "\n")
            print(table_line(row), flush=True)
            if "failed" in row or row["wall_s"] > a.timeout * 0.8:
                break  # the larger sizes of this case would fail too


if __name__ == "__main__":
    main()
