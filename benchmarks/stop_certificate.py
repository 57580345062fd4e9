"""A certified stop for the hub-form ADMM: a duality-gap bound on the function error, measured in process.

Prototype for issues 10 and 14 (docs/algorithm.md, "Stopping" / "What is left"): the hub's stop rule
bounds r / (1 - rate), a heuristic that Anderson plateaus fool. This script computes, every round,
a *certificate* -- an upper bound on the fleet's function error against the exact optimum (the
measure of `GridBasis.function_error`) -- from what the fleet could compute: function-space vectors
the hub copies already hold and a few scalars per robot. Nothing of the core changes; the fleets run
exactly as `simulate` (the cores in lock step, `benchmarks.rounds.fleet_probe`) and the certificate
is read from the cores' state.

The mathematics (hard margin, rows a_i = y_i [phi_i; 1], v = (x, gamma), x = K^{1/2} c):

* Primal. At the fleet's mean x_bar let m+ = min of phi_i' x_bar over the positive rows and m- = max
  over the negative rows (two scalars, a min-reduce over robots). If m+ > m-, the point
  s (x_bar, g) with g = -(m+ + m-)/2, s = 2/(m+ - m-) holds every margin (the best offset and scale
  for the direction x_bar): P = s^2 |x_bar|^2 / 2 >= P*.
* Dual. Robot l's local step solves min |x|^2/(2N) + prox s.t. A_l v >= 1; its multipliers
  lam_l >= 0 satisfy A_l' lam_l = grad_l := P_l v_l + q_l (P_l, q_l the step's diagonal and linear
  term; robot-local, recovered here by NNLS: `local_multipliers`). Concatenated they are a candidate for
  the central dual  max sum lam - 1/2 |sum lam_i y_i phi_i|^2  s.t. sum lam_i y_i = 0, lam >= 0,
  once balanced: scale the positive side by a and the negative by b with a S+ = b S- = sigma
  (S+- the sides' sums of lam). The best sigma gives D = 2 / |U|^2, U = V+/S+ + V-/S- (V+- the sides'
  vectors sum lam_i y_i phi_i): "exact" below, needing per-side vector sums (2 M floats). The
  "hub" variant needs no vector at all: sum_l grad_l is computable by every hub copy from the frames'
  v_l and its own state (the centres z - u_l), W = its x part; then with t = S_small / S_big,
  |W_balanced| <= |W| + sum_l |r_l| + (1 - t) S_big phi_max =: B (r_l the NNLS residual, phi_max
  the largest |phi_i|) and D >= (2 S_small)^2 / (2 B^2). Scalars per robot: S_l+, S_l-, |r_l|.
* Gap. P >= P* >= D (weak duality) and, 1/2 |x|^2 being 1-strongly convex, every feasible v has
  |x - x*|^2 <= 2 (P(v) - P*): e0 := sqrt(2 (P - D)) >= |s x_bar - x*|.  |x*| >= sqrt(2 D).
* Offset. Both classes have an active row at the optimum (x* != 0), so gamma* = 1 - min_+ phi' x*
  = -1 - max_- phi' x*; with |phi_i| <= phi_max both give |gamma* - s g| <= e0 phi_max.
* Bound for robot l's (x_l, gamma_l):
      (|x_l - s x_bar| + e0) / sqrt(2 D)  +  (|gamma_l - s g| + e0 phi_max) / max(1, |s g| - e0 phi_max)
  >= function_error (rkhs norm = |x| on a full-rank grid, checked). The fleet's bound: the max over l.
  The certified point s (x_bar, g) itself has the bound e0 / sqrt(2 D) + e0 phi_max / max(1, ...).

Per fleet: the round the current rule stops and its true error; the first round the certified bound
<= tol (and the true error there), the first round the certified point's bound <= tol; the ratio
bound / true error over the run (rounds with a finite bound). If the certificate has not passed by
the rule's stop, the fleet is run again with tol 1e-14 (the same path: tol only sets the stop
flags; checked on the error at the old stop round) until it passes or the cap.

    .venv/bin/python benchmarks/stop_certificate.py                  # every fleet (~5 min on 2 busy cores)
    .venv/bin/python benchmarks/stop_certificate.py --fleet "L shape (test_simulate), WARM_QP on"
    .venv/bin/python benchmarks/stop_certificate.py --sweep 3        # polish_sweep's 3-robot set (--sweep 8: 8)
    .venv/bin/python benchmarks/stop_certificate.py --warm           # every fleet with WARM_QP on
    .venv/bin/python benchmarks/stop_certificate.py --cost           # a robot's NNLS, thread CPU
    .venv/bin/python benchmarks/stop_certificate.py --trace 400 --fleet "8 robots, blob, seed 2"
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.optimize import nnls

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import agents.admm as admm  # noqa: E402
from agents.problem import solve_central  # noqa: E402
from agents.relay_hub import RelayHubADMM  # noqa: E402
from benchmarks.common import add_row, lockstep_round, write_results  # noqa: E402
from benchmarks.polish import fleet_kwargs  # noqa: E402
from benchmarks.rounds import fleet_probe, form_name  # noqa: E402
from launcher.scenario import shape_names  # noqa: E402
from launcher.world import Options, build_world  # noqa: E402

TOL = 1e-3
#: the L shape of tests/test_simulate.py::test_data_file_and_shape_file
L_SHAPE = "x,y\n-2,-1.5\n2,-1.5\n2,0\n0,0\n0,1.5\n-2,1.5\n"


#: rows with margin <= 1 + CERT_ACTIVE form the robot's "active" NNLS (see local_multipliers)
CERT_ACTIVE = 1e-5


def local_multipliers(core, rows: np.ndarray, *, every_row: bool) -> tuple[np.ndarray, float, np.ndarray]:
    """Robot `core`'s multipliers lam >= 0 of its last local step, the residual |A' lam - grad| of the
    local KKT condition grad = P v + q = A' lam, and grad. What the robot itself could compute; never
    sent. Any lam >= 0 gives a valid dual bound, so the choice only sets how tight it is: NNLS on the
    rows within CERT_ACTIVE of tight (complementary, the tighter exact dual: 8 robots certified at
    456, against never in 5000 rounds with every row) or on every row (`every_row`: the smaller
    residual, which the hub variant pays in full -- piqp's interior-point answers leave small
    multipliers on nearly tight rows: bean's residual 5e-6 on the active rows, a floor of ~4e-3 on
    the hub bound). `certificate` takes the better of the two."""
    v = core.values
    pdiag = np.diag(core._qp._P)[: len(v)]
    if isinstance(core, RelayHubADMM):  # prox centre t_l: the robot's block of the fleet state
        S = core._S.get(core.round)
        t = S[core._slots[core.robot_id]] if S is not None else core._a[core.robot_id][0]
        grad = pdiag * v - core._P * t
    else:  # hub form: centre z - u_l of the state at which v was computed
        grad = pdiag * v - core._hub.penalty * core._hub.center(core.robot_id)
    lam = np.zeros(len(rows))
    act = np.arange(len(rows)) if every_row else np.flatnonzero(rows @ v <= 1 + CERT_ACTIVE)
    if len(act):
        lam[act], res = nnls(rows[act].T, grad)
    else:
        res = float(np.linalg.norm(grad))
    return lam, float(res), grad


@dataclass
class Certificate:
    """One round's bounds (inf where no certificate exists) and their parts."""

    bound_exact: float  # max over robots, dual from per-side vector sums
    bound_hub: float  # max over robots, dual from the hub copies' sum of gradients + scalars
    point_exact: float  # the certified point s (x_bar, g)'s bound (exact dual)
    point_error: float  # its true function error
    gap_rel: float  # (P - D) / P (exact dual)


