"""Free-running robots vs lockstep under loss and delay (issue 13), in-process, virtual time.

Scenario: the default world (3 robots, complete graph, 20 points each) on the paper's fixed grid
(5x3, sigma 1) -- free sync needs a fixed grid (autogrid is lockstep-only). Errors are against the
certified central solve (agents/problem.py). Times are the robots' own (virtual) seconds from the
first round to the last robot's stop, deterministic for a seed; "to 1e-3" is the first time after
which every robot's error stayed below 1e-3 (measured against the exact answer, which robots do
not know). Wall-clock figures of this machine do not enter any table.

    .venv/bin/python benchmarks/free.py        # writes benchmarks/results/free.md (~5 min)
    .venv/bin/python benchmarks/free.py --sweep runs/<sweep>/sweep.csv --sweep-wall 184
                                               # only (re)writes the sweep section from a sweep.csv
    .venv/bin/python benchmarks/free.py --only headline,hub   # reruns those sections in place
                                               # (headline fresh selection four hub rate zenoh floor faults ct plots)
"""

from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from agents.problem import solve_central  # noqa: E402
from launcher.simulate import FleetFailure, simulate_fleet, simulate_free  # noqa: E402
from launcher.world import Options, build_world  # noqa: E402
from protocol.links import LinkFaults  # noqa: E402

OUT = ROOT / "benchmarks" / "results" / "free.md"
CLAIM = 1e-3


def scenario(seed: int = 0):
    world, spec = build_world(Options(grid="5x3", sigma=1.0, algorithm="admm", fleet_id="bench", seed=seed))
    return world, spec, solve_central(spec.basis, world.points, world.labels, spec.C)


def _err(spec, central, v) -> float:
    b = spec.basis
    return b.function_error(b.c_from_x(np.asarray(v[:-1])), float(v[-1]), central.c, central.gamma)


def run_free(spec, central, faults, trace: list[tuple[float, float]] | None = None, **kw) -> dict:
    """A free run's figures; ``trace`` (if given) gets (virtual s, worst robot's latest error) per tick."""
    s = dataclasses.replace(spec, faults=faults)
    last_bad: dict[int, float] = {}
    latest: dict[int, float] = {}

    def on_tick(t, rid, v):
        latest[rid] = _err(spec, central, v)
        if latest[rid] >= CLAIM:
            last_bad[rid] = t
        if trace is not None and len(latest) == spec.n_robots:
            trace.append((t, max(latest.values())))

    try:
        o = simulate_free(s, on_tick=on_tick, **kw)
    except FleetFailure as exc:
        return {"failed": str(exc)}
    errs = [_err(spec, central, np.append(r["x"], r["gamma"])) for r in o.robots]
    return {
        "ticks": max(r["rounds"] for r in o.robots), "t": o.virtual_s, "err": max(errs),
        "to_claim": max(last_bad.values(), default=0.0) if max(errs) < CLAIM else None,
        "converged": all(r["converged"] for r in o.robots), "frames": o.link_stats["sent"],
        "bytes": o.link_stats["bytes_sent"], "restarts": sum(r.get("anderson_restarts", 0) for r in o.robots),
    }


def run_lockstep(spec, central, faults, **params) -> dict:
    s = dataclasses.replace(spec, faults=faults, params={**spec.params, **params})
    o = simulate_fleet(s)
    errs = [_err(spec, central, np.append(r["x"], r["gamma"])) for r in o.robots]
    return {"rounds": max(r["rounds"] for r in o.robots), "t": o.virtual_s, "err": max(errs),
            "converged": all(r["converged"] for r in o.robots), "frames": o.link_stats["sent"]}


#: measured with the calm-stop estimate before RelaxedADMM.distance_estimate (branch main at dcb6833)
BEFORE_STOP_RULE = ("Before the stop-rule change (change and gap summed together as one series; main at dcb6833, "
                    "same seeds): free stopped at 11.99 / 12.09 / 13.04 s (10 ms) and 10.48 / 10.43 / 10.62 s (5 ms); "
                    "the times to 1e-3 are the same (the rule only decides when to stop).")


def target_line(where: str, lockstep: list[float], free: list[float], algorithm: str = "hub",
                period: str = "5 ms", seeds: str = "") -> str:
    """The issue's target in one line: free (the hub at ``period``) stops before lockstep, seed by seed?"""
    met = all(f < lk for f, lk in zip(free, lockstep))
    pairs = ", ".join(f"{f:.2f} vs {lk:.2f}" for f, lk in zip(free, lockstep))
    return (f"**Target ({where}, period {period}): free ({algorithm}) within 1e-3 in less time than lockstep under "
            f"loss 0.3 and 20 ms -- {'met' if met else 'NOT met'}**: free against lockstep, time to stop seed by seed"
            f"{seeds}: {pairs} s.")


HUB_NAME = "hub (Anderson 35, rho 8, eta 1.5)"
#: the candidate measured against the default and not adopted (4-robot fleets stopped outside tol)
HUB_CANDIDATE = {"hub_relax": 1.6, "hub_every_tick": True, "hub_step_cap": 10.0}
HUB_BEFORE = {"hub_relax": 1.5, "hub_every_tick": False, "hub_step_cap": 0.0}  # = the default
#: the hub's settings chosen on these seeds; the headline's other seeds are held out
CHOSEN_ON, HEADLINE_SEEDS = (0, 1, 2), range(10)


