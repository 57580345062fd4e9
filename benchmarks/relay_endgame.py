"""The relay hub's paused end-game, measured before it was built (branch ringend, phase 1): the ADMM alone runs
each relay fleet in process; at chosen rounds r every robot's state -- its own QP, its step at its own t_l and
that step's multipliers -- starts one end-game attempt run centrally (one SoftEndgame per robot, C = inf,
payloads exchanged instantly) until it certifies or ends (its first fresh guess). A paused fleet would stop at
r + k x R: k end-game steps, each one gather of the payloads over R rounds (`relay_hub.relay_endgame_plan`).

Why: on a relay fleet an end-game step cannot ride beside the ADMM (the frame is full), so an attempt costs
R rounds a step; this tells where attempts certify and how long they take, and what the start signal (the
copies' quiet streak: steps in a row with no robot's piece changed, `relay_hub.piece_changed`) and the stop
tests' estimate say there.

    .venv/bin/python benchmarks/relay_endgame.py --fleets 16-ring 8-ring --seeds 0 1 2 --at 200 300 400 500 600 700 800 900

Columns: the ADMM's error at r (max over robots, against the exact QP), the quiet streak and the estimate the
copies hold at r, the attempt's steps k, whether it certified, its error, the projected stop r + k R, and the
ADMM alone's stop.
"""

from __future__ import annotations

import argparse
import math
import multiprocessing
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agents import relay_hub  # noqa: E402
from agents.soft_endgame import SoftEndgame  # noqa: E402
from benchmarks.common import lockstep_round  # noqa: E402
from benchmarks.relay_anderson import RELAY_FLEETS  # noqa: E402

#: end-game steps after which a centrally run attempt is given up (none took more than 117)
MAX_STEPS = 400


def attempt(cores: list[relay_hub.RelayHubADMM], qps: list[Any]) -> tuple[int, np.ndarray | None]:
    """One attempt from every robot's step at its own t (the copy's S of this round; the robot's own QP solved
    afresh, keeping its multipliers): (steps k, the certified optimum or None when the attempt ended)."""
    ids = tuple(c.robot_id for c in cores)
    solvers, steps = [], []
    for c, qp in zip(cores, qps):
        t = c._S[c.round][c._blocks[c.robot_id]]
        qp.keep_multipliers = True
        sol = qp.solve(-c._P * t)
        v = np.append(sol.x, sol.gamma)
        eg = SoftEndgame(qp, ids, c.robot_id, math.inf, block=relay_hub.RELAY_ENDGAME_BLOCK, wide_start=True)
        eg.guess(v)
        solvers.append(eg)
        steps.append(v)
    for k in range(1, MAX_STEPS + 1):
        payloads = np.array([eg.payload for eg in solvers])
        done = [eg.step(payloads, v) for eg, v in zip(solvers, steps)]
        if done[0] is not None:
            return k, done[0]
        if solvers[0].attempts > 1:  # its first fresh guess: the attempt is over
            return k, None
    return MAX_STEPS, None


def run(task: tuple[str, dict[str, Any], list[int]]) -> dict[str, Any]:
    """The ADMM alone on one fleet, attempts at the rounds `at` (those before its stop)."""
    from agents.problem import MarginQP, solve_central
    from agents.spec import build_core
    from launcher.world import Options, build_world

    label, kwargs, at = task
    relay_hub.RELAY_ENDGAME = False  # the ADMM alone; the attempts beside it
    world, spec = build_world(Options(fleet_id="bench", preset="paper", max_rounds=5000, **kwargs))
    central = solve_central(spec.basis, world.points, world.labels, spec.C)
    b = spec.basis
    cores = [build_core(spec, i, keep_trace=False) for i in spec.robot_ids]
    qps = [MarginQP(spec.share(i).features, spec.share(i).labels, x_weight=1.0 / c.n, prox_weight=c._P, C=None)
           for i, c in zip(spec.robot_ids, cores)]
    plan = relay_hub.relay_endgame_plan(spec.graph, spec.robot_ids[0], len(spec.grid) + 1)
    assert plan is not None
    copy, step = cores[0], relay_hub.RelayHubADMM._fleet_step
    quiet, pieces = [0], [None]

    def watched(self: relay_hub.RelayHubADMM, S: np.ndarray, A: np.ndarray) -> bool:  # the copies' start signal
        below = step(self, S, A)
        T = S.reshape(self.n, self.dim)
        X = 0.5 * (A + T)
        W = relay_hub.step_normals(self._pdiag, self._P, X, T)
        steady = pieces[0] is not None and self.round + 1 - self.delay > 1 and not relay_hub.piece_changed(
            *pieces[0], X, W).any()
        quiet[0] = quiet[0] + 1 if steady else 0
        pieces[0] = (X, W)
        return below

    relay_hub.RelayHubADMM._fleet_step = watched  # type: ignore[method-assign]
    error_of = lambda v: b.function_error(b.c_from_x(v[:-1]), v[-1], central.c, central.gamma)  # noqa: E731
    rows = []
    try:
        while not all(c.finished for c in cores):
            lockstep_round(cores)
            r = copy.round
            if r in at and not copy.finished:
                k, done = attempt(cores, qps)
                rows.append({"r": r, "admm_error": max(error_of(c.values) for c in cores), "quiet": quiet[0],
                             "estimate": copy.estimate(), "k": k, "certified": done is not None,
                             "error": None if done is None else error_of(done), "projected": r + k * plan.rounds})
    finally:
        relay_hub.RelayHubADMM._fleet_step = step  # type: ignore[method-assign]
    return {"fleet": label, "D": copy.delay, "R": plan.rounds, "slots": plan.slots, "stop": copy.round, "rows": rows}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fleets", nargs="*", default=["4-ring", "5-line", "6-ring", "8-ring", "16-ring", "16-geo"],
                    choices=list(RELAY_FLEETS))
    ap.add_argument("--seeds", nargs="*", type=int, default=[0])
    ap.add_argument("--at", nargs="*", type=int, default=[200, 300, 400, 500, 600, 700, 800, 900])
    ap.add_argument("--jobs", type=int, default=1)
    args = ap.parse_args()
    tasks = [(f"{f} s{s}", {**RELAY_FLEETS[f], "seed": s}, sorted(args.at)) for f in args.fleets for s in args.seeds]
    print("| fleet | D | R (rounds per step, payloads per frame) | ADMM alone: stop | r | ADMM error at r | quiet | "
          "estimate | k | certified | error | projected stop r + k R |")
    print("|---|---:|---|---:|---:|---:|---:|---:|---:|:---:|---:|---:|")
    with multiprocessing.Pool(args.jobs) as pool:
        for out in pool.imap(run, tasks):
            for row in out["rows"]:
                err = "-" if row["error"] is None else f"{row['error']:.1e}"
                print(f"| {out['fleet']} | {out['D']} | {out['R']} ({out['slots']}) | {out['stop']} | {row['r']} | "
                      f"{row['admm_error']:.1e} | {row['quiet']} | {row['estimate']:.2g} | {row['k']} | "
                      f"{'yes' if row['certified'] else 'no'} | {err} | {row['projected']} |", flush=True)
            if not out["rows"]:
                print(f"| {out['fleet']} | {out['D']} | {out['R']} ({out['slots']}) | {out['stop']} | - (stopped "
                      f"before {min(args.at)}) | | | | | | | |", flush=True)


if __name__ == "__main__":
    main()