def certificate(cores, rows: list[np.ndarray], phi_max: float) -> tuple[Certificate, np.ndarray]:
    """The round's certificate from the cores' state (module doc); also the certified point (x, gamma)."""
    inf = math.inf
    values = np.array([c.values for c in cores])
    x_bar = values[:, :-1].mean(axis=0)
    all_rows = np.vstack(rows)
    y = all_rows[:, -1]
    phi = all_rows[:, :-1] * y[:, None]
    f = phi @ x_bar
    m_pos, m_neg = float(f[y > 0].min()), float(f[y < 0].max())
    if not m_pos > m_neg:
        return Certificate(inf, inf, inf, inf, inf), None
    s = 2.0 / (m_pos - m_neg)
    g = -(m_pos + m_neg) / 2.0
    primal = s * s * float(x_bar @ x_bar) / 2.0
    point = np.append(s * x_bar, s * g)
    pos, neg = y > 0, y < 0
    duals = []
    for every_row in (False, True):
        lams, resid, W = [], 0.0, np.zeros(len(x_bar))
        for c, r in zip(cores, rows):
            lam, res, grad = local_multipliers(c, r, every_row=every_row)
            lams.append(lam)
            resid += res
            W += grad[:-1]
        lam = np.concatenate(lams)
        duals.append(_duals(lam, all_rows, pos, neg, float(lam[pos].sum()), float(lam[neg].sum()), W, resid, phi_max))
    bounds = []
    for dual in (max(d[0] for d in duals), max(d[1] for d in duals)):
        if not dual > 0:
            bounds.append((inf, inf, inf))
            continue
        gap = max(primal - dual, 0.0)
        e0 = math.sqrt(2.0 * gap)
        den_x = math.sqrt(2.0 * dual)
        den_g = max(1.0, abs(s * g) - e0 * phi_max)
        per_robot = [
            (float(np.linalg.norm(v[:-1] - s * x_bar)) + e0) / den_x + (abs(v[-1] - s * g) + e0 * phi_max) / den_g
            for v in values
        ]
        bounds.append((max(per_robot), e0 / den_x + e0 * phi_max / den_g, gap / primal))
    (b_exact, p_exact, gap_rel), (b_hub, _, _) = bounds
    return Certificate(b_exact, b_hub, p_exact, inf, gap_rel), point