def headline(lines: list[str]) -> None:
    f = LinkFaults(loss=0.3, delay=0.02)
    lines += ["## Loss 0.3, delay 20 ms: lockstep against free (robots' virtual seconds)", "",
              "| seed | mode | algorithm | rounds/ticks | time to stop (s) | time to 1e-3 (s) | error vs exact | converged | frames sent |",
              "|---|---|---|---|---|---|---|---|---|"]
    lock_stop: list[float] = []
    free_stop: dict[float, list[float]] = {0.01: [], 0.005: []}
    for seed in HEADLINE_SEEDS:
        _, spec, central = scenario(seed)
        spec = dataclasses.replace(spec, seed=seed)
        for name, extra in (("admm (Anderson, default)", {}), ("admm, no acceleration", {"anderson": 0})):
            r = run_lockstep(spec, central, f, **extra)
            lock_stop += [r["t"]] if not extra else []
            lines.append(f"| {seed} | lockstep | {name} | {r['rounds']} | {r['t']:.2f} | - | {r['err']:.1e} | {r['converged']} | {r['frames']} |")
        for algorithm, name in (("radmm", "radmm (alpha 0.9, rho 15)"), ("hub", HUB_NAME)):
            for period in (0.01, 0.005):
                r = run_free(spec, central, f, period=period, max_virtual_s=60.0, algorithm=algorithm)
                if algorithm == "hub":
                    free_stop[period].append(r["t"] if r["converged"] and r["err"] < CLAIM else float("inf"))
                lines.append(
                    f"| {seed} | free, period {period * 1e3:g} ms | {name} | {r['ticks']} | {r['t']:.2f} | "
                    f"{r['to_claim'] if r['to_claim'] is None else round(r['to_claim'], 2)} | {r['err']:.1e} | {r['converged']} | {r['frames']} |")
        print("\n".join(lines[-6:]), flush=True)
    held = [i for i, s in enumerate(HEADLINE_SEEDS) if s not in CHOSEN_ON]
    chosen = [i for i, s in enumerate(HEADLINE_SEEDS) if s in CHOSEN_ON]
    lines += ["", BEFORE_STOP_RULE, "", BEFORE_HUB_TUNING, ""]
    for period, label in ((0.01, "10 ms (the default)"), (0.005, "5 ms")):
        for idx, which in ((chosen, f" (seeds {CHOSEN_ON[0]}-{CHOSEN_ON[-1]}: settings chosen on them)"),
                           (held, f" (seeds {HEADLINE_SEEDS[held[0]]}-{HEADLINE_SEEDS[held[-1]]}: held out; seed 3 only partly: "
                                 "the known failure, looked at, never used to choose)")):
            lines += [target_line("in-process, virtual seconds", [lock_stop[i] for i in idx],
                                  [free_stop[period][i] for i in idx], "hub", label, which), ""]


#: the hub's 10 ms figures before the settings were chosen for the default period (main at f8ba273)
BEFORE_HUB_TUNING = ("Before (main at f8ba273: eta 1.3, Anderson 30, a 40-tick stop window at every period), free hub "
                     "at 10 ms stopped at 3.90 / 3.57 / 4.22 / 4.26 / 3.39 / 3.49 / 3.46 s on seeds 0-6 (seeds 2 and 3 "
                     "slower than lockstep) and at 5 ms at 3.06 / 3.97 / 2.73 / 3.19 / 2.72 / 3.25 / 2.83 s.")


def fresh_seeds(lines: list[str]) -> None:
    """Seeds 10-19, never looked at while choosing: lockstep against the hub and the candidate."""
    f = LinkFaults(loss=0.3, delay=0.02)
    lines += ["", "## Held-out seeds 10-19 (loss 0.3, 20 ms; robots' virtual seconds)", "",
              f"Fresh seeds, not run while choosing. Free: {HUB_NAME} (the default); \"candidate\": eta 1.6, a step "
              "every tick, step cap 10 (measured, not adopted). Cells: time to stop, time to 1e-3, error vs exact at the stop.", "",
              "| seed | lockstep stop (s) | free 10 ms | candidate, 10 ms | free 5 ms | candidate, 5 ms |", "|---|---|---|---|---|---|"]
    lock: list[float] = []
    stops: dict[tuple[float, bool], list[float]] = {}
    for seed in range(10, 20):
        _, spec, central = scenario(seed)
        spec = dataclasses.replace(spec, seed=seed)
        lk = run_lockstep(spec, central, f)
        lock.append(lk["t"])
        cells = []
        for period in (0.01, 0.005):
            for before in (False, True):
                r = run_free(spec, central, f, period=period, max_virtual_s=60.0, algorithm="hub",
                             params=HUB_CANDIDATE if before else None)
                good = "failed" not in r and r["converged"] and r["err"] < CLAIM
                stops.setdefault((period, before), []).append(r["t"] if good else float("inf"))
                cells.append("failed" if not good else f"{r['t']:.2f}, {r['to_claim']:.2f}, {r['err']:.1e}")
        _add_row(lines, f"| {seed} | {lk['t']:.2f} | " + " | ".join(cells) + " |")
    lines.append("")
    for period, label in ((0.01, "10 ms (the default)"), (0.005, "5 ms")):
        lines += [target_line("in-process, virtual seconds", lock, stops[(period, False)], "hub", label,
                              " (seeds 10-19: held out)"), ""]
        lines += [f"Candidate, period {label}: " + target_line("in-process", lock, stops[(period, True)], "hub candidate",
                                                                    label, " (seeds 10-19)").split("--", 1)[1].strip().replace("**", ""), ""]


