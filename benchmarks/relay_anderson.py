"""The relay hub's Anderson design, swept in process: rounds at stop, error against the exact central
QP, restarts and CPU for every relay fleet under a variant of the relay's constants.

Why: issue 10's ring targets (8-ring <= 600 rounds at stop, 16-ring <= 1000) depend on the relay's
Anderson memory, regularisation, safeguard and relaxation; `simulate` is deterministic, so a variant
is judged by its rounds and errors (no A/B needed), its CPU beside them (noisy: a shared machine).

    .venv/bin/python benchmarks/relay_anderson.py                       # today's constants, the fleets
    .venv/bin/python benchmarks/relay_anderson.py --memory "min(100, n * dim // 2)" --reg 1e-3
    .venv/bin/python benchmarks/relay_anderson.py --fleets 8-ring 16-ring --jobs 2
    .venv/bin/python benchmarks/relay_anderson.py --fleets 4-ring 6-ring 8-ring --seeds 0 1 2 3 4 --warm-qp on

--warm-qp sets RELAY_WARM_QP (the exact warm-started local QP where the guard decides), --seeds runs
every chosen fleet at each seed (the hold's safety check), --no-frame-budget lets the guard's payload
ride wherever a frame's MAX_DIM allows (a what-if for the 16-robot fleets, beyond the frame budget).
--memory is a Python expression in n (robots), dim (M + 1), D (the graph's diameter) and a (the
fleet's ADMMParams.anderson); the other flags replace the module's constants for the run.
"""

from __future__ import annotations

import argparse
import multiprocessing
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agents import relay_hub  # noqa: E402
from agents.admm import ADMMParams  # noqa: E402
from benchmarks.common import lockstep_round  # noqa: E402

#: the relay fleets of issue 10 and rounds.md (label: Options keywords)
RELAY_FLEETS: dict[str, dict[str, Any]] = {
    "4-ring": {"robots": 4, "topology": "ring"},
    "5-line": {"robots": 5, "topology": "line"},
    "6-ring": {"robots": 6, "topology": "ring"},
    "8-ring": {"robots": 8, "topology": "ring"},
    "16-ring": {"robots": 16, "topology": "ring"},
    "16-geo": {"robots": 16, "topology": "geometric", "comm_range": 3.0},
    "16-geo-s1": {"robots": 16, "topology": "geometric", "comm_range": 3.0, "seed": 1},
    "8-ring-s1": {"robots": 8, "topology": "ring", "seed": 1},
    "8-ring-s2": {"robots": 8, "topology": "ring", "seed": 2},
    "16-ring-s1": {"robots": 16, "topology": "ring", "seed": 1},
}


def stop_check_fleets() -> dict[str, dict[str, Any]]:
    """benchmarks/rounds.py's --stop-check fleets: every built-in shape x (ring 6, line 4) x seeds 0-2."""
    from benchmarks.rounds import STOP_CHECK_FLEETS, STOP_CHECK_SEEDS
    from launcher.scenario import SHAPES

    fleets, seen = {}, set()
    for shape in sorted(SHAPES):
        if SHAPES[shape] in seen:  # an alias: the same runs again
            continue
        seen.add(SHAPES[shape])
        for topology, robots in STOP_CHECK_FLEETS:
            for seed in STOP_CHECK_SEEDS:
                fleets[f"{shape} {topology} {robots} s{seed}"] = {"shape": shape, "robots": robots,
                                                                  "topology": topology, "seed": seed}
    return fleets


def configure(variant: dict[str, Any]) -> None:
    """Replace the relay module's constants (and its memory rule) by the variant's."""
    for key in ("RELAY_REG", "RELAY_SAFEGUARD", "RELAY_RELAX", "RELAY_HOLD", "RELAY_HOLD_CERTIFIED", "RELAY_WARM_QP"):
        if variant.get(key) is not None:
            setattr(relay_hub, key, variant[key])
    if variant.get("no_frame_budget"):  # what-if: the guard's payload on every relay fleet (MAX_DIM only)
        relay_hub.relay_cert_slot = lambda params, n, dim: (  # noqa: E731
            relay_hub.certify_slot(params) and n * (dim + relay_hub.cert_math.PAYLOAD) <= relay_hub.MAX_DIM)
    if variant.get("memory"):
        expr = variant["memory"]
        relay_hub.relay_memory = lambda params, n, dim, D: int(eval(expr, {"min": min, "max": max},  # noqa: E731
                                                                    {"n": n, "dim": dim, "D": D, "a": params.anderson}))


