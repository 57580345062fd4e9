"""`shapefleet sweep`: a map of how delay and loss move the answer, lockstep against free.

One in-process run (virtual time, deterministic) per cell of delay x loss x sync, on the default
world and the paper's fixed grid (5x3, sigma 1): lockstep runs today's ADMM (exact rounds, resends),
free runs what `simulate --sync free` runs (the free hub ADMM on a complete graph, agents/free_hub.py,
else the relaxed ADMM, agents/pdmm.py; free-radmm the relaxed ADMM always; never waits). Runs go to a process pool (one per core).
Each row: the final error of the robots' own answers against the certified central solve, the
first time after which every robot stayed within 1e-3 of it (robots' virtual seconds), the time
to stop, the bytes put on the links, and the agreement verdict. Writes sweep.csv and
robustness.png (heatmaps), prints a summary table.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import multiprocessing
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

CLAIM = 1e-3
#: sweep modes: lockstep (today's ADMM, the reference) and the free cores (launcher/simulate.py);
#: free-newest and free-ct are the measurements of docs/robustness.md (they may diverge: a row says so)
MODES = {"lockstep": None, "free": "auto", "free-radmm": "radmm", "free-newest": "admm-newest",
         "free-ct": "ct-admm-free"}
FIELDS = ("sync", "delay_s", "loss", "converged", "error", "time_to_claim_s", "stop_s", "rounds", "bytes_sent",
          "frames_sent", "verdict", "wall_s", "cpu_s", "over")
#: where a sweep runs: in process (virtual time) or over Zenoh (processes, wall-clock time)
OVER = ("inprocess", "zenoh")
#: the modes a Zenoh robot process runs (agents/robot.py, agents/free_robot.py)
ZENOH_MODES = ("lockstep", "free")
#: the grid when --delays / --losses are not given: the full map in process, spot checks over Zenoh
DEFAULT_GRID = {"inprocess": ("0ms,10ms,20ms,50ms", "0,0.1,0.3,0.5"), "zenoh": ("0ms,20ms", "0,0.3")}
_CACHE: dict[tuple[int, int], Any] = {}


def parse_list(text: str, parse: Callable[[str], float], what: str) -> list[float]:
    """A comma-separated list of values (e.g. "0ms,20ms"); ValueError names ``what``."""
    items = [t.strip() for t in str(text).split(",") if t.strip()]
    if not items:
        raise ValueError(f"{what}: give at least one value")
    return [parse(t) for t in items]


def _scenario(seed: int, robots: int) -> Any:
    key = (seed, robots)
    if key not in _CACHE:
        from agents.problem import solve_central
        from launcher.options import Options
        from launcher.world import build_world

        world, spec = build_world(Options(grid="5x3", sigma=1.0, algorithm="admm", fleet_id="sweep", seed=seed,
                                          robots=robots))
        _CACHE[key] = (world, spec, solve_central(spec.basis, world.points, world.labels, spec.C))
    return _CACHE[key]


def _error(spec: Any, central: Any, v: np.ndarray) -> float:
    b = spec.basis
    return float(b.function_error(b.c_from_x(np.asarray(v[:-1])), float(v[-1]), central.c, central.gamma))


def run_cell(cell: dict[str, Any]) -> dict[str, Any]:
    """One run of the sweep (in a worker process): the row of FIELDS."""
    from launcher.simulate import FleetFailure, simulate_fleet, simulate_free
    from protocol.links import LinkFaults

    t0, c0 = time.perf_counter(), time.process_time()
    world, spec, central = _scenario(cell["seed"], cell["robots"])
    spec = dataclasses.replace(spec, faults=LinkFaults(delay=cell["delay_s"], loss=cell["loss"]),
                               timing=dataclasses.replace(spec.timing, max_wall_s=cell["max_s"]))
    last_bad: dict[int, float] = {}

    def on_tick(t: float, rid: int, v: np.ndarray) -> None:
        if _error(spec, central, v) >= CLAIM:
            last_bad[rid] = t

    over = cell.get("over", "inprocess")
    row: dict[str, Any] = {"sync": cell["sync"], "delay_s": cell["delay_s"], "loss": cell["loss"], "over": over}
    if over == "zenoh":
        return {**row, **_zenoh_cell(cell, spec, central), "wall_s": time.perf_counter() - t0,
                "cpu_s": time.process_time() - c0}
    try:
        if cell["sync"] != "lockstep":
            out = simulate_free(spec, period=cell["period"], on_tick=on_tick, max_virtual_s=cell["max_s"],
                                algorithm=MODES[cell["sync"]], params={"max_ticks": int(cell["max_s"] / cell["period"])})
        else:
            out = simulate_fleet(spec, max_virtual_s=cell["max_s"])
    except FleetFailure as exc:
        return {**row, "converged": False, "error": math.nan, "time_to_claim_s": math.nan, "stop_s": math.nan,
                "rounds": 0, "bytes_sent": 0, "frames_sent": 0, "verdict": str(exc), "wall_s": time.perf_counter() - t0,
                "cpu_s": time.process_time() - c0}
    errors = [_error(spec, central, np.append(r["x"], r["gamma"])) for r in out.robots]
    if cell["sync"] == "lockstep":  # the trace holds every round, round_times when it was reached
        for r in out.robots:
            bad = [int(k) for k, v in r["trace"].items() if _error(spec, central, np.asarray(v)) >= CLAIM]
            if bad:
                last_bad[int(r["id"])] = float(r["round_times"].get(max(bad) + 1, out.virtual_s))
    verdict = _verdict(spec, out.robots)
    return {**row, "converged": verdict["converged"], "error": max(errors),
            "time_to_claim_s": max(last_bad.values(), default=0.0) if max(errors) < CLAIM else math.nan,
            "stop_s": out.virtual_s, "rounds": max(int(r["rounds"]) for r in out.robots),
            "bytes_sent": int(out.link_stats.get("bytes_sent", 0)), "frames_sent": int(out.link_stats["sent"]),
            "verdict": verdict["verdict"], "wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0}


def _verdict(spec: Any, robots: list[dict[str, Any]]) -> dict[str, Any]:
    """The launcher's agreement verdict on the robots' final answers (never a claim of accuracy)."""
    from launcher.report import agreement_verdict

    b = spec.basis

    def pair(p: dict[str, Any], q: dict[str, Any]) -> float:
        return b.function_error(b.c_from_x(np.asarray(p["x"])), p["gamma"], b.c_from_x(np.asarray(q["x"])), q["gamma"])

    return agreement_verdict(robots, pair, tol=CLAIM)


def _zenoh_cell(cell: dict[str, Any], spec: Any, central: Any) -> dict[str, Any]:
    """One spot check over Zenoh: a router and robot processes on loopback (launcher/fleet.py),
    faults on the robots' receiving links. Times are each robot's wall-clock seconds from its own
    start (lockstep: its session's round_times; free: its tick log, SHAPEFLEET_PROFILE); the
    worst robot counts. Bytes: each robot's encoded frames times its neighbours (one copy per link,
    as the in-process links count them)."""
    import tempfile

    from launcher.fleet import LaunchError, launch_fleet

    argv = ("-m", "agents.free_robot", "--period", repr(float(cell["period"]))) if cell["sync"] == "free" else (
        "-m", "agents.robot")
    before = os.environ.get("SHAPEFLEET_PROFILE")
    os.environ["SHAPEFLEET_PROFILE"] = "1"  # the free robots' tick logs (inherited by the processes)
    try:
        with tempfile.TemporaryDirectory(prefix="sweep-zenoh-") as tmp:
            try:
                out = launch_fleet(spec, workdir=Path(tmp), crashes=[], restart_after=0.5, restart=False,
                                   zenoh_port=None, progress=False, robot_argv=argv)
            except LaunchError as exc:
                return _failed(f"launch failed: {exc}")
            last_bad = [_last_bad_time(spec, central, r, Path(tmp)) for r in out.robots]
    finally:
        if before is None:
            os.environ.pop("SHAPEFLEET_PROFILE", None)
        else:
            os.environ["SHAPEFLEET_PROFILE"] = before
    if len(out.robots) != spec.n_robots:
        return _failed(f"{spec.n_robots - len(out.robots)} robots wrote no result")
    errors = [_error(spec, central, np.append(r["x"], r["gamma"])) for r in out.robots]
    verdict = _verdict(spec, out.robots)
    deg = {i: len(r.neighbours) for i, r in spec.robots.items()}
    return {"converged": verdict["converged"], "error": max(errors),
            "time_to_claim_s": max(last_bad) if max(errors) < CLAIM else math.nan,
            "stop_s": max(float(r["wall_s"]) for r in out.robots), "rounds": max(int(r["rounds"]) for r in out.robots),
            "bytes_sent": sum(int(r["bytes_sent"]) * deg[int(r["id"])] for r in out.robots),
            "frames_sent": sum(int(r["frames_sent"]) for r in out.robots), "verdict": verdict["verdict"]}


def _failed(why: str) -> dict[str, Any]:
    return {"converged": False, "error": math.nan, "time_to_claim_s": math.nan, "stop_s": math.nan, "rounds": 0,
            "bytes_sent": 0, "frames_sent": 0, "verdict": why}


def _last_bad_time(spec: Any, central: Any, row: dict[str, Any], workdir: Path) -> float:
    """The robot's own seconds at which its answer was last 1e-3 or more from the exact one."""
    ticks = workdir / f"robot-{row['id']}.json.ticks.json"
    if ticks.exists():  # free: [t, *values] per tick
        log = json.loads(ticks.read_text())["ticks"]
        bad = [t for t, *v in log if _error(spec, central, np.asarray(v)) >= CLAIM]
        return max(bad, default=0.0)
    bad = [int(k) for k, v in row["trace"].items() if _error(spec, central, np.asarray(v)) >= CLAIM]
    times = row["round_times"]
    return float(times.get(max(bad) + 1, row["wall_s"])) if bad else 0.0