#: the candidates of the selection (worlds 0-2 only), each a change of the chosen setting
SELECTION = [("default: eta 1.5, step on news only, no cap", HUB_BEFORE),
             ("eta 1.5, every tick, no cap", {"hub_relax": 1.5, "hub_every_tick": True}),
             ("eta 1.6, every tick, no cap", {"hub_relax": 1.6, "hub_every_tick": True}),
             ("eta 1.6, every tick, cap 5", {**HUB_CANDIDATE, "hub_step_cap": 5.0}),
             ("**candidate: eta 1.6, every tick, cap 10**", HUB_CANDIDATE),
             ("eta 1.6, every tick, cap 20", {**HUB_CANDIDATE, "hub_step_cap": 20.0}),
             ("eta 1.8, every tick, cap 10", {**HUB_CANDIDATE, "hub_relax": 1.8}),
             ("rho 10, eta 1.6, every tick, cap 10", {**HUB_CANDIDATE, "rho": 10.0}),
             ("safeguard 30, eta 1.6, every tick, cap 10", {**HUB_CANDIDATE, "hub_safeguard": 30.0}),
             ("Anderson 45, eta 1.6, every tick, cap 10", {**HUB_CANDIDATE, "hub_anderson": 45})]


def four_robots(lines: list[str]) -> None:
    """The default against the candidate on a 4-robot complete fleet (why the candidate was not adopted)."""
    f = LinkFaults(loss=0.3, delay=0.02)
    lines += ["", "## 4 robots, complete graph: the default against the candidate (loss 0.3, 20 ms)", "",
              "Cells: time to stop (s), error vs exact at the stop (**bold**: outside the 1e-3 tolerance).", "",
              "| seed | lockstep stop (s) | default 10 ms | candidate 10 ms | default 5 ms | candidate 5 ms |",
              "|---|---|---|---|---|---|"]
    for seed in (0, 1, 2):
        world, spec = build_world(Options(grid="5x3", sigma=1.0, algorithm="admm", fleet_id="bench", seed=seed, robots=4))
        central = solve_central(spec.basis, world.points, world.labels, spec.C)
        spec = dataclasses.replace(spec, seed=seed)
        cells = []
        for period in (0.01, 0.005):
            for cfg in (None, HUB_CANDIDATE):
                r = run_free(spec, central, f, period=period, max_virtual_s=80.0, algorithm="hub", params=cfg)
                err = f"{r['err']:.1e}" if r.get("err", 1) < CLAIM else f"**{r.get('err', 1):.1e}**"
                cells.append("failed" if "failed" in r else f"{r['t']:.2f}, {err}")
        _add_row(lines, f"| {seed} | {run_lockstep(spec, central, f)['t']:.2f} | " + " | ".join(cells) + " |")


def selection(lines: list[str]) -> None:
    """How the setting was chosen: worlds 0-2 only, each under several link/clock realisations (the
    link and clock seed world + 100 k, k < 10 at 10 ms, k < 6 at 5 ms); the ratio free stop / lockstep
    stop of the same realisation. Seeds 3-19 are not used here."""
    f = LinkFaults(loss=0.3, delay=0.02)
    lines += ["", "## How the hub's setting was chosen (worlds 0-2 only; loss 0.3, 20 ms)", "",
              "Worlds (points) of seeds 0-2, each under 10 link/clock realisations (spec seed world + 100 k, k = 0..9; "
              "k = 0 is the headline's seed): free hub's time to stop / lockstep's time to stop of the same realisation, "
              "over the 30 runs. The error at the stop is the largest over the runs. Seeds 3-19 were not run for this.", "",
              "| setting | period | worst ratio | mean ratio | free faster | largest error at stop | mean stop - 1e-3 (s) |",
              "|---|---|---|---|---|---|---|"]
    runs = []
    for w in (0, 1, 2):
        _, spec, central = scenario(w)
        for k in range(10):
            s = dataclasses.replace(spec, seed=w + 100 * k)
            runs.append((k, s, central, run_lockstep(s, central, f)["t"]))
    for period, ks, names in ((0.01, 10, [n for n, _ in SELECTION]), (0.005, 6, [SELECTION[0][0], SELECTION[4][0]])):
        for name, cfg in SELECTION:
            if name not in names:
                continue
            ratios, errs, gaps = [], [], []
            for k, s, central, lk in runs:
                if k >= ks:
                    continue
                r = run_free(s, central, f, period=period, max_virtual_s=60.0, algorithm="hub", params=cfg)
                good = "failed" not in r and r["converged"] and r["err"] < CLAIM
                ratios.append(r["t"] / lk if good else float("inf"))
                if good:
                    errs.append(r["err"])
                    gaps.append(r["t"] - r["to_claim"])
            _add_row(lines, f"| {name} | {period * 1e3:g} ms | {max(ratios):.2f} | {np.mean(ratios):.3f} | "
                            f"{sum(x < 1 for x in ratios)}/{len(ratios)} | {max(errs):.0e} | {np.mean(gaps):.2f} |")


