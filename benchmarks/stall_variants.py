"""Prototypes of changes to the hub's stall switch, measured on complete fleets (issues 10/14).

Each variant patches agents/admm.py's hub *at run time* in this process only: a prototype to
measure rounds at stop and the error against the exact central QP, not a protocol (the active-set
restart reads every robot's active set directly instead of carrying a bit in the frames, as a
real one would). The figures and the verdicts are in docs/algorithm.md ("Complete fleets of
24-48 robots") and benchmarks/results/rounds-complete.md.

    .venv/bin/python benchmarks/stall_variants.py '{"robots": 32, "topology": "geometric"}' '{"ACT": 0}'

The first argument is the fleet (launcher Options on the paper preset), the second the variant:
  STALL_PLAIN n     plain stretch of n rounds after a firing (main: STALL_WINDOW = 300)
  DOUBLE true       the k-th plain stretch lasts STALL_PLAIN x 2^(k-1) rounds
  JUMP f            at a re-arm, s jumps f x the plain map's geometric tail along its last step
  STALL_RETRY n     the re-armed watch's window after the first firing (main: 300)
  ACT 0 | k | "after"   every copy clears Anderson's memory when any robot's active set changed
                    (0), after it has been stable for k rounds, or on changes after the first firing
  ANDERSON_REG r, REG_AFTER r   the regularisation always / after the first firing
  RELAX_AFTER a     over-relaxation a after the first firing
Prints one JSON line: rounds to 1e-3, at stop, error at stop, the rounds the mode changed.

    .venv/bin/python benchmarks/stall_variants.py --affine-piece

runs the 32-robot fleet (main's rule) to its re-arm at round 1447, where every robot's active set
stays the same until round 2087 (the hub's map is affine there), and continues 300 rounds from that
state under Anderson variants and the plain map; prints the error every 50 rounds.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

import agents.admm as A  # noqa: E402
from benchmarks.common import lockstep_round  # noqa: E402
from benchmarks.rounds import fleet_probe  # noqa: E402

#: the variant's knobs (module attributes the patched hub reads), main's values by default
KNOBS: dict[str, Any] = {"STALL_PLAIN": A.STALL_WINDOW, "DOUBLE": False, "JUMP": None, "STALL_RETRY": A.STALL_WINDOW, "REG_AFTER": None,
                         "RELAX_AFTER": None}


def _watch(self: A._Hub, residual: float) -> None:
    """`_Hub.watch` with the plain stretch and the re-armed window as knobs (main: both 300)."""
    if self.plain:
        self.since += 1
        plain = KNOBS["STALL_PLAIN"] * (2 ** (getattr(self, "firings", 1) - 1) if KNOBS["DOUBLE"] else 1)
        if KNOBS["JUMP"] is not None:
            self.trail = (getattr(self, "trail", []) + [self.s])[-22:]
        if self.since >= plain:
            self.plain, self.mark, self.since = False, math.inf, 0
            if KNOBS["JUMP"] is not None and len(self.trail) == 22:
                self.s = _jump(self.trail, KNOBS["JUMP"])
        return
    if self.resync:
        self.mark, self.since = math.inf, 0
        return
    window = KNOBS["STALL_RETRY"] if getattr(self, "fired_once", False) else A.STALL_WINDOW
    if residual < self.mark / A.STALL_DROP or self.mark == math.inf:
        self.mark, self.since = residual, 0
        return
    self.since += 1
    if self.since >= window:
        self.fired_once = True
        self.firings = getattr(self, "firings", 0) + 1
        self.plain, self.since = True, 0
        self._forget()


def _jump(trail: list[np.ndarray], share: float) -> np.ndarray:
    """The plain map's geometric tail extrapolated from 10-round displacements (they average out
    over-relaxation's period-2 swings): D = s - s_10 and D_old = s_10 - s_20, q = |D| / |D_old|,
    s + share x q / (1 - q) x D (a prototype in plain numpy arithmetic)."""
    d, d_old = trail[-1] - trail[-11], trail[-11] - trail[-21]
    q = float(np.linalg.norm(d)) / float(np.linalg.norm(d_old))
    if not 0 < q < 1:
        return trail[-1]
    return trail[-1] + share * q / (1.0 - q) * d


_EXTRAPOLATE = A._Hub._extrapolate


def _extrapolate(self: A._Hub) -> np.ndarray:
    """`_Hub._extrapolate` with REG_AFTER as the regularisation once the switch has fired."""
    if KNOBS["REG_AFTER"] is None or not getattr(self, "fired_once", False):
        return _EXTRAPOLATE(self)
    saved, A.ANDERSON_REG = A.ANDERSON_REG, KNOBS["REG_AFTER"]
    try:
        return _EXTRAPOLATE(self)
    finally:
        A.ANDERSON_REG = saved


def run(kwargs: dict[str, Any], variant: dict[str, Any], max_rounds: int = 5000) -> dict[str, Any]:
    """One in-process run of the fleet under the variant (lock-step, as benchmarks/rounds.py)."""
    variant = dict(variant)
    act = variant.pop("ACT", None)
    for k, v in variant.items():
        if k in KNOBS:
            KNOBS[k] = v
        else:
            setattr(A, k, v)
    A._Hub.watch, A._Hub._extrapolate = _watch, _extrapolate
    cores, error, active = fleet_probe(kwargs, max_rounds)
    modes: list[int] = []
    first, plain, seen, stable, restarts = None, False, active(), 0, 0
    while not all(c.finished for c in cores):
        lockstep_round(cores)
        hub = cores[0]._hub
        if KNOBS["RELAX_AFTER"] is not None and getattr(hub, "fired_once", False) and hub.relax != KNOBS["RELAX_AFTER"]:
            for c in cores:  # (the first round after the change the copies see unsynced w's: one plain step)
                c._hub.relax = KNOBS["RELAX_AFTER"]
        if act is not None:
            now = active()
            changed, seen = now != seen, now
            stable = 0 if changed else stable + 1
            due = changed if act in (0, "after") else stable == act
            if act == "after" and not getattr(hub, "fired_once", False):
                due = False
            if due and not hub.plain:
                restarts += 1
                for c in cores:
                    c._hub._forget()
        if hub.plain != plain:
            modes.append(cores[0].round)
            plain = hub.plain
        if first is None and error() < 1e-3:
            first = cores[0].round
    return {"first": first, "stop": cores[0].round, "err": error(), "converged": all(c.converged for c in cores),
            "mode_changes": modes, "restarts": restarts if act is not None else None}


#: (name, hub attributes, admm module constants) continued from the affine piece
PIECE_VARIANTS: list[tuple[str, dict[str, Any], dict[str, Any]]] = [
    ("main (memory 30, reg 1e-5, safeguard 2)", {}, {}),
    ("memory 60", {"memory": 60}, {}),
    ("memory 10", {"memory": 10}, {}),
    ("no restarts (safeguard and stall off)", {"safeguard": math.inf}, {"STALL": 1e9}),
    ("regularisation 1e-10", {}, {"ANDERSON_REG": 1e-10}),
    ("regularisation 1e-3", {}, {"ANDERSON_REG": 1e-3}),
    ("plain map", {"plain": True, "since": -(10 ** 9)}, {}),
]


def affine_piece(start: int = 1447, rounds: int = 300) -> None:
    """Anderson against the plain map on one affine piece of the 32-robot fleet's map (docs)."""
    import copy

    cores, error, _ = fleet_probe({"robots": 32, "topology": "geometric"}, 5000)
    while cores[0].round < start:
        lockstep_round(cores)
    print(f"round {cores[0].round}, error {error():.3g}, plain {cores[0]._hub.plain}")
    base = copy.deepcopy(cores)
    for name, attrs, constants in PIECE_VARIANTS:
        A._SHARED_STEPS.clear()  # no step may be adopted across variants
        saved = {k: getattr(A, k) for k in constants}
        for k, v in constants.items():
            setattr(A, k, v)
        cores[:] = copy.deepcopy(base)  # (`error` reads this list)
        for c in cores:
            for k, v in attrs.items():
                setattr(c._hub, k, v)
        errors = []
        for k in range(rounds):
            lockstep_round(cores)
            if k % 50 == 49:
                errors.append(f"{error():.3g}")
        for k, v in saved.items():
            setattr(A, k, v)
        print(f"{name}: {' '.join(errors)}", flush=True)


def _json_object(text: str) -> dict[str, Any]:
    """An argument that must be a JSON object (argparse turns the ValueError into exit 2)."""
    value = json.loads(text)
    if not isinstance(value, dict):
        raise ValueError(text)
    return value


def main(argv: list[str] | None = None) -> None:
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("fleet", nargs="?", type=_json_object, help='the fleet, e.g. \'{"robots": 32, "topology": "geometric"}\'')
    ap.add_argument("variant", nargs="?", type=_json_object, default={}, help='the variant, e.g. \'{"ACT": 0}\'')
    ap.add_argument("--affine-piece", action="store_true", help="the 32-robot fleet's affine piece (docs)")
    args = ap.parse_args(argv)
    if args.affine_piece:
        affine_piece()
        return
    if args.fleet is None:
        ap.error("give a fleet (a JSON object) or --affine-piece")
    print(json.dumps({"fleet": args.fleet, "variant": args.variant, **run(args.fleet, args.variant)}), flush=True)


if __name__ == "__main__":
    main()
