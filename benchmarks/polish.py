"""An exact active-set end-game ("polish") for the ADMM: its potential, measured in process.

OSQP-style solution polishing for the hard-margin SVM: on a fixed set W of active margin rows the
QP  min 1/2 |x|^2  s.t.  a_i' v >= 1  becomes the equality-constrained QP  A_W v = 1, whose KKT
system is one linear solve (as `agents.problem.certify_hard_margin` does for the central
reference). A guess of W read from the ADMM iterate, plus a few primal-dual active-set (PDAS)
corrections -- drop the rows whose multiplier is negative, add the rows the point violates
(Hintermueller, Ito & Kunisch 2002) -- may reach the exact, KKT-certified optimum long before the
ADMM's own stop rule ends the run.

This is an oracle study, not a protocol: the fleet runs exactly as `simulate` (the cores in lock
step, `benchmarks/rounds.py fleet_probe`), and every K rounds the polish is run *centrally* on all
robots' rows from several guesses:

* ``union``: every robot's locally active rows (rows @ v_l <= 1 + 1e-7, fleet_probe's `active`);
* ``mean 1e-3`` / ``mean 1e-2``: the rows within that relative slack of equality at the mean iterate;
* ``local mult``: the rows with a positive multiplier in their robot's local QP (the multipliers
  recovered from the local KKT condition P v + q = A_act' lam, q the robot's proximal term).

A polish counts when its point passes `certify_hard_margin` on all rows (the KKT system on the
point's active rows, every multiplier positive, every margin held) and is then compared with
`solve_central`'s certified solution (function error). Hard margin only.

    .venv/bin/python benchmarks/polish.py              # every fleet (over an hour on 2 busy cores: the
                                                       # 24-48-robot fleets dominate; split with --fleet/--out)
    .venv/bin/python benchmarks/polish.py --quick      # the paper preset and the 8-ring
    .venv/bin/python benchmarks/polish.py --fleet "8 robots, ring" --every 5
    .venv/bin/python benchmarks/polish.py --implemented   # the hub form's polish as built (~5 minutes)
    .venv/bin/python benchmarks/polish.py --zenoh 2       # 32 robots over Zenoh, 2 A/B pairs (~3 minutes)
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agents.admm import POLISH_EQ, POLISH_RHO, POLISH_STAT, _pairwise_sum, polish_solve  # noqa: E402
from agents.problem import certify_hard_margin, solve_central  # noqa: E402
from agents.relay_hub import RelayHubADMM  # noqa: E402
from agents.spec import build_core  # noqa: E402
from benchmarks.common import FLEETS, add_row, lockstep_round, write_results  # noqa: E402
from benchmarks.rounds import LARGE_COMPLETE, fleet_probe, form_name  # noqa: E402
from launcher.world import Options, build_world  # noqa: E402

#: the fleets of the study, by their labels in benchmarks/common.py FLEETS and rounds.py LARGE_COMPLETE
FLEET_LABELS = [
    "paper setting: 3 robots, blob, complete",
    "3 robots, star",
    "3 robots, crescent",
    "8 robots, complete",
    "16 robots, complete",
    "24 robots",
    "32 robots, geometric",
    "32 robots, geometric, seed 1",
    "32 robots, geometric, bean",
    "48 robots, geometric",
    "4 robots, ring",
    "5 robots, line",
    "8 robots, ring",
    "16 robots, ring",
    "16 robots, geometric 3.0",
]
QUICK = ["paper setting: 3 robots, blob, complete", "8 robots, ring"]
GUESSES = ("union", "mean 1e-3", "mean 1e-2", "local mult")
#: corrections thresholds reported: first round certified with at most this many PDAS corrections
THRESHOLDS = (0, 1, 2, 5, 10)
MAX_CORRECTIONS = 10
#: a guess of more than this many times the dimension M + 1 rows is not tried (early rounds of large
#: fleets: hundreds of rows; PDAS from there needs far more than MAX_CORRECTIONS corrections)
MAX_GUESS = 4


def fleet_kwargs(label: str) -> dict:
    """Options keywords of a fleet named in FLEETS or LARGE_COMPLETE."""
    table = {name: kw for name, kw in FLEETS} | {name: kw for name, kw, _before in LARGE_COMPLETE}
    return table[label]


@dataclass
class Polish:
    """One PDAS run: did it certify, after how many corrections, the point and its error."""

    certified: bool
    corrections: int
    v: np.ndarray | None
    size: int  # |W| of the final set
    W: np.ndarray | None = None  # the final set, when certified


def kkt_on(rows: np.ndarray, W: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """The equality-constrained QP min 1/2|x|^2 s.t. rows[W] v = 1: (v, multipliers, KKT residual).

    Least squares (minimum norm) as certify_hard_margin: a guess with more rows than the
    dimension, or dependent rows, gives an inconsistent or singular system; its residual says so."""
    A = rows[W]
    n, k = rows.shape[1], len(W)
    p = np.eye(n)
    p[-1, -1] = 0.0
    kkt = np.block([[p, -A.T], [A, np.zeros((k, k))]])
    rhs = np.concatenate([np.zeros(n), np.ones(k)])
    sol = np.linalg.lstsq(kkt, rhs, rcond=None)[0]
    return sol[:n], sol[n:], float(np.abs(kkt @ sol - rhs).max())


def _robot_moves(W: np.ndarray, lam: np.ndarray, add: np.ndarray, slack: np.ndarray, owner: np.ndarray) -> np.ndarray:
    """Each robot moves at most one of its own rows: it drops its row of most negative multiplier,
    or, with none negative, adds its most violated row -- a choice each robot makes alone."""
    drop: list[int] = []
    new: list[int] = []
    for robot in np.unique(np.concatenate([owner[W], owner[add]])):
        mine = owner[W] == robot
        if mine.any() and lam[mine].min() <= 0:
            drop.append(int(W[mine][np.argmin(lam[mine])]))
            continue
        theirs = add[owner[add] == robot]
        if len(theirs):
            new.append(int(theirs[np.argmin(slack[theirs])]))
    return np.union1d(np.setdiff1d(W, drop), np.array(new, dtype=int))


def pdas(rows: np.ndarray, guess: np.ndarray, max_corrections: int = MAX_CORRECTIONS, *, mode: str = "swap",
         owner: np.ndarray | None = None) -> Polish:
    """Primal-dual active set from `guess` (row indices): solve on W; unless the point satisfies
    the KKT conditions with W (residual < 1e-10, every multiplier positive, every margin held) and
    `certify_hard_margin` certifies it on its own active rows, correct W and solve again.
    Corrections by `mode`:

    * swap: W <- {i in W: lam_i > 0} + {i not in W: a_i v < 1} (PDAS proper; each robot can make
      its share of it alone);
    * one: drop the fleet's most negative multiplier, or else add its most violated row (one row
      per correction: a fleet-wide argmin, a second all-reduce when distributed);
    * robot: every robot drops its own most negative multiplier or adds its own most violated row
      (`_robot_moves`, row owners in `owner`).

    `corrections` counts the corrections taken (so corrections + 1 solves); a guess larger than
    MAX_GUESS x the dimension is not tried (one solve's worth: 0 corrections, not certified)."""
    W = np.unique(np.asarray(guess, dtype=int))
    if len(W) > MAX_GUESS * rows.shape[1]:  # far more rows than unknowns: not a guess worth a solve
        return Polish(False, 0, None, len(W))
    for corrections in range(max_corrections + 1):
        if len(W) == 0:
            return Polish(False, corrections, None, 0)
        v, lam, res = kkt_on(rows, W)
        slack = rows @ v - 1.0
        if res < 1e-10 and lam.min() > 0 and slack.min() > -1e-12:  # the KKT conditions hold on W ...
            exact = certify_hard_margin(rows, v)  # ... and on the point's own active rows
            if exact is not None:
                return Polish(True, corrections, exact, len(W), W)
        if corrections == max_corrections:
            break
        inside = np.zeros(len(rows), dtype=bool)
        inside[W] = True
        add = np.flatnonzero(~inside & (slack < -1e-12))
        if mode == "one" and lam.min() <= 0:
            new = np.delete(W, int(np.argmin(lam)))
        elif mode == "one":
            new = np.union1d(W, add[np.argmin(slack[add])]) if len(add) else W
        elif mode == "robot":
            assert owner is not None
            new = _robot_moves(W, lam, add, slack, owner)
        else:
            new = np.union1d(W[lam > 0], add)
        if np.array_equal(new, W):  # no PDAS move left (a degenerate or inconsistent set)
            return Polish(False, corrections, None, len(W))
        W = new
    return Polish(False, max_corrections, None, len(W))


def gram_route(rows: np.ndarray, W: np.ndarray, owner: np.ndarray, n_robots: int) -> tuple[np.ndarray, bool, int]:
    """The polish on set W as the fleet computes it (option (a) with Gram sums, as built in
    agents/admm.py `_Polish`): robot l contributes H_l = A_l' A_l and b_l = A_l' 1 over its rows in W
    (newton's A_l' D A_l with D the 0/1 indicator of W_l), the fleet sums them exactly
    (`_pairwise_sum`, robot order), every copy runs `polish_solve` (the method of multipliers on
    {H v = b} = {A_W v = 1}) and robot l keeps its own multipliers lam_l = -rho sum_k (A_l v_k - 1).
    Verdict = the AND of every robot's checks (its lam_l > 0, |A_l v - 1| <= POLISH_EQ, its margins
    >= 1 - POLISH_EQ) and the copy's stationarity |P v - y| <= POLISH_STAT max(1, |P v|).
    Returns (v, verdict, iterations)."""
    n = rows.shape[1]
    parts = np.zeros((n_robots, n * (n + 1) // 2 + n))
    for l in range(n_robots):
        A = rows[W[owner[W] == l]]
        parts[l, : n * (n + 1) // 2] = (A.T @ A)[np.triu_indices(n)]
        parts[l, n * (n + 1) // 2 :] = A.sum(axis=0)
    sums = _pairwise_sum(parts)
    H = np.zeros((n, n))
    H[np.triu_indices(n)] = sums[: n * (n + 1) // 2]
    H = H + np.triu(H, 1).T
    v, y, iterates = polish_solve(H, sums[n * (n + 1) // 2 :])
    A_W = rows[W]
    lam = -POLISH_RHO * np.sum([A_W @ x - 1.0 for x in iterates], axis=0)
    pv = v.copy()
    pv[-1] = 0.0
    verdict = bool(lam.min() > 0 and np.abs(A_W @ v - 1.0).max() <= POLISH_EQ and (rows @ v).min() >= 1.0 - POLISH_EQ
                   and np.abs(pv - y).max() <= POLISH_STAT * max(1.0, np.abs(pv).max()))
    return v, verdict, len(iterates)


def local_multiplier_rows(core, rows: np.ndarray) -> np.ndarray:
    """The robot's rows with a positive multiplier in its last local QP (local indices).

    Local KKT: P v + q = A_act' lam over its active rows (rows @ v <= 1 + 1e-7), P the QP's
    diagonal, q its proximal term: -rho (z - u_l) in the hub form, -P t_l in the relay hub."""
    v = core.values
    dim = len(v)
    act = np.flatnonzero(rows @ v <= 1 + 1e-7)
    if len(act) == 0:
        return act
    qp = core._qp
    pdiag = np.diag(qp._P)[:dim]
    if isinstance(core, RelayHubADMM):
        S = core._S.get(core.round)
        t = S[core._slots[core.robot_id]] if S is not None else core._a[core.robot_id][0]
        q = -core._P * t
    elif core._hub is not None and core._hub.s is not None:
        q = -core._hub.penalty * core._hub.center(core.robot_id)
    else:  # round 0 (own solve, no prox) or the edge form: not read
        return act
    grad = pdiag * v + q
    lam = np.linalg.lstsq(rows[act].T, grad, rcond=None)[0]
    return act[lam > 1e-9 * (1.0 + np.abs(lam).max())]


def guesses(cores, local_rows: list[np.ndarray], offsets: list[int], active: list[frozenset],
            all_rows: np.ndarray) -> dict[str, np.ndarray]:
    """The active-set guesses of one round, as indices into the fleet's stacked rows."""
    union = np.array(sorted(o + i for o, a in zip(offsets, active) for i in a), dtype=int)
    mean = np.add.reduce(np.array([c.values for c in cores]), axis=0) / len(cores)
    slack = all_rows @ mean - 1.0
    mult = [o + local_multiplier_rows(c, r) for c, r, o in zip(cores, local_rows, offsets)]
    return {
        "union": union,
        "mean 1e-3": np.flatnonzero(slack <= 1e-3),
        "mean 1e-2": np.flatnonzero(slack <= 1e-2),
        "local mult": np.concatenate(mult).astype(int) if mult else np.zeros(0, int),
    }


MODES = ("swap", "one", "robot")  # `pdas`'s correction modes
VARIANTS = [(g, m) for g in GUESSES for m in MODES]


def kkt_residual(rows: np.ndarray, v: np.ndarray) -> float:
    """The KKT residual of a point, independently of how it was found: stationarity
    |P v - A_act' lam| (lam by least squares on the rows within 1e-6 of equality), their equality
    |A_act v - 1|, the worst margin violation and the most negative multiplier."""
    act = rows[rows @ v - 1.0 < 1e-6]
    pv = v.copy()
    pv[-1] = 0.0
    lam = np.linalg.lstsq(act.T, pv, rcond=None)[0]
    return float(max(np.abs(act.T @ lam - pv).max(), np.abs(act @ v - 1.0).max(),
                     max(0.0, -(rows @ v - 1.0).min()), max(0.0, -lam.min())))


#: the correction caps of the attempt schedule (`Schedule`)
SCHEDULE_CAPS = (2, 5)
#: option (b), a Krylov method (MINRES/CG) on the KKT system with the multipliers kept local: one
#: all-reduce of an (M+1)-vector and a few scalars per iteration, and at least n + |W| ~ 30
#: iterations per solve in exact arithmetic (16 unknowns v, ~13 local multipliers): a lower bound
KRYLOV_REDUCES = 30


@dataclass
class Schedule:
    """One distributed polish strategy, replayed on the fleet's run: attempts one after another.

    An attempt starts at a round from that round's guess (each robot picks its own rows: locally
    active, near equality at the mean, positive local multiplier), then runs PDAS with at most
    `cap` corrections. Each solve is one all-reduce of the robots' projector sums (docs: option
    (a)), D rounds (`allreduce_rounds`); the global mode 'one' needs a second all-reduce (the
    fleet's argmin) per correction. A certified attempt ends the run after its last all-reduce
    and the stop flags' D rounds; a failed one frees the slot for the next attempt. The ADMM runs
    on meanwhile (the polish rides along in the frames), so a failure costs bytes, not rounds."""

    guess: str
    mode: str
    cap: int
    per_solve: int = 1  # all-reduces per KKT solve: 1 for option (a); ~n + |W| for option (b), a Krylov solve
    next_start: int = 1
    stop: int | None = None
    attempts: int = 0
    corrections: int = 0  # of the certifying attempt
    start: int | None = None  # the certifying attempt's first round
    final: Polish | None = None  # its PDAS result
    admm_error: float = float("nan")  # the ADMM's error at `start`
    verdict: bool = False  # `gram_route` on the final set: the fleet's verdict, its error, its iterations
    al_error: float = float("nan")
    al_iterations: int = 0

    def due(self, r: int) -> bool:
        return self.stop is None and r == self.next_start

    def attempt(self, r: int, p: Polish, D: int) -> None:
        reduces = (1 + p.corrections) * self.per_solve + (p.corrections if self.mode == "one" else 0)
        self.attempts += 1
        if p.certified:
            self.stop, self.corrections, self.start, self.final = r + reduces * D + D, p.corrections, r, p
        else:
            self.next_start = r + reduces * D


def allreduce_rounds(core) -> int:
    """Rounds of one exact all-reduce (newton's gather): the graph's diameter; 1 on a complete graph."""
    return core.delay if isinstance(core, RelayHubADMM) else 1


def study(label: str, every: int, max_rounds: int) -> dict:
    """Run one fleet to its stop; every `every` rounds polish from each guess (see the module)."""
    kwargs = fleet_kwargs(label)
    cores, error, active = fleet_probe(kwargs, max_rounds)
    world, spec = build_world(Options(fleet_id="bench", preset="paper", max_rounds=max_rounds, **kwargs))
    b = spec.basis
    central = solve_central(b, world.points, world.labels, spec.C)
    assert central.certified, f"{label}: the central reference is not KKT-certified"
    local_rows = [c._qp._rows for c in cores]
    offsets = list(np.cumsum([0] + [len(r) for r in local_rows[:-1]]))
    all_rows = np.vstack(local_rows)
    owner = np.repeat(np.arange(len(cores)), [len(r) for r in local_rows])
    v_star = np.append(central.x, central.gamma)
    opt_active = int(np.sum(all_rows @ v_star - 1.0 < 1e-6))
    checks: list[tuple[int, float, dict[tuple[str, str], tuple[int, Polish]]]] = []
    first_1e3 = None
    worst_err = worst_kkt = 0.0
    D = allreduce_rounds(cores[0])
    errors: dict[int, float] = {}  # the ADMM's error by round
    schedules = [Schedule(g, m, cap) for g in GUESSES for m in MODES for cap in SCHEDULE_CAPS]
    krylov = [Schedule(g, m, 5, KRYLOV_REDUCES) for g in ("union", "mean 1e-2") for m in MODES]
    while not all(c.finished for c in cores):
        lockstep_round(cores)
        r = cores[0].round
        e = errors[r] = error()
        if first_1e3 is None and e < 1e-3:
            first_1e3 = r
        due = [sch for sch in schedules + krylov if sch.due(r)]
        if due:
            now = guesses(cores, local_rows, offsets, active(), all_rows)
            for sch in due:
                sch.attempt(r, pdas(all_rows, now[sch.guess], sch.cap, mode=sch.mode, owner=owner), D)
        if r % every == 0 or all(c.finished for c in cores):
            out = {}
            for name, W in guesses(cores, local_rows, offsets, active(), all_rows).items():
                for mode in MODES:
                    p = pdas(all_rows, W, mode=mode, owner=owner)
                    if p.certified:
                        err = b.function_error(b.c_from_x(p.v[:-1]), p.v[-1], central.c, central.gamma)
                        worst_err = max(worst_err, err)
                        worst_kkt = max(worst_kkt, kkt_residual(all_rows, p.v))
                    out[name, mode] = (len(W), p)
            checks.append((r, e, out))
    for sch in schedules:  # the certified polishes again, by the fleet's own arithmetic (option (a))
        if sch.final is not None:
            v, sch.verdict, sch.al_iterations = gram_route(all_rows, sch.final.W, owner, len(cores))
            sch.al_error = b.function_error(b.c_from_x(v[:-1]), v[-1], central.c, central.gamma)
            sch.admm_error = errors[sch.start]
    return {"label": label, "form": form_name(cores[0]), "stop": cores[0].round, "first_1e3": first_1e3, "D": D,
            "schedules": schedules, "krylov": krylov,
            "error_stop": error(), "checks": checks, "opt_active": opt_active, "worst_err": worst_err,
            "worst_kkt": worst_kkt, "rows": len(all_rows), "dim": all_rows.shape[1]}


def _ok(p: Polish, limit: int) -> bool:
    return p.certified and p.corrections <= limit


def first_round(checks, variants, limit: int) -> tuple[int, tuple] | None:
    """The first checked round whose polish from one of `variants` certified within `limit`
    corrections, and that variant."""
    for r, _e, out in checks:
        for var in variants:
            if _ok(out[var][1], limit):
                return r, var
    return None


def stable_round(checks, var: tuple, limit: int) -> int | None:
    """The first checked round from which every later check of `var` certified within `limit`
    corrections."""
    start = None
    for r, _e, out in checks:
        start = (start if start is not None else r) if _ok(out[var][1], limit) else None
    return start


def _cell(found) -> str:
    return "-" if found is None else str(found[0])


def summary(results: list[dict]) -> list[str]:
    """Per fleet: the first round any guess certifies within 0/1/2/5/10 corrections, the first from
    which one variant always does (<= 5), against the ADMM's own 1e-3 and stop rounds."""
    head = " | ".join(f"<= {t}" for t in THRESHOLDS)
    lines = [
        f"| fleet | form | rows / dim | active rows at optimum | ADMM first 1e-3 | ADMM stop | first certified, any guess, "
        f"{head} corrections | always certified (<= 5) from (variant) | error vs solve_central | KKT residual |",
        "|---|---|---:|---:|---:|---:|" + "---:|" * len(THRESHOLDS) + "---|---:|---:|",
    ]
    for res in results:
        cells = " | ".join(_cell(first_round(res["checks"], VARIANTS, t)) for t in THRESHOLDS)
        stables = [(s, var) for var in VARIANTS if (s := stable_round(res["checks"], var, 5)) is not None]
        best = min(stables) if stables else None
        stab = f"{best[0]} ({best[1][0]}, {best[1][1]})" if best else "-"
        lines.append(
            f"| {res['label']} | {res['form']} | {res['rows']} / {res['dim']} | {res['opt_active']} | "
            f"{res['first_1e3']} | {res['stop']} | {cells} | {stab} | {res['worst_err']:.1e} | {res['worst_kkt']:.1e} |")
    return lines


def table(results: list[dict]) -> list[str]:
    """Per fleet and variant (guess, correction mode): first certified round per number of
    corrections, the round from which it always certifies, and the guess's size there."""
    head = " | ".join(f"<= {t}" for t in THRESHOLDS)
    lines = [
        f"| fleet | guess | corrections | first certified with {head} | always certified (<= 5) from | guess size there |",
        "|---|---|---|" + "---:|" * len(THRESHOLDS) + "---:|---:|",
    ]
    for res in results:
        for var in VARIANTS:
            cells = " | ".join(_cell(first_round(res["checks"], [var], t)) for t in THRESHOLDS)
            stable = stable_round(res["checks"], var, 5)
            size = next((out[var][0] for r, _e, out in res["checks"] if r == stable), None)
            lines.append(f"| {res['label']} | {var[0]} | {var[1]} | {cells} | {stable if stable is not None else '-'} | "
                         f"{size if size is not None else '-'} |")
    return lines


def schedule_table(results: list[dict]) -> list[str]:
    """Per fleet: the best distributed schedule's stop round against the ADMM's own stop, and the
    strategies' spread (every guess x mode x cap)."""
    lines = [
        "| fleet | D (rounds per all-reduce) | ADMM stop | polish stop: best (strategy, attempts, corrections) "
        "| ADMM error at its start | union, swap, cap 5 | union, one, cap 5 | union, robot, cap 5 | mean 1e-2, robot, cap 5 "
        "| strategies that stop before the ADMM | fleet arithmetic (gram_route): verdicts certified; worst error; AL iterations |",
        "|---|---:|---:|---|---:|---:|---:|---:|---:|---:|---|",
    ]
    for res in results:
        schs = res["schedules"]
        done = [s for s in schs if s.stop is not None and s.stop < res["stop"]]
        best = min(done, key=lambda s: s.stop) if done else None
        best_cell = (f"{best.stop} ({best.guess}, {best.mode}, cap {best.cap}; {best.attempts}, {best.corrections})"
                     if best else "-")
        certified = [s for s in schs if s.final is not None]
        al = (f"{sum(s.verdict for s in certified)} of {len(certified)}; "
              f"{max(s.al_error for s in certified):.1e}; {max(s.al_iterations for s in certified)}" if certified else "-")
        admm_err = f"{best.admm_error:.1e}" if best else "-"

        def pick(g: str, m: str) -> str:
            s = next(s for s in schs if (s.guess, s.mode, s.cap) == (g, m, 5))
            return str(s.stop) if s.stop is not None else "-"

        lines.append(f"| {res['label']} | {res['D']} | {res['stop']} | {best_cell} | {admm_err} | {pick('union', 'swap')} | "
                     f"{pick('union', 'one')} | {pick('union', 'robot')} | {pick('mean 1e-2', 'robot')} | {len(done)} of {len(schs)} | {al} |")
    return lines


def strategy_table(results: list[dict]) -> list[str]:
    """Every strategy (guess x mode x cap) on every fleet: the replayed stop ('-': no certified
    attempt before the ADMM's own stop), and over the fleets the sum of min(polish, ADMM) stops and
    the worst ratio to the ADMM's stop -- one rule has to serve every fleet."""
    head = " | ".join(res["label"] for res in results)
    lines = [f"| strategy (guess, mode, cap) | {head} | sum of stops (ADMM alone: "
             f"{sum(res['stop'] for res in results)}) | worst stop / ADMM stop |",
             "|---|" + "---:|" * (len(results) + 2)]
    for k, sch in enumerate(results[0]["schedules"] if results else []):
        cells, total, worst = [], 0, 0.0
        for res in results:
            s = res["schedules"][k]
            stop = s.stop if s.stop is not None and s.stop < res["stop"] else None
            cells.append(str(stop) if stop is not None else "-")
            total += stop if stop is not None else res["stop"]
            worst = max(worst, (stop if stop is not None else res["stop"]) / res["stop"])
        lines.append(f"| {sch.guess}, {sch.mode}, {sch.cap} | {' | '.join(cells)} | {total} | {worst:.2f} |")
    return lines


def krylov_table(results: list[dict]) -> list[str]:
    """Option (b)'s replay: the same attempts with KRYLOV_REDUCES all-reduces per solve (cap 5)."""
    lines = [
        f"| fleet | D | ADMM stop | option (a) best | option (b): union swap | union one | union robot "
        "| mean 1e-2 swap | mean 1e-2 one | mean 1e-2 robot |",
        "|---|---:|---:|---:|" + "---:|" * 6,
    ]
    for res in results:
        done = [s.stop for s in res["schedules"] if s.stop is not None and s.stop < res["stop"]]
        cells = " | ".join(str(s.stop) if s.stop is not None else "-" for s in res["krylov"])
        lines.append(f"| {res['label']} | {res['D']} | {res['stop']} | {min(done) if done else '-'} | {cells} |")
    return lines


#: the complete fleets the implemented polish (hub form) is measured on
IMPLEMENTED = [lb for lb in FLEET_LABELS if "ring" not in lb and "line" not in lb and "3.0" not in lb]


def run_implemented(label: str, max_rounds: int) -> dict:
    """The fleet with ADMMParams.polish on (agents/admm.py `_Polish`), in lock step as `simulate`:
    rounds at stop, error of every robot against the certified central solve, whether the copies
    are bit-identical, the polish's attempts, bytes of one encoded frame and compute per robot-round."""
    from protocol.frames import encode_state

    world, spec = build_world(Options(fleet_id="bench", preset="paper", max_rounds=max_rounds, **fleet_kwargs(label)))
    spec.params["polish"] = True
    b = spec.basis
    central = solve_central(b, world.points, world.labels, spec.C)
    cores = [build_core(spec, i, keep_trace=False) for i in spec.robot_ids]
    def frame_bytes(core) -> int:
        return len(encode_state(core.outgoing(), fleet=spec.fleet, seq=0, config_tag=spec.config_tag,
                                auth=spec.frame_auth(core.robot_id)))

    spec.params["polish"] = False  # a plain frame for comparison, after one round (last round piggybacked)
    plain = [build_core(spec, i, keep_trace=False) for i in spec.robot_ids]
    lockstep_round(plain)
    plain_frame = frame_bytes(plain[0])
    spec.params["polish"] = True
    compute = 0.0
    sent = sum(frame_bytes(c) for c in cores)  # every robot's encoded frame, once per round (as rounds.py measure)
    while not all(c.finished for c in cores):
        compute += lockstep_round(cores)[1]
        sent += sum(frame_bytes(c) for c in cores)
    frame = frame_bytes(cores[0])
    rounds = cores[0].round
    return {"label": label, "rounds": rounds, "converged": all(c.converged for c in cores),
            "polished": cores[0]._polish.result is not None,
            "error": max(b.function_error(b.c_from_x(c.values[:-1]), c.values[-1], central.c, central.gamma) for c in cores),
            "identical": all(c.values.tobytes() == cores[0].values.tobytes() for c in cores),
            "attempts": cores[0]._polish.attempts, "frame": frame, "bytes": sent / len(cores), "plain_frame": plain_frame,
            "ms": 1e3 * compute / max(rounds * len(cores), 1)}


def implemented_table(max_rounds: int, labels: list[str]) -> list[str]:
    lines = [
        "| fleet (complete, hub form) | rounds at stop with polish | ends polished | error vs solve_central | copies "
        "bit-identical | attempts | bytes per frame, steady (without polish) | bytes per robot per run | compute ms per robot-round |",
        "|---|---:|:---:|---:|:---:|---:|---:|---:|---:|",
    ]
    for label in labels:
        r = run_implemented(label, max_rounds)
        add_row(lines, f"| {label} | {r['rounds']} | {'yes' if r['polished'] else 'no'} | {r['error']:.1e} | "
                       f"{'yes' if r['identical'] else 'NO'} | {r['attempts']} | {r['frame']} ({r['plain_frame']}) | {r['bytes']:.0f} | "
                       f"{r['ms']:.2f} |")
    return lines


def zenoh_pairs(label: str, pairs: int) -> list[str]:
    """Wall time of `launch_fleet` (router + robot processes on loopback, robots per process "auto",
    start-up included), polish off and on back to back, `pairs` times; rounds, bytes sent per robot,
    and whether the polished run's results equal `simulate`'s (x, gamma, rounds of every robot)."""
    import os
    import shutil
    import tempfile
    import time

    from launcher.fleet import launch_fleet
    from launcher.simulate import simulate_fleet

    lines = ["| pair | polish | rounds | converged | wall s | ms per round | bytes sent per robot | load average |",
             "|---:|:---:|---:|:---:|---:|---:|---:|---|"]
    work = Path(tempfile.mkdtemp(prefix="polish-zenoh-"))
    try:
        for pair in range(pairs):
            for polish in (False, True):
                _world, spec = build_world(Options(fleet_id="polish-zenoh", preset="paper", **fleet_kwargs(label)))
                spec.params["polish"] = polish
                load = " ".join(f"{x:.2f}" for x in os.getloadavg())
                started = time.perf_counter()
                out = launch_fleet(spec, workdir=work / f"{pair}-{polish}", crashes=[], restart_after=1.0, restart=False,
                                   zenoh_port=None, progress=False)
                wall = time.perf_counter() - started
                rows = out.robots
                rounds = max(r["rounds"] for r in rows)
                add_row(lines, f"| {pair + 1} | {'on' if polish else 'off'} | {rounds} | "
                               f"{'yes' if all(r['converged'] for r in rows) else 'no'} | {wall:.1f} | "
                               f"{1e3 * wall / rounds:.1f} | {sum(r['bytes_sent'] for r in rows) / len(rows):.0f} | {load} |")
                if polish and pair == 0:
                    sim = {r["id"]: r for r in simulate_fleet(spec).robots}
                    same = all((r["x"], r["gamma"], r["rounds"]) == (sim[r["id"]]["x"], sim[r["id"]]["gamma"],
                                                                     sim[r["id"]]["rounds"]) for r in rows)
                    lines.insert(0, f"Polished run equal to `simulate` (x, gamma, rounds of every robot): {'yes' if same else 'NO'}.\n")
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="only the paper preset and the 8-ring")
    ap.add_argument("--fleet", action="append", help="a fleet label (FLEET_LABELS); repeatable")
    ap.add_argument("--every", type=int, default=10, help="polish every K rounds (default 10)")
    ap.add_argument("--max-rounds", type=int, default=5000)
    ap.add_argument("--out", default="polish.md", help="file under benchmarks/results/")
    ap.add_argument("--implemented", action="store_true",
                    help="the polish as implemented (ADMMParams.polish, complete fleets), polish-implemented.md")
    ap.add_argument("--zenoh", type=int, metavar="PAIRS", default=0,
                    help="the 32-robot fleet over Zenoh, polish off/on, PAIRS A/B pairs (polish-zenoh.md)")
    args = ap.parse_args()
    if args.zenoh:
        label = (args.fleet or ["32 robots, geometric"])[0]
        write_results("polish-zenoh.md", f"# Polish over Zenoh: {label}, wall time of `launch_fleet`\n\n"
                      f"`benchmarks/polish.py --zenoh {args.zenoh}`: paper preset, router and robot processes on "
                      "loopback (robots per process: auto), start-up included, polish off and on back to back.\n\n"
                      + "\n".join(zenoh_pairs(label, args.zenoh)) + "\n")
        return
    if args.implemented:
        labels = args.fleet or IMPLEMENTED
        write_results("polish-implemented.md", "# Polish as implemented: complete fleets, ADMMParams.polish on\n\n"
                      "`benchmarks/polish.py --implemented`: paper preset, cores in lock step (as `simulate`); rounds "
                      "without the polish: `benchmarks/results/rounds.md` / `rounds-complete.md` (the flag off changes "
                      "nothing). Errors against solve_central's KKT-certified solution. Compute ms per robot-round: "
                      "in process (the fleet step and the polish's common solve computed once per process), measured "
                      "under a load average of 6-10 on 2 cores: not comparable across rows or runs.\n\n"
                      + "\n".join(implemented_table(args.max_rounds, labels)) + "\n")
        return
    labels = args.fleet or (QUICK if args.quick else FLEET_LABELS)
    unknown = [lb for lb in labels if lb not in FLEET_LABELS]
    if unknown:
        ap.exit(2, f"polish.py: unknown fleet {unknown[0]!r}; known: {', '.join(FLEET_LABELS)}\n")
    if args.every < 1:
        ap.exit(2, "polish.py: --every must be >= 1\n")
    results = []
    for label in labels:
        res = study(label, args.every, args.max_rounds)
        results.append(res)
        for line in summary([res])[2:] + schedule_table([res])[2:] + krylov_table([res])[2:]:
            add_row([], line)
        write_report(args, results)  # after every fleet: a long run stopped early keeps what it measured


def write_report(args: argparse.Namespace, results: list[dict]) -> None:
    """benchmarks/results/<out> with every table of the fleets measured so far."""
    text = ["# Polish: the oracle potential of an exact active-set end-game", "",
            f"`benchmarks/polish.py {' '.join(repr(a) if ' ' in a else a for a in sys.argv[1:])}` (fleets: "
            f"{'; '.join(r['label'] for r in results)}): every fleet "
            "runs its ADMM as `simulate` does (cores in lock step, paper preset: grid 5x3, sigma 1, hard margin); "
            f"every {args.every} rounds (and at the stop) the polish runs centrally from each guess (module "
            "docstring), with PDAS corrections ('swap': all of them at once; 'one': the fleet's one worst row; "
            "'robot': each robot's worst row) capped at "
            f"{MAX_CORRECTIONS}. A polish counts when `certify_hard_margin` certifies its point on all rows. "
            "Errors: the worst over every certified polish of the fleet (function error against solve_central's "
            "certified solution; the KKT residual of the point on its own).", "",
            "## Summary", "", *summary(results), "",
            "## Distributed schedules (rounds counted, option (a): one all-reduce per solve)", "",
            *schedule_table(results), "",
            "## Every strategy on every fleet (replayed stop round; '-': the ADMM stops first)", "",
            *strategy_table(results), "",
            f"## Option (b): a Krylov solve per polish ({KRYLOV_REDUCES} all-reduces per solve, a lower bound; cap 5)", "",
            *krylov_table(results), "", "## Per guess and correction mode", "", *table(results)]
    write_results(args.out, "\n".join(text) + "\n")


if __name__ == "__main__":
    main()
