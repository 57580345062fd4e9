"""Where a robot process's time goes: per-round phases and the start-up / shut-down timeline.

Runs ``launcher.fleet.launch_fleet`` on the paper preset (3 robots, complete graph, 5x3 grid) for
a fixed number of rounds (``tol`` tiny) with ``SHAPEFLEET_PROFILE=1``: every robot shell then writes
``robot-I.json.profile.json`` beside its result (agents/robot.py ``RobotShell.profile`` and
``marks``). It prints, per round and averaged over the robots:

* receive    -- Zenoh sample -> fault link -> frame decode/auth/dedup -> core.receive (loop side);
* checkpoint -- the crash-safe checkpoint written before each advance;
* advance    -- core.advance(): the local QP solve and the ADMM updates, plus the frame encode;
* send       -- publisher.put of the new frame;
* status     -- the JSON status line to the launcher;
* wait       -- awaiting the neighbours' frames (idle, or other callbacks of the loop);
* other      -- the rest of the loop (timers, deadlines, asyncio bookkeeping),

and the timeline from ``launch`` to the first round and to every process stopped, split into the
launcher's part (router, spawning, stopping) and the robot's (interpreter + imports, core build,
session open, first round, linger, close). Then it runs the bare exchange among the same number of
processes (benchmarks/zenoh_exchange.py, ``asyncio`` variant) and prints the ratio.

    .venv/bin/python benchmarks/round_cost.py                 # 3 robots, 300 rounds
    .venv/bin/python benchmarks/round_cost.py --robots 8 --robots-per-process 4
    .venv/bin/python benchmarks/round_cost.py --compute --base /tmp/main-copy --repeats 2
    .venv/bin/python benchmarks/round_cost.py --in-process --base /tmp/main-copy --repeats 2
    .venv/bin/python benchmarks/round_cost.py --frames --base /tmp/main-copy --repeats 3
    .venv/bin/python benchmarks/round_cost.py --in-process --advance --base /tmp/main-copy --repeats 8

``--compute`` measures the core's cost instead (the "compute per round" section of
results/round_cost.md): the default run (autogrid, 3 robots, complete graph) in process --
``simulate_fleet`` alone, no report or plots -- as process CPU seconds, rounds and CPU ms per
fleet round, then ``launch`` of the same run (3 robot processes + router over loopback Zenoh, what
``make demo`` runs) as wall seconds. With ``--base`` (another checkout, e.g. an export of main:
``git archive main | tar -x -C DIR``) every measurement alternates between that tree and this
one, run back to back with the same interpreter, so that the load of the shared machine hits
both alike; the load average is printed beside each figure.

``--in-process`` measures the per-round compute of the paper preset the same way (3 robots to
convergence, 16 robots for 60 rounds; CPU ms per fleet round), this tree also with the hub's
shared step off (what a process hosting one robot computes; agents/admm.py SHARED_STEPS_KEPT),
with a digest of every robot's result (both trees must print the same). With ``--robots N``
(and ``--rounds``, ``--topology``) it measures that one fleet instead, every round run (``tol``
1e-14), sharing on: ``--in-process --robots 32 --rounds 300 --topology geometric``.
``--in-process --interleaved --base DIR`` loads both trees into one process and alternates their
runs of ``--robots`` (``--rounds``, every round run, ``--repeats`` pairs; ``--no-sharing``: the hub
step computed by every robot, as a process hosting one robot does): thread CPU per fleet round and
the ratio within each pair, which a machine shared with other jobs leaves far steadier than runs in
separate processes (branch corecost, results/round_cost.md).
``--in-process --advance --base DIR`` does the same for the core's ``RoundCore.advance`` alone (thread
CPU per fleet round, beside the whole loop's), each tree's fleet of ``--robots`` run to its own stop at
``--tol`` (default 1e-3): a change that moves the bits (branch core3's warm KKT solve) may move the
rounds, so each tree's rounds and result digest are printed.

``--frames`` measures the per-frame receive path (issue 14, branch framecost): the in-process fleet
of ``--robots`` (32 here unless given) on the geometric graph for ``--rounds`` (200 here unless
given) rounds -- ``simulate_fleet``'s process CPU per received frame -- and the frames it received
replayed through fresh authenticated decoders and through the link layer (best of 3 each), with a
digest of the robots' final values (the trees must agree bit for bit).

Bounded: every run has ``max_wall_s`` and the launcher's own time bound.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from agents.spec import Timing  # noqa: E402
from launcher.fleet import launch_fleet  # noqa: E402
from launcher.world import Options, build_world  # noqa: E402

PHASES = ("receive", "checkpoint", "advance", "send", "status", "wait")
RESULTS = ROOT / "benchmarks" / "results" / "round_cost.md"


def profile_run(robots: int, rounds: int, *, topology: str | None = None, per_process: int | None = None,
                max_wall_s: float = 120.0, preset: str = "paper") -> dict:
    """One profiled launch: phase ms per round (mean over robots), timeline, round ms median."""
    timing = Timing(retransmit_s=0.02, dead_after_s=10.0, max_wall_s=max_wall_s, linger_s=1.0)
    extra = {} if topology is None else {"topology": topology}
    _world, spec = build_world(Options(robots=robots, preset=preset, tol=1e-12, max_rounds=rounds, timing=timing,
                                       fleet_id=f"cost-{robots}-{int(time.time() * 1e3) % 100000}", **extra))
    os.environ["SHAPEFLEET_PROFILE"] = "1"
    kw = {} if per_process is None else {"robots_per_process": per_process}
    try:
        with tempfile.TemporaryDirectory(prefix="shapefleet-cost-") as tmp:
            out = launch_fleet(spec, workdir=Path(tmp), crashes=[], restart_after=1.0, restart=True,
                               zenoh_port=None, progress=False, **kw)
            profs = [json.loads(p.read_text()) for p in sorted(Path(tmp).glob("robot-*.json.profile.json"))]
    finally:
        os.environ.pop("SHAPEFLEET_PROFILE", None)
    if len(out.robots) != robots or len(profs) != robots:
        raise RuntimeError(f"{robots} robots: {len(out.robots)} results, {len(profs)} profiles ({out.states})")
    medians = [r["round_ms"]["median"] for r in out.robots]
    n = [max(p["rounds"] - 1, 1) for p in profs]
    phase_ms, cpu_ms = {}, {}
    for ph in PHASES:
        phase_ms[ph] = statistics.fmean(1e3 * p["phases_s"][ph] / k for p, k in zip(profs, n))
        if ph != "wait":
            cpu_ms[ph] = statistics.fmean(1e3 * p["phases_s"][ph + ":cpu"] / k for p, k in zip(profs, n))
    run_ms = statistics.fmean(1e3 * (p["marks"]["last_round"] - p["marks"]["first_round"]) / k
                              for p, k in zip(profs, n))
    phase_ms["wait"] -= phase_ms["receive"]  # frames are received by callbacks run while we wait
    phase_ms["other"] = run_ms - sum(phase_ms.values())
    # CPU of whole processes per round (every thread: Zenoh's too), summed over processes, and the
    # router's over the whole run divided by the rounds
    seen: dict[float, float] = {}
    for p, k in zip(profs, n):
        m = p["marks"]
        seen[m["process"]] = 1e3 * (m["process_cpu_last"] - m["process_cpu_first"]) / k
    fleet_cpu_ms = sum(seen.values())
    rounds_run = max(r["rounds"] for r in out.robots)
    router_cpu_ms = 1e3 * out.timeline.get("router_cpu_s", float("nan")) / max(rounds_run, 1)
    tl = out.timeline
    marks = [p["marks"] for p in profs]

    def span(a: str, b: str) -> float:
        return max(m[b] - m[a] for m in marks)

    timeline = {
        "launch -> robot processes spawned": tl["robots_started"] - tl["launch"],
        "launch -> router ready": tl["router_ready"] - tl["launch"],
        "robot: interpreter start -> robot shell imported": span("process", "imported"),
        "robot: -> algorithms imported (agents.spec)": span("imported", "algorithms_imported"),
        "robot: -> core built (first local solve)": span("algorithms_imported", "shell"),
        "robot: -> Zenoh session open": span("shell", "session_open"),
        "robot: -> first round (declare, wait for the neighbours)": span("session_open", "first_round"),
        "launch -> first round (slowest robot)": max(m["first_round"] for m in marks) - tl["launch"],
        "rounds (first -> last, slowest robot)": span("first_round", "last_round"),
        "last round -> drive done (linger)": span("last_round", "done"),
        "drive done -> session closed": span("done", "closed"),
        "every robot exited -> every process stopped (router)": tl["stopped"] - tl["robots_exited"],
        "launch -> every process stopped": tl["stopped"] - tl["launch"],
    }
    resends: dict[str, int] = {}
    for p in profs:
        for k, v in p.get("resends", {}).items():
            resends[k] = resends.get(k, 0) + v
    frames = sum(r["frames_sent"] for r in out.robots)
    wakeups = sum(p.get("wakeups", 0) for p in profs) / max(sum(p["rounds"] for p in profs), 1)
    return {"robots": robots, "rounds": rounds_run, "round_ms_median": statistics.median(medians),
            "resends": resends, "frames_per_robot_round": frames / max(robots * (rounds_run + 1), 1),
            "phase_ms": phase_ms, "cpu_ms": cpu_ms, "run_ms": run_ms, "timeline": timeline, "wall_s": out.wall_s,
            "per_process": per_process, "fleet_cpu_ms": fleet_cpu_ms, "router_cpu_ms": router_cpu_ms,
            "processes": len(seen), "wakeups_per_round": wakeups}


def bare_exchange(robots: int, rounds: int = 500) -> float | None:
    """p50 ms/round of the bare Zenoh exchange among ``robots`` processes (None if it failed)."""
    try:
        out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "zenoh_exchange.py"), "--robots", str(robots),
                              "--rounds", str(rounds), "--variants", "asyncio", "--json", "--timeout", "60"],
                             capture_output=True, text=True, timeout=150, cwd=ROOT)
        return float(json.loads(out.stdout.strip().splitlines()[-1])["p50_ms"])
    except (subprocess.SubprocessError, ValueError, IndexError, KeyError):
        return None


def render(res: dict, bare: float | None, label: str) -> str:
    lines = [f"### {label}", "",
             f"{res['robots']} robots in {res['processes']} process(es), {res['rounds']} rounds; robots' round time, "
             f"median of medians: **{res['round_ms_median']:.3f} ms**"
             + (f"; bare exchange p50 {bare:.3f} ms, ratio **{res['round_ms_median'] / bare:.2f}**" if bare else ""),
             f"CPU per round: robot processes {res['fleet_cpu_ms']:.3f} ms (all threads, summed), router "
             f"{res['router_cpu_ms']:.3f} ms (whole run / rounds)",
             f"frames sent per robot-round {res['frames_per_robot_round']:.2f}; main-loop wake-ups per robot-round "
             f"{res.get('wakeups_per_round', float('nan')):.2f}; resends by cause "
             f"{res['resends'] or 'none'}",
             "", "| phase | wall ms/round (mean over robots) | share | main-thread CPU ms/round |", "|---|---:|---:|---:|"]
    total = res["run_ms"]
    for ph, ms in res["phase_ms"].items():
        cpu = res["cpu_ms"].get(ph)
        lines.append(f"| {ph} | {ms:.3f} | {100 * ms / total:.0f} % | {'' if cpu is None else f'{cpu:.3f}'} |")
    lines.append(f"| **round (first -> last / rounds)** | **{total:.3f}** | | **{sum(res['cpu_ms'].values()):.3f}** |")
    lines += ["", "| start-up / shut-down | s |", "|---|---:|"]
    lines += [f"| {k} | {v:.3f} |" for k, v in res["timeline"].items()]
    return "\n".join(lines)


COMPUTE_SNIPPET = """
import json, os, sys, time
sys.path.insert(0, os.getcwd())
from launcher.simulate import simulate_fleet
from launcher.world import Options, build_world
_, spec = build_world(Options(fleet_id="compute"))
cpu, wall = time.process_time(), time.perf_counter()
out = simulate_fleet(spec)
cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
print(json.dumps({"cpu_s": cpu, "wall_s": wall, "rounds": max(r["rounds"] for r in out.robots)}))
"""


def _compute_run(tree: Path) -> dict:
    """CPU of the default run's ``simulate_fleet`` in a fresh interpreter importing ``tree``."""
    load = os.getloadavg()[0]
    out = subprocess.run([sys.executable, "-c", COMPUTE_SNIPPET], cwd=tree, capture_output=True, text=True,
                         timeout=600, env={**os.environ, "PYTHONPATH": str(tree)})
    if out.returncode != 0:
        raise RuntimeError(f"compute run in {tree} failed: {out.stderr.strip()[-500:]}")
    return {**json.loads(out.stdout.strip().splitlines()[-1]), "load": load}