def _add_row(lines: list[str], row: str) -> None:
    """Append a table row and show it at once (the runs take minutes)."""
    lines.append(row)
    print(row, flush=True)


def floor(lines: list[str]) -> None:
    _, spec, central = scenario(0)
    lines += ["", "## Plain ADMM fed the newest values (free, period 10 ms) against the relaxed ADMM", "",
              "| loss | delay | admm-newest relax 1.95 | admm-newest relax 1.0 | radmm: error, time to stop |",
              "|---|---|---|---|---|"]
    for loss in (0.0, 0.1, 0.3):
        for delay in (0.0, 0.02):
            f = LinkFaults(loss=loss, delay=delay)
            newest = [run_free(spec, central, f, algorithm="admm-newest", params={"relax": relax, "max_ticks": 1500},
                               max_virtual_s=20.0) for relax in (1.95, 1.0)]
            cells = [f"diverged ({r['failed'].split(': ', 1)[0]})" if "failed" in r
                     else f"error {r['err']:.1e} after {r['ticks']} ticks" for r in newest]
            r = run_free(spec, central, f, max_virtual_s=60.0, algorithm="radmm")
            _add_row(lines, f"| {loss:g} | {delay * 1e3:g} ms | {cells[0]} | {cells[1]} | {r['err']:.1e}, {r['t']:.2f} s |")


def fault_models(lines: list[str]) -> None:
    """Bursty loss and a partition: the same mean loss, lockstep against free."""
    _, spec, central = scenario(0)
    lines += ["", "## Fault models: bursts and a partition (seed 0)", "",
              "| faults | lockstep: stop (s), error | free radmm: stop (s), to 1e-3 (s), error | "
              "free hub, 5 ms: stop (s), to 1e-3 (s), error |", "|---|---|---|---|"]
    cases = [("loss 0.3, 20 ms, independent", LinkFaults(loss=0.3, delay=0.02)),
             ("loss 0.3, 20 ms, bursts of 5 (--loss-burst 5)", LinkFaults(loss=0.3, delay=0.02, loss_burst=5)),
             ("loss 0.3, 20 ms pareto (mean +10 ms)", LinkFaults(loss=0.3, delay=0.02, jitter=0.01, delay_dist="pareto")),
             ("robot 2 at loss 0.6, others 0.1, 20 ms", LinkFaults(loss=0.1, delay=0.02, robot_loss=((2, 0.6),))),
             ("{0} cut from {1,2} 2 s-5 s, 10 ms", LinkFaults(delay=0.01, partitions=(((0,), (1, 2), 2.0, 5.0),)))]
    for name, f in cases:
        lk = run_lockstep(spec, central, f)
        free = [run_free(spec, central, f, max_virtual_s=60.0, **kw)
                for kw in ({"algorithm": "radmm"}, {"algorithm": "hub", "period": 0.005})]
        free_cells = [f"failed: {fr['failed']}" if "failed" in fr else
                      f"{fr['t']:.2f}, {fr['to_claim'] if fr['to_claim'] is None else round(fr['to_claim'], 2)}, {fr['err']:.1e}"
                      for fr in free]
        _add_row(lines, f"| {name} | {lk['t']:.2f}, {lk['err']:.1e} | {free_cells[0]} | {free_cells[1]} |")


def ct_admm(lines: list[str]) -> None:
    """The paper's CT-ADMM on the robot's clock: one period of flow per tick, samples held."""
    _, spec, central = scenario(0)
    lines += ["", "## CT-ADMM with sampled-and-held neighbour samples", "",
              "(a) all robots tick together, every sample arrives after `lag` periods (no loss, no clock offsets): "
              "10 s of flow (1000 periods of 10 ms); lag 0 is the lockstep CT-ADMM.", "",
              "| lag (periods) | delay | final error vs exact |", "|---|---|---|"]
    for lag in (0, 1, 2, 5):
        err = _ct_lag_trace(spec, central, lag)[-1]
        lines.append(f"| {lag} | {lag * 10} ms | {err:.1e} |")
    lines += ["", "(b) free sync in-process (own clocks: offsets, 0.1 % drift, 2 ms compute jitter), no loss:", "",
              "| one-way delay | outcome |", "|---|---|"]
    for delay in (0.0, 0.02, 0.1):
        r = run_free(spec, central, LinkFaults(delay=delay), algorithm="ct-admm-free", params={"max_ticks": 1500},
                     max_virtual_s=30.0)
        lines.append(f"| {delay * 1e3:g} ms | " + (f"diverged ({r['failed'].split(': ', 1)[0]})" if "failed" in r
                                                   else f"error {r['err']:.1e} after {r['ticks']} ticks") + " |")
    print("\n".join(lines[-12:]), flush=True)


def _ct_lag_trace(spec, central, lag: int, periods: int = 1000) -> list[float]:
    """CT-ADMM with every sample held `lag` periods: the worst robot's error after every period."""
    from agents.ct_admm import CTADMMParams
    from agents.pdmm import FreeCTADMM, RelaxedADMMParams
    from agents.rounds import RobotShare

    shares = {rid: RobotShare(rid, r.neighbours, spec.basis.features(r.points), r.labels, n_robots=spec.n_robots)
              for rid, r in spec.robots.items()}
    cores = {rid: FreeCTADMM(share, RelaxedADMMParams(max_ticks=periods), ct_params=CTADMMParams())
             for rid, share in shares.items()}
    queue, errs = [], []
    for _ in range(periods):
        queue.append({rid: c.tick() for rid, c in cores.items()})
        if len(queue) > lag:
            sent = queue.pop(0)
            for rid, c in cores.items():
                for j, p in zip(c.neighbours, sent[rid]):
                    cores[j].receive(p)
        errs.append(max(_err(spec, central, c.values) for c in cores.values()))
    return errs


