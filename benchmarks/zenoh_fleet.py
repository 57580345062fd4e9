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
    .venv/bin/python benchmarks/zenoh_fleet.py --threads 300 --base /tmp/main-copy \
        --variant-env SHAPEFLEET_ZENOH_INDIRECT=1          # CPU per process and thread class (/proc)
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import re
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
    topology: str = "complete"
    processes: int = 0
    cpu_ms: float = float("nan")  # robot processes' + router's CPU per round (every thread)
    first_round_s: float = float("nan")  # launch_fleet start -> the slowest robot's first round


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
        retransmit_s: float = 0.02, topology: str = "complete", per_process: str = "auto") -> Row:
    timing = Timing(retransmit_s=retransmit_s, dead_after_s=10.0, max_wall_s=max_wall_s, linger_s=1.0)
    _world, spec = build_world(Options(robots=robots, preset="paper", tol=tol, max_rounds=max_rounds, faults=faults, timing=timing,
                                       topology=topology,
                                       fleet_id=f"bench-{re.sub(r'[^A-Za-z0-9_-]+', '-', scenario)}-{robots}-{int(time.time() * 1e3) % 100000}"))
    sim = simulate_fleet(spec)
    want = {r["id"]: r for r in sim.robots}
    os.environ["SHAPEFLEET_PROFILE"] = "1"  # the robots' own CPU and marks (benchmarks/round_cost.py)
    try:
        with tempfile.TemporaryDirectory(prefix="shapefleet-bench-") as tmp:
            out = launch_fleet(spec, workdir=Path(tmp), crashes=[], restart_after=1.0, restart=True,
                               zenoh_port=None, progress=False, robots_per_process=per_process)
            profs = [json.loads(p.read_text()) for p in Path(tmp).glob("robot-*.json.profile.json")]
    finally:
        os.environ.pop("SHAPEFLEET_PROFILE", None)
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
    per_proc: dict[float, float] = {}  # process start -> its CPU per round (each process once)
    for p in profs:
        m = p["marks"]
        if "process_cpu_last" in m:
            per_proc[m.get("process", p["robot"])] = (m["process_cpu_last"] - m["process_cpu_first"]) / max(p["rounds"] - 1, 1)
    cpu_ms = 1e3 * (sum(per_proc.values()) + out.timeline.get("router_cpu_s", float("nan")) / max(rounds, 1))
    first = max((p["marks"].get("first_round", float("nan")) for p in profs), default=float("nan"))
    return Row(
        scenario, robots, _fault_text(faults), 1e3 * retransmit_s, rounds, all(r["converged"] for r in res),
        statistics.median(medians), statistics.fmean(means), 1e3 * run_s / max(rounds, 1), run_s, out.wall_s,
        1e3 * sim.wall_s / max(sim_rounds, 1),
        sum(r["frames_lost"] for r in res), sum(r["frames_sent"] for r in res), same,
        topology, len(per_proc), cpu_ms, first - out.timeline["launch"],
    )