def _launch_run(tree: Path) -> dict:
    """Wall seconds of ``launch`` (the default run, what ``make demo`` starts) from ``tree``."""
    load = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="shapefleet-demo-") as tmp:
        t = time.perf_counter()
        out = subprocess.run([sys.executable, "-m", "launcher.cli", "launch", "--out", tmp], cwd=tree,
                             capture_output=True, text=True, timeout=600, env={**os.environ, "PYTHONPATH": str(tree)})
        wall = time.perf_counter() - t
        rounds = json.loads((Path(tmp) / "result.json").read_text())["rounds"] if out.returncode == 0 else None
    if out.returncode != 0:
        raise RuntimeError(f"launch in {tree} failed: {out.stderr.strip()[-500:]}")
    return {"wall_s": wall, "rounds": rounds, "load": load}


def compute_table(base: Path | None, repeats: int, demo: bool) -> str:
    """Markdown rows: per tree and repeat, in-process CPU and rounds, and launch wall time."""
    trees = ([("before", base)] if base else []) + [("after", ROOT)]
    lines = ["| tree | run | rounds | simulate_fleet CPU s | CPU ms per fleet round | load | launch wall s | rounds | load |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    print("\n".join(lines), flush=True)
    for k in range(repeats):
        for label, tree in trees:
            c = _compute_run(tree)
            row = (f"| {label} | {k + 1} | {c['rounds']} | {c['cpu_s']:.2f} | {1e3 * c['cpu_s'] / c['rounds']:.1f} "
                   f"| {c['load']:.1f} |")
            if demo:
                d = _launch_run(tree)
                row += f" {d['wall_s']:.1f} | {d['rounds']} | {d['load']:.1f} |"
            else:
                row += " | | |"
            lines.append(row)
            print(row, flush=True)
    return "\n".join(lines)


PER_ROUND_SNIPPET = """
import json, os, sys, time
sys.path.insert(0, os.getcwd())
import agents.admm as admm
from launcher.simulate import simulate_fleet
from launcher.world import Options, build_world
robots, rounds, share = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3] == "1"
if not share and hasattr(admm, "SHARED_STEPS_KEPT"):
    admm.SHARED_STEPS_KEPT = 0
kw = {} if rounds <= 0 else {"max_rounds": rounds, "tol": 1e-12}
if len(sys.argv) > 4:  # one named fleet (--robots): its topology, every round run
    kw.update(topology=sys.argv[4], tol=1e-14)
_, spec = build_world(Options(fleet_id="per-round", preset="paper", robots=robots, **kw))
simulate_fleet(spec)  # warm: first-call imports and caches
cpu = time.process_time()
out = simulate_fleet(spec)
cpu = time.process_time() - cpu
import hashlib
h = hashlib.sha256()  # every robot's final (x, gamma), rounds, residual and how it stopped: trees must agree
for r in sorted(out.robots, key=lambda r: r["id"]):
    h.update(repr((r["id"], r["x"], r["gamma"], r["rounds"], r["residual"], r["converged"])).encode())
print(json.dumps({"cpu_s": cpu, "rounds": max(r["rounds"] for r in out.robots), "digest": h.hexdigest()[:16]}))
"""


def per_round_table(base: Path | None, sizes: list[tuple[int, int]], repeats: int, *, topology: str | None = None,
                    unshared: bool = True) -> str:
    """In-process CPU per fleet round of the paper preset (``simulate_fleet``, no report), per tree,
    with a digest of the result (the trees must agree bit for bit); with ``unshared`` this tree
    also with the hub's shared step turned off (agents/admm.py SHARED_STEPS_KEPT = 0: what one
    robot per process computes)."""
    runs = (([("before", base, True)] if base else []) + [("after", ROOT, True)]
            + ([("after, no sharing", ROOT, False)] if unshared else []))
    lines = ["| robots | rounds | tree | CPU ms per fleet round | per robot-round | result digest | load |",
             "|---:|---:|---|---:|---:|---|---:|"]
    print("\n".join(lines), flush=True)
    for robots, rounds in sizes:
        for _ in range(repeats):
            for label, tree, share in runs:
                load = os.getloadavg()[0]
                argv = [str(robots), str(rounds), "1" if share else "0"] + ([topology or "complete"] if not unshared else [])
                out = subprocess.run([sys.executable, "-c", PER_ROUND_SNIPPET, *argv],
                                     cwd=tree, capture_output=True, text=True, timeout=900,
                                     env={**os.environ, "PYTHONPATH": str(tree)})
                if out.returncode != 0:
                    raise RuntimeError(f"in-process run in {tree} failed: {out.stderr.strip()[-500:]}")
                got = json.loads(out.stdout.strip().splitlines()[-1])
                ms = 1e3 * got["cpu_s"] / got["rounds"]
                lines.append(f"| {robots} | {got['rounds']} | {label} | {ms:.2f} | {ms / robots:.3f} | `{got['digest']}` "
                             f"| {load:.1f} |")
                print(lines[-1], flush=True)
    return "\n".join(lines)


#: both trees' modules loaded into one process, one tree after the other (the snippets below)
TREE_LOADER = """
import hashlib, importlib, json, os, statistics, sys, time
def load(tree):  # a tree's modules under their own names, then out of sys.modules for the next tree
    for m in [m for m in sys.modules if m.split(".")[0] in ("agents", "protocol", "launcher")]:
        del sys.modules[m]
    sys.path.insert(0, tree)
    mods = [importlib.import_module(m) for m in ("launcher.simulate", "launcher.world", "agents.admm")]
    sys.path.remove(tree)
    return mods
"""

INTERLEAVED_SNIPPET = TREE_LOADER + """robots, rounds, reps, share, trees = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), sys.argv[4] == "1", sys.argv[5:]
runs = []
for tree in trees:
    sim, world, admm = load(tree)
    if not share:
        admm.SHARED_STEPS_KEPT = 0
    kw = {"preset": "paper", "robots": robots, "max_rounds": rounds, "tol": 1e-300}
    if robots > 16:
        kw["topology"] = "geometric"
    spec = world.build_world(world.Options(fleet_id="interleaved", **kw))[1]
    out = sim.simulate_fleet(spec)  # warm, and the digest
    h = hashlib.sha256(repr([(r["id"], r["x"], r["gamma"], r["rounds"], r["residual"]) for r in out.robots]).encode())
    runs.append((sim.simulate_fleet, spec, max(r["rounds"] for r in out.robots), h.hexdigest()[:16]))
ms, loads = [[] for _ in trees], []
for i in range(reps):
    for k in (range(len(trees)) if i % 2 == 0 else reversed(range(len(trees)))):
        fn, spec, n, _ = runs[k]
        t = time.thread_time()
        fn(spec)
        ms[k].append(1e3 * (time.thread_time() - t) / n)
    loads.append(os.getloadavg()[0])
print(json.dumps({"ms": ms, "rounds": [r[2] for r in runs], "digests": [r[3] for r in runs], "load": [min(loads), max(loads)]}))
"""


def interleaved_table(base: Path, robots: int, rounds: int, repeats: int, share: bool) -> str:
    """Both trees in ONE process, their `simulate_fleet` runs alternating (thread CPU per fleet round,
    every round run): the other helpers' load then hits both alike within each pair, which separate
    processes minutes apart do not. Per pair the ratio before/after; the digests must agree."""
    out = subprocess.run([sys.executable, "-c", INTERLEAVED_SNIPPET, str(robots), str(rounds), str(repeats),
                          "1" if share else "0", str(base), str(ROOT)], capture_output=True, text=True, timeout=3600)
    if out.returncode != 0:
        raise RuntimeError(f"interleaved run failed: {out.stderr.strip()[-500:]}")
    got = json.loads(out.stdout.strip().splitlines()[-1])
    (before, after), ratios = got["ms"], [b / a for b, a in zip(*got["ms"])]
    lines = ["| robots | rounds | sharing | before ms/fleet round (min, median) | after | ratio per pair (min, median, max) "
             "| digests | load |", "|---:|---:|---|---:|---:|---:|---|---:|",
             f"| {robots} | {got['rounds'][1]} | {'on' if share else 'off'} | {min(before):.3f}, {statistics.median(before):.3f} "
             f"| {min(after):.3f}, {statistics.median(after):.3f} | {min(ratios):.3f}, {statistics.median(ratios):.3f}, "
             f"{max(ratios):.3f} | `{got['digests'][0]}` / `{got['digests'][1]}` | {got['load'][0]:.1f}-{got['load'][1]:.1f} |"]
    print("\n".join(lines), flush=True)
    return "\n".join(lines)


FRAMES_SNIPPET = """
import gc, hashlib, json, os, sys, time
sys.path.insert(0, os.getcwd())
import numpy as np
from launcher.simulate import simulate_fleet
from launcher.world import Options, build_world
from protocol import frames
from protocol.auth import FrameAuth
from protocol.links import LinkLayer
from protocol.session import RobotSession
robots, rounds = int(sys.argv[1]), int(sys.argv[2])
_, spec = build_world(Options(fleet_id="frames", preset="paper", robots=robots, topology="geometric",
                              max_rounds=rounds, tol=1e-12))
log = []  # (receiver, source, payload, now) of every frame the fleet's sessions received
orig = RobotSession.receive
def rec(self, source, payload, now):
    log.append((self.me, source, payload, now))
    return orig(self, source, payload, now)
RobotSession.receive = rec
simulate_fleet(spec)  # warm-up run, recording the frames for the replays below
RobotSession.receive = orig
gc.collect()
cpu = time.process_time()
out = simulate_fleet(spec)
cpu = time.process_time() - cpu
h = hashlib.sha256()
for r in sorted(out.robots, key=lambda r: r["id"]):
    h.update(np.asarray(r["x"] + [r["gamma"]], "<f8").tobytes())
def replay_decode():
    frames._MEMO = frames._ParseMemo()
    decs = {r: frames.FrameDecoder(spec.fleet, spec.robot_ids, spec.dim, spec.config_tag, auth=spec.frame_auth(r))
            for r in spec.robot_ids}
    t = time.process_time()
    for me, src, payload, now in log:
        decs[me].decode(payload, expected_sender=src)
    t = time.process_time() - t
    assert sum(d.accepted for d in decs.values()) == len(log)
    return t
def replay_links():
    links, n = LinkLayer(spec.faults, spec.seed), 0
    t = time.process_time()
    for i, (me, src, payload, now) in enumerate(log):
        links.send(src, me, payload, now)
        if i % 512 == 511:
            n += len(links.deliver(now))
    n += len(links.deliver(float("inf")))
    t = time.process_time() - t
    assert n == len(log)
    return t
dec = min(replay_decode() for _ in range(3))
lnk = min(replay_links() for _ in range(3))
print(json.dumps({"cpu_s": cpu, "rounds": max(r["rounds"] for r in out.robots), "frames": len(log),
                  "decode_us": 1e6 * dec / len(log), "links_us": 1e6 * lnk / len(log), "digest": h.hexdigest()[:16]}))
"""


def frames_table(base: Path | None, robots: int, rounds: int, repeats: int) -> str:
    """CPU of the in-process fleet (geometric graph, paper preset, a fixed number of rounds) per
    tree: the whole ``simulate_fleet``, and the frames it received replayed through fresh
    decoders (authenticate, check, equivocation, fresh arrays) and through the link layer."""
    trees = ([("before", base)] if base else []) + [("after", ROOT)]
    lines = ["| robots | rounds | tree | frames received | simulate_fleet CPU s | us per frame received | "
             "replay: decode us/frame | replay: links us/frame | result digest | load |",
             "|---:|---:|---|---:|---:|---:|---:|---:|---|---:|"]
    print("\n".join(lines), flush=True)
    for _ in range(repeats):
        for label, tree in trees:
            load = os.getloadavg()[0]
            out = subprocess.run([sys.executable, "-c", FRAMES_SNIPPET, str(robots), str(rounds)], cwd=tree,
                                 capture_output=True, text=True, timeout=900, env={**os.environ, "PYTHONPATH": str(tree)})
            if out.returncode != 0:
                raise RuntimeError(f"frames run in {tree} failed: {out.stderr.strip()[-500:]}")
            g = json.loads(out.stdout.strip().splitlines()[-1])
            lines.append(f"| {robots} | {g['rounds']} | {label} | {g['frames']} | {g['cpu_s']:.2f} | "
                         f"{1e6 * g['cpu_s'] / g['frames']:.1f} | {g['decode_us']:.2f} | {g['links_us']:.2f} | "
                         f"`{g['digest']}` | {load:.1f} |")
            print(lines[-1], flush=True)
    return "\n".join(lines)


ADVANCE_SNIPPET = TREE_LOADER + """
robots, tol, reps, trees = int(sys.argv[1]), float(sys.argv[2]), int(sys.argv[3]), sys.argv[4:]
runs = []
for tree in trees:
    sim, world, admm = load(tree)
    spent = [0]
    def timed(self, orig=admm.RoundCore.advance, spent=spent):  # the core's advance, thread CPU
        t = time.thread_time_ns()
        try:
            return orig(self)
        finally:
            spent[0] += time.thread_time_ns() - t
    admm.RoundCore.advance = timed
    spec = world.build_world(world.Options(fleet_id="advance", preset="paper", robots=robots, tol=tol,
                                           max_rounds=5000))[1]
    out = sim.simulate_fleet(spec)  # warm, rounds and the digest
    h = hashlib.sha256(repr([(r["id"], r["x"], r["gamma"], r["rounds"], r["residual"]) for r in out.robots]).encode())
    runs.append((sim.simulate_fleet, spec, max(r["rounds"] for r in out.robots), h.hexdigest()[:16], spent))
adv, whole, loads = [[] for _ in trees], [[] for _ in trees], []
for i in range(reps):
    for k in (range(len(trees)) if i % 2 == 0 else reversed(range(len(trees)))):
        fn, spec, n, _, spent = runs[k]
        spent[0] = 0
        t = time.thread_time_ns()
        fn(spec)
        whole[k].append((time.thread_time_ns() - t) / 1e6 / n)
        adv[k].append(spent[0] / 1e6 / n)
    loads.append(os.getloadavg()[0])
print(json.dumps({"advance": adv, "whole": whole, "rounds": [r[2] for r in runs], "digests": [r[3] for r in runs],
                  "load": [min(loads), max(loads)]}))
"""


def advance_table(base: Path, robots: int, tol: float, repeats: int) -> str:
    """The core's `RoundCore.advance` (and the whole `simulate_fleet` loop) in thread CPU per fleet
    round, both trees in one process, runs alternating, each fleet run to its own stop at ``tol``
    (issue 14's core3 pass: a change that moves the bits may move the rounds too, so each tree
    runs its own number; both are printed with the results' digests)."""
    out = subprocess.run([sys.executable, "-c", ADVANCE_SNIPPET, str(robots), repr(tol), str(repeats), str(base),
                          str(ROOT)], capture_output=True, text=True, timeout=3600)
    if out.returncode != 0:
        raise RuntimeError(f"advance run failed: {out.stderr.strip()[-500:]}")
    got = json.loads(out.stdout.strip().splitlines()[-1])
    (b_adv, a_adv), (b_all, a_all) = got["advance"], got["whole"]
    ratios = sorted(b / a for b, a in zip(b_adv, a_adv))
    med = statistics.median
    lines = ["| robots | tol | rounds before / after | advance ms/fleet round before (min, median) | after | ratio per pair "
             "(min, median, max) | whole loop before / after (median) | digests | load |",
             "|---:|---:|---|---:|---:|---:|---|---|---:|",
             f"| {robots} | {tol:g} | {got['rounds'][0]} / {got['rounds'][1]} | {min(b_adv):.3f}, {med(b_adv):.3f} "
             f"| {min(a_adv):.3f}, {med(a_adv):.3f} | {ratios[0]:.3f}, {med(ratios):.3f}, {ratios[-1]:.3f} "
             f"| {med(b_all):.3f} / {med(a_all):.3f} | `{got['digests'][0]}` / `{got['digests'][1]}` "
             f"| {got['load'][0]:.1f}-{got['load'][1]:.1f} |"]
    print("\n".join(lines), flush=True)
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", type=int, default=3)
    ap.add_argument("--rounds", type=int, default=300)
    ap.add_argument("--topology", default=None, help="complete (preset default), ring, geometric, ...")
    ap.add_argument("--robots-per-process", type=int, default=None)
    ap.add_argument("--label", default=None)
    ap.add_argument("--no-bare", action="store_true")
    ap.add_argument("--compute", action="store_true", help="the core's cost on the default run (module doc)")
    ap.add_argument("--base", type=Path, default=None, help="with --compute: another checkout to compare against")
    ap.add_argument("--repeats", type=int, default=1, help="with --compute: alternations of the trees")
    ap.add_argument("--no-launch", action="store_true", help="with --compute: skip the launch (make demo) timing")
    ap.add_argument("--in-process", action="store_true",
                    help="in-process CPU per fleet round of the paper preset, 3 robots to convergence and 16 "
                         "robots for 60 rounds (with --base: against another checkout; --repeats)")
    ap.add_argument("--interleaved", action="store_true",
                    help="with --in-process and --base: both trees in one process, runs alternating (--robots, "
                         "--rounds, --repeats pairs; module doc)")
    ap.add_argument("--no-sharing", action="store_true", help="with --interleaved: the hub's shared step off")
    ap.add_argument("--advance", action="store_true",
                    help="with --in-process and --base: the core's advance CPU per fleet round, both trees in one "
                         "process, each fleet run to its own stop at --tol (--robots, --repeats pairs)")
    ap.add_argument("--tol", type=float, default=1e-3, help="with --advance: the stopping tolerance (default 1e-3)")
    ap.add_argument("--frames", action="store_true",
                    help="CPU per received frame of the in-process fleet (--robots, default 32 here; --rounds, "
                         "default 200 here; geometric graph), whole run and replays (with --base; --repeats)")
    args = ap.parse_args(argv)
    if args.frames:
        robots = 32 if args.robots == ap.get_default("robots") else args.robots
        rounds = 200 if args.rounds == ap.get_default("rounds") else args.rounds
        print(f"# in-process CPU per received frame, {os.cpu_count()} cores", flush=True)
        frames_table(args.base, robots, rounds, args.repeats)
        return 0
    if args.in_process and args.advance:
        if args.base is None:
            ap.error("--advance needs --base")
        print(f"# in-process thread CPU of the core's advance per fleet round, {os.cpu_count()} cores", flush=True)
        advance_table(args.base, args.robots, args.tol, max(args.repeats, 2))
        return 0
    if args.in_process and args.interleaved:
        if args.base is None:
            ap.error("--interleaved needs --base")
        print(f"# in-process thread CPU per fleet round, both trees in one process, {os.cpu_count()} cores", flush=True)
        interleaved_table(args.base, args.robots, args.rounds, max(args.repeats, 2), not args.no_sharing)
        return 0
    if args.in_process:
        print(f"# in-process CPU per fleet round, {os.cpu_count()} cores", flush=True)
        if args.robots != ap.get_default("robots"):  # one fleet: --robots, --rounds, --topology; sharing on
            per_round_table(args.base, [(args.robots, args.rounds)], args.repeats, topology=args.topology,
                            unshared=False)
        else:
            per_round_table(args.base, [(3, 0), (16, 60)], args.repeats)
        return 0
    if args.compute:
        print(f"# compute per round, {os.cpu_count()} cores", flush=True)
        compute_table(args.base, args.repeats, not args.no_launch)
        return 0
    load = os.getloadavg()[0]
    res = profile_run(args.robots, args.rounds, topology=args.topology, per_process=args.robots_per_process)
    bare = None if args.no_bare else bare_exchange(args.robots)
    label = args.label or (f"{args.robots} robots, paper preset"
                           + (f", {args.robots_per_process} per process" if args.robots_per_process else ""))
    print(render(res, bare, f"{label} (load average {load:.1f} at start, {os.cpu_count()} cores)"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