PLOT_FLOOR, PLOT_CT = OUT.parent / "free-floor.png", OUT.parent / "free-ct-limit.png"


def plots(lines: list[str]) -> None:
    """The plain-ADMM floor and the CT-ADMM stability limit as pictures (seed 0, the default world)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    def figure(size: tuple[float, float]) -> tuple[Any, Any]:
        fig = Figure(figsize=size, dpi=110)
        return fig, FigureCanvasAgg(fig)

    _, spec, central = scenario(0)
    f = LinkFaults(loss=0.3, delay=0.02)
    lock = run_lockstep(spec, central, f)
    fig, canvas = figure((9.0, 4.2))
    panels = [fig.add_axes((0.07, 0.13, 0.40, 0.74)), fig.add_axes((0.57, 0.13, 0.40, 0.74))]
    ended: list[str] = []
    for ax, (loss, delay) in zip(panels, ((0.0, 0.0), (0.3, 0.02))):
        faults = LinkFaults(loss=loss, delay=delay)
        runs = [("plain ADMM, newest values (relax 1.0)", dict(algorithm="admm-newest", params={"relax": 1.0, "max_ticks": 1500}, max_virtual_s=20.0)),
                ("relaxed ADMM (unbiased)", dict(algorithm="radmm", max_virtual_s=60.0)),
                ("free hub ADMM (default)", dict(algorithm="hub", max_virtual_s=60.0))]
        for label, kw in runs:
            trace: list[tuple[float, float]] = []
            r = run_free(spec, central, faults, trace=trace, **kw)
            ts, errs = [t for t, _ in trace], [e for _, e in trace]
            how = ("diverged: " + r["failed"].split(": ", 1)[0] if "failed" in r
                   else "met its stop rule" if r["converged"] else "ran to its tick cap")
            ended.append(f"loss {loss:g}, {delay * 1e3:g} ms, {label}: {how} at {ts[-1] if ts else 0:.2f} s, last error {errs[-1] if errs else float('nan'):.1e}")
            ax.plot(ts, np.maximum(errs, 1e-12), label=label, lw=1.2)
        if loss:
            ax.axvline(lock["t"], color="k", ls=":", lw=1, label=f"lockstep stops ({lock['t']:.2f} s)")
        ax.axhline(CLAIM, color="grey", ls="--", lw=0.8)
        ax.set_yscale("log")
        ax.set_xlabel("robots' seconds (virtual clock, period 10 ms)")
        ax.set_title(f"loss {loss:g}, delay {delay * 1e3:g} ms", fontsize=10)
    panels[0].set_ylabel("worst robot's error vs the exact answer")
    panels[1].legend(fontsize=7, loc="upper right")
    fig.suptitle("Free-running robots: plain ADMM fed the newest values settles far from the answer", fontsize=10)
    canvas.print_png(PLOT_FLOOR)

    fig, canvas = figure((6.0, 4.2))
    ax = fig.add_axes((0.12, 0.13, 0.84, 0.76))
    for lag in (0, 1, 2, 5):
        errs = _ct_lag_trace(spec, central, lag)
        ended.append(f"CT-ADMM lag {lag}: error after 10 s {errs[-1]:.1e}")
        ax.plot(np.arange(1, len(errs) + 1) * 0.01, np.clip(errs, 1e-12, 1e6), label=f"samples {lag * 10} ms old ({lag} period{'' if lag == 1 else 's'})", lw=1.2)
    ax.axhline(CLAIM, color="grey", ls="--", lw=0.8)
    ax.set_yscale("log")
    ax.set_xlabel("flow time (s), period 10 ms")
    ax.set_ylabel("worst robot's error vs the exact answer (clipped at 1e6)")
    ax.set_title("CT-ADMM with sampled-and-held neighbour samples", fontsize=10)
    ax.legend(fontsize=7)
    canvas.print_png(PLOT_CT)
    lines += ["", "## Plots: the plain-ADMM floor and the CT-ADMM stability limit", "",
              f"![plain ADMM fed the newest values against the unbiased methods]({PLOT_FLOOR.name})", "",
              f"![CT-ADMM error against the age of its neighbour samples]({PLOT_CT.name})", "",
              "What the curves end at (seed 0, `benchmarks/free.py --only plots`):", ""]
    lines += [f"* {e}" for e in ended]
    print("\n".join(lines[-len(ended):]), flush=True)


def study_row(lines: list[str], labels: list[str], r: dict, restarts: bool = False) -> None:
    """One row of a study table: ticks, time to 1e-3, stop, their difference, the error (and restarts)."""
    head = " | ".join(labels)
    if "failed" in r or r["to_claim"] is None:
        cells = ["-"] * 4 + [r.get("failed", "not within 1e-3")] + (["-"] if restarts else [])
    else:
        cells = [str(r["ticks"]), f"{r['to_claim']:.2f}", f"{r['t']:.2f}", f"{r['t'] - r['to_claim']:.2f}",
                 f"{r['err']:.1e}"] + ([str(r["restarts"])] if restarts else [])
    lines.append(f"| {head} | " + " | ".join(cells) + " |")
    print(lines[-1], flush=True)


def _study(lines: list[str], title: str, *head: str) -> tuple[Any, Any, LinkFaults]:
    """Start a study of seed 0 under loss 0.3 and 20 ms: its heading and table head; the scenario."""
    _, spec, central = scenario(0)
    lines += ["", f"## {title}", "", *head]
    return spec, central, LinkFaults(loss=0.3, delay=0.02)


def rate_study(lines: list[str]) -> None:
    """Why free is slower than lockstep: the relaxed ADMM's penalty, relaxation and period."""
    spec, central, f = _study(
        lines, "Rate study: penalty, relaxation, period (loss 0.3, 20 ms, seed 0)",
        "Each row changes one setting of the default (rho 15, alpha 0.9, period 10 ms). Zero-delay row: "
        "the same fleet with loss 0.3 and no delay, for the iteration count without staleness.", "",
        "| fleet | setting | ticks | time to 1e-3 (s) | time to stop (s) | stop - 1e-3 (s) | error at stop |",
        "|---|---|---|---|---|---|---|")

    def row(fleet: str, name: str, r: dict) -> None:
        study_row(lines, [fleet, name], r)

    row("3 complete", "default, no delay", run_free(spec, central, LinkFaults(loss=0.3), max_virtual_s=60.0,
                                                    algorithm="radmm"))
    for name, kw in [("default", {}), ("rho 4", {"params": {"rho": 4.0}}), ("rho 8", {"params": {"rho": 8.0}}),
                     ("rho 30", {"params": {"rho": 30.0}}), ("alpha 0.5", {"params": {"alpha": 0.5}}),
                     ("alpha 0.7", {"params": {"alpha": 0.7}}), ("alpha 0.95", {"params": {"alpha": 0.95}}),
                     ("rho 8, alpha 0.95", {"params": {"rho": 8.0, "alpha": 0.95}}),
                     ("period 20 ms", {"period": 0.02}), ("period 5 ms", {"period": 0.005}),
                     ("period 2 ms", {"period": 0.002}), ("window 20 ticks", {"params": {"window": 20}})]:
        row("3 complete", name, run_free(spec, central, f, max_virtual_s=60.0, algorithm="radmm", **kw))
    world4, spec4 = build_world(Options(grid="5x3", sigma=1.0, algorithm="admm", fleet_id="bench", seed=0, robots=4))
    central4 = solve_central(spec4.basis, world4.points, world4.labels, spec4.C)
    for name, kw in [("default", {}), ("rho 8, alpha 0.95", {"params": {"rho": 8.0, "alpha": 0.95}})]:
        row("4 complete", name, run_free(spec4, central4, f, max_virtual_s=80.0, algorithm="radmm", **kw))
    lk = run_lockstep(spec4, central4, f)
    lines.append(f"| 4 complete | lockstep admm (reference) | {lk['rounds']} rounds | - | {lk['t']:.2f} | - | {lk['err']:.1e} |")


