"""The relay hub's Anderson design, swept in process: rounds at stop, error against the exact central
QP, restarts and CPU for every relay fleet under a variant of the relay's constants.

Why: issue 10's ring targets (8-ring <= 600 rounds at stop, 16-ring <= 1000) depend on the relay's
Anderson memory, regularisation, safeguard and relaxation; `simulate` is deterministic, so a variant
is judged by its rounds and errors (no A/B needed), its CPU beside them (noisy: a shared machine).

    .venv/bin/python benchmarks/relay_anderson.py                       # today's constants, the fleets
    .venv/bin/python benchmarks/relay_anderson.py --memory "min(100, n * dim // 2)" --reg 1e-3
    .venv/bin/python benchmarks/relay_anderson.py --fleets 8-ring 16-ring --jobs 2
    .venv/bin/python benchmarks/relay_anderson.py --fleets 4-ring 6-ring 8-ring --seeds 0 1 2 3 4 --warm-qp on
    .venv/bin/python benchmarks/relay_anderson.py --jobs 2 --seeds 0 1 2 --endgame off   # the ADMM alone (before ringend)

--endgame sets RELAY_ENDGAME (the paused exact end-game, branch ringend; on by default for hard margins); the
table's last column gives its attempts, paused rounds and whether it certified. --C runs every chosen fleet with
a soft margin at each C (errors against the exact central soft QP), --soft-endgame sets RELAY_SOFT_ENDGAME (branch
relaysoft); --quiet / --estimate / --gap / --max-steps / --judge replace the end-game's start rule and its
ends of a failing attempt (RELAY_ENDGAME_QUIET, _ESTIMATE, _GAP, _MAX_STEPS, _JUDGE).

    .venv/bin/python benchmarks/relay_anderson.py --jobs 1 --fleets 4-ring 6-ring 8-ring --seeds 0 1 2 --C 1 10 100 --soft-endgame off

--warm-qp sets RELAY_WARM_QP (the exact warm-started local QP where the guard decides), --seeds runs
every chosen fleet at each seed (the hold's safety check), --no-frame-budget lets the guard's payload
ride wherever a frame's MAX_DIM allows (a what-if for the 16-robot fleets, beyond the frame budget).
--check computes the certificate every round (the same path and stops) and counts the robot-rounds whose
certified bound (`error_bound`) is below the robot's true error (never, if the proof holds).
--memory is a Python expression in n (robots), dim (M + 1), D (the graph's diameter) and a (the
fleet's ADMMParams.anderson); the other flags replace the module's constants for the run.

The stop's lag (branch relaystop): a stop rule changes when the fleet stops, never the path, so rules are
compared offline. --trace DIR runs each fleet with the stop disabled and records per round what a copy's
rule may see and the true error of the robots' answer (DIR/<fleet>.json); --replay FILES replays main's
rule (MAIN_RULES) and the module's (`relay_stop_tests`) on them, --as-unguarded the unguarded rule on
every trace (its safety on the guarded fleets' plateaus too); --certify 0 runs every fleet without guard.

    .venv/bin/python benchmarks/relay_anderson.py --jobs 2 --fleets 8-ring 16-ring --seeds 0 1 2 --trace /tmp/tr
    .venv/bin/python benchmarks/relay_anderson.py --replay /tmp/tr/*.json [--as-unguarded] [--trace-tols 1e-3 1e-4]

The slow phase (branch ring16): --emulate-delay D... runs the chosen fleets' own map and the module's Anderson
with another delay (1: the undelayed accelerated hub on the same robots' data), to tell a plateau that is the
hub ADMM's own from one the delay makes (benchmarks/results/rounds-stop-relay.md, top).

    .venv/bin/python benchmarks/relay_anderson.py --fleets 16-ring --seeds 0 1 2 3 4 5 --emulate-delay 1 2 4 8 --jobs 2

Identification and cuts (branch hubactive): with --emulate-delay, --identify restart|skip restarts Anderson or
leaves out the secant pair where a robot's active set changed (--signal oracle: the rows' truth; test: the
copies' `piece_changed`; --cool C: at most once every C x D rounds), --cut-model replaces Anderson's iterate by
the fixed point of the relaxed QP on the cuts every copy can compute (`step_cuts`; steps: every round until
--handoff; rows: the robots' own rows, beyond the frames; potential: the path unchanged, the model's first round
within 1e-3). --emulate-delay 0 runs each fleet at its own D.

    .venv/bin/python benchmarks/relay_anderson.py --fleets 16-ring --seeds 0 1 2 3 4 5 --emulate-delay 8 --identify restart --cool 2
    .venv/bin/python benchmarks/relay_anderson.py --fleets 16-ring 8-ring --seeds 0 1 2 3 4 5 --emulate-delay 0 --cut-model steps --handoff 200
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agents import admm, relay_hub  # noqa: E402
from agents.admm import ADMMParams  # noqa: E402
from benchmarks.common import lockstep_round  # noqa: E402

#: rounds a trace runs on past the last stop of main's rule (`--trace`)
TRACE_EXTRA = 300

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


#: the relay module's constants a variant may replace
_DEFAULTS = {key: getattr(relay_hub, key) for key in ("RELAY_REG", "RELAY_SAFEGUARD", "RELAY_RELAX", "RELAY_HOLD",
                                                      "RELAY_HOLD_CERTIFIED", "RELAY_FAST_HOLD", "RELAY_WARM_QP",
                                                      "RELAY_ENDGAME", "RELAY_SOFT_ENDGAME", "RELAY_ENDGAME_QUIET",
                                                      "RELAY_ENDGAME_ESTIMATE", "RELAY_ENDGAME_GAP",
                                                      "RELAY_ENDGAME_MAX_STEPS", "RELAY_ENDGAME_JUDGE")}


def configure(variant: dict[str, Any]) -> None:
    """Replace the relay module's constants (and its memory rule) by the variant's."""
    for key, default in _DEFAULTS.items():  # (a pool's process runs several tasks: reset what a trace changed)
        setattr(relay_hub, key, default if variant.get(key) is None else variant[key])
    if variant.get("no_frame_budget"):  # what-if: the guard's payload on every relay fleet (MAX_DIM only)
        relay_hub.relay_cert_slot = lambda params, n, dim: (  # noqa: E731
            relay_hub.certify_slot(params) and n * (dim + relay_hub.cert_math.PAYLOAD) <= relay_hub.MAX_DIM)
    if variant.get("memory"):
        expr = variant["memory"]
        relay_hub.relay_memory = lambda params, n, dim, D: int(eval(expr, {"min": min, "max": max},  # noqa: E731
                                                                    {"n": n, "dim": dim, "D": D, "a": params.anderson}))


#: main's relay stop tests before branch relaystop, ((window, margin, hold), ...) without and with the guard
MAIN_RULES: dict[bool, tuple[tuple[int, float, int], ...]] = {False: ((20, 2.0, 40),), True: ((20, 2.0, 20),)}
Rules = dict[bool, tuple[tuple[int, float, int], ...]]


def rule_stop(residuals: list[float | None], bounds: list[float], *, tol: float, guarded: bool, delay: int,
              threshold: float, tests: tuple[tuple[int, float, int], ...]) -> int | None:
    """A relay stop rule replayed on a trace (row R: the residual of the step that formed round R and
    the guard's bound of that step): any test (window, margin, hold) with margin x error_estimate(window)
    below tol for `hold` rounds in a row, and where the guard decides the bound <= threshold; the fleet
    stops in that round (`RelayHubADMM.fleet_wide_verdict`; D rounds of flags later before: pass `delay`
    to replay that) -- the core's arithmetic: a replay gives the core's stop round for round. Returns
    the round the fleet stops at, or None."""
    kept = 2 * max(w for w, _, _ in tests)
    window: list[float] = []
    held: tuple[int, ...] = (0,) * len(tests)
    for R, r in enumerate(residuals):
        if r is None:
            continue
        window = (window + [r])[-kept:]
        held = relay_hub.relay_stop_held(held, window, tests, tol)
        if relay_hub.relay_stop_passed(held, tests) and (not guarded or bounds[R] <= threshold):
            return R + delay
    return None


def trace_stops(doc: dict[str, Any], tol: float, rules: Rules,
                guarded: bool | None = None, flag_rounds: bool = False) -> int | None:
    """The stop of `rules` (by guarded) on a trace document at tol; guarded=False replays the unguarded
    rule on a guarded run (its safety on every trace, the guard ignored)."""
    rows = doc["rows"]
    on = doc["guarded"] if guarded is None else guarded
    res = [row.get("residual") for row in rows]
    bounds = [math.inf if row.get("bound") is None else row["bound"] for row in rows]
    return rule_stop(res, bounds, tol=tol, guarded=on, delay=doc["D"] if flag_rounds else 0,
                     threshold=doc["certify"] * max(tol, admm.CERTIFY_TOL_FLOOR), tests=rules[on])


def current_rules() -> Rules:
    """The relay module's stop tests (as configured), by guarded."""
    return {g: relay_hub.relay_stop_tests(g) for g in (False, True)}


def trace_run(label: str, cores: list[Any], error: Any, max_rounds: int, tols: list[float],
              out: Path, rules: Rules) -> dict[str, Any]:
    """Run the fleet past every stop main's rule and `rules` would make (at each of `tols`, + TRACE_EXTRA
    rounds or to the cap) with the stop disabled, recording per round everything a copy's stop rule may see and
    the true error of the robots' answer (a stop rule changes when the fleet stops, never the path:
    rules are then compared offline, `--replay`). Writes DIR/<label>.json."""
    core = cores[0]
    steps: dict[int, dict[str, Any]] = {}
    step = relay_hub.RelayHubADMM._fleet_step
    forget = relay_hub.RelayHubADMM._forget

    def counted(self: relay_hub.RelayHubADMM) -> None:
        steps.setdefault(self.round + 1, {})["restart"] = True
        forget(self)

    def recorded(self: relay_hub.RelayHubADMM, S: Any, A: Any) -> bool:
        below = step(self, S, A)
        g = self._hist_g[-1]
        steps.setdefault(self.round + 1, {}).update(
            residual=self.residual, fixed_point=math.sqrt(float(g @ g)), pairs=len(self._dg),
            xnorm=math.sqrt(float(self._prev_mean[:-1] @ self._prev_mean[:-1])), gamma=float(self._prev_mean[-1]))
        return below

    relay_hub.RelayHubADMM._fleet_step = recorded  # type: ignore[method-assign]
    relay_hub.RelayHubADMM._forget = counted  # type: ignore[method-assign]
    rows: list[dict[str, Any]] = [{"round": 0, "error": error()}]
    params = core.params
    stops: dict[tuple[float, int], int | None] = {}
    while core.round < max_rounds:
        lockstep_round(cores)
        R = core.round
        info = steps.pop(R, {})
        rows.append({"round": R, "error": error(), "residual": info.get("residual"),
                     "fixed_point": info.get("fixed_point"), "pairs": info.get("pairs"),
                     "xnorm": info.get("xnorm"), "gamma": info.get("gamma"),
                     "restart": bool(info.get("restart")), "bound": core._fleet_bound if core._cert_on else None})
        if R % 50 == 0 or R == max_rounds:
            doc = {"rows": rows, "guarded": core._cert_on, "D": core.delay, "certify": params.certify}
            for tol in tols:
                for k, rs in enumerate((MAIN_RULES, rules)):
                    if stops.get((tol, k)) is None:
                        stops[tol, k] = trace_stops(doc, tol, rs, flag_rounds=k == 0)
            if all(s is not None and R >= s + TRACE_EXTRA for s in stops.values()):
                break
    relay_hub.RelayHubADMM._fleet_step = step  # type: ignore[method-assign]
    relay_hub.RelayHubADMM._forget = forget  # type: ignore[method-assign]
    doc = {"label": label, "n": core.n, "D": core.delay, "guarded": core._cert_on, "tol": params.tol,
           "certify": params.certify, "rules": [MAIN_RULES[core._cert_on], rules[core._cert_on]],
           "stops": {f"{t:g} {('main', 'rule')[k]}": s for (t, k), s in stops.items()}, "rows": rows}
    out.mkdir(parents=True, exist_ok=True)
    (out / (label.replace(" ", "_") + ".json")).write_text(json.dumps(doc))
    return doc


def replay(paths: list[Path], tols: list[float], as_unguarded: bool = False) -> dict[str, Any]:
    """Main's stop rule and the module's replayed on traces (`--trace`): per run and tol the round of
    the stop and the true error there, and a summary (the rule's rounds against main's where both stop,
    runs that stop later or no longer stop, every stop above tol). as_unguarded: the unguarded rule on
    every trace, the guard ignored (its safety on the guarded fleets' plateaus too)."""
    rules = current_rules()
    print(f"main {MAIN_RULES}, rule {rules} ((window, margin, hold), ... by guarded); "
          f"{'every run as unguarded' if as_unguarded else 'guard as run'}")
    print("| run | guarded | D | tol | error < tol first | main: stop (error) | rule: stop (error) |")
    print("|---|---|---:|---:|---:|---:|---:|")
    sums = {"main": 0, "rule": 0, "both": 0, "earlier": 0, "later": 0, "no_longer": 0, "newly": 0,
            "unsafe_main": [], "unsafe_rule": [], "worst_main": 0.0, "worst_rule": 0.0}
    for path in paths:
        doc = json.loads(path.read_text())
        errors = [row["error"] for row in doc["rows"]]
        guarded = False if as_unguarded else None
        for tol in tols:
            first = next((R for R, e in enumerate(errors) if e < tol), None)
            cells, stops = [], []
            for key, rs in (("main", MAIN_RULES), ("rule", rules)):
                stop = trace_stops(doc, tol, rs, guarded, flag_rounds=key == "main")
                if stop is not None and stop >= len(errors):
                    stop = None  # (past the trace's end: not seen)
                stops.append(stop)
                if stop is None:
                    cells.append("-")
                    continue
                err = errors[stop]
                cells.append(f"{stop} ({err:.1e}{' ABOVE TOL' if err > tol else ''})")
                sums[f"worst_{key}"] = max(sums[f"worst_{key}"], err)
                if err > tol:
                    sums[f"unsafe_{key}"].append(f"{doc['label']} tol {tol:g}: {stop} ({err:.2e})")
            m, r = stops
            if m is not None and r is not None:
                sums["main"] += m
                sums["rule"] += r
                sums["both"] += 1
                sums["earlier"] += r < m
                sums["later"] += r > m
            sums["no_longer"] += m is not None and r is None
            sums["newly"] += m is None and r is not None
            print(f"| {doc['label']} | {'yes' if doc['guarded'] and not as_unguarded else 'no'} | {doc['D']} | "
                  f"{tol:g} | {first} | {cells[0]} | {cells[1]} |")
    print(f"where both stop ({sums['both']} runs x tols): main {sums['main']} rounds, rule {sums['rule']} "
          f"({sums['earlier']} earlier, {sums['later']} later); no longer stop {sums['no_longer']}, newly stop "
          f"{sums['newly']}; largest error at a stop main {sums['worst_main']:.1e}, rule {sums['worst_rule']:.1e}; "
          f"above tol: main {len(sums['unsafe_main'])} {sums['unsafe_main']}, rule {len(sums['unsafe_rule'])} "
          f"{sums['unsafe_rule']}")
    return sums


def run(task: tuple[str, dict[str, Any], dict[str, Any], int]) -> dict[str, Any]:
    """One fleet under one variant: rounds to 1e-3 and at stop, error, restarts, CPU."""
    from agents.problem import solve_central
    from agents.spec import build_core
    from launcher.world import Options, build_world

    label, kwargs, variant, max_rounds = task
    configure(variant)
    trace = variant.get("trace")
    rules = current_rules()
    if variant.get("check"):  # the payload and the certificate every round (the same path and stops)
        admm.CERTIFY_EVERY_ROUND, admm.CERTIFY_ARM = True, math.inf
    if trace:  # never stop; the guard's bound every round (the path is the same: admm.CERTIFY_EVERY_ROUND)
        relay_hub.RELAY_HOLD = relay_hub.RELAY_HOLD_CERTIFIED = relay_hub.RELAY_FAST_HOLD = 10**9  # every test
        relay_hub.RELAY_ENDGAME = False  # (the ADMM's own path: no end-game ends the trace)
        admm.CERTIFY_EVERY_ROUND, admm.CERTIFY_ARM = True, math.inf
    restarts = [0]
    forget = relay_hub.RelayHubADMM._forget

    def counted(self: relay_hub.RelayHubADMM) -> None:
        restarts[0] += 1
        forget(self)

    relay_hub.RelayHubADMM._forget = counted  # type: ignore[method-assign]
    extra = {} if variant.get("certify") is None else {"certify": variant["certify"]}
    world, spec = build_world(Options(fleet_id="bench", preset="paper", max_rounds=max_rounds, **kwargs, **extra))
    central = solve_central(spec.basis, world.points, world.labels, spec.C)
    b = spec.basis
    started = time.process_time()
    cores = [build_core(spec, i, keep_trace=False) for i in spec.robot_ids]
    assert isinstance(cores[0], relay_hub.RelayHubADMM), "not a relay fleet"
    restarts[0] = 0  # (every core forgets once at its start)

    def error() -> float:
        return max(b.function_error(b.c_from_x(c.values[:-1]), c.values[-1], central.c, central.gamma) for c in cores)

    if trace:
        doc = trace_run(label, cores, error, max_rounds, variant["trace_tols"], Path(trace), rules)
        stop = doc["stops"][f"{variant['trace_tols'][0]:g} rule"]
        errs = [row["error"] for row in doc["rows"]]
        first = next((R for R, e in enumerate(errs) if e < 1e-3), None)
        return {"fleet": label, "first": first, "stop": stop or max_rounds,
                "error": errs[stop] if stop is not None and stop < len(errs) else errs[-1],
                "converged": stop is not None, "restarts": sum(row.get("restart", False) for row in doc["rows"]),
                "memory": cores[0]._memory, "D": cores[0].delay, "cpu": time.process_time() - started,
                "ms_round": 0.0}
    first = None
    checked = unsafe = 0
    while not all(c.finished for c in cores):
        lockstep_round(cores)
        if first is None and error() < 1e-3:
            first = cores[0].round
        if variant.get("check"):  # every robot's certified bound against its true error (never below)
            for c in cores:
                bound = c.error_bound()
                if bound is not None:
                    checked += 1
                    unsafe += bound < b.function_error(b.c_from_x(c.values[:-1]), c.values[-1], central.c,
                                                       central.gamma)
    cpu = time.process_time() - started
    rounds = cores[0].round
    bounds = [c.error_bound() for c in cores]
    core = cores[0]
    return {"fleet": label, "first": first, "stop": rounds, "error": error(),
            "endgame": "-" if core._endgame is None else
                       f"{core._attempts} / {core._paused} / {'yes' if core._mode == 'certified' else 'no'}",
            "converged": all(c.converged for c in cores), "restarts": restarts[0],
            "memory": cores[0]._memory, "D": cores[0].delay, "cpu": cpu, "ms_round": 1e3 * cpu / max(rounds, 1),
            "bound": None if None in bounds else max(bounds), "checked": checked, "unsafe": unsafe}


#: a margin row counts as active in a step when within this of tight (the emulation's truth; piqp: ~1e-10)
ACTIVE_TOL = 1e-7
def step_normals(copy: relay_hub.RelayHubADMM, X: np.ndarray, T: np.ndarray) -> np.ndarray:
    """`relay_hub.step_normals` with a copy's step diagonal and P (the end-game's piece test, moved there)."""
    return relay_hub.step_normals(copy._pdiag, copy._P, X, T)


piece_changed = relay_hub.piece_changed


def step_cuts(X: np.ndarray, W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The cuts of a step, hard margins: w_l = W_l / (W_l . x_l) satisfies w_l . v >= 1 at every v that
    satisfies robot l's margins, since W_l . x_l = sum lam_i (complementarity: a_i . x_l = 1 where lam_i >
    0) and w_l is a convex combination of its active rows -- an outer approximation of the fleet's feasible
    set from held values. Returns (cuts, owners) for the robots with an active row."""
    s = np.sum(W * X, axis=1)
    ok = (np.linalg.norm(W, axis=1) > 0) & (s > 0)
    return W[ok] / s[ok, None], np.nonzero(ok)[0]


def cut_model(cuts: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The relaxed central QP min 1/2 |x|^2 s.t. cuts @ v >= 1 (piqp to 1e-10): its v and the cuts'
    multipliers, or None (unbounded or unsolved: too few cuts yet)."""
    import piqp

    dim = cuts.shape[1]
    solver = piqp.DenseSolver()
    solver.settings.eps_abs = solver.settings.eps_rel = 1e-10
    P = np.eye(dim)
    P[-1, -1] = 0.0
    m = len(cuts)
    solver.setup(P, np.zeros(dim), None, None, np.ascontiguousarray(cuts), np.ones(m), np.full(m, np.inf), None, None)
    if solver.solve() != piqp.PIQP_SOLVED:
        return None
    return np.array(solver.result.x), np.array(solver.result.z_l)


def model_state(copy: relay_hub.RelayHubADMM, z: np.ndarray, mu: np.ndarray, cuts: np.ndarray,
                owners: np.ndarray) -> np.ndarray:
    """The fleet state whose fixed point the cut model says z is: robot l's multiplier combination W_l =
    sum of mu_c w_c over its cuts, t_l = ((P + 1/N on x) z - W_l) / P (then sum_l t_l = N z, as at a fixed
    point). Exact where the model's rows are robot l's (the model then equals the problem near z)."""
    Wm = np.zeros((copy.n, copy.dim))
    np.add.at(Wm, owners, mu[:, None] * cuts)
    return ((copy._pdiag * z - Wm) / copy._P).ravel()


def emulate(task: tuple[str, dict[str, Any], int, int, dict[str, Any]]) -> dict[str, Any]:
    """The relay's fleet iteration with another delay D, in process (`--emulate-delay`): the same map F
    (every robot's own QP step) and the same Anderson code (`RelayHubADMM._fleet_step` of one copy), S^(k+1)
    formed from F(S^(k+1-D)); D = 1 is the undelayed accelerated hub on these robots' data. Why: it tells
    a plateau that is the hub ADMM's own (in iterations) from one the delay makes. Returns the first round
    whose x_l (the step of round k + 1 - D, max over robots) is within 1e-3 of the exact QP, restarts, and
    the active sets (rows with margin < 1 + ACTIVE_TOL in each robot's step): changes and the last round one
    changed.

    Variants (branch hubactive, `--identify`, `--cut-model`): `identify` restarts Anderson ("restart") or
    leaves out the secant pair ("skip") wherever a robot's active set changed between two steps -- by the
    truth ("oracle") or by `piece_changed` ("test"), at most once every `cool` x D rounds; `cut_model`
    replaces Anderson's S^(k+1) by `model_state` of the relaxed QP on the cuts so far ("steps": the cuts the
    last model used plus the newest; "rows": the robots' own active rows instead of the cuts, beyond the
    frames) until round `handoff`, or only solves it on every cut so far ("potential": the path unchanged)."""
    from agents.problem import solve_central
    from agents.spec import build_core
    from launcher.world import Options, build_world

    label, kwargs, delay, max_rounds, variant = task
    identify, signal, cool = variant.get("identify"), variant.get("signal", "oracle"), variant.get("cool", 0.0)
    model, handoff = variant.get("cut_model"), variant.get("handoff") or max_rounds
    configure({})
    world, spec = build_world(Options(fleet_id="bench", preset="paper", max_rounds=max_rounds, **kwargs))
    central = solve_central(spec.basis, world.points, world.labels, spec.C)
    b = spec.basis
    cores = [build_core(spec, i, keep_trace=False) for i in spec.robot_ids]
    copy = cores[0]
    assert isinstance(copy, relay_hub.RelayHubADMM), "not a relay fleet"
    n, d = copy.n, copy.dim
    delay = delay or copy.delay  # (0: the fleet's own D)
    restarts = [0]
    forget = copy._forget

    def counted() -> None:
        restarts[0] += 1
        forget()

    copy._forget = counted  # type: ignore[method-assign]
    S: dict[int, Any] = {0: np.concatenate([c._values for c in cores])}  # S^0: every robot's own solution
    rows = [c._qp._rows for c in cores]
    error_of = lambda v: b.function_error(b.c_from_x(v[:-1]), v[-1], central.c, central.gamma)  # noqa: E731
    first, changes, settled, previous = None, 0, 0, None
    prev_XW: tuple[np.ndarray, np.ndarray] | None = None
    last_identify, signalled, missed, false = -(10**9), 0, 0, 0
    cuts, owners, model_first, model_steps = np.zeros((0, d)), np.zeros(0, int), None, 0
    for k in range(max_rounds):
        j = k + 1 - delay
        if j < 0:
            S[k + 1] = S[0]
            continue
        T = S[j].reshape(n, d)
        X = np.array([c._values if j == 0 else c._solve(T[l]) for l, c in enumerate(cores)])
        active = [tuple(np.nonzero(r @ x < 1.0 + ACTIVE_TOL)[0]) for r, x in zip(rows, X)]
        truth = np.array([previous is not None and a != p for a, p in zip(active, previous or active)])
        W = step_normals(copy, X, T)
        seen = np.zeros(n, bool) if prev_XW is None or j == 1 else piece_changed(*prev_XW, X, W)
        prev_XW = (X, W)
        signalled, missed, false = signalled + int(np.sum(seen & truth)), missed + int(np.sum(truth & ~seen)), \
            false + int(np.sum(seen & ~truth))
        if identify and (truth if signal == "oracle" else seen).any() and k - last_identify >= cool * delay:
            last_identify = k
            if identify == "restart":
                copy._forget()
            else:  # "skip": the pair across the change is not recorded; older pairs stay
                copy._hist_g, copy._hist_F = [], []
        copy.round = k
        copy._fleet_step(S[j], 2.0 * X - T)
        S[k + 1] = copy._S.pop(k + 1)
        if j > 1:  # (S^0 stays: the steps before round D read it)
            S.pop(j - 1, None)
        if model and j > 0:
            if model == "rows":  # the robots' own active rows (beyond the frames): the model's best case
                new = [r[list(a)] for r, a in zip(rows, active)]
                c_new, o_new = np.vstack(new), np.repeat(np.arange(n), [len(a) for a in new])
            else:
                c_new, o_new = step_cuts(X, W)
            cuts, owners = np.vstack([cuts, c_new]), np.concatenate([owners, o_new])
            if model == "potential" and (k + 1) % 10 == 0 and model_first is None:
                solved = cut_model(cuts)
                if solved is not None and error_of(solved[0]) < 1e-3:
                    model_first = k + 1
            elif model != "potential" and k < handoff and len(cuts) >= d:
                solved = cut_model(cuts)
                if solved is not None:
                    z, mu = solved
                    S[k + 1] = model_state(copy, z, mu, cuts, owners)
                    model_steps += 1
                    keep = mu > 1e-9 * max(1.0, float(mu.max()))  # the pool: the cuts the model used
                    cuts, owners = cuts[keep], owners[keep]
        if previous is not None and active != previous:
            changes += int(np.sum(truth))
            settled = k + 1
        previous = active
        if max(error_of(x) for x in X) < 1e-3:
            first = k + 1
            break
    return {"fleet": label, "D": delay, "real_D": copy.delay, "first": first, "restarts": restarts[0],
            "changes": changes, "settled": settled, "signalled": signalled, "missed": missed, "false": false,
            "model_first": model_first, "model_steps": model_steps}


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
    ap.add_argument("--endgame", choices=("on", "off"), default=None,
                    help="RELAY_ENDGAME: the paused exact end-game (hard margins); off: the ADMM alone")
    ap.add_argument("--soft-endgame", choices=("on", "off"), default=None,
                    help="RELAY_SOFT_ENDGAME: the paused end-game on soft margins too (with --C)")
    ap.add_argument("--C", nargs="*", type=float, default=None,
                    help="soft margins: every chosen fleet at each C (errors against the exact central soft QP)")
    ap.add_argument("--quiet", type=int, default=None, help="RELAY_ENDGAME_QUIET: the start rule's quiet steps")
    ap.add_argument("--estimate", type=float, default=None, help="RELAY_ENDGAME_ESTIMATE: the start rule's estimate")
    ap.add_argument("--gap", type=int, default=None, help="RELAY_ENDGAME_GAP: ADMM rounds after a failed attempt")
    ap.add_argument("--max-steps", type=int, default=None,
                    help="RELAY_ENDGAME_MAX_STEPS: end-game steps after which an attempt ends uncertified")
    ap.add_argument("--judge", type=int, default=None,
                    help="RELAY_ENDGAME_JUDGE: robots with a violated row after an attempt's first solve that end it")
    ap.add_argument("--no-frame-budget", action="store_true",
                    help="what-if: the guard's payload wherever a frame's MAX_DIM allows (the 16-robot fleets), "
                         "beyond the frame budget of FRAME_BUDGET x (M + 1) floats")
    ap.add_argument("--seeds", nargs="*", type=int, default=None,
                    help="run every chosen fleet at each of these seeds (the safety check of the hold)")
    ap.add_argument("--trace", default=None, metavar="DIR",
                    help="record per round the stop rule's inputs and the true error into DIR/<fleet>.json, "
                         "the stop disabled (past main's stop by TRACE_EXTRA rounds): rules replayed offline")
    ap.add_argument("--trace-tols", nargs="*", type=float, default=[1e-3],
                    help="the trace runs past main's stop at each of these tolerances")
    ap.add_argument("--replay", nargs="*", default=None, metavar="TRACE",
                    help="no runs: replay main's stop rule and the module's on these trace files (at --trace-tols)")
    ap.add_argument("--as-unguarded", action="store_true",
                    help="with --replay: the unguarded rule on every trace, the guard ignored")
    ap.add_argument("--label", default="", help="a prefix of the fleets' labels (trace file names)")
    ap.add_argument("--certify", type=float, default=None,
                    help="the fleets' certify (0: no guard anywhere, the unguarded stop rule on every fleet)")
    ap.add_argument("--check", action="store_true",
                    help="the certificate every round and every robot's certified bound against its true error "
                         "(columns: bound at the stop, robot-rounds with the bound below the error of those checked)")
    ap.add_argument("--emulate-delay", nargs="*", type=int, default=None, metavar="D",
                    help="no real runs: the chosen fleets' map and Anderson with each delay D in turn (1: no delay, "
                         "0: the fleet's own), "
                         "rounds until the step's x is within 1e-3 and the active sets' changes")
    ap.add_argument("--identify", choices=("restart", "skip"), default=None,
                    help="with --emulate-delay: restart Anderson / leave out the secant pair where a robot's active "
                         "set changed (branch hubactive)")
    ap.add_argument("--signal", choices=("oracle", "test"), default="oracle",
                    help="with --identify: the change by the truth (rows) or by the copies' piece test")
    ap.add_argument("--cool", type=float, default=0.0, help="with --identify: at most once every COOL x D rounds")
    ap.add_argument("--cut-model", choices=("potential", "steps", "rows"), default=None,
                    help="with --emulate-delay: the relaxed QP on the cuts the copies can compute (branch hubactive)")
    ap.add_argument("--handoff", type=int, default=None, help="with --cut-model steps/rows: model steps until this round")
    ap.add_argument("--normal-floor", type=float, default=None,
                    help="with --emulate-delay: NORMAL_FLOOR (W_l below it relative to its terms: no active row)")
    ap.add_argument("--max-rounds", type=int, default=5000)
    ap.add_argument("--jobs", type=int, default=1)
    args = ap.parse_args()
    if args.replay is not None:
        replay([Path(p) for p in args.replay], args.trace_tols, args.as_unguarded)
        return
    fleets = stop_check_fleets() if args.stop_check else {f: RELAY_FLEETS[f] for f in args.fleets}
    if args.seeds is not None:
        fleets = {f"{f.split('-s')[0]} s{seed}": {**kw, "seed": seed} for f, kw in fleets.items() for seed in args.seeds}
    if args.C is not None:
        fleets = {f"{f} C{C:g}": {**kw, "C": C} for f, kw in fleets.items() for C in args.C}
    if args.emulate_delay is not None:
        if args.normal_floor is not None:  # (the pool's workers fork)
            relay_hub.NORMAL_FLOOR = args.normal_floor
        emulated = {"identify": args.identify, "signal": args.signal, "cool": args.cool, "cut_model": args.cut_model,
                    "handoff": args.handoff}
        print(f"variant: {emulated}, NORMAL_FLOOR {relay_hub.NORMAL_FLOOR:g}")
        print("| fleet | its D | emulated D | rounds to 1e-3 | restarts | active-set changes | last change | "
              "piece test: seen / missed / false | model: steps, potential's first < 1e-3 |")
        print("|---|---:|---:|---:|---:|---:|---:|---|---|")
        tasks = [(f, kw, D, args.max_rounds, emulated) for f, kw in fleets.items() for D in args.emulate_delay]
        with multiprocessing.Pool(args.jobs) as pool:
            for r in pool.imap(emulate, tasks):
                print(f"| {r['fleet']} | {r['real_D']} | {r['D']} | {r['first'] or 'cap'} | {r['restarts']} | "
                      f"{r['changes']} | {r['settled']} | {r['signalled']} / {r['missed']} / {r['false']} | "
                      f"{r['model_steps']}, {r['model_first'] or '-'} |", flush=True)
        return
    variant = {"memory": args.memory, "RELAY_REG": args.reg, "RELAY_SAFEGUARD": args.safeguard,
               "RELAY_RELAX": args.relax, "RELAY_HOLD": args.hold,
               "RELAY_HOLD_CERTIFIED": args.hold_certified,
               "RELAY_WARM_QP": None if args.warm_qp is None else args.warm_qp == "on",
               "RELAY_ENDGAME": None if args.endgame is None else args.endgame == "on",
               "RELAY_SOFT_ENDGAME": None if args.soft_endgame is None else args.soft_endgame == "on",
               "RELAY_ENDGAME_QUIET": args.quiet, "RELAY_ENDGAME_ESTIMATE": args.estimate,
               "RELAY_ENDGAME_GAP": args.gap, "RELAY_ENDGAME_MAX_STEPS": args.max_steps,
               "RELAY_ENDGAME_JUDGE": args.judge,
               "no_frame_budget": args.no_frame_budget, "trace": args.trace, "trace_tols": args.trace_tols,
               "certify": args.certify, "check": args.check}
    tol = ADMMParams().tol
    print(f"variant: {variant}", flush=True)
    print("| fleet | D | memory | rounds to 1e-3 | rounds at stop | converged | error at stop | restarts | "
          "CPU s | CPU ms per round | bound at stop | bound < error | end-game: attempts / paused / certified |",
          flush=True)
    tasks = [(args.label + f, kw, variant, args.max_rounds) for f, kw in fleets.items()]
    total, worst, checked, unsafe = 0, 0.0, 0, 0
    with multiprocessing.Pool(args.jobs) as pool:
        for r in pool.imap(run, tasks):
            total += r["stop"]
            worst = max(worst, r["error"] if r["converged"] else 0.0)
            flag = "" if r["error"] <= tol or not r["converged"] else " ABOVE TOL"
            checked, unsafe = checked + r.get("checked", 0), unsafe + r.get("unsafe", 0)
            bound = "-" if r.get("bound") is None else f"{r['bound']:.1e}"
            check = f"{r['unsafe']} of {r['checked']}" if args.check else "-"
            print(f"| {r['fleet']} | {r['D']} | {r['memory']} | {r['first']} | {r['stop']} | "
                  f"{'yes' if r['converged'] else 'no'} | {r['error']:.1e}{flag} | {r['restarts']} | "
                  f"{r['cpu']:.1f} | {r['ms_round']:.1f} | {bound} | {check} | {r.get('endgame', '-')} |", flush=True)
    print(f"total rounds at stop {total}; largest error at a stop {worst:.1e} (tol {tol:g})"
          + (f"; bound below the true error on {unsafe} of {checked} robot-rounds" if args.check else ""), flush=True)


if __name__ == "__main__":
    main()