def _duals(lam, rows, pos, neg, s_pos, s_neg, W, resid, phi_max) -> tuple[float, float]:
    """(exact, hub) dual lower bounds D of the balanced, optimally scaled multipliers (module doc)."""
    if not (s_pos > 0 and s_neg > 0):
        return 0.0, 0.0
    v_pos = rows[pos, :-1].T @ lam[pos]
    v_neg = rows[neg, :-1].T @ lam[neg]
    U = v_pos / s_pos + v_neg / s_neg
    exact = 2.0 / float(U @ U)
    small, big = min(s_pos, s_neg), max(s_pos, s_neg)
    B = float(np.linalg.norm(W)) + resid + (1.0 - small / big) * big * phi_max
    hub = (2.0 * small) ** 2 / (2.0 * B * B)
    return exact, hub


@dataclass
class Run:
    """A fleet's record: per round the true error (max over robots) and the certificate."""

    label: str
    form: str = ""
    stop: int = 0
    converged: bool = False
    error_stop: float = math.nan
    rows: dict[int, tuple[float, Certificate]] = field(default_factory=dict)
    rerun: bool = False
    horizon: int = 0  # the last round recorded (the re-run's end when there was one)


def run_fleet(label: str, kwargs: dict, *, warm: bool, max_rounds: int, cert_from: int = 1,
              tol: float | None = None, until_certified: bool = False) -> Run:
    """Run the fleet as `simulate` does (lock step), certificate from round `cert_from` on."""
    old = admm.WARM_QP
    admm.WARM_QP = warm
    try:
        kw = dict(kwargs)
        if tol is not None:
            kw["tol"] = tol
        cores, error, _active = fleet_probe(kw, max_rounds)
        world, spec = build_world(Options(fleet_id="bench", preset="paper", max_rounds=max_rounds, **kw))
        b = spec.basis
        assert b.rank == b.size, f"{label}: truncated basis (rkhs norm != |x|)"
        central = solve_central(b, world.points, world.labels, spec.C)
        rows = [c._qp._rows for c in cores]
        all_rows = np.vstack(rows)
        phi_max = float(np.linalg.norm(all_rows[:, :-1], axis=1).max())
        out = Run(label, form_name(cores[0]))
        while not all(c.finished for c in cores):
            lockstep_round(cores)
            r = cores[0].round
            e = error()
            if r >= cert_from:
                cert, point = certificate(cores, rows, phi_max)
                if point is not None:
                    cert.point_error = b.function_error(b.c_from_x(point[:-1]), point[-1], central.c, central.gamma)
                out.rows[r] = (e, cert)
                if until_certified and cert.bound_exact <= TOL and cert.bound_hub <= TOL:
                    break
            else:
                out.rows[r] = (e, None)
        out.stop = cores[0].round
        out.converged = all(c.converged for c in cores)
        out.error_stop = error()
        return out
    finally:
        admm.WARM_QP = old


def first(run: Run, key: str, after: int = 0) -> int | None:
    """First round > after whose certificate field `key` is <= TOL."""
    for r in sorted(run.rows):
        cert = run.rows[r][1]
        if r > after and cert is not None and getattr(cert, key) <= TOL:
            return r
    return None