def cells(delays: list[float], losses: list[float], syncs: list[str], *, seed: int = 0, robots: int = 3,
          period: float = 0.01, max_s: float | None = None, over: str = "inprocess") -> list[dict[str, Any]]:
    """Every run of the grid, slowest first (free runs at high delay) so the pool ends together.
    ``max_s``: each run's bound (robots' seconds; default 60 in process, 30 over Zenoh)."""
    if over not in OVER:
        raise ValueError(f"--over: {over!r} is not one of {', '.join(OVER)}")
    unknown = [m for m in syncs if m not in MODES]
    if unknown:
        raise ValueError(f"unknown sweep mode {unknown[0]!r}; choose from {', '.join(MODES)}")
    if over == "zenoh" and set(syncs) - set(ZENOH_MODES):
        raise ValueError(f"--syncs: over Zenoh the modes are {', '.join(ZENOH_MODES)} (robot processes), "
                         f"not {sorted(set(syncs) - set(ZENOH_MODES))[0]}")
    max_s = max_s if max_s is not None else (60.0 if over == "inprocess" else 30.0)
    out = [{"sync": s, "delay_s": d, "loss": p, "seed": seed, "robots": robots, "period": period, "max_s": max_s,
            "over": over} for s in syncs for d in delays for p in losses]
    return sorted(out, key=lambda c: (c["sync"] == "lockstep", -c["delay_s"], -c["loss"]))


