"""CT-ADMM under network delay: time to reach 1e-2 function error, in simulated time.

The robots advance one communication period T_sp per round and wait for their neighbours'
exact samples (lost frames are recovered, never replaced by stale ones), so delay and loss do
not change the trajectory in the flow's own time (flow time t = round * T_sp): they stretch the
wall clock. This benchmark reports both, per one-way delay, with 20 % loss, on the default
scenario, using the in-process fleet's virtual network clock. Writes benchmarks/results/ct_delay.md.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agents.problem import solve_central  # noqa: E402
from benchmarks.common import add_row, write_results  # noqa: E402
from launcher.simulate import simulate_fleet  # noqa: E402
from launcher.world import Options, build_world  # noqa: E402
from protocol.links import LinkFaults  # noqa: E402

TARGET = 1e-2


def first_round_below(spec, central, robots) -> int | None:
    b = spec.basis
    rounds = sorted(set.intersection(*[set(map(int, r["trace"])) for r in robots]))
    for k in rounds:
        err = max(
            b.function_error(b.c_from_x(np.asarray(r["trace"][k][:-1])), r["trace"][k][-1], central.c, central.gamma)
            for r in robots
        )
        if err < TARGET:
            return k
    return None


def main() -> None:
    lines = [
        "| one-way delay | loss | round of 1e-2 | flow time to 1e-2 | network time to 1e-2 | rounds run | frames lost |",
        "|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for delay_ms in (0, 10, 20, 50):
        loss = 0.2 if delay_ms else 0.0
        faults = LinkFaults(delay=delay_ms / 1e3, loss=loss)
        world, spec = build_world(Options(fleet_id="bench", preset="paper", algorithm="ct-admm", faults=faults, ct_tol=1e-9))
        central = solve_central(spec.basis, world.points, world.labels)
        out = simulate_fleet(spec)
        k = first_round_below(spec, central, out.robots)
        period = spec.algorithm_params.period
        net_t = max(r["round_times"].get(k, float("nan")) for r in out.robots) if k is not None else float("nan")
        line = (
            f"| {delay_ms} ms | {loss:.0%} | {k} | {k * period:.2f} s | {net_t:.2f} s | "
            f"{out.robots[0]['rounds']} | {sum(r['frames_lost'] for r in out.robots)} |"
        )
        add_row(lines, line)
    write_results(
        "ct_delay.md",
        "# CT-ADMM: time to 1e-2 against network delay (default scenario, in-process fleet)\n\n"
        "Flow time = round x T_sp (10 ms), the paper's clock. Network time = the virtual network clock when\n"
        "the last robot computed that round (without compute time): each round waits for the\n"
        "neighbours' exact samples, so delay and loss stretch it, and retransmissions after a loss add\n"
        "the 20 ms retransmit interval.\n\n" + "\n".join(lines) + "\n",
    )


if __name__ == "__main__":
    main()
