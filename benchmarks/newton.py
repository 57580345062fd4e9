"""`--algorithm newton` (distributed interior point) next to the fixed-grid ADMM, in process.

For each scenario of benchmarks/rounds.py that the issue names (and a few more): rounds until
every robot stays within 1e-6 (newton) / 1e-3 (admm) of the exact solution, rounds at the stop,
the error there, mean compute per robot-round, floats and encoded bytes per frame and bytes
published per robot per run (one frame per round; retransmissions not counted).

"Exact solution": piqp's central solve (agents/problem.py), and -- because that solve is itself
off by more than 1e-6 on some scenarios -- the KKT-certified optimum: the KKT system on the
constraints active at the central solution, solved directly and accepted only when its
multipliers are positive and every margin holds. Errors are given against both.

    .venv/bin/python benchmarks/newton.py          # the table (about a minute)
    .venv/bin/python benchmarks/newton.py --no-admm
    .venv/bin/python benchmarks/newton.py --sweep  # newton_sweep.md: 7 shapes x 3 seeds x 10 fleets (~10 min)

The sweep only reads a core's `result()`, so it runs unchanged on an older checkout (that is how
the "before" column of newton_sweep.md was measured: the same script from an export of the
commit before, with `--label before`).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agents.newton import payload_size  # noqa: E402
from agents.problem import certify_hard_margin, margin_rows, solve_central  # noqa: E402
from agents.spec import build_core  # noqa: E402
from benchmarks.common import FLEETS, RESULTS, add_row, lockstep_round, write_results  # noqa: E402
from launcher.world import Options, build_world  # noqa: E402
from protocol.frames import encode_state  # noqa: E402

#: benchmarks/rounds.py's fleets on the paper's blob, but the 16-robot complete graph
SCENARIOS = [(name, kw) for name, kw in FLEETS if "shape" not in kw and name != "16 robots, complete"]


def measure(kwargs: dict, algorithm: str, params: dict | None = None, tol: float = 1e-6) -> dict:
    world, spec = build_world(Options(fleet_id="bench", preset="paper", algorithm=algorithm, **kwargs))
    if params:
        spec = dataclasses.replace(spec, params={**spec.params, **params})
    central = solve_central(spec.basis, world.points, world.labels, spec.C)
    b = spec.basis
    rows = margin_rows(b.features(world.points), world.labels)
    best = certify_hard_margin(rows, np.append(central.x, central.gamma))
    ref = best if best is not None else np.append(central.x, central.gamma)
    cores = [build_core(spec, i, keep_trace=False) for i in spec.robot_ids]

    def error(v_ref: np.ndarray) -> float:
        c_ref = b.c_from_x(v_ref[:-1])
        return max(b.function_error(b.c_from_x(c.values[:-1]), c.values[-1], c_ref, v_ref[-1]) for c in cores)

    last_bad = 0
    compute = 0.0
    frame_bytes = 0
    while not all(c.finished for c in cores):
        updates, seconds = lockstep_round(cores)
        frame_bytes = max(frame_bytes, len(encode_state(updates[0], fleet=spec.fleet, seq=0, config_tag=spec.config_tag)))
        compute += seconds
        if not error(ref) < tol:
            last_bad = cores[0].round
    rounds = cores[0].round
    res = cores[0].result()
    return {
        "first": last_bad + 1 if last_bad < rounds else None,
        "stop": rounds,
        "iterations": res.get("iterations"),
        "converged": all(c.converged for c in cores),
        "error_central": error(np.append(central.x, central.gamma)),
        "error_exact": error(ref),
        "certified": best is not None,
        "ms": 1e3 * compute / max(rounds * len(cores), 1),
        "floats": spec.dim,
        "frame_bytes": frame_bytes,
        "run_kb": frame_bytes * (rounds + 1) / 1e3,
        "schedule": res.get("allreduce", ""),
    }


#: the sweep of issue 14's fleets: complete graphs (geometric, default comm-range) and rings
SWEEP_FLEETS = [("geometric", n) for n in (3, 8, 16, 24, 32, 48, 64)] + [("ring", n) for n in (4, 8, 16)]
SWEEP_SHAPES = ("blob", "bean", "crescent", "cross", "ellipse", "kidney", "star")
SWEEP_SEEDS = (0, 1, 2)


def sweep_one(shape: str, seed: int, topology: str, robots: int) -> dict:
    """One newton run of the sweep, in lock step: outcome, rounds and error against the exact
    reference (the certified central optimum when the certificate holds, piqp's point otherwise)."""
    world, spec = build_world(
        Options(fleet_id="sweep", preset="paper", algorithm="newton", shape=shape, seed=seed, robots=robots, topology=topology)
    )
    central = solve_central(spec.basis, world.points, world.labels, spec.C)
    cores = [build_core(spec, i, keep_trace=False) for i in spec.robot_ids]
    while not all(c.finished for c in cores):
        lockstep_round(cores)
    res = cores[0].result()
    b = spec.basis
    same = all(np.array_equal(c.values, cores[0].values) for c in cores)
    err = (
        max(b.function_error(b.c_from_x(c.values[:-1]), c.values[-1], central.c, central.gamma) for c in cores)
        if central.solved
        else float("nan")
    )
    converged = all(c.converged for c in cores)
    if converged and central.solved and err < 1e-6 and same:
        outcome = "solved" if central.certified else "solved (ref. uncertified)"
    elif not converged and not central.solved and "infeasible" in res["message"]:
        outcome = "infeasible (both)"
    else:
        outcome = "WRONG"
    return {
        "outcome": outcome, "rounds": res["rounds"], "iterations": res.get("iterations"), "resyncs": res.get("resyncs", 0),
        "error": err, "kb": res["payload_bytes_sent"] / 1e3, "central": central.status, "certified": central.certified,
        "message": res["message"],
    }


def sweep(label: str) -> None:
    """Every fleet x shape x seed; one summary row per fleet and every run that is not right."""
    lines = [
        f"## {label}",
        "",
        "| fleet | runs | solved (cert. / uncert. ref.) | infeasible (central agrees) | WRONG | rounds median (max) "
        "| re-syncs median | max error of solved | kB/robot median |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    wrong: list[str] = []
    for topology, robots in SWEEP_FLEETS:
        rows = []
        for shape in SWEEP_SHAPES:
            for seed in SWEEP_SEEDS:
                r = sweep_one(shape, seed, topology, robots)
                rows.append(r)
                if r["outcome"] == "WRONG":
                    wrong.append(
                        f"* {robots} robots, {topology}, {shape}, seed {seed}: central {r['central']}"
                        f"{' (certified)' if r['certified'] else ''}, {r['rounds']} rounds, error {r['error']:.1e}: "
                        f"{r['message'][:160] or 'converged'}"
                    )
        solved = [r for r in rows if r["outcome"].startswith("solved")]
        n_cert = sum(r["outcome"] == "solved" for r in rows)
        rounds = [r["rounds"] for r in solved] or [0]
        add_row(
            lines,
            f"| {robots}, {'complete (geometric)' if topology == 'geometric' else topology} | {len(rows)} | "
            f"{n_cert} / {len(solved) - n_cert} | {sum(r['outcome'].startswith('infeasible') for r in rows)} | "
            f"{sum(r['outcome'] == 'WRONG' for r in rows)} | {int(np.median(rounds))} ({max(rounds)}) | "
            f"{int(np.median([r['resyncs'] for r in solved] or [0]))} | "
            f"{max((r['error'] for r in solved), default=float('nan')):.1e} | {np.median([r['kb'] for r in solved] or [0]):.0f} |",
        )
    lines += ["", "Not right (converged off the reference, or stopped while the central solve found a solution):", ""]
    lines += wrong or ["* none"]
    out = RESULTS / "newton_sweep.md"
    old = out.read_text() if out.exists() else ""
    head = (
        "# `--algorithm newton` sweep: 7 shapes x seeds 0-2 x 10 fleets (in process, lock step)\n\n"
        "Written by `benchmarks/newton.py --sweep`. Paper preset (5x3 grid, sigma 1, 20 points per robot; the "
        "default world gives the same data for a fixed grid). 'solved': every robot converged, all hold the same "
        "bits, within 1e-6 (function error) of the central optimum, certified by its KKT conditions or (uncert.) "
        "piqp's point. 'infeasible': newton stopped with its certificate and piqp finds the problem infeasible too. "
        "Rounds and errors are deterministic; kB/robot: payload bytes published per robot per run.\n\n"
    )
    sections = [s for s in old.split("\n## ")[1:] if not s.startswith(label + "\n")]
    text = head + "".join("## " + s.rstrip("\n") + "\n\n" for s in sections) + "\n".join(lines) + "\n"
    out.write_text(text)
    print(f"wrote {out}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--no-admm", action="store_true", help="newton only")
    ap.add_argument("--sweep", action="store_true", help="the 420-run sweep into newton_sweep.md instead")
    ap.add_argument("--label", default="after", help="the sweep's section title in newton_sweep.md")
    args = ap.parse_args()
    if args.sweep:
        sweep(args.label)
        return
    lines = [
        "Paper preset (grid 5x3, sigma 1, 20 points per robot), M + 1 = 16: a newton contribution is "
        f"{payload_size(16)} floats (5 scalars, triu(H) 136, g, u, A'mu 16 each; frames carry the schedule's "
        "contributions per frame). newton: the fixed rule of agents/newton.py (centering (1 - alpha)^2 in "
        "[0.1, 0.3], tau 0.99, multipliers capped at 10x the target after full steps once m < 1e-4, stop at "
        "mean s*mu < 1e-10 with v settled); admm: the project's defaults (tol 1e-3). 'to tol': the first round after which every "
        "robot stays within 1e-6 (newton) / 1e-3 (admm) of the exact optimum. 'err exact': vs the "
        "KKT-certified optimum (see the script), 'err central': vs piqp's solve_central. Frame bytes: one "
        "encoded frame (msgpack, with the piggybacked previous round); per run: frame bytes x (rounds + 1), "
        "retransmissions not counted. ms per robot-round: compute only, 2-core machine shared with other "
        "work (under load).",
        "",
        "| scenario | algorithm (all-reduce) | to tol | at stop | IPM its | conv | err exact | err central | "
        "ms/robot-round | floats/frame | bytes/frame | kB/robot/run |",
        "|---|---|---:|---:|---:|:---:|---:|---:|---:|---:|---:|---:|",
    ]
    runs = [("newton", {"allreduce": "gather"}, 1e-6), ("newton", {"allreduce": "tree"}, 1e-6)]
    if not args.no_admm:
        runs.append(("admm", {}, 1e-3))
    for name, kwargs in SCENARIOS:
        for algorithm, params, tol in runs:
            if algorithm == "newton" and params["allreduce"] == "tree" and kwargs.get("topology") not in ("ring", "line", "geometric"):
                continue  # on a complete graph both schedules are the same single round
            r = measure(kwargs, algorithm, params, tol)
            label = f"newton ({r['schedule']})" if algorithm == "newton" else "admm"
            line = (
                f"| {name} | {label} | {r['first'] if r['first'] is not None else '>' + str(r['stop'])} | "
                f"{r['stop']} | {r['iterations'] if r['iterations'] is not None else '-'} | "
                f"{'yes' if r['converged'] else 'no'} | {r['error_exact']:.1e}{'' if r['certified'] else ' (uncertified)'} | "
                f"{r['error_central']:.1e} | {r['ms']:.3f} | {r['floats']} | {r['frame_bytes']} | {r['run_kb']:.0f} |"
            )
            add_row(lines, line)
    write_results(
        "newton.md",
        "# Distributed interior point (`--algorithm newton`) vs ADMM (in process)\n\n"
        "Written by `benchmarks/newton.py`.\n\n" + "\n".join(lines) + "\n",
    )


if __name__ == "__main__":
    main()
