"""The LiDAR least-squares fleet (--algorithm lsq): rounds, compute per round, error against the exact
central fit and IoU, in process (lock-step rounds, no network). Writes benchmarks/results/lsq.md.

Cases: the default world (3 robots x 20 points, blob) and benchmarks/outlines/letter_e.csv (5 robots x 40
points), each on a fixed grid and sigma given as flags: sigma = diag / K of the data's bounding box (K 16 as
the task set it, and 8), the grid the CLI's --grid NXxNY over its default (padded) box at a spacing of about
sigma (NX = round(width / sigma)), so every row is one `shapefleet simulate` command (printed in the table).
Each on a complete graph (hub form) and a sparse one (edge form: a line of 3, a ring of 5). Beside the fleet: the central fit's IoU, and the
same least-squares fit without the midpoint rows (pairs' +1 / -1 rows only: what the return's 0 row adds).

    nice -n 15 .venv/bin/python benchmarks/lsq.py              # the table (~1-2 minutes)
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from agents.kernel import GridBasis  # noqa: E402
from agents.lsq_model import lidar_pairs, lsq_rows, normal_equations  # noqa: E402
from agents.spec import build_core  # noqa: E402
from benchmarks.common import add_row, lockstep_round, write_results  # noqa: E402
from launcher import scenario  # noqa: E402
from launcher.world import Options, build_world  # noqa: E402

#: (row label, Options keywords, topologies: the complete graph's hub form and a sparse graph's edge form --
#: a line for 3 robots, whose ring is complete)
CASES = [
    ("default world (blob, 3 x 20)", {}, ("complete", "line")),
    ("letter_e (5 x 40)", {"shape_file": str(ROOT / "benchmarks" / "outlines" / "letter_e.csv"), "robots": 5,
                           "points": 40}, ("complete", "ring")),
]
KS = (16, 8)
MAX_ROUNDS = 5000


def flags_for(world_kw: dict, k: int) -> dict:
    """--grid and --sigma for diag / k of the case's data: the grid over the CLI's default box at ~sigma."""
    world, _ = build_world(Options(fleet_id="bench", algorithm="lsq", grid="2x2", sigma=1.0, **world_kw))
    points = world.points
    lo, hi = points.min(axis=0), points.max(axis=0)
    sigma = float(np.hypot(*(hi - lo))) / k
    x0, x1, y0, y1 = world.bounds
    nx, ny = max(1, round((x1 - x0) / sigma)), max(1, round((y1 - y0) / sigma))
    return {"grid": f"{nx}x{ny}", "sigma": float(f"{sigma:.6g}")}


def without_midpoints(basis: GridBasis, world, lam: float):
    """The central least-squares fit of the pairs' +1 / -1 rows alone (no return row): the ablation."""
    rows, targets = [], []
    for r in world.robots:
        p, t = lsq_rows(r.points, r.labels)
        keep = t != 0
        rows.append(p[keep])
        targets.append(t[keep])
    H, b = normal_equations(basis.features(np.vstack(rows)), np.concatenate(targets), lam)
    v = np.linalg.solve(H, b)
    return basis.c_from_x(v[:-1]), float(v[-1])


def iou(world, basis: GridBasis, c: np.ndarray, gamma: float) -> float:
    return scenario.iou_on_raster(world.shape, lambda p: basis.decision(p, c, gamma) < 0, world.bounds)


def run(label: str, world_kw: dict, k: int, topology: str) -> str:
    flags = flags_for(world_kw, k)
    world, spec = build_world(Options(fleet_id="bench", algorithm="lsq", topology=topology, max_rounds=MAX_ROUNDS,
                                      **flags, **world_kw))
    basis, lam = spec.basis, spec.algorithm_params.lam
    ref = spec.central([(r.id, r.points, r.labels) for r in world.robots])
    cores = [build_core(spec, i, keep_trace=False) for i in spec.robot_ids]
    compute = 0.0
    rounds = 0
    while not all(c.finished for c in cores) and rounds < MAX_ROUNDS + 1:
        _, seconds = lockstep_round(cores)
        compute += seconds
        rounds += 1
    results = [c.result() for c in cores]
    errors = [basis.function_error(basis.c_from_x(np.asarray(r["x"])), r["gamma"], ref.c, ref.gamma) for r in results]
    worst = int(np.argmax(errors))
    fleet_iou = min(iou(world, basis, basis.c_from_x(np.asarray(r["x"])), r["gamma"]) for r in results)
    pairs = sum(len(lidar_pairs(r.labels)) for r in world.robots)
    ms = 1e3 * compute / max(1, rounds * len(cores))
    c0, g0 = without_midpoints(basis, world, lam)
    converged = all(r["converged"] for r in results)
    command = (f"`simulate --algorithm lsq --grid {flags['grid']} --sigma {flags['sigma']:g} --topology {topology}"
               + "".join(f" --{key.replace('_', '-')} {Path(v).relative_to(ROOT) if key == 'shape_file' else v}"
                         for key, v in world_kw.items()) + "`")
    return (f"| {label} | diag/{k} | {len(spec.grid)} | {pairs} | {topology} | {rounds - 1 if rounds else 0}"
            f"{'' if converged else ' (not converged)'} | {ms:.3f} | {errors[worst]:.1e} | {fleet_iou:.3f} | "
            f"{iou(world, basis, ref.c, ref.gamma):.3f} | {iou(world, basis, c0, g0):.3f} | {command} |")


def main() -> None:
    load = os.getloadavg()
    lines = [
        "# The LiDAR least-squares fleet (--algorithm lsq), in process",
        "",
        f"`nice -n 15 .venv/bin/python benchmarks/lsq.py` on {time.strftime('%Y-%m-%d')}, {os.cpu_count()} cores, "
        f"load average at the start {load[0]:.2f} / {load[1]:.2f} / {load[2]:.2f} (1 / 5 / 15 min; the machine is "
        "shared: ms per round are loaded figures). Defaults: lam 0.1, rho 1, tol 1e-3, Anderson 30 on complete graphs.",
        "",
        "rounds: the round the fleet's own stop rule ended the run; ms: compute per robot-round (the cores' `advance`, "
        "no messaging); error: the largest robot's function error against the exact central least-squares fit "
        "(`solve_central_lsq`); IoU: the worst robot's against the true outline (200 x 200 raster of the run's box); "
        "central: the exact fit's IoU; no midpoint: the same least-squares fit without the return rows (targets 0).",
        "",
        "| case | sigma | grid points | pairs | topology | rounds | ms / robot-round | error vs exact | IoU fleet | "
        "IoU central | IoU no midpoint | command |",
        "|---|---|---:|---:|---|---:|---:|---:|---:|---:|---:|---|",
    ]
    for label, kw, topologies in CASES:
        for k in KS:
            for topology in topologies:
                add_row(lines, run(label, kw, k, topology))
    write_results("lsq.md", "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