def lockstep_ticks(spec, central, algorithm: str, params: dict, lag: int = 0, ticks: int = 1200) -> int | None:
    """Free cores driven in lockstep (every robot ticks, then every packet arrives ``lag`` ticks
    later, none lost): the iterations to 1e-3 without a clock's staleness."""
    from agents.pdmm import build_free_core

    cores = [build_free_core(spec, r, {**params, "tol": 1e-12, "max_ticks": ticks + 1}, algorithm) for r in spec.robot_ids]
    queue, first = [], None
    for k in range(ticks):
        queue.append([c.tick() for c in cores])
        if len(queue) > lag:
            for i, packets in enumerate(queue.pop(0)):
                for p, j in zip(packets, cores[i].neighbours):
                    cores[j].receive(p)
        bad = max(_err(spec, central, c.values) for c in cores) >= CLAIM
        first = None if bad else (k + 1 if first is None else first)
    return first


def hub_study(lines: list[str]) -> None:
    """The free hub ADMM (agents/free_hub.py): what its acceleration, penalty and period do."""
    spec, central, f = _study(lines, "The free hub ADMM: acceleration, penalty, period (loss 0.3, 20 ms, seed 0)",
                              "Iterations without a clock (free cores driven in lockstep, no loss; `lag` ticks between "
                              "a send and its arrival):", "", "| core | lag 0 | lag 2 |", "|---|---|---|")
    for name, algorithm, params in (("radmm (alpha 0.9, rho 15)", "radmm", {}),
                                    ("hub, no acceleration (eta 1.5, rho 8)", "hub", {"hub_anderson": 0}),
                                    ("hub, no acceleration, eta 1.9", "hub", {"hub_anderson": 0, "hub_relax": 1.9}),
                                    (HUB_NAME, "hub", {})):
        n0, n2 = (lockstep_ticks(spec, central, algorithm, params, lag) for lag in (0, 2))
        lines.append(f"| {name} | {n0} | {n2} |")
    lines += ["", "Free sync in-process: each row changes one setting of the default (rho 8, Anderson 35, eta 1.5, "
              "safeguard 10, a step only on news, no step cap, period 5 ms, the stop window `hub_window(period)`: 40 ticks at 5 ms, 20 at 10 ms).", "",
              "| setting | ticks | time to 1e-3 (s) | time to stop (s) | stop - 1e-3 (s) | error at stop | restarts |",
              "|---|---|---|---|---|---|---|"]

    def row(name: str, r: dict) -> None:
        study_row(lines, [name], r, restarts=True)

    row("default, no delay", run_free(spec, central, LinkFaults(loss=0.3), period=0.005, max_virtual_s=60.0, algorithm="hub"))
    for name, kw in [("default", {}), ("no acceleration", {"params": {"hub_anderson": 0}}),
                     ("no acceleration, eta 1.0", {"params": {"hub_anderson": 0, "hub_relax": 1.0}}),
                     ("Anderson 5", {"params": {"hub_anderson": 5}}), ("Anderson 15", {"params": {"hub_anderson": 15}}),
                     ("eta 1.0", {"params": {"hub_relax": 1.0}}), ("safeguard 2", {"params": {"hub_safeguard": 2.0}}),
                     ("candidate: eta 1.6, every tick, step cap 10", {"params": HUB_CANDIDATE}),
                     ("Anderson 30, eta 1.3 (the setting before)", {"params": {**HUB_BEFORE, "hub_anderson": 30, "hub_relax": 1.3}}),
                     ("Anderson 15, eta 1.0, safeguard 2 (first setting)",
                      {"params": {**HUB_BEFORE, "hub_anderson": 15, "hub_relax": 1.0, "hub_safeguard": 2.0}}),
                     ("rho 5", {"params": {"rho": 5.0}}),
                     ("rho 15", {"params": {"rho": 15.0}}), ("period 10 ms", {"period": 0.01}),
                     ("period 10 ms, window 40 ticks", {"period": 0.01, "params": {"window": 40}}),
                     ("period 3 ms", {"period": 0.003}), ("period 2 ms", {"period": 0.002}),
                     ("window 20 ticks", {"params": {"window": 20}})]:
        row(name, run_free(spec, central, f, max_virtual_s=60.0, algorithm="hub", **{"period": 0.005, **kw}))
    world4, spec4 = build_world(Options(grid="5x3", sigma=1.0, algorithm="admm", fleet_id="bench", seed=0, robots=4))
    central4 = solve_central(spec4.basis, world4.points, world4.labels, spec4.C)
    r4 = run_free(spec4, central4, f, period=0.005, max_virtual_s=80.0, algorithm="hub")
    lines.append(f"| 4 robots, complete (lockstep: the rate study's reference) | {r4.get('ticks', '-')} | "
                 f"{r4.get('to_claim') or 0:.2f} | {r4.get('t', 0):.2f} | - | {r4.get('err', 0):.1e} | {r4.get('restarts', '-')} |")