def table(rows: list[Row], bare: float | None = None) -> str:
    head = ("| scenario | N | graph | procs | faults | rounds | converged | ms/round median | x bare | ms/round mean "
            "| CPU ms/round | run s | launch -> 1st round s | launch s | simulate ms/round | frames sent | lost | = simulate |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        ratio = f"{r.ms_median / bare:.1f}" if bare and r.robots == 3 else ""
        lines.append(
            f"| {r.scenario} | {r.robots} | {r.topology} | {r.processes} | {r.faults} | {r.rounds} "
            f"| {'yes' if r.converged else 'no (cap)'} | {r.ms_median:.2f} | {ratio} | {r.ms_mean:.2f} | {r.cpu_ms:.1f} "
            f"| {r.run_s:.2f} | {r.first_round_s:.2f} | {r.launch_s:.2f} "
            f"| {r.sim_ms:.2f} | {r.sent} | {r.lost} | {'yes' if r.same else 'NO'} |"
        )
    return "\n".join(lines)


def cli_launch(tree: Path, env: dict[str, str] | None = None) -> dict:
    """``python -m launcher.cli launch --preset paper`` from ``tree`` (another checkout, e.g. main
    exported with ``git archive``), timed from outside: wall seconds from the command's start to its
    end (pictures, result.json and every process stopped included), CPU seconds of it and of every
    process it started, rounds and the error against the exact solve."""
    import resource
    import subprocess

    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    load = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="shapefleet-cli-") as tmp:
        t = time.perf_counter()
        out = subprocess.run([sys.executable, "-m", "launcher.cli", "launch", "--preset", "paper", "--out", tmp],
                             cwd=tree, capture_output=True, text=True, timeout=300,
                             env={**os.environ, "PYTHONPATH": str(tree), **(env or {})})
        wall = time.perf_counter() - t
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        if out.returncode != 0:
            raise RuntimeError(f"launch in {tree} failed: {out.stderr.strip()[-500:]}")
        res = json.loads((Path(tmp) / "result.json").read_text())
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    round_ms = statistics.median(r["round_ms"]["median"] for r in res["robots"])  # issue 14's ms/round
    return {"wall_s": wall, "cpu_s": cpu, "rounds": res["rounds"], "error": res["metrics"]["function_error"],
            "load": load, "round_ms": round_ms, "digest": result_digest(res)}


def result_digest(res: dict) -> str:
    """sha256 (16 hex digits) of every robot's (id, c, gamma, rounds, residual, converged) in a
    result.json: equal digests = the same answers bit for bit."""
    h = hashlib.sha256()
    for r in sorted(res["robots"], key=lambda r: r["id"]):
        h.update(repr((r["id"], r["c"], r["gamma"], r["rounds"], r["residual"], r["converged"])).encode())
    return h.hexdigest()[:16]


def cli_launch_table(trees: list[tuple[str, Path, dict[str, str]]], runs: int, bare: float | None = None) -> str:
    """The whole `launch --preset paper` command, the trees alternating run by run (same minutes);
    with ``bare`` (ms) each median ms/round also as a ratio to the bare Zenoh exchange."""
    lines = ["| tree | wall s (each run) | median | CPU s, all processes (each run) | median | ms/round (each run) "
             "| median | load | rounds, error, digest |",
             "|---|---|---:|---|---:|---|---:|---|---|"]
    got: dict[str, list[dict]] = {label: [] for label, _t, _e in trees}
    for _ in range(runs):
        for label, tree, env in trees:
            got[label].append(cli_launch(tree, env))
    for label, runs_ in got.items():
        walls, cpus, ms = [r["wall_s"] for r in runs_], [r["cpu_s"] for r in runs_], [r["round_ms"] for r in runs_]
        outcomes = ", ".join(sorted({f"{r['rounds']} rounds, {r['error']:.6e}, `{r['digest']}`" for r in runs_}))
        lines.append(f"| {label} | {', '.join(f'{w:.2f}' for w in walls)} | **{statistics.median(walls):.2f}** "
                     f"| {', '.join(f'{c:.2f}' for c in cpus)} | {statistics.median(cpus):.2f} "
                     f"| {', '.join(f'{m:.3f}' for m in ms)} | {statistics.median(ms):.3f}"
                     f"{'' if bare is None else f' ({statistics.median(ms) / bare:.2f} x bare)'} "
                     f"| {min(r['load'] for r in runs_):.1f}-{max(r['load'] for r in runs_):.1f} "
                     f"| {outcomes} |")
    return "\n".join(lines)