def run_sweep(grid: list[dict[str, Any]], *, jobs: int | None = None,
              progress: Callable[[dict[str, Any]], None] | None = None) -> list[dict[str, Any]]:
    """Run every cell on ``jobs`` processes (default: one per core); rows in the grid's order.
    Zenoh cells run one at a time (each is a fleet of processes on its own: parallel runs would
    share the cores and slow each other's wall clock)."""
    jobs = 1 if any(c.get("over") == "zenoh" for c in grid) else (jobs or os.cpu_count() or 1)
    rows: list[dict[str, Any]] = []
    if jobs == 1:
        for c in grid:
            rows.append(run_cell(c))
            if progress:
                progress(rows[-1])
    else:
        with multiprocessing.get_context("spawn").Pool(jobs) as pool:
            for row in pool.imap_unordered(run_cell, grid):
                rows.append(row)
                if progress:
                    progress(row)
    key = {(c["sync"], c["delay_s"], c["loss"]): i for i, c in enumerate(grid)}
    return sorted(rows, key=lambda r: key[(r["sync"], r["delay_s"], r["loss"])])


def write_csv(path: Path, rows: list[dict[str, Any]]) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=FIELDS)
        w.writeheader()
        for r in rows:
            w.writerow({k: r.get(k) for k in FIELDS})