def zenoh_side_by_side(lines: list[str]) -> None:
    """The same comparison over Zenoh: a router and 3 robot processes per run, wall-clock seconds."""
    import os

    from launcher import sweep

    lines += ["", "## Over Zenoh: lockstep against free (loss 0.3, 20 ms; wall-clock seconds)", "",
              "One router and 3 robot processes per run (`launch`, `launch --sync free`), runs one after another; "
              "times are each robot's own seconds from its start, the worst robot counts (`sweep --over zenoh`'s "
              f"rule). Load average before: {os.getloadavg()[0]:.1f}.", "",
              "| seed | mode | rounds/ticks | time to 1e-3 (s) | time to stop (s) | error vs exact | converged | MB sent |",
              "|---|---|---|---|---|---|---|---|"]
    stops: dict[tuple[str, float], list[float]] = {}
    for seed in ZENOH_SEEDS:
        for sync, period in (("lockstep", 0.01), ("free", 0.01), ("free", 0.005)):  # A/B in the same minute
            cell = sweep.cells([0.02], [0.3], [sync], seed=seed, period=period, over="zenoh")[0]
            r = sweep.run_cell(cell)
            good = r["converged"] and r["error"] < CLAIM
            stops.setdefault((sync, period), []).append(r["stop_s"] if good else float("inf"))
            mode = sync if sync == "lockstep" else f"free hub, period {period * 1e3:g} ms"
            to = r["time_to_claim_s"]
            lines.append(f"| {seed} | {mode} | {r['rounds']} | {'-' if to != to else f'{to:.2f}'} | {r['stop_s']:.2f} | "
                         f"{r['error']:.1e} | {r['converged']} | {r['bytes_sent'] / 1e6:.2f} |")
            print(lines[-1], flush=True)
    lines.append(f"\nLoad average after: {os.getloadavg()[0]:.1f} (2 cores shared with other engineers).")
    lines += ["", ZENOH_REPEAT, "", ZENOH_BEFORE, ""]
    for period, label in ((0.01, "10 ms (the default)"), (0.005, "5 ms")):
        lines += [target_line("over Zenoh, wall-clock seconds", stops[("lockstep", 0.01)], stops[("free", period)],
                              "hub", label, f" (seeds {ZENOH_SEEDS[0]}-{ZENOH_SEEDS[-1]})"), ""]