#: run in a child interpreter (``python -c``, PYTHONPATH = the tree measured): `shapefleet launch
#: --preset paper --out OUT` as the program runs it (argv[0] "shapefleet": the early router
#: starts before the imports; the robots are forked from the launcher), with the launcher's phases marked on the robots' monotonic clock in
#: seconds from this process's start (/proc), and its own CPU at each mark; written to OUT/timeline.json
_TIMELINE_CHILD = r"""
import json, os, sys, threading, time
with open("/proc/self/stat") as f:
    ticks = int(f.read().rsplit(")", 1)[1].split()[19])
with open("/proc/uptime") as f:
    up = float(f.read().split()[0])
start = time.monotonic() - (up - ticks / os.sysconf("SC_CLK_TCK"))
out = sys.argv[1]
sys.argv = ["shapefleet", "launch", "--preset", "paper", "--out", out]
marks = {}
def mark(k):
    marks[k] = [time.monotonic() - start, time.process_time()]
import launcher.cli as cli
mark("cli imported")
from launcher import fleet, report
def wrap(mod, name):
    f = getattr(mod, name)
    def g(*a, **k):
        mark(name + " start"); r = f(*a, **k); mark(name + " end"); return r
    setattr(mod, name, g)
for mod, name in ((fleet, "launch_fleet"), (report, "write_json"), (report, "plot_shapes"),
                  (report, "plot_convergence"), (report, "_fork_drawing"), (report, "_wait_drawing")):
    if hasattr(mod, name):  # the last two: a tree that draws shapes.png in a forked child
        wrap(mod, name)
try:
    code = cli.main()
except SystemExit as e:
    code = e.code
mark("main returned")
robots = []
for name in os.listdir(os.path.join(out, "fleet")):
    if name.endswith(".profile.json"):
        with open(os.path.join(out, "fleet", name)) as f:
            robots.append({k: v - start for k, v in json.load(f)["marks"].items()
                           if k in ("imported", "adopted", "first_round", "last_round", "closed")})
with open(os.path.join(out, "timeline.json"), "w") as f:
    json.dump({"code": code, "launcher": marks, "robots": robots}, f)
"""


def cli_timeline(tree: Path) -> dict:
    """One `launch --preset paper` of ``tree`` with its timeline (_TIMELINE_CHILD): the launcher's
    phases and CPU, the slowest robot's marks, the wall and CPU of every process from outside."""
    import resource
    import subprocess

    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    load = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="shapefleet-timeline-") as tmp:
        t = time.perf_counter()
        done = subprocess.run([sys.executable, "-c", _TIMELINE_CHILD, tmp], cwd=tree, capture_output=True, text=True,
                              timeout=300, env={**os.environ, "PYTHONPATH": str(tree), "SHAPEFLEET_PROFILE": "1"})
        wall = time.perf_counter() - t
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        if done.returncode != 0:
            raise RuntimeError(f"launch in {tree} failed: {done.stderr.strip()[-500:]}")
        got = json.loads((Path(tmp) / "timeline.json").read_text())
    m = got["launcher"]
    slowest = {k: max(r[k] for r in got["robots"]) for k in ("imported", "first_round", "last_round", "closed")}
    return {
        "load": load, "wall": wall,
        "cpu_all": (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime),
        "imports": m["cli imported"][0], "robots_imported": slowest["imported"],
        "fleet_start": m["launch_fleet start"][0], "first_round": slowest["first_round"],
        "last_round": slowest["last_round"], "stopped": m["launch_fleet end"][0],
        "result_json": m["write_json end"][0],
        # drawn in a forked child (report.drawn_aside): from the fork to the end of the wait for it;
        # by the painter (report.Painter): the launcher's wait for it after result.json
        "shapes": _span(m, "plot_shapes start", "plot_shapes end") if "plot_shapes end" in m
        else _span(m, "_fork_drawing end" if "_fork_drawing end" in m else "_wait_drawing start", "_wait_drawing end"),
        "convergence": _span(m, "plot_convergence start", "plot_convergence end"),
        "pictures": max(m[k][0] for k in ("plot_shapes end", "plot_convergence end", "_wait_drawing end") if k in m),
        "returned": m["main returned"][0],
        "cpu_start": m["launch_fleet start"][1],
        "cpu_fleet": m["launch_fleet end"][1] - m["launch_fleet start"][1],
        "cpu_finish": m["main returned"][1] - m["launch_fleet end"][1],
    }


