"""The Zenoh process fleet (``shapefleet launch``): ms per ADMM round, and rounds / wall time
under network faults.

Runs ``launcher.fleet.launch_fleet`` -- a loopback router plus one process per robot, each robot
the real ADMM core in the asyncio Zenoh shell -- on the default scenario (the L-block, 20 points
per robot, 5x3 grid, complete graph):

* no faults, N = 3, 8, 16, a fixed number of rounds (``tol`` tiny, ``--rounds`` rounds): the
  robots' own advance-to-advance intervals (``round_ms`` in their results) give ms per round;
* N = 3 to convergence (default tol) on a clean network, under
  ``--loss 0.3 --delay 20ms --jitter 10ms --duplicate 0.05 --reorder 0.1``, and with ``--loss 0.5``.

Every run is also simulated in-process (``launcher.simulate``) and the column "= simulate" says
whether every robot's trace (all iterates, round for round) is bit-identical to it.

Bounded: every run has ``max_wall_s`` and the launcher's own time bound; every process is stopped
by its PID. Loopback only, multicast scouting off.

    .venv/bin/python benchmarks/zenoh_fleet.py            # full table, writes benchmarks/results/zenoh_fleet.md
    .venv/bin/python benchmarks/zenoh_fleet.py --quick    # N = 3 and 8 only, fewer rounds
"""

from __future__ import annotations

import argparse
import platform
import statistics
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from agents.spec import Timing  # noqa: E402
from launcher.fleet import launch_fleet  # noqa: E402
from launcher.simulate import simulate_fleet  # noqa: E402
from launcher.world import DEFAULT_MAX_ROUNDS, Options, build_world  # noqa: E402
from protocol.links import LinkFaults  # noqa: E402

FAULTS = LinkFaults(delay=0.020, jitter=0.010, loss=0.3, duplicate=0.05, reorder=0.1)
LOSS50 = LinkFaults(loss=0.5)
RESULTS = ROOT / "benchmarks" / "results" / "zenoh_fleet.md"


@dataclass
class Row:
    scenario: str
    robots: int
    faults: str
    retransmit_ms: float
    rounds: int
    converged: bool
    ms_median: float
    ms_mean: float
    ms_wall: float  # robots' run wall / rounds (includes waiting for the slowest at start)
    run_s: float  # longest robot run (session open -> result)
    launch_s: float  # launch_fleet, processes started to processes stopped
    sim_ms: float  # in-process simulator, ms per round (all robots in one process)
    lost: int
    sent: int
    same: bool


def _fault_text(f: LinkFaults) -> str:
    if f.is_clean:
        return "none"
    parts = []
    if f.loss:
        parts.append(f"loss {f.loss:g}")
    if f.delay:
        parts.append(f"delay {f.delay * 1e3:g}ms")
    if f.jitter:
        parts.append(f"jitter {f.jitter * 1e3:g}ms")
    if f.duplicate:
        parts.append(f"dup {f.duplicate:g}")
    if f.reorder:
        parts.append(f"reorder {f.reorder:g}")
    return ", ".join(parts)


def run(scenario: str, robots: int, faults: LinkFaults, *, tol: float, max_rounds: int, max_wall_s: float,
        retransmit_s: float = 0.02) -> Row:
    timing = Timing(retransmit_s=retransmit_s, dead_after_s=10.0, max_wall_s=max_wall_s, linger_s=1.0)
    _world, spec = build_world(Options(robots=robots, preset="paper", tol=tol, max_rounds=max_rounds, faults=faults, timing=timing,
                                       fleet_id=f"bench-{scenario.replace(' ', '-')}-{robots}-{int(time.time() * 1e3) % 100000}"))
    sim = simulate_fleet(spec)
    want = {r["id"]: r for r in sim.robots}
    with tempfile.TemporaryDirectory(prefix="shapefleet-bench-") as tmp:
        out = launch_fleet(spec, workdir=Path(tmp), crashes=[], restart_after=1.0, restart=True,
                           zenoh_port=None, progress=False)
    res = out.robots
    if len(res) != robots:
        raise RuntimeError(f"{scenario} N={robots}: only {len(res)} results ({out.states})")
    same = all(
        r["stopped"] == "finished"
        and r["trace"].keys() == want[r["id"]]["trace"].keys()
        and all(np.array_equal(r["trace"][k], want[r["id"]]["trace"][k]) for k in r["trace"])
        for r in res
    )
    rounds = max(r["rounds"] for r in res)
    medians = [r["round_ms"]["median"] for r in res if r["round_ms"]["median"] is not None]
    means = [r["round_ms"]["mean"] for r in res if r["round_ms"]["mean"] is not None]
    run_s = max(r["wall_s"] for r in res)
    sim_rounds = max(w["rounds"] for w in want.values())
    return Row(
        scenario, robots, _fault_text(faults), 1e3 * retransmit_s, rounds, all(r["converged"] for r in res),
        statistics.median(medians), statistics.fmean(means), 1e3 * run_s / max(rounds, 1), run_s, out.wall_s,
        1e3 * sim.wall_s / max(sim_rounds, 1),
        sum(r["frames_lost"] for r in res), sum(r["frames_sent"] for r in res), same,
    )


