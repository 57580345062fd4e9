"""`--polish` on and off over every built-in shape x seeds x fleet sizes (complete graph, the paper's
5x3 grid and sigma 1, hard margin), in process (the cores in lock step, as `simulate`).

Answers: does the exact end-game end every run at the certified optimum, and with fewer rounds?
Errors are against `solve_central`'s solution (KKT-certified when it certifies). Writes
benchmarks/results/polish-sweep.md.

    .venv/bin/python benchmarks/polish_sweep.py                  # 3 and 8 robots, seeds 0-3 (~6 min)
    .venv/bin/python benchmarks/polish_sweep.py --robots 3 --seeds 2
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agents.problem import solve_central  # noqa: E402
from agents.spec import build_core  # noqa: E402
from benchmarks.rounds import lockstep_round  # noqa: E402
from launcher.options import Options  # noqa: E402
from launcher.scenario import shape_names  # noqa: E402
from launcher.world import build_world  # noqa: E402

OUT = Path(__file__).resolve().parent / "results" / "polish-sweep.md"


def run(polish: bool, max_rounds: int, **world: object) -> tuple[int, bool, float, bool, str]:
    """(rounds, every robot converged, worst function error vs the central solve, every robot's
    values the same bits, the central solve's status) of one fleet."""
    w, spec = build_world(Options(fleet_id="sweep", preset="paper", topology="complete", polish=polish,
                                  max_rounds=max_rounds, **world))
    central = solve_central(spec.basis, w.points, w.labels, spec.C)
    cores = [build_core(spec, i, keep_trace=False) for i in spec.robot_ids]
    while not all(c.finished for c in cores):
        lockstep_round(cores)
    b = spec.basis
    err = max(b.function_error(b.c_from_x(c.values[:-1]), c.values[-1], central.c, central.gamma) for c in cores)
    same = all(c.values.tobytes() == cores[0].values.tobytes() for c in cores)
    return cores[0].round, all(c.converged for c in cores), err, same, central.status


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", type=int, nargs="+", default=[3, 8], help="fleet sizes (default 3 8)")
    ap.add_argument("--seeds", type=int, default=4, help="seeds 0..N-1 per shape (default 4)")
    ap.add_argument("--max-rounds", type=int, default=5000)
    ap.add_argument("--no-write", action="store_true", help="print the table only")
    args = ap.parse_args()
    lines = ["| robots | shape | seed | rounds off | converged | error off | rounds --polish | converged | error "
             "--polish | one point, bit for bit | central |", "|---:|---|---:|---:|:---:|---:|---:|:---:|---:|:---:|---|"]
    for n in args.robots:
        for shape in shape_names():
            for seed in range(args.seeds):
                off = run(False, args.max_rounds, robots=n, shape=shape, seed=seed)
                on = run(True, args.max_rounds, robots=n, shape=shape, seed=seed)
                yes = {True: "yes", False: "**no**"}
                lines.append(f"| {n} | {shape} | {seed} | {off[0]} | {yes[off[1]]} | {off[2]:.1e} | {on[0]} | "
                             f"{yes[on[1]]} | {on[2]:.1e} | {yes[on[3]]} | {off[4]} |")
                print(lines[-1], flush=True)
    if not args.no_write:
        head = ["# `--polish` on and off: every built-in shape x seeds, complete graphs (paper grid)", "",
                f"`.venv/bin/python {' '.join(['benchmarks/polish_sweep.py', *sys.argv[1:]])}`; max rounds "
                f"{args.max_rounds}. Errors: function error against solve_central.", ""]
        OUT.write_text("\n".join(head + lines) + "\n")


if __name__ == "__main__":
    main()
