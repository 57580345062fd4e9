"""The certified stop guard of the hub form (agents/certificate.py, ADMMParams.certify), measured in process.

The hub's stop rule (r / (1 - rate)) is a heuristic that Anderson plateaus fool; since branch guard every
hub copy also computes a proven bound (a duality gap; since branch certtight, a KKT-residual radius) on the fleet's function error against the exact optimum
(agents/certificate.py: the mathematics) and a stop needs the rule AND bound <= certify x tol; since
branch relayguard the relay hub's copies too (agents/relay_hub.py, where the payload fits). This
script runs each fleet exactly as `simulate` does (the cores in lock step, `benchmarks.rounds.fleet_probe`)
for several values of certify (0: the rule alone, main's bits) with `agents.admm.WARM_QP` off and on, and
reports the round at stop, the true error there (max over robots, `GridBasis.function_error` against
`solve_central`), the fleet's certified bound at the stop (max over robots of their `error_bound`, the
bound of their *final* values), whether it stopped by its rule, and -- with --check -- on how many
robot-rounds the bound was below the true error (never, if the proof and its arithmetic hold). --check and
--trace arm the payload every round (`admm.CERTIFY_ARM` = inf; by default only where the next round's rule
can pass, branch guardcost), so that every round has a fresh certificate.

    .venv/bin/python benchmarks/stop_certificate.py                  # the issue fleets, certify 0 / 10 / 1, piqp and WARM_QP
    .venv/bin/python benchmarks/stop_certificate.py --fleet "8 robots, blob, seed 2" --certify 10
    .venv/bin/python benchmarks/stop_certificate.py --sweep 3        # every shape x seeds 0-3, 3 robots (--sweep 8: 8)
    .venv/bin/python benchmarks/stop_certificate.py --check          # also the bound against the error every round
    .venv/bin/python benchmarks/stop_certificate.py --trace 50 --fleet "8 robots, complete"  # error and bound, tol 1e-14
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import agents.admm as admm  # noqa: E402
import agents.relay_hub as relay_hub  # noqa: E402
from benchmarks.common import add_row, lockstep_round, write_results  # noqa: E402
from benchmarks.polish import fleet_kwargs  # noqa: E402
from benchmarks.rounds import fleet_probe, form_name  # noqa: E402
from launcher.scenario import shape_names  # noqa: E402

TOL = 1e-3
#: the L shape of tests/test_simulate.py::test_data_file_and_shape_file
L_SHAPE = "x,y\n-2,-1.5\n2,-1.5\n2,0\n0,0\n0,1.5\n-2,1.5\n"


def _l_shape_kwargs() -> dict:
    path = Path(tempfile.gettempdir()) / "stop_certificate_l.csv"
    path.write_text(L_SHAPE)
    return {"shape_file": str(path)}


#: (label, Options keywords)
FLEETS: list[tuple[str, dict]] = [
    ("paper setting: 3 robots, blob, complete", fleet_kwargs("paper setting: 3 robots, blob, complete")),
    ("3 robots, star", fleet_kwargs("3 robots, star")),
    ("3 robots, bean", fleet_kwargs("3 robots, bean")),
    ("3 robots, crescent", fleet_kwargs("3 robots, crescent")),
    ("8 robots, complete", fleet_kwargs("8 robots, complete")),
    ("16 robots, complete", fleet_kwargs("16 robots, complete")),
    ("L shape (test_simulate)", _l_shape_kwargs()),
    ("8 robots, blob, seed 2", {"robots": 8, "shape": "blob", "seed": 2}),
    ("24 robots", fleet_kwargs("24 robots")),
    ("32 robots, geometric", fleet_kwargs("32 robots, geometric")),
    ("4 robots, ring (relay hub)", fleet_kwargs("4 robots, ring")),
    ("8 robots, ring (relay hub)", fleet_kwargs("8 robots, ring")),
    # (since branch relayguard the relay hub has the guard where N (M + 1 + 6) fits the frame budget:
    # not at N = 16, whose rows stay the rule alone)
    ("5 robots, line (relay hub)", fleet_kwargs("5 robots, line")),
    ("16 robots, geometric 3.0 (relay hub)", fleet_kwargs("16 robots, geometric 3.0")),
    ("16 robots, ring (relay hub)", fleet_kwargs("16 robots, ring")),
]


@dataclass
class Stop:
    """How one fleet run ended."""

    form: str
    rounds: int
    error: float  # max over robots, against the exact optimum
    bound: float | None  # max over robots of their certified error_bound (None: no certificate)
    converged: bool
    unsafe: int  # robot-rounds with bound < true error (--check), else 0
    checked: int  # robot-rounds with a bound (--check)


def run(kwargs: dict, *, certify: float, warm: bool, max_rounds: int, check: bool = False,
        tol: float = TOL, trace: int = 0) -> Stop:
    """The fleet as `simulate` runs it (lock step), with ADMMParams.certify as given and the warm QP
    on (`warm`) wherever it applies -- also with the guard off and on the relay hub, as branch core3
    measured it (by default it runs only where the guard decides) -- or nowhere (piqp)."""
    old = admm.WARM_QP, admm.CERTIFY_EVERY_ROUND, admm.CERTIFY_ARM, relay_hub.RELAY_WARM_QP
    old_guess = admm.ConsensusADMM._warm_guess
    admm.WARM_QP, admm.CERTIFY_EVERY_ROUND = warm, check or bool(trace)  # (the same stops either way)
    relay_hub.RELAY_WARM_QP = warm
    if warm:
        admm.ConsensusADMM._warm_guess = lambda self: self._values
    if check or trace:  # the payload in every frame (else only in armed rounds): a fresh bound every round
        admm.CERTIFY_ARM = math.inf
    try:
        cores, error, _active = fleet_probe({**kwargs, "tol": tol}, max_rounds, params={"certify": certify})
        unsafe = checked = 0
        while not all(c.finished for c in cores):
            lockstep_round(cores)
            r = cores[0].round
            if check or (trace and r % trace == 0):
                errors = error(each=True)
                bounds = [getattr(c, "error_bound", lambda: None)() for c in cores]
                for e, b in zip(errors, bounds):
                    if b is not None:
                        checked += 1
                        unsafe += b < e
                if trace and r % trace == 0:
                    known = [b for b in bounds if b is not None]
                    print(f"round {r} | error {max(errors):.2e} | bound {max(known) if len(known) == len(bounds) else math.nan:.2e}",
                          flush=True)
        bounds = [getattr(c, "error_bound", lambda: None)() for c in cores]
        return Stop(form_name(cores[0]), cores[0].round, error(), None if None in bounds else max(bounds),
                    all(c.converged for c in cores), unsafe, checked)
    finally:
        admm.WARM_QP, admm.CERTIFY_EVERY_ROUND, admm.CERTIFY_ARM, relay_hub.RELAY_WARM_QP = old
        admm.ConsensusADMM._warm_guess = old_guess


def _cell(s: Stop) -> str:
    bound = "-" if s.bound is None else f"{s.bound:.1e}"
    return f"{s.rounds}{'' if s.converged else ' cap'} ({s.error:.1e}; {bound})"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fleet", action="append", help="only these labels (repeatable)")
    ap.add_argument("--sweep", type=int, metavar="ROBOTS", help="every built-in shape x seeds 0-3, complete")
    ap.add_argument("--certify", type=float, action="append", help="these values (default 0, 10, 1)")
    ap.add_argument("--warm", choices=("off", "on", "both"), default="both", help="agents.admm.WARM_QP")
    ap.add_argument("--check", action="store_true", help="the bound against the true error on every robot-round")
    ap.add_argument("--trace", type=int, metavar="EVERY", help="instead of the table: error and bound every EVERY "
                    "rounds, tol 1e-14, certify 10 (where a fleet stagnates)")
    ap.add_argument("--max-rounds", type=int, default=5000)
    ap.add_argument("--out", help="also write the table to benchmarks/results/OUT")
    args = ap.parse_args()
    fleets = FLEETS
    if args.sweep:
        fleets = [(f"{args.sweep} robots, {shape}, seed {seed}",
                   {"robots": args.sweep, "topology": "complete", "shape": shape, "seed": seed})
                  for shape in shape_names() for seed in range(4)]
    if args.fleet:
        fleets = [f for f in fleets if f[0] in args.fleet]
    warms = {"off": [False], "on": [True], "both": [False, True]}[args.warm]
    if args.trace:
        for label, kwargs in fleets:
            for warm in warms:
                print(f"{label}, WARM_QP {'on' if warm else 'off'}")
                run(kwargs, certify=10.0, warm=warm, max_rounds=args.max_rounds, tol=1e-14, trace=args.trace)
        return
    certifies = args.certify or [0.0, 10.0, 1.0]
    lines = ["| fleet | form | WARM_QP | " + " | ".join(f"certify {c:g}" for c in certifies) + " | bound < error |",
             "|---|---|:---:|" + "---:|" * len(certifies) + ":---:|"]
    for label, kwargs in fleets:
        for warm in warms:
            try:
                stops = [run(kwargs, certify=c, warm=warm, max_rounds=args.max_rounds, check=args.check) for c in certifies]
            except Exception as exc:  # an infeasible sweep fleet: say so and go on
                add_row(lines, f"| {label} | - | {'on' if warm else 'off'} | {type(exc).__name__}: {exc} |")
                continue
            safe = (f"{sum(s.unsafe for s in stops)} of {sum(s.checked for s in stops)}" if args.check else "-")
            add_row(lines, f"| {label} | {stops[0].form} | {'on' if warm else 'off'} | "
                           + " | ".join(_cell(s) for s in stops) + f" | {safe} |")
    if args.out:
        cmd = " ".join(["benchmarks/stop_certificate.py", *sys.argv[1:]])
        write_results(args.out, "\n".join([f"`nice -n 15 .venv/bin/python {cmd}`; tol {TOL}; a cell: rounds at "
                                           "stop (true error; certified bound at the stop).", ""] + lines) + "\n")


if __name__ == "__main__":
    main()