def table(rows: list[Row]) -> str:
    head = ("| scenario | N | faults | retransmit ms | rounds | converged | ms/round median | ms/round mean | run wall / rounds ms "
            "| run s | launch s | simulate ms/round | frames sent | lost | = simulate |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        lines.append(
            f"| {r.scenario} | {r.robots} | {r.faults} | {r.retransmit_ms:g} | {r.rounds} | {'yes' if r.converged else 'no (cap)'} "
            f"| {r.ms_median:.2f} | {r.ms_mean:.2f} | {r.ms_wall:.2f} | {r.run_s:.2f} | {r.launch_s:.2f} "
            f"| {r.sim_ms:.2f} | {r.sent} | {r.lost} | {'yes' if r.same else 'NO'} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="3,8,16", help="fleet sizes for the fixed-rounds runs (default 3,8,16)")
    ap.add_argument("--rounds", type=int, default=200, help="rounds of the fixed-rounds runs (default 200)")
    ap.add_argument("--tol", type=float, default=Options().tol, help="tolerance of the convergence runs")
    ap.add_argument("--max-wall", type=float, default=120.0, help="seconds, per run (robots' max_wall_s)")
    ap.add_argument("--slow-retransmit", type=float, default=0.1,
                    help="also run the largest fleet with this retransmit_s (default 0.1; 0: skip)")
    ap.add_argument("--quick", action="store_true", help="N = 3, 8 and 100 rounds; skip the loss 0.5 run")
    ap.add_argument("--no-write", action="store_true", help=f"do not write {RESULTS.relative_to(ROOT)}")
    args = ap.parse_args(argv)
    sizes = [3, 8] if args.quick else [int(s) for s in args.sizes.split(",")]
    rounds = 100 if args.quick else args.rounds

    rows: list[Row] = []
    started = time.perf_counter()
    for n in sizes:
        rows.append(run("fixed rounds", n, LinkFaults.none(), tol=1e-12, max_rounds=rounds, max_wall_s=args.max_wall))
        print(table(rows[-1:]).splitlines()[-1], flush=True)
    if max(sizes) > 8 and args.slow_retransmit > 0:  # see the note under the table
        rows.append(run("fixed rounds", max(sizes), LinkFaults.none(), tol=1e-12, max_rounds=rounds,
                        max_wall_s=args.max_wall, retransmit_s=args.slow_retransmit))
        print(table(rows[-1:]).splitlines()[-1], flush=True)
    conv = [("to convergence", LinkFaults.none()), ("to convergence", FAULTS)]
    if not args.quick:
        conv.append(("to convergence", LOSS50))
    for name, faults in conv:
        rows.append(run(name, 3, faults, tol=args.tol, max_rounds=DEFAULT_MAX_ROUNDS, max_wall_s=args.max_wall))
        print(table(rows[-1:]).splitlines()[-1], flush=True)

    text = "\n".join([
        "# Zenoh process fleet: ms per round and rounds under faults",
        "",
        f"`benchmarks/zenoh_fleet.py` on {platform.node() or 'this machine'} ({platform.machine()}, "
        f"{_cpus()} CPUs, Python {platform.python_version()}), {time.strftime('%Y-%m-%d')}; "
        f"total {time.perf_counter() - started:.0f} s.",
        "",
        "Default scenario (L-block, 20 points/robot, 5x3 grid, complete graph, rho 40, relax 1.95); one "
        "loopback Zenoh router, one process per robot (asyncio shell, express publisher, checkpoint every "
        "round, retransmit 20 ms). *ms/round*: each robot's advance-to-advance interval (median over the "
        "run, then median over robots; *mean*: mean of the robots' means). *run wall / rounds*: longest "
        "robot run (session open to result, including waiting for the last robot to come up and the final "
        "linger) divided by rounds. *launch s*: launch_fleet from router start to every process stopped. "
        f"Convergence runs: tol {args.tol:g}. *= simulate*: every iterate of every robot bit-identical to "
        "the in-process simulator.",
        "",
        table(rows),
        "",
        "Reference points: a bare Zenoh exchange among 3 processes costs ~0.5 ms/round on this machine "
        "(benchmarks/zenoh_exchange.py); an MPI-based ADMM framework spends ~12 ms/round on a 3-robot problem.",
        "",
        "Retransmission: a waiting robot resends its latest frame every `retransmit_s` (and sooner when a "
        "neighbour's frame shows it is a round behind). Once a round takes longer than `retransmit_s` -- "
        "a large complete graph on few cores -- every robot resends every round to all its neighbours, "
        "the extra frames cost CPU, rounds get slower still: compare *frames sent* with N x rounds, and "
        "the largest fleet with the default 20 ms and with a longer `retransmit_s` (`--retransmit`). "
        "The iterates are the same either way (= simulate); only the time changes.",
        "",
    ])
    print()
    print(table(rows))
    if not args.no_write:
        RESULTS.parent.mkdir(parents=True, exist_ok=True)
        RESULTS.write_text(text)
        print(f"\nwrote {RESULTS.relative_to(ROOT)}")
    return 0


def _cpus() -> int:
    import os

    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


if __name__ == "__main__":
    raise SystemExit(main())