def _matrix(rows: list[dict[str, Any]], sync: str, key: str, delays: list[float], losses: list[float]) -> np.ndarray:
    m = np.full((len(losses), len(delays)), np.nan)
    for r in rows:
        if r["sync"] == sync:
            m[losses.index(r["loss"]), delays.index(r["delay_s"])] = r[key]
    return m


def plot(path: Path, rows: list[dict[str, Any]], delays: list[float], losses: list[float], syncs: list[str]) -> None:
    """Heatmaps (rows: sync mode; columns: final error, time to 1e-3, bytes), loss x delay each."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = (("error", "final error vs exact (log10)", True), ("time_to_claim_s", "time to 1e-3 (s)", False),
              ("bytes_sent", "bytes sent (MB)", False))
    fig, axes = plt.subplots(len(syncs), 3, figsize=(13, 3.6 * len(syncs)), squeeze=False)
    for k, (key, title, log) in enumerate(panels):
        shown_all = []
        for sync in syncs:
            m = _matrix(rows, sync, key, delays, losses)
            shown_all.append(np.log10(np.maximum(m, 1e-16)) if log else (m / 1e6 if key == "bytes_sent" else m))
        finite = np.concatenate([a[np.isfinite(a)] for a in shown_all] + [np.zeros(0)])
        lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
        for i, sync in enumerate(syncs):  # one colour scale per column: lockstep and free compare
            ax, shown = axes[i][k], shown_all[i]
            im = ax.imshow(shown, origin="lower", aspect="auto", cmap="viridis", vmin=lo, vmax=hi)
            for (a, b), v in np.ndenumerate(shown):
                ax.text(b, a, "n/a" if not np.isfinite(v) else f"{v:.2g}", ha="center", va="center", color="w", fontsize=8)
            ax.set_xticks(range(len(delays)), [f"{d * 1e3:g}" for d in delays])
            ax.set_yticks(range(len(losses)), [f"{p:g}" for p in losses])
            ax.set_xlabel("delay (ms)")
            ax.set_ylabel("loss")
            ax.set_title(f"{sync}: {title}", fontsize=10)
            fig.colorbar(im, ax=ax)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def summary(rows: list[dict[str, Any]]) -> Any:
    """A rich table: one line per run."""
    from rich.table import Table

    t = Table(title="sweep: error vs exact and time to 1e-3 (robots' seconds: virtual in process, wall-clock over "
                "Zenoh); agree = the verdict "
                "(robots agree, connected) -- a biased fleet can agree on a wrong answer")
    for name in ("mode", "delay", "loss", "agree", "error", "to 1e-3", "stop", "rounds", "MB"):
        t.add_column(name, justify="right", no_wrap=True)
    for r in rows:
        to = r["time_to_claim_s"]
        t.add_row(r["sync"], f"{r['delay_s'] * 1e3:g}ms", f"{r['loss']:g}", "yes" if r["converged"] else "NO",
                  "div." if not np.isfinite(r["error"]) else f"{r['error']:.0e}", "-" if not np.isfinite(to) else f"{to:.2f}s", "-" if not np.isfinite(r["stop_s"]) else f"{r['stop_s']:.2f}s",
                  str(r["rounds"]), f"{r['bytes_sent'] / 1e6:.2f}")
    return t