def measure(label: str, kwargs: dict, warm: bool, max_rounds: int) -> dict:
    """The current rule's run, then (if needed) the same path on until the certificate passes."""
    base = run_fleet(label, kwargs, warm=warm, max_rounds=max_rounds)
    rows = dict(base.rows)
    if first(base, "bound_exact") is None or first(base, "bound_hub") is None:
        more = run_fleet(label, kwargs, warm=warm, max_rounds=max_rounds, tol=1e-14, cert_from=base.stop + 1,
                         until_certified=True)
        a, b = more.rows[base.stop][0], base.rows[base.stop][0]
        same = a == b or (math.isnan(a) and math.isnan(b))  # (NaN: the central QP is infeasible)
        assert same, f"{label}: the tol-1e-14 run left the path ({more.rows[base.stop][0]} vs {base.rows[base.stop][0]})"
        rows.update({r: v for r, v in more.rows.items() if r > base.stop})
        base.rerun = True
    base.rows = rows
    base.horizon = max(rows)
    ratios = [cert.bound_exact / e for r, (e, cert) in rows.items() if cert is not None and math.isfinite(cert.bound_exact) and e > 0]
    ratios_hub = [cert.bound_hub / e for r, (e, cert) in rows.items() if cert is not None and math.isfinite(cert.bound_hub) and e > 0]
    unsafe = [r for r, (e, cert) in rows.items() if cert is not None and cert.bound_exact < e * (1 - 1e-9)]
    unsafe_hub = [r for r, (e, cert) in rows.items() if cert is not None and cert.bound_hub < e * (1 - 1e-9)]
    res = {"run": base, "ratios": ratios, "ratios_hub": ratios_hub, "unsafe": unsafe + unsafe_hub}
    for key in ("bound_exact", "bound_hub", "point_exact"):
        r = first(base, key)
        res[key] = (r, rows[r][0] if r is not None else math.nan,
                    rows[r][1].point_error if r is not None else math.nan)
    # first round the true error is below tol and stays so (over the recorded rounds)
    below = None
    for r in sorted(rows):
        if rows[r][0] <= TOL:
            below = r if below is None else below
        else:
            below = None
    res["first_below"] = below
    return res


def _l_shape_kwargs() -> dict:
    path = Path(tempfile.gettempdir()) / "stop_certificate_l.csv"
    path.write_text(L_SHAPE)
    return {"shape_file": str(path)}


#: (label, Options keywords, WARM_QP)
FLEETS: list[tuple[str, dict, bool]] = [
    ("paper setting: 3 robots, blob, complete", fleet_kwargs("paper setting: 3 robots, blob, complete"), False),
    ("3 robots, star", fleet_kwargs("3 robots, star"), False),
    ("3 robots, bean", fleet_kwargs("3 robots, bean"), False),
    ("3 robots, crescent", fleet_kwargs("3 robots, crescent"), False),
    ("8 robots, complete", fleet_kwargs("8 robots, complete"), False),
    ("16 robots, complete", fleet_kwargs("16 robots, complete"), False),
    ("L shape (test_simulate), WARM_QP off", _l_shape_kwargs(), False),
    ("L shape (test_simulate), WARM_QP on", _l_shape_kwargs(), True),
    ("8 robots, blob, seed 2", {"robots": 8, "shape": "blob", "seed": 2}, False),
    ("8 robots, blob, seed 2, WARM_QP on", {"robots": 8, "shape": "blob", "seed": 2}, True),
    ("4 robots, ring (relay hub)", fleet_kwargs("4 robots, ring"), False),
    ("8 robots, ring (relay hub)", fleet_kwargs("8 robots, ring"), False),
    ("24 robots", fleet_kwargs("24 robots"), False),
    ("32 robots, geometric", fleet_kwargs("32 robots, geometric"), False),
]


def _r(x: tuple) -> str:
    r, e, pe = x
    return "-" if r is None else f"{r} ({e:.1e})"


def table_row(label: str, res: dict) -> str:
    run = res["run"]
    q = lambda xs, p: f"{np.quantile(xs, p):.2g}" if xs else "-"  # noqa: E731
    pr, pe, ppe = res["point_exact"]
    at_stop = run.rows.get(run.stop, (None, None))[1]
    b_stop = "-" if at_stop is None else f"{at_stop.bound_exact:.1e} / {at_stop.bound_hub:.1e}"
    return (f"| {label} | {run.form} | {run.stop} ({run.error_stop:.1e}){'' if run.converged else ' cap'} | {b_stop} | "
            f"{res['first_below'] or '-'} | {_r(res['bound_exact'])} | {_r(res['bound_hub'])} | "
            f"{'-' if pr is None else f'{pr} ({ppe:.1e})'} | "
            f"{q(res['ratios'], 0)} / {q(res['ratios'], 0.5)} / {q(res['ratios'], 1)} | "
            f"{q(res['ratios_hub'], 0.5)} | {'none' if not res['unsafe'] else len(res['unsafe'])} | {run.horizon} |")