def _span(marks: dict, start: str, end: str) -> float:
    """Seconds between two marks of the timeline (nan when one is missing: drawn in another process)."""
    return marks[end][0] - marks[start][0] if start in marks and end in marks else float("nan")


_TIMELINE_COLUMNS = (
    ("load", "load"), ("imports", "launcher imported"), ("robots_imported", "robots imported"),
    ("fleet_start", "fleet handed over"), ("first_round", "first round"), ("last_round", "last round"),
    ("stopped", "every process stopped"), ("result_json", "result.json"), ("shapes", "shapes.png s"),
    ("convergence", "convergence.png s"), ("pictures", "pictures written"), ("returned", "main returns"), ("wall", "wall (outside)"),
    ("cpu_start", "launcher CPU to hand-over"), ("cpu_fleet", "launcher CPU during fleet"),
    ("cpu_finish", "launcher CPU after"), ("cpu_all", "CPU all processes"),
)


def cli_timeline_table(trees: list[tuple[str, Path]], runs: int) -> str:
    """Medians over ``runs`` timelines per tree, the trees alternating run by run; seconds from the
    launcher's process start (robots: the slowest), CPU seconds."""
    got: dict[str, list[dict]] = {label: [] for label, _t in trees}
    for _ in range(runs):
        for label, tree in trees:
            got[label].append(cli_timeline(tree))
    lines = ["| step | " + " | ".join(f"{label} (median of {runs})" for label, _t in trees) + " |",
             "|---|" + "---:|" * len(trees)]
    for key, title in _TIMELINE_COLUMNS:
        cells = []
        for label, _t in trees:
            values = [r[key] for r in got[label]]
            values = [v for v in values if v == v] or [float("nan")]  # nan: not in the launcher
            cells.append(f"{min(values):.1f}-{max(values):.1f}" if key == "load" else f"{statistics.median(values):.2f}")
        lines.append(f"| {title} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


_PROC_KINDS = ("robot", "router", "launcher")


def _task_stats(pid: int) -> dict[int, tuple[str, float, float, int, int]]:
    """``{tid: (name, user s, sys s, voluntary, involuntary context switches)}`` of ``pid`` (/proc)."""
    tick = os.sysconf("SC_CLK_TCK")
    out = {}
    for tdir in Path(f"/proc/{pid}/task").iterdir():
        try:
            stat = (tdir / "stat").read_text()
            status = (tdir / "status").read_text()
        except OSError:  # the thread ended
            continue
        rest = stat[stat.rindex(")") + 2:].split()
        sw = {k: int(v) for k, v in (ln.split(":") for ln in status.splitlines() if "ctxt_switches" in ln)}
        out[int(tdir.name)] = (stat[stat.index("(") + 1:stat.rindex(")")], int(rest[11]) / tick, int(rest[12]) / tick,
                               sw.get("voluntary_ctxt_switches", 0), sw.get("nonvoluntary_ctxt_switches", 0))
    return out


def _descendants(pid: int) -> list[int]:
    todo, seen = [pid], []
    while todo:
        p = todo.pop()
        seen.append(p)
        try:
            todo.extend(int(c) for c in Path(f"/proc/{p}/task/{p}/children").read_text().split())
        except OSError:
            pass
    return seen


def thread_cpu(tree: Path, robots: int, rounds: int, env: dict[str, str] | None = None) -> dict:
    """One ``launch --preset paper --robots N --topology geometric --max-rounds R`` from ``tree``,
    its processes' threads polled every 50 ms from /proc (the last reading of each thread counts):
    CPU user/sys and context switches per process kind (robot, router, launcher) and thread class
    (the Python loop's main thread, Zenoh's named runtime threads rx/tx/app/acc/net, other Python
    threads -- zenoh-python's callback threads among them). Linux only."""
    import subprocess

    with tempfile.TemporaryDirectory(prefix="shapefleet-threads-") as tmp:
        load = os.getloadavg()[0]
        t = time.perf_counter()
        proc = subprocess.Popen([sys.executable, "-m", "launcher.cli", "launch", "--preset", "paper", "--robots",
                                 str(robots), "--topology", "geometric", "--max-rounds", str(rounds), "--out", tmp],
                                cwd=tree, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                env={**os.environ, "PYTHONPATH": str(tree), **(env or {})})
        seen: dict[int, dict] = {}
        try:
            while proc.poll() is None and time.perf_counter() - t < 900:  # bounded
                for pid in _descendants(proc.pid):
                    try:
                        cmd = Path(f"/proc/{pid}/cmdline").read_bytes()
                        ent = seen.setdefault(pid, {"threads": {}})
                        ent["router"] = ent.get("router") or b"launcher.router" in cmd  # after its exec
                        ent["threads"].update(_task_stats(pid))
                    except OSError:
                        continue
                time.sleep(0.05)
        finally:
            if proc.poll() is None:
                proc.kill()
            proc.wait()
        wall = time.perf_counter() - t
        res = json.loads((Path(tmp) / "result.json").read_text())
    rows: dict[tuple[str, str], list[float]] = {}
    for pid, ent in seen.items():
        # the router: its command line once exec'd, or its acceptor threads (robots listen nowhere)
        router = ent["router"] or any(name.startswith("acc-") for name, *_ in ent["threads"].values())
        kind = "router" if router else "launcher" if pid == proc.pid else "robot"
        for tid, (name, u, s, v, n) in ent["threads"].items():
            cls = "main" if tid == pid else name.rstrip("0123456789-") if name.split("-")[0] in (
                "rx", "tx", "app", "acc", "net") else "python"
            row = rows.setdefault((kind, cls), [0.0, 0.0, 0, 0, 0])
            for i, x in enumerate((u, s, v, n, 1)):
                row[i] += x
    return {"wall_s": wall, "load": load, "rounds": res["rounds"], "error": res["metrics"]["function_error"],
            "digest": result_digest(res), "rows": rows,
            "round_ms": statistics.median(r["round_ms"]["median"] for r in res["robots"]),
            "sent": sum(r["frames_sent"] for r in res["robots"])}


def thread_cpu_table(variants: list[tuple[str, Path, dict[str, str]]], robots: int, rounds: int, runs: int) -> str:
    """:func:`thread_cpu` for each variant, alternating run by run; one table row per run and thread class."""
    lines = ["| variant | run | load | wall s | ms/round | frames sent | digest | process | threads | n "
             "| user s | sys s | CPU ms/round | switches vol. / invol. |",
             "|---|---:|---:|---:|---:|---:|---|---|---|---:|---:|---:|---:|---|"]
    for i in range(runs):
        for label, tree, env in variants:
            got = thread_cpu(tree, robots, rounds, env)
            head = (f"| {label} | {i + 1} | {got['load']:.1f} | {got['wall_s']:.2f} | {got['round_ms']:.2f} "
                    f"| {got['sent']} | `{got['digest']}` (err {got['error']:.6e}, {got['rounds']} rounds)")
            order = sorted(got["rows"], key=lambda k: (_PROC_KINDS.index(k[0]), k[1]))
            for kind in _PROC_KINDS:
                tot = [sum(got["rows"][k][j] for k in order if k[0] == kind) for j in range(5)]
                if tot[4]:
                    got["rows"][(kind, "**all**")] = tot
            order = sorted(got["rows"], key=lambda k: (_PROC_KINDS.index(k[0]), k[1]))
            for k in order:
                u, s, v, n, count = got["rows"][k]
                lines.append(f"{head} | {k[0]} | {k[1]} | {count} | {u:.2f} | {s:.2f} "
                             f"| {1000 * (u + s) / max(1, got['rounds']):.2f} | {v:,} / {n:,} |")
                head = "| | | | | | |"
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="3,8,16", help="fleet sizes for the fixed-rounds runs (default 3,8,16)")
    ap.add_argument("--rounds", type=int, default=200, help="rounds of the fixed-rounds runs (default 200)")
    ap.add_argument("--tol", type=float, default=Options().tol, help="tolerance of the convergence runs")
    ap.add_argument("--max-wall", type=float, default=120.0, help="seconds, per run (robots' max_wall_s)")
    ap.add_argument("--one-per-process", type=int, default=16,
                    help="also run this fixed-rounds size with one process per robot, as before issue 14 (0: skip)")
    ap.add_argument("--large", type=int, default=32, help="robots of the geometric-graph convergence run (0: skip)")
    ap.add_argument("--quick", action="store_true", help="N = 3, 8 and 100 rounds; skip the loss 0.5 and large runs")
    ap.add_argument("--no-write", action="store_true", help=f"do not write {RESULTS.relative_to(ROOT)}")
    ap.add_argument("--launch-runs", type=int, default=0,
                    help="only time the whole `launch --preset paper` command this many times (with --base: "
                         "alternating with another checkout), print the table and stop")
    ap.add_argument("--base", type=Path, default=None,
                    help="with --launch-runs or --timeline: a checkout to compare against")
    ap.add_argument("--timeline", type=int, default=0,
                    help="only run `launch --preset paper` this many times (with --base: alternating with another "
                         "checkout) with the launcher's phases and the robots' marks, print the medians and stop")
    ap.add_argument("--threads", type=int, default=0, metavar="ROUNDS",
                    help="only run `launch --preset paper --topology geometric --max-rounds ROUNDS` (with --base: "
                         "alternating with another checkout) and table CPU per process and thread class from /proc")
    ap.add_argument("--threads-robots", type=int, default=32, help="with --threads: robots (default 32)")
    ap.add_argument("--threads-runs", type=int, default=1, help="with --threads: alternations (default 1)")
    ap.add_argument("--variant-env", action="append", default=[], metavar="NAME=VALUE",
                    help="with --threads: also run this tree with this environment variable set (repeatable)")
    args = ap.parse_args(argv)
    if args.threads:
        variants = ([("base", args.base.resolve(), {})] if args.base else []) + [("this tree", ROOT, {})]
        for item in args.variant_env:
            name, sep, value = item.partition("=")
            if not sep or not name:
                ap.error(f"--variant-env: expected NAME=VALUE, got {item!r}")
            variants.append((f"this tree, {item}", ROOT, {name: value}))
        print(thread_cpu_table(variants, args.threads_robots, args.threads, args.threads_runs))
        return 0
    if args.timeline:
        trees = ([("base", args.base.resolve())] if args.base else []) + [("this tree", ROOT)]
        print(cli_timeline_table(trees, args.timeline))
        return 0
    if args.launch_runs:
        trees = ([("base", args.base.resolve(), {})] if args.base else []) + [("this tree", ROOT, {})]
        print(cli_launch_table(trees, args.launch_runs))
        return 0
    sizes = [3, 8] if args.quick else [int(s) for s in args.sizes.split(",")]
    rounds = 100 if args.quick else args.rounds
    from benchmarks.round_cost import bare_exchange

    load0 = os.getloadavg()
    rows: list[Row] = []
    started = time.perf_counter()
    bare = bare_exchange(3)
    print(f"bare exchange, 3 processes: p50 {bare} ms", flush=True)
    for n in sizes:
        rows.append(run("fixed rounds", n, LinkFaults.none(), tol=1e-12, max_rounds=rounds, max_wall_s=args.max_wall))
        print(table(rows[-1:], bare).splitlines()[-1], flush=True)
    if args.one_per_process and not args.quick:
        rows.append(run("fixed rounds, 1 robot/process", args.one_per_process, LinkFaults.none(), tol=1e-12,
                        max_rounds=rounds, max_wall_s=args.max_wall, per_process="1"))
        print(table(rows[-1:], bare).splitlines()[-1], flush=True)
    conv = [(3, "complete", LinkFaults.none()), (3, "complete", FAULTS)]
    if not args.quick:
        conv.append((3, "complete", LOSS50))
        if args.large:
            conv.append((args.large, "geometric", LinkFaults.none()))
    for n, topo, faults in conv:
        rows.append(run("to convergence", n, faults, tol=args.tol, max_rounds=DEFAULT_MAX_ROUNDS, max_wall_s=args.max_wall,
                        topology=topo))
        print(table(rows[-1:], bare).splitlines()[-1], flush=True)
    # issue 14's 3-robot figure as a user meets it: the whole `launch --preset paper` command, several
    # runs (one run's median swings by several percent; the rows above also carry the profiling marks)
    paper_line = ("3 robots, the whole `shapefleet launch --preset paper` command (no profiling marks):\n\n"
                  + cli_launch_table([("this tree", ROOT, {})], 3 if args.quick else 6, bare))
    print(paper_line, flush=True)
    load1 = os.getloadavg()

    text = "\n".join([
        "# Zenoh process fleet: ms per round and rounds under faults",
        "",
        f"`benchmarks/zenoh_fleet.py` on {platform.node() or 'this machine'} ({platform.machine()}, "
        f"{_cpus()} CPUs, Python {platform.python_version()}), {time.strftime('%Y-%m-%d %H:%M')}; "
        f"total {time.perf_counter() - started:.0f} s; load average {load0[0]:.1f} at the start, {load1[0]:.1f} "
        "at the end (anything else running inflates the wall-clock figures, ms/round and s; rounds and = simulate "
        "do not move).",
        "",
        "Default scenario (L-block, 20 points/robot, 5x3 grid, paper preset); one loopback Zenoh router; "
        "robots as processes chosen by `--robots-per-process auto` (one per robot up to 2 per core, else one "
        "process per core, robots of a process sharing one Zenoh session; *procs*), asyncio shell, express "
        "publisher, checkpoint every round (one pwrite) where a process hosts part of the fleet, every 16 rounds where it hosts all of it, retransmit 20 ms. *ms/round*: each robot's "
        "advance-to-advance interval (median over the run, then median over robots; *mean*: mean of the "
        "robots' means). *x bare*: ratio to the bare Zenoh exchange among 3 processes measured in the same run "
        f"({'n/a' if bare is None else f'{bare:.3f} ms p50'}, benchmarks/zenoh_exchange.py). *CPU ms/round*: "
        "CPU time of every robot process (all threads) between its first and last round, per round, plus the "
        "router's over the run / rounds. *run s*: longest robot run (session open to result). "
        "*launch -> 1st round s*: from launch_fleet's start to the slowest robot's first round. *launch s*: "
        "launch_fleet from start to every process stopped. Convergence runs: tol "
        f"{args.tol:g}. *= simulate*: every iterate of every robot bit-identical to the in-process simulator.",
        "",
        table(rows, bare),
        "",
        paper_line,
        "",
        "Before issue 14 (same machine, 2026-11-22, one process per robot, checkpoint by tmp file + rename, a "
        "status line per round, robots started after the router): 3 robots 2.70 ms/round, 8 robots 24.9, 16 robots "
        "114.6 (launch 32.4 s for 200 rounds), 3 robots to convergence launch 3.18 s.",
        "",
    ])
    print()
    print(table(rows, bare))
    if not args.no_write:
        RESULTS.parent.mkdir(parents=True, exist_ok=True)
        RESULTS.write_text(text)
        print(f"\nwrote {RESULTS.relative_to(ROOT)}")
    return 0


def _cpus() -> int:
    from launcher.cores import usable_cores

    return usable_cores()


if __name__ == "__main__":
    raise SystemExit(main())