def run(task: tuple[str, dict[str, Any], dict[str, Any], int]) -> dict[str, Any]:
    """One fleet under one variant: rounds to 1e-3 and at stop, error, restarts, CPU."""
    from agents.problem import solve_central
    from agents.spec import build_core
    from launcher.world import Options, build_world

    label, kwargs, variant, max_rounds = task
    configure(variant)
    restarts = [0]
    forget = relay_hub.RelayHubADMM._forget

    def counted(self: relay_hub.RelayHubADMM) -> None:
        restarts[0] += 1
        forget(self)

    relay_hub.RelayHubADMM._forget = counted  # type: ignore[method-assign]
    world, spec = build_world(Options(fleet_id="bench", preset="paper", max_rounds=max_rounds, **kwargs))
    central = solve_central(spec.basis, world.points, world.labels, spec.C)
    b = spec.basis
    started = time.process_time()
    cores = [build_core(spec, i, keep_trace=False) for i in spec.robot_ids]
    assert isinstance(cores[0], relay_hub.RelayHubADMM), "not a relay fleet"
    restarts[0] = 0  # (every core forgets once at its start)

    def error() -> float:
        return max(b.function_error(b.c_from_x(c.values[:-1]), c.values[-1], central.c, central.gamma) for c in cores)

    first = None
    while not all(c.finished for c in cores):
        lockstep_round(cores)
        if first is None and error() < 1e-3:
            first = cores[0].round
    cpu = time.process_time() - started
    rounds = cores[0].round
    return {"fleet": label, "first": first, "stop": rounds, "error": error(),
            "converged": all(c.converged for c in cores), "restarts": restarts[0],
            "memory": cores[0]._memory, "D": cores[0].delay, "cpu": cpu, "ms_round": 1e3 * cpu / max(rounds, 1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fleets", nargs="*", default=list(RELAY_FLEETS), choices=list(RELAY_FLEETS))
    ap.add_argument("--stop-check", action="store_true", help="rounds.py's --stop-check fleets instead")
    ap.add_argument("--memory", default=None, help="memory rule: a Python expression in n, dim, D, a")
    ap.add_argument("--reg", type=float, default=None)
    ap.add_argument("--safeguard", type=float, default=None)
    ap.add_argument("--relax", type=float, default=None)
    ap.add_argument("--hold", type=int, default=None)
    ap.add_argument("--hold-certified", type=int, default=None, help="the hold where the certified guard decides")
    ap.add_argument("--warm-qp", choices=("on", "off"), default=None,
                    help="RELAY_WARM_QP: the exact warm-started local QP where the certified guard decides")
    ap.add_argument("--no-frame-budget", action="store_true",
                    help="what-if: the guard's payload wherever a frame's MAX_DIM allows (the 16-robot fleets), "
                         "beyond the frame budget of FRAME_BUDGET x (M + 1) floats")
    ap.add_argument("--seeds", nargs="*", type=int, default=None,
                    help="run every chosen fleet at each of these seeds (the safety check of the hold)")
    ap.add_argument("--max-rounds", type=int, default=5000)
    ap.add_argument("--jobs", type=int, default=1)
    args = ap.parse_args()
    variant = {"memory": args.memory, "RELAY_REG": args.reg, "RELAY_SAFEGUARD": args.safeguard,
               "RELAY_RELAX": args.relax, "RELAY_HOLD": args.hold,
               "RELAY_HOLD_CERTIFIED": args.hold_certified,
               "RELAY_WARM_QP": None if args.warm_qp is None else args.warm_qp == "on",
               "no_frame_budget": args.no_frame_budget}
    tol = ADMMParams().tol
    print(f"variant: {variant}", flush=True)
    print("| fleet | D | memory | rounds to 1e-3 | rounds at stop | converged | error at stop | restarts | "
          "CPU s | CPU ms per round |", flush=True)
    fleets = stop_check_fleets() if args.stop_check else {f: RELAY_FLEETS[f] for f in args.fleets}
    if args.seeds is not None:
        fleets = {f"{f.split('-s')[0]} s{seed}": {**kw, "seed": seed} for f, kw in fleets.items() for seed in args.seeds}
    tasks = [(f, kw, variant, args.max_rounds) for f, kw in fleets.items()]
    total, worst = 0, 0.0
    with multiprocessing.Pool(args.jobs) as pool:
        for r in pool.imap(run, tasks):
            total += r["stop"]
            worst = max(worst, r["error"] if r["converged"] else 0.0)
            flag = "" if r["error"] <= tol or not r["converged"] else " ABOVE TOL"
            print(f"| {r['fleet']} | {r['D']} | {r['memory']} | {r['first']} | {r['stop']} | "
                  f"{'yes' if r['converged'] else 'no'} | {r['error']:.1e}{flag} | {r['restarts']} | "
                  f"{r['cpu']:.1f} | {r['ms_round']:.1f} |", flush=True)
    print(f"total rounds at stop {total}; largest error at a stop {worst:.1e} (tol {tol:g})", flush=True)


if __name__ == "__main__":
    main()