HEAD = [
    "| fleet | form | current rule: stop (error) | bound there (exact / hub) | error <= tol from | certified (exact dual): round (true error) "
    "| certified (hub dual): round (true error) | certified point s(x, g): round (its error) "
    "| bound / error min / median / max (exact) | median (hub) | rounds bound < error | rounds recorded |",
    "|---|---|---:|---:|---:|---:|---:|---:|---|---:|:---:|---:|",
]


def nnls_cost(calls: int = 300) -> None:
    """What a robot's multipliers would cost per round (thread CPU, `local_multipliers`)."""
    import time

    cores, _error, _active = fleet_probe({}, 200)
    rows = [c._qp._rows for c in cores]
    for _ in range(60):
        lockstep_round(cores)
    for every_row in (False, True):
        started = time.thread_time()
        for _ in range(calls):
            for c, r in zip(cores, rows):
                local_multipliers(c, r, every_row=every_row)
        us = 1e6 * (time.thread_time() - started) / (calls * len(cores))
        print(f"paper preset, {len(rows[0])} rows a robot, every_row={every_row}: {us:.1f} us per robot-round")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fleet", action="append", help="only these labels (repeatable)")
    ap.add_argument("--sweep", type=int, metavar="ROBOTS", help="polish_sweep's set: every shape x seeds 0-3, complete")
    ap.add_argument("--warm", action="store_true", help="every fleet with agents.admm.WARM_QP on")
    ap.add_argument("--cost", action="store_true", help="instead of the table: thread CPU of one robot's NNLS "
                    "(both row choices) on the paper preset at round 60")
    ap.add_argument("--trace", type=int, metavar="EVERY", help="instead of the table: every EVERY rounds the true "
                    "error, both bounds and the relative gap, tol 1e-14 to --max-rounds (where a fleet stagnates)")
    ap.add_argument("--max-rounds", type=int, default=5000)
    ap.add_argument("--out", help="also write the table to benchmarks/results/OUT (stop_certificate.md collects "
                                   "every run's table by hand: not overwritten by default)")
    args = ap.parse_args()
    fleets = FLEETS
    if args.sweep:
        n = args.sweep
        fleets = [(f"{n} robots, {shape}, seed {seed}", {"robots": n, "topology": "complete", "shape": shape, "seed": seed},
                   False) for shape in shape_names() for seed in range(4)]
    if args.fleet:
        fleets = [f for f in fleets if f[0] in args.fleet]
    if args.warm:
        fleets = [(label if label.endswith("WARM_QP on") else label.removesuffix(", WARM_QP off") + ", WARM_QP on",
                   kwargs, True) for label, kwargs, _warm in fleets if not label.endswith("WARM_QP on")]
    if args.cost:
        nnls_cost()
        return
    if args.trace:
        for label, kwargs, warm in fleets:
            run = run_fleet(label, kwargs, warm=warm, max_rounds=args.max_rounds, tol=1e-14)
            for r, (e, c) in sorted(run.rows.items()):
                if r % args.trace == 0 and c is not None:
                    print(f"{label} | round {r} | error {e:.2e} | bound exact {c.bound_exact:.2e} | hub {c.bound_hub:.2e} "
                          f"| gap / P {c.gap_rel:.1e}", flush=True)
        return
    lines = list(HEAD)
    for label, kwargs, warm in fleets:
        try:
            res = measure(label, kwargs, warm, args.max_rounds)
        except Exception as exc:  # an infeasible sweep fleet: say so and go on
            add_row(lines, f"| {label} | - | {type(exc).__name__}: {exc} | | | | | | | | | |")
            continue
        add_row(lines, table_row(label, res))
    if args.out:
        cmd = " ".join(["benchmarks/stop_certificate.py", *sys.argv[1:]])
        write_results(args.out, "\n".join([f"`nice -n 15 .venv/bin/python {cmd}`; tol {TOL}.", ""] + lines) + "\n")


if __name__ == "__main__":
    main()