ZENOH_SEEDS = (0, 1, 2, 3)
#: the candidate (HUB_CANDIDATE, not adopted) over Zenoh: two A/Bs of seeds 0-3 at 52305da + the candidate
ZENOH_REPEAT = ("The candidate (eta 1.6, every tick, step cap 10; not the default) over Zenoh, seeds 0-3: first A/B "
                "(lockstep first, load 3.6 before, 5.3 after) lockstep 5.80 / 5.88 / 6.12 / 4.93 s, candidate 10 ms "
                "3.16 / 3.55 / 5.15 / 4.42 s, 5 ms 4.05 / 2.22 / 3.72 / 3.18 s; second A/B (free first, 10 ms, load 4.7 "
                "before, 7.3 after) candidate 4.86 / 3.42 / 3.37 / 3.54 s against lockstep's 5.83 / 6.28 / 5.48 / "
                "4.67 s -- the candidate first in all 12 pairs, errors 3e-7 to 1.4e-4.")
#: over Zenoh before: the relaxed ADMM, then the hub's setting before this one (HUB_BEFORE)
ZENOH_BEFORE = ("Before (the relaxed ADMM, main at ee98edc, load 14-16): free stopped at 11.46 / 12.45 s (10 ms) and "
                "9.91 / 9.99 s (5 ms) against lockstep's 6.45 / 6.97 s. With the hub's setting before this one (free.md "
                "as of 52305da, load 5.4-7.2), seeds 0-1: 4.03 / 5.25 s (10 ms) and 3.32 / 2.75 s (5 ms) against "
                "lockstep's 7.24 / 10.59 s.")

SWEEP_HEADER = "## `shapefleet sweep`, default grid"


def sweep_section(csv_path: Path, wall_s: float) -> list[str]:
    """The default sweep's table from its sweep.csv, with the run's wall and CPU seconds."""
    import csv

    rows = list(csv.DictReader(open(csv_path)))
    cpu = sum(float(r["cpu_s"]) for r in rows)
    lines = [SWEEP_HEADER, "",
             f"`shapefleet sweep` (4 delays x 4 losses x lockstep/free = {len(rows)} runs, 2 worker processes): "
             f"{wall_s:.0f} s wall on the shared 2-core machine under the other engineers' load, {cpu:.0f} s of CPU "
             f"in the runs ({cpu / 2:.0f} s per core: the figure an idle 2-core machine approaches).", "",
             "| sync | delay | loss | converged | error vs exact | time to 1e-3 (s) | stop (s) | rounds/ticks | MB sent |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['sync']} | {float(r['delay_s']) * 1e3:g} ms | {float(r['loss']):g} | {r['converged']} | "
                     f"{float(r['error']):.1e} | {float(r['time_to_claim_s']):.2f} | {float(r['stop_s']):.2f} | "
                     f"{r['rounds']} | {int(r['bytes_sent']) / 1e6:.2f} |")
    return lines


SECTIONS = {"headline": headline, "fresh": fresh_seeds, "selection": selection, "four": four_robots, "hub": hub_study, "rate": rate_study, "zenoh": zenoh_side_by_side, "floor": floor,
            "faults": fault_models, "ct": ct_admm, "plots": plots}


def only(names: list[str]) -> None:
    """Rerun the named sections and put each in place of its namesake (same "## " heading) in OUT."""
    text = OUT.read_text()
    for name in names:
        lines: list[str] = []
        SECTIONS[name](lines)
        block = "\n".join(lines).strip("\n")
        heading = next(line for line in block.splitlines() if line.startswith("## "))
        if heading not in text:  # a new section: before the hub study (after the headline's)
            at = text.index("## The free hub ADMM")
            text = text[:at] + block + "\n\n" + text[at:]
        else:
            start = text.index(heading)
            end = text.find("\n## ", start + len(heading))
            text = text[:start] + block + "\n" + (text[end:] if end >= 0 else "")
        OUT.write_text(text)
        print(f"rewrote the {name} section of {OUT}", flush=True)


def main() -> None:
    if "--sweep" in sys.argv:
        path = Path(sys.argv[sys.argv.index("--sweep") + 1])
        wall = float(sys.argv[sys.argv.index("--sweep-wall") + 1])
        text = OUT.read_text().split(SWEEP_HEADER)[0].rstrip("\n")
        OUT.write_text(text + "\n\n" + "\n".join(sweep_section(path, wall)) + "\n")
        print(f"wrote the sweep section of {OUT}")
        return
    if "--only" in sys.argv:
        only(sys.argv[sys.argv.index("--only") + 1].split(","))
        return
    t0 = time.perf_counter()
    lines = ["# Free-running sync (issue 13)", "", __doc__.split("\n\n")[1].replace("\n", " "), ""]
    headline(lines)
    fresh_seeds(lines)
    selection(lines)
    four_robots(lines)
    hub_study(lines)
    rate_study(lines)
    zenoh_side_by_side(lines)
    floor(lines)
    fault_models(lines)
    ct_admm(lines)
    plots(lines)
    lines += ["", f"Benchmark wall time {time.perf_counter() - t0:.0f} s on the shared 2-core machine (under load; not a figure of the runs)."]
    old = OUT.read_text() if OUT.exists() else ""
    if SWEEP_HEADER in old:  # the sweep section is written by --sweep from a sweep run; keep it
        lines += ["", SWEEP_HEADER + old.split(SWEEP_HEADER)[1].rstrip("\n")]
    OUT.write_text("\n".join(lines) + "\n")
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
