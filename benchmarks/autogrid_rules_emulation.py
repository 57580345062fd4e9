"""Issue 15, step 6: central emulation of sigma rules (benchmarks/results/autogrid.md, "step 6").

`collect`: per data set (default run, the sparse five-shape test's data, the six benchmark shapes, the 12
development outlines), per candidate diag/{4, 6, 8, 12, 16, 24} and fold (5 folds, the fleet's units), one
exact central soft solve on the candidate's coarse lattice (held-out errors, hinge, solid strict / holes
allowed) and the IoU of the fleet's final pipeline at r = 1 and 3; SVC 5-fold CV and the oracle. One pickle
per data set in OUT. `rank`: every rule of the grid below on those pickles, the ones that keep the IoU rails
sorted by the outlines' mean. Never run it on the held-out-2 outlines.

    .venv/bin/python benchmarks/autogrid_rules_emulation.py collect default,sparse,six,out OUT
    .venv/bin/python benchmarks/autogrid_rules_emulation.py rank OUT

`multiscale` (issue 15, the multiscale step): models beyond one width against SVC-CV and the oracle on the 24
development outlines (the original 12, held-out 2 and 3), the six benchmark shapes and the default run, each
with the data `simulate` gives (5 x 40; six shapes 6 x 40; default 3 x 20). Kernels on the data (SVC,
precomputed, C = 1e6: what a model can do without a grid) and on grids (the exact central QP, hard margin,
soft C = 1e3 if infeasible, one lattice per width, block-diagonal K_G); today's default emulated as in step 6.
One pickle per data set in OUT (kept: a second call only prints the table).

    .venv/bin/python benchmarks/autogrid_rules_emulation.py multiscale OUT [--jobs 2]

`fill` (issue 15, "what a LiDAR cannot see is inside"): the same data sets and the sparse five-shape test's data;
the estimate {f < 0} with its enclosed holes filled (scipy.ndimage.binary_fill_holes, 4-connected outside), for SVC
at diag/{2..32} and for the fleet's final model at each candidate diag/{4..32}; rules decided from the data (the
fleet's held-out folds on exact central soft solves, or SVC's 5-fold CV) with the solid check on the filled region
(islands only) against SVC-CV and the oracle, raw and filled. One pickle per data set in OUT (kept). Never run on
benchmarks/outlines/heldout4/ or a heldout5/ folder.

    .venv/bin/python benchmarks/autogrid_rules_emulation.py fill OUT [--jobs 2]
"""
import dataclasses, glob, itertools, pickle, sys, time
from pathlib import Path
import numpy as np
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
import autogrid as B
from agents.autogrid_rules import AutoGridParams, coarse_lattice, is_solid, solid_on_raster
from agents.kernel import GridBasis
from agents.problem import solve_central
from launcher import scenario
from launcher.world import Options, build_world

DIVS = (4, 6, 8, 12, 16, 24)
TMM = {"standoff": 1500.0, "lidar_range": 4000.0, "offset": 300.0, "noise": 10.0}

def datasets(which):
    out = []
    if "default" in which:
        out.append(("default", {}, None))
    if "sparse" in which:
        for n, kw in [("star", {"shape": "star"}), ("bean", {"shape": "bean"}), ("crescent", {"shape": "crescent"}),
                      ("cross", {"shape": "cross"}), ("bracket", {"shape_file": str(ROOT / "benchmarks/data/bracket_mm.csv"), **TMM})]:
            out.append(("sparse_" + n, dict(robots=3, points=20, **kw), {"tol": 1e-3, "max_points": 100}))
    if "six" in which:
        for n, kw in B.SHAPES:
            out.append(("six_" + n.split()[0], dict(robots=6, points=40, **kw), {"tol": 1e-3, "max_points": 200}))
    if "out" in which:
        for n in ("letter_e", "digit_3", "wrench_mm", "gear_mm", "fork_mm", "letter_k", "letter_m", "digit_2",
                  "key_mm", "comb_mm", "tslot_mm", "clamp_mm"):
            out.append(("out_" + n, dict(robots=5, points=40, shape_file=str(ROOT / f"benchmarks/outlines/{n}.csv")), None))
    return out

def sweep_solves(folds, bounds, sigma: float, params: AutoGridParams, slot: int):
    """One sweep candidate emulated: its coarse lattice (coarsened to `slot` points, as the fleet's frame block)
    and, per fold (training points, labels, held-out points, labels), the exact central soft solve (C = soft_C).
    Returns (lattice box, basis, [(solution, held-out points, held-out labels)])."""
    lbox, _, grid = coarse_lattice(bounds, sigma, params.spacing_ratio, slot)
    basis = GridBasis(grid, sigma)
    return lbox, basis, [(solve_central(basis, tp, tl, params.soft_C), hp, hl) for tp, tl, hp, hl in folds]


def one(name, kw, pkw):
    world, spec = build_world(Options(fleet_id="bench", **kw))
    params = spec.autogrid_params
    if pkw:
        params = dataclasses.replace(params, **pkw)
    params = dataclasses.replace(params, validate_folds=5, validate_divisors=DIVS)
    lo, hi = world.points.min(axis=0), world.points.max(axis=0)
    bounds, diag = (lo[0], hi[0], lo[1], hi[1]), float(np.hypot(*(hi - lo)))
    res = 120 if name.startswith("sparse") else 200
    x0, x1, y0, y1 = scenario.shape_bounds(world.shape); pad = 0.2 * max(x1 - x0, y1 - y0)
    box = (x0 - pad, x1 + pad, y0 - pad, y1 + pad)
    folds = [B._fold_sets(spec, params, f) for f in range(5)]
    row = {"name": name, "n": len(world.labels), "cand": {}}
    for d in DIVS:
        sigma = diag / d
        lbox, basis, sols = sweep_solves(folds, bounds, sigma, params, params.sweep_slot(d))
        fl = []
        for sol, hp, hl in sols:
            yf = hl * basis.decision(hp, sol.c, sol.gamma)
            fl.append({"err": int(np.sum(yf <= 0)), "hinge": float(np.sum(np.maximum(0, 1 - yf))), "held": len(hl),
                       "solid": solid_on_raster(basis, sol.c, sol.gamma, lbox, params.solid_raster, False),
                       "solid_h": solid_on_raster(basis, sol.c, sol.gamma, lbox, params.solid_raster, True)})
        iou = {}
        for r in (1.0, 3.0):
            p = dataclasses.replace(params, narrow_ratio=r)
            b, s = B.central_final_model(world.points, world.labels, p, bounds, sigma)
            iou[r] = scenario.iou_on_raster(world.shape, lambda q: b.decision(q, s.c, s.gamma) < 0, box, resolution=res)
        row["cand"][d] = {"folds": fl, "iou": iou}
    # SVC: CV and oracle over the outline sweep (test: 2..16 for sparse)
    from sklearn.model_selection import StratifiedKFold, cross_val_score
    from sklearn.svm import SVC
    ks = (2, 4, 6, 8, 12, 16) if name.startswith("sparse") else (2, 3, 4, 6, 8, 12, 16, 24, 32)
    def svc(s):
        clf = SVC(kernel="rbf", C=1e6, gamma=1 / (2 * s * s)).fit(world.points, world.labels)
        return scenario.iou_on_raster(world.shape, lambda q: clf.decision_function(q) < 0, box, resolution=res)
    sw = {k: svc(diag / k) for k in ks}
    cv = StratifiedKFold(5, shuffle=True, random_state=0)
    sc = {k: cross_val_score(SVC(kernel="rbf", C=1e6, gamma=k * k / (2 * diag * diag)), world.points, world.labels, cv=cv).mean() for k in ks}
    row["svc_cv"] = sw[max(sc, key=lambda k: (sc[k], -k))]
    row["svc_best"] = max(sw.values())
    row["svc_same"] = {d: svc(diag / d) for d in DIVS}
    return row


CANDS = {"t5": (4, 6, 8, 12, 16), "p4": (4, 8, 16, 24), "a6": (4, 6, 8, 12, 16, 24), "e3": (4, 8, 16), "b5": (4, 6, 8, 16, 24)}

def choose(row, cands, folds, solidkey, crit, ties):
    recs = []
    for d in cands:
        fl = row["cand"][d]["folds"][:folds]
        recs.append((d, sum(f["err"] for f in fl), sum(f["hinge"] for f in fl), all(f[solidkey] for f in fl), sum(f["held"] for f in fl)))
    pool = [r for r in recs if r[3]] or recs
    sign = 1 if ties == "smaller" else -1  # smaller sigma = larger divisor
    if crit == "err":
        key = lambda r: (r[1], -sign * r[0])
    elif crit == "errh":
        key = lambda r: (r[1], r[2], -sign * r[0])
    elif crit == "hinge":
        key = lambda r: (r[2], -sign * r[0])
    elif crit == "mix":  # errors + hinge/held (hinge per held-out point as fraction)
        key = lambda r: (r[1] + r[2] / max(1, r[4]), -sign * r[0])
    best = min(pool, key=key)
    return best[0], best[4] / folds

def evaluate(rows, rule):
    cands, folds, solidkey, crit, ties, rpol = rule
    out = {}
    for name, row in rows.items():
        d, heldper = choose(row, CANDS[cands], folds, solidkey, crit, ties)
        if rpol == "r1": r = 1.0
        elif rpol == "r3": r = 3.0
        else: r = 3.0 if heldper >= rpol else 1.0
        out[name] = (d, r, row["cand"][d]["iou"][r])
    return out

def summary(rows, out):
    g = lambda p: [k for k in rows if k.startswith(p)]
    s = {}
    s["def"] = out["default"][2] if "default" in out else np.nan
    sp = g("sparse_"); s["sparse"] = np.mean([out[k][2] for k in sp]) if sp else np.nan
    s["sparse_bound"] = np.mean([rows[k]["svc_cv"] for k in sp]) - 0.005 if sp else np.nan
    six = g("six_"); s["six"] = np.mean([out[k][2] for k in six]) if six else np.nan
    o = g("out_"); s["out"] = np.mean([out[k][2] for k in o]) if o else np.nan
    s["out_ge_cv"] = sum(out[k][2] >= rows[k]["svc_cv"] - 1e-9 for k in o)
    s["out_worst"] = min(out[k][2] - rows[k]["svc_cv"] for k in o) if o else np.nan
    return s


def rank(out_dir):
    rows = {}
    for f in sorted(glob.glob(f"{out_dir}/*.pkl")):
        r = pickle.load(open(f, "rb")); rows[r["name"]] = r
    res = []
    for rule in itertools.product(CANDS, (2, 3, 4), ("solid", "solid_h"), ("err", "errh", "hinge", "mix"), ("smaller", "larger"), ("r1", "r3", 15, 25, 30)):
        if rule[3] == "hinge" and rule[4] == "larger": continue
        s = summary(rows, evaluate(rows, rule)); res.append((rule, s))
    ok = [(r, s) for r, s in res if s["def"] >= 0.893 and s["six"] >= 0.897 and s["sparse"] >= s["sparse_bound"]]
    print(len(res), "rules;", len(ok), "meet the IoU rails")
    for r, s in sorted(ok, key=lambda t: -t[1]["out"])[:40]:
        print(r, {k: round(float(v), 3) for k, v in s.items()})


# --- issue 15, multiscale: models beyond one width (benchmarks/results/autogrid.md, "multiscale") ---

MS_KS = (2, 3, 4, 6, 8, 12, 16, 24, 32)  # SVC's single widths diag/k (CV and the oracle choose among them)
MS_POWERS = (0, 1, 2, 3, 4, 6)  # sum-kernel weights (k / k_min)^p: p > 0 makes the narrow components cheaper


def ms_datasets() -> list[tuple[str, dict]]:
    """The default run, the six benchmark shapes (6 x 40) and the 24 development outlines (5 x 40)."""
    out = [("default", {})] + [("six_" + n.split()[0], dict(robots=6, points=40, **kw)) for n, kw in B.SHAPES]
    sets = {"dev": ("letter_e", "digit_3", "wrench_mm", "gear_mm", "fork_mm", "letter_k", "letter_m", "digit_2",
                    "key_mm", "comb_mm", "tslot_mm", "clamp_mm"),
            "ho2": ("letter_f", "letter_h", "digit_7", "hook_mm", "saw_mm", "slotted_mm"),
            "ho3": ("heldout3/letter_s", "heldout3/digit_4", "heldout3/digit_5", "heldout3/caliper_mm",
                    "heldout3/tuning_fork_mm", "heldout3/bolt_mm")}
    for tag, names in sets.items():
        out += [(f"{tag}_{Path(n).name}", dict(robots=5, points=40, shape_file=str(ROOT / f"benchmarks/outlines/{n}.csv")))
                for n in names]
    return out


def _sum_kernel(d2: np.ndarray, diag: float, weights: dict[float, float]) -> np.ndarray:
    """sum_k w_k exp(-|x - y|^2 / (2 (diag/k)^2)) from squared distances: one RKHS, each width's norm / w_k."""
    return sum(w * np.exp(-d2 * k * k / (2 * diag * diag)) for k, w in weights.items())


def _gibbs(d2: np.ndarray, la: np.ndarray, lb: np.ndarray) -> np.ndarray:
    """Gibbs' kernel with a width per point (positive definite for any widths; 2-D prefactor)."""
    s2 = la[:, None] ** 2 + lb[None, :] ** 2
    return 2 * la[:, None] * lb[None, :] / s2 * np.exp(-d2 / s2)


class SumBasis:
    """A weighted sum of widths on a grid (block s: its lattice at width s, kernel w_s k_s; K_G block-diagonal),
    with the features solve_central needs. GridBasis has widths but no weights, hence this emulation-only class."""

    def __init__(self, blocks: list[tuple[np.ndarray, float, float]]) -> None:
        from scipy.linalg import block_diag

        from agents.kernel import RCOND, gaussian_kernel
        self.blocks, self.grid = blocks, np.vstack([g for g, _, _ in blocks])
        lam, u = np.linalg.eigh(block_diag(*[w * gaussian_kernel(g, g, s) for g, s, w in blocks]))
        keep = lam > RCOND * lam[-1]
        self.rank, self.inv_sqrt = int(keep.sum()), (u[:, keep] / np.sqrt(lam[keep])) @ u[:, keep].T

    @property
    def size(self) -> int:
        return len(self.grid)

    def _k(self, pts: np.ndarray) -> np.ndarray:
        from agents.kernel import gaussian_kernel
        return np.hstack([w * gaussian_kernel(pts, g, s) for g, s, w in self.blocks])

    def features(self, pts: np.ndarray) -> np.ndarray:
        return self._k(pts) @ self.inv_sqrt

    def c_from_x(self, x: np.ndarray) -> np.ndarray:
        return self.inv_sqrt @ x

    def decision(self, pts: np.ndarray, c: np.ndarray, gamma: float) -> np.ndarray:
        return self._k(pts) @ c + gamma


def _sum_grid(points: np.ndarray, bounds, diag: float, weights: dict[float, float], spacing_ratio: float) -> SumBasis:
    """One lattice per width diag/k (spacing spacing_ratio x width, the fleet's level 0), its nodes near data."""
    import math

    from agents.autogrid_rules import coarse_lattice, near_data_marks
    blocks = []
    for k, w in sorted(weights.items()):
        s = diag / k
        _, h0, g = coarse_lattice(bounds, s, spacing_ratio, 10**6)
        blocks.append((g[near_data_marks(points, g, s + h0 / math.sqrt(2)) > 0], s, w))
    return SumBasis(blocks)


def ms_one(item: tuple[str, dict]) -> dict:
    """Every model's IoU (and 5-fold CV accuracy where a choice needs it) on one data set."""
    import shapely
    from scipy.spatial import cKDTree
    from sklearn.model_selection import StratifiedKFold
    from sklearn.svm import SVC

    from agents.kernel import _squared_distances as sqd  # the kernels' own distances (cdist moves IoU by 2e-4)
    name, kw = item
    world, spec = build_world(Options(fleet_id="bench", **kw))
    p, y = world.points, world.labels
    lo, hi = p.min(axis=0), p.max(axis=0)
    bounds, diag = (lo[0], hi[0], lo[1], hi[1]), float(np.hypot(*(hi - lo)))
    q = scenario.make_grid(200, 200, B.padded_bounds(world.shape))  # the raster of scenario.iou_on_raster
    truth = shapely.contains_xy(world.shape, q[:, 0], q[:, 1])
    iou = lambda inside: float(np.count_nonzero(truth & inside) / max(1, np.count_nonzero(truth | inside)))  # noqa: E731
    dp, dq = sqd(p, p), sqd(q, p)
    folds = list(StratifiedKFold(5, shuffle=True, random_state=0).split(p, y))

    def svc(kp, kq, C=1e6):
        return iou(SVC(kernel="precomputed", C=C).fit(kp, y).decision_function(kq) < 0)

    def cv(kp, C=1e6):
        return float(np.mean([np.mean(np.sign(SVC(kernel="precomputed", C=C).fit(kp[np.ix_(a, a)], y[a])
                                                  .decision_function(kp[np.ix_(b, a)])) == y[b]) for a, b in folds]))

    row = {"name": name, "n": len(y), "iou": {}, "cv": {}, "grid": {}}
    for k in MS_KS:
        w = {k: 1.0}
        row["iou"][f"s{k}"], row["cv"][f"s{k}"] = svc(_sum_kernel(dp, diag, w), _sum_kernel(dq, diag, w)), cv(_sum_kernel(dp, diag, w))
    for ks in ((4, 8, 16, 32), (4, 8, 16, 32, 48)):
        for pw in MS_POWERS:
            w = {k: (k / ks[0]) ** pw for k in ks}
            key = f"sum{ks[-1]}_p{pw}"
            row["iou"][key], row["cv"][key] = svc(_sum_kernel(dp, diag, w), _sum_kernel(dq, diag, w)), cv(_sum_kernel(dp, diag, w))
    w = {k: 1.0 for k in (4, 8, 16, 32)}
    for C in (1.0, 10.0, 100.0):
        key = f"sum32_p0_C{C:g}"
        row["iou"][key], row["cv"][key] = svc(_sum_kernel(dp, diag, w), _sum_kernel(dq, diag, w), C), cv(_sum_kernel(dp, diag, w), C)
    # data-adaptive local widths: a * the distance to the 3rd nearest opposite-label point, within [diag/32, diag/8]
    opp = np.empty(len(y))
    for c in (-1, 1):
        opp[y == c] = cKDTree(p[y != c]).query(p[y == c], k=3)[0][:, -1]
    near = cKDTree(p).query(q)[1]  # a raster point takes its nearest data point's width
    for a in (0.5, 1.0, 2.0):
        lw = np.clip(a * opp, diag / 32, diag / 8)
        row["iou"][f"local{a:g}"] = svc(_gibbs(dp, lw, lw), _gibbs(dq, lw[near], lw))
    # today's default, emulated (its sweep on exact solves, then its final model), and sums anchored at its sigma
    params = spec.autogrid_params
    if name.startswith("six"):
        params = dataclasses.replace(params, tol=1e-3, max_points=200)  # the benchmark's budget for the six shapes
    sigma = B._central_sweep_choice(spec, params, bounds, diag)
    basis, sol = B.central_final_model(p, y, params, bounds, sigma)
    row["today_k"], k0 = diag / sigma, diag / sigma
    row["iou"]["today"], row["grid"]["today"] = iou(basis.decision(q, sol.c, sol.gamma) < 0), basis.size
    models = {"anch_p2": {k0: 1.0, 2 * k0: 4.0, 4 * k0: 16.0}, "anch_p3": {k0: 1.0, 2 * k0: 8.0, 4 * k0: 64.0}}
    for key, w in models.items():
        row["iou"][key] = svc(_sum_kernel(dp, diag, w), _sum_kernel(dq, diag, w))
    models.update({"sum32_p0": {k: 1.0 for k in (4, 8, 16, 32)}, "sum32_p3": {k: (k / 4) ** 3 for k in (4, 8, 16, 32)},
                   "sum48_p3": {k: (k / 4) ** 3 for k in (4, 8, 16, 32, 48)}})
    for key, w in models.items():  # the same models on grids, exact central QP
        gb = _sum_grid(p, bounds, diag, w, params.spacing_ratio)
        s = solve_central(gb, p, y, None)
        s = s if s.solved else solve_central(gb, p, y, params.soft_C)
        row["iou"]["grid_" + key], row["grid"]["grid_" + key] = iou(gb.decision(q, s.c, s.gamma) < 0), gb.size
    return row


def ms_table(rows: list[dict]) -> list[str]:
    """Per data set and the means: SVC-CV, oracle, today, and the models beyond one width."""
    def cv_pick(r, keys):  # the best 5-fold CV accuracy, ties -> the first (the larger sigma / the smaller p)
        best = max(r["cv"][k] for k in keys)
        return next(k for k in keys if r["cv"][k] == best)
    cols = [("SVC-CV", lambda r: r["iou"][cv_pick(r, [f"s{k}" for k in MS_KS])]),
            ("oracle", lambda r: max(r["iou"][f"s{k}"] for k in MS_KS)),
            ("today", lambda r: r["iou"]["today"])]
    cols += [(k, (lambda k: lambda r: r["iou"][k])(k)) for k in
             ("sum32_p0", "sum32_p3", "sum48_p3", "anch_p2", "anch_p3", "local0.5", "local1", "local2")]
    cols += [("sum48, p by CV", lambda r: r["iou"][cv_pick(r, [f"sum48_p{pw}" for pw in MS_POWERS])]),
             ("sum32_p0, C by CV", lambda r: r["iou"][cv_pick(r, ["sum32_p0_C1", "sum32_p0_C10", "sum32_p0_C100", "sum32_p0"])])]
    cols += [(k, (lambda k: lambda r: r["iou"][k])(k)) for k in
             ("grid_sum32_p0", "grid_sum32_p3", "grid_sum48_p3", "grid_anch_p3")]
    lines = ["| data set | n | today's sigma | " + " | ".join(c for c, _ in cols) + " | grid points (today; sum32; sum48; anch) |",
             "|---|---:|---|" + "---:|" * len(cols) + "---|"]
    for r in rows:
        g = r["grid"]
        lines.append(f"| {r['name']} | {r['n']} | /{r['today_k']:.3g} | " + " | ".join(f"{f(r):.3f}" for _, f in cols)
                     + f" | {g['today']}; {g['grid_sum32_p0']}; {g['grid_sum48_p3']}; {g['grid_anch_p3']} |")
    groups = {"24 development outlines": ("dev_", "ho2_", "ho3_"), "original 12": ("dev_",), "held-out 2": ("ho2_",),
              "held-out 3": ("ho3_",), "six shapes": ("six_",), "default run": ("default",)}
    lines += ["", "| mean (>= SVC-CV: count) | " + " | ".join(c for c, _ in cols) + " |", "|---|" + "---|" * len(cols)]
    for g, pref in groups.items():
        rs = [r for r in rows if r["name"].startswith(pref)]
        if not rs:
            continue
        cvs = [cols[0][1](r) for r in rs]
        cells = [f"{np.mean([f(r) for r in rs]):.3f} ({sum(f(r) >= c - 1e-9 for r, c in zip(rs, cvs))}/{len(rs)})"
                 for _, f in cols]
        lines.append(f"| {g} | " + " | ".join(cells) + " |")
    return lines


def collect_rows(out_dir: str, jobs: int, prefix: str, items: list[tuple], work) -> list[dict]:
    """`work(item)` for every data set whose pickle OUT/prefix_NAME.pkl is missing (in `jobs` processes; the
    pickles are kept, so a second call only reads them), then every data set's row in the order of `items`."""
    from concurrent.futures import ProcessPoolExecutor
    todo = [it for it in items if not Path(f"{out_dir}/{prefix}_{it[0]}.pkl").exists()]
    with ProcessPoolExecutor(max_workers=jobs) as pool:
        for row in pool.map(work, todo):
            pickle.dump(row, open(f"{out_dir}/{prefix}_{row['name']}.pkl", "wb"))
            print(row["name"], "done", flush=True)
    return [pickle.load(open(f"{out_dir}/{prefix}_{it[0]}.pkl", "rb")) for it in items]


def multiscale(out_dir: str, jobs: int) -> None:
    """Collect the pickles OUT lacks (in `jobs` processes), then print the tables."""
    print("\n".join(ms_table(collect_rows(out_dir, jobs, "ms", ms_datasets(), ms_one))))


# --- issue 15, fill: "what a LiDAR cannot see is inside" (benchmarks/results/autogrid.md, "Issue 15, fill") ---

FILL_KS = (4, 6, 8, 12, 16, 24, 32)  # the fleet-style candidates: today's diag/{4..16} extended to /24 and /32
FILL_TODAY = (4, 6, 8, 12, 16)  # today's candidates
#: the outside's connectivity in the fill: 4 (scipy's default), so a region is a hole exactly when it is an
#: "enclosed outside cell" of the fleet's solid check (`is_solid`: ndimage.label's 4-connected outside) -- the fill
#: removes what the check calls holes, no more; a corner-to-corner pinch of two inside cells is no gap a ray can use
FILL_4 = np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], dtype=bool)
FILL_8 = np.ones((3, 3), dtype=bool)  # the other choice, measured alongside (a diagonal pinch lets the outside in)


def fill_datasets() -> list[tuple[str, dict, dict]]:
    """The development data: `ms_datasets()` (default run, six shapes, the 24 outlines) and the sparse five-shape
    test's data (3 x 20, budget 100); each with the AutoGridParams overrides its benchmark uses. Never held-out 4/5."""
    out = [(n, kw, {"tol": 1e-3, "max_points": 200} if n.startswith("six") else {}) for n, kw in ms_datasets()]
    out += [(n, kw, pkw) for n, kw, pkw in datasets(["sparse"])]
    return out


def _filled(inside: np.ndarray, structure: np.ndarray = FILL_4) -> np.ndarray:
    """{f < 0} on a 2-D raster with every region the outside cannot reach (connectivity `structure`) filled."""
    from scipy import ndimage
    return ndimage.binary_fill_holes(inside, structure=structure)


def _on_raster(box, r: int) -> np.ndarray:
    """An r x r raster of `box`, rows in y (the solid check's raster, `solid_on_raster`)."""
    gx, gy = np.meshgrid(np.linspace(box[0], box[1], r), np.linspace(box[2], box[3], r))
    return np.column_stack([gx.ravel(), gy.ravel()])


def _cells(pts: np.ndarray, box, r: int) -> np.ndarray:
    """Flat index of the raster node of `_on_raster(box, r)` nearest to each point (clipped to the raster)."""
    ix = np.clip(np.rint((pts[:, 0] - box[0]) / (box[1] - box[0]) * (r - 1)), 0, r - 1).astype(int)
    iy = np.clip(np.rint((pts[:, 1] - box[2]) / (box[3] - box[2]) * (r - 1)), 0, r - 1).astype(int)
    return iy * r + ix


def _judge(decide, box, r: int, hp: np.ndarray, hl: np.ndarray) -> dict:
    """One trained model seen as the fleet would see it: held-out errors of {f < 0} raw and filled (a held-out
    point in a filled hole counts as inside), the solid check strict / islands only, one piece after the fill,
    and that piece bounded (`solid_fb`: no inside cell on the box's rim -- where the outside points surround the
    object a real object never reaches the box's rim, and f < 0 there means gamma < 0, the far field inside; on
    sparse data they need not surround it)."""
    inside = (decide(_on_raster(box, r)) < 0).reshape(r, r)
    filled = _filled(inside)
    f = decide(hp) if len(hp) else np.zeros(0)
    ins_f = (f < 0) | filled.ravel()[_cells(hp, box, r)]
    solid_f = is_solid(filled, True)
    return {"err": int(np.sum(hl * f <= 0)), "err_f": int(np.sum((hl < 0) != ins_f)), "held": len(hl),
            "solid": is_solid(inside, False), "solid_h": is_solid(inside, True), "solid_f": solid_f,
            "solid_fb": solid_f and not _rim(inside)}


def _rim(inside: np.ndarray) -> bool:
    """True when a raster's inside region touches its border."""
    return bool(inside[0].any() or inside[-1].any() or inside[:, 0].any() or inside[:, -1].any())


def dataset_world(item: tuple[str, dict, dict]):
    """(name, world, spec, AutoGridParams with the item's overrides, the data box, its diagonal) of one data set."""
    name, kw, pkw = item
    world, spec = build_world(Options(fleet_id="bench", **kw))
    params = dataclasses.replace(spec.autogrid_params, **pkw)
    lo, hi = world.points.min(axis=0), world.points.max(axis=0)
    return name, world, spec, params, (lo[0], hi[0], lo[1], hi[1]), float(np.hypot(*(hi - lo)))


def fill_one(item: tuple[str, dict, dict]) -> dict:
    """Per data set: SVC (C = 1e6) at diag/k raw and filled (IoU, 5-fold CV raw and filled, pieces), and the
    fleet-style sweep (exact central soft solves per candidate and fold on its coarse lattice) with each
    candidate's final model (`central_final_model`, one width) raw and filled."""
    import shapely
    from scipy import ndimage
    from sklearn.model_selection import StratifiedKFold
    from sklearn.svm import SVC

    from agents.autogrid_rules import lattice_box
    from agents.kernel import _squared_distances as sqd
    name, world, spec, params, bounds, diag = dataset_world(item)
    p, y = world.points, world.labels
    res = 200
    q = scenario.make_grid(res, res, B.padded_bounds(world.shape))  # the IoU raster (benchmarks/autogrid.py)
    truth = shapely.contains_xy(world.shape, q[:, 0], q[:, 1])

    def scores(inside_flat: np.ndarray) -> dict:
        """IoU raw, filled (4- and 8-connected outside), pieces after the fill, whether f < 0 reaches the raster's
        rim (there the raster cuts the region and the fill can only under-fill), areas, the truth covered."""
        ins = inside_flat.reshape(res, res)
        f4, f8 = _filled(ins, FILL_4), _filled(ins, FILL_8)
        iou = lambda a: float(np.count_nonzero(truth & a.ravel()) / max(1, np.count_nonzero(truth | a.ravel())))  # noqa: E731
        return {"raw": iou(ins), "fill": iou(f4), "fill8": iou(f8), "pieces": int(ndimage.label(f4)[1]), "rim": _rim(ins),
                "area": int(ins.sum()), "area_f": int(f4.sum()),
                "recall": float(np.count_nonzero(truth & f4.ravel()) / max(1, np.count_nonzero(truth)))}

    row = {"name": name, "n": len(y), "diag": diag, "svc": {}, "cand": {}}
    # SVC on the data (the references): the multiscale subcommand's kernels, folds and raster
    dp, dq = sqd(p, p), sqd(q, p)
    folds = list(StratifiedKFold(5, shuffle=True, random_state=0).split(p, y))
    r = params.solid_raster
    for k in MS_KS:
        g = k * k / (2 * diag * diag)
        clf = SVC(kernel="precomputed", C=1e6).fit(np.exp(-dp * g), y)
        rec = scores(clf.decision_function(np.exp(-dq * g)) < 0)
        box = lattice_box(bounds, diag / k)  # a raster the fleet could draw: the candidate's lattice box
        rb = _on_raster(box, r)
        acc, acc_f = [], []
        for a, b in folds:
            m = SVC(kernel="precomputed", C=1e6).fit(np.exp(-dp[np.ix_(a, a)] * g), y[a])
            jd = _judge(lambda x: m.decision_function(np.exp(-sqd(x, p[a]) * g)), box, r, p[b], y[b])
            acc.append(1 - jd["err"] / len(b)); acc_f.append(1 - jd["err_f"] / len(b))
        whole = (clf.decision_function(np.exp(-sqd(rb, p) * g)) < 0).reshape(r, r)
        solid_f = is_solid(_filled(whole), True)
        rec.update(cv=float(np.mean(acc)), cv_f=float(np.mean(acc_f)), solid_f=solid_f, solid_fb=solid_f and not _rim(whole))
        row["svc"][k] = rec
    # fleet-style: the sweep's exact soft solves on each candidate's coarse lattice, 5 folds (the rules use 2 or 5)
    fsets = [B._fold_sets(spec, dataclasses.replace(params, validate_folds=5), f) for f in range(5)]
    for d in FILL_KS:
        sigma = diag / d
        lbox, basis, sols = sweep_solves(fsets, bounds, sigma, params, params.sweep_slot(d))
        fl = [_judge(lambda x, s=sol: basis.decision(x, s.c, s.gamma), lbox, r, hp, hl) for sol, hp, hl in sols]
        fb, fs = B.central_final_model(p, y, params, bounds, sigma)
        rec = scores(fb.decision(q, fs.c, fs.gamma) < 0)
        rec.update(folds=fl, lattice=basis.size, grid=fb.size, margin="hard" if fs.solved else "soft", gamma=fs.gamma)
        row["cand"][d] = rec
    return row


def fill_choose(row: dict, cands, folds: int, solid: str, err: str, ties: str = "smaller") -> int:
    """The fleet's rule on the emulated tallies: the candidates solid (`solid` key) in every fold, else all;
    the fewest held-out errors (`err` key) summed over the first `folds` folds; ties -> `ties` sigma."""
    recs = [(d, sum(f[err] for f in row["cand"][d]["folds"][:folds]), all(f[solid] for f in row["cand"][d]["folds"][:folds]))
            for d in cands]
    pool = [t for t in recs if t[2]] or recs
    return min(pool, key=lambda t: (t[1], -t[0] if ties == "smaller" else t[0]))[0]


def svc_choose(row: dict, key: str, solid: str | None, ties: str) -> int:
    """SVC with sigma by 5-fold CV (`key`: accuracy raw or filled), optionally among the widths whose filled inside
    region passes the check `solid` (a key of the row); ties -> the larger sigma (SVC-CV as in `multiscale`) or
    the smaller."""
    ks = [k for k in MS_KS if solid is None or row["svc"][k][solid]] or list(MS_KS)
    best = max(row["svc"][k][key] for k in ks)
    tied = [k for k in ks if row["svc"][k][key] == best]
    return tied[0] if ties == "larger" else tied[-1]


#: the columns, fixed before the first run: (label, function of a row -> (divisor, IoU))
FILL_COLS = {
    "SVC-CV raw": lambda r: (k := svc_choose(r, "cv", None, "larger"), r["svc"][k]["raw"]),
    "SVC-CV filled": lambda r: (k := svc_choose(r, "cv", None, "larger"), r["svc"][k]["fill"]),
    "oracle raw": lambda r: max(((k, r["svc"][k]["raw"]) for k in MS_KS), key=lambda t: t[1]),
    "oracle filled": lambda r: max(((k, r["svc"][k]["fill"]) for k in MS_KS), key=lambda t: t[1]),
    "today raw": lambda r: (d := fill_choose(r, FILL_TODAY, 2, "solid", "err"), r["cand"][d]["raw"]),
    "today filled": lambda r: (d := fill_choose(r, FILL_TODAY, 2, "solid", "err"), r["cand"][d]["fill"]),
    "fill rule /4-16": lambda r: (d := fill_choose(r, FILL_TODAY, 2, "solid_f", "err_f"), r["cand"][d]["fill"]),
    "fill rule /4-32": lambda r: (d := fill_choose(r, FILL_KS, 2, "solid_f", "err_f"), r["cand"][d]["fill"]),
    "fill rule /4-32, 5 folds": lambda r: (d := fill_choose(r, FILL_KS, 5, "solid_f", "err_f"), r["cand"][d]["fill"]),
    "SVC fill-CV": lambda r: (k := svc_choose(r, "cv_f", "solid_f", "smaller"), r["svc"][k]["fill"]),
    # added after the first run (the leak table: gamma < 0 turned the far field inside, six_crescent and
    # sparse_bracket at diag/32): the filled piece must also be bounded, i.e. off the lattice box's rim
    "fill rule /4-32 bounded": lambda r: (d := fill_choose(r, FILL_KS, 2, "solid_fb", "err_f"), r["cand"][d]["fill"]),
    "SVC fill-CV bounded": lambda r: (k := svc_choose(r, "cv_f", "solid_fb", "smaller"), r["svc"][k]["fill"]),
}
FILL_GROUPS = {"24 development outlines": ("dev_", "ho2_", "ho3_"), "original 12": ("dev_",), "held-out 2": ("ho2_",),
               "held-out 3": ("ho3_",), "six shapes": ("six_",), "default run": ("default",),
               "sparse five (3 x 20)": ("sparse_",)}


def fill_table(rows: list[dict]) -> list[str]:
    """Markdown: per data set and k the SVC IoU raw / filled; the rules per data set; the means and counts; leaks."""
    out = ["| data set | n | " + " | ".join(f"SVC /{k} raw / filled" for k in MS_KS) + " |",
           "|---|---:|" + "---|" * len(MS_KS)]
    for r in rows:
        out.append(f"| {r['name']} | {r['n']} | " + " | ".join(
            f"{r['svc'][k]['raw']:.3f} / {r['svc'][k]['fill']:.3f}" for k in MS_KS) + " |")
    means = {k: (np.mean([r["svc"][k]["raw"] for r in rows if r["name"].startswith(("dev_", "ho2_", "ho3_"))]),
                 np.mean([r["svc"][k]["fill"] for r in rows if r["name"].startswith(("dev_", "ho2_", "ho3_"))])) for k in MS_KS}
    out.append("| mean, 24 outlines | | " + " | ".join(f"{a:.3f} / {b:.3f}" for a, b in means.values()) + " |")
    # the same for the fleet's final model at each candidate (its grid budget), per group of data sets
    out += ["", "| mean raw / filled | " + " | ".join(f"SVC /{k}" for k in FILL_KS) + " | "
            + " | ".join(f"fleet final /{d}" for d in FILL_KS) + " |", "|---|" + "---|" * 2 * len(FILL_KS)]
    for g, pref in FILL_GROUPS.items():
        rs = [r for r in rows if r["name"].startswith(pref)]
        if rs:
            out.append(f"| {g} | " + " | ".join(
                f"{np.mean([r[src][k]['raw'] for r in rs]):.3f} / {np.mean([r[src][k]['fill'] for r in rs]):.3f}"
                for src in ("svc", "cand") for k in FILL_KS) + " |")
    out += ["", "| data set | " + " | ".join(FILL_COLS) + " |", "|---|" + "---:|" * len(FILL_COLS)]
    for r in rows:
        out.append(f"| {r['name']} | " + " | ".join(f"{v:.3f} (/{k:g})" for k, v in (f(r) for f in FILL_COLS.values())) + " |")
    out += ["", "| mean (>= SVC-CV raw; >= SVC-CV filled: counts) | " + " | ".join(FILL_COLS) + " |",
            "|---|" + "---|" * len(FILL_COLS)]
    for g, pref in FILL_GROUPS.items():
        rs = [r for r in rows if r["name"].startswith(pref)]
        if not rs:
            continue
        cv = [FILL_COLS["SVC-CV raw"](r)[1] for r in rs]
        cvf = [FILL_COLS["SVC-CV filled"](r)[1] for r in rs]
        cells = []
        for f in FILL_COLS.values():
            v = [f(r)[1] for r in rs]
            cells.append(f"{np.mean(v):.3f} ({sum(a >= b - 1e-9 for a, b in zip(v, cv))}; "
                         f"{sum(a >= b - 1e-9 for a, b in zip(v, cvf))}/{len(rs)})")
        out.append(f"| {g} | " + " | ".join(cells) + " |")
    # leaks: a rule's narrow choice, filled, far below a wider width filled; why (the fill's area, pieces, the share
    # of the truth it covers, f < 0 on the raster's rim: gamma < 0)
    out += ["", "| data set | rule | chosen | filled IoU | best wider (filled) | area raw -> filled (cells) | pieces | "
            "truth covered | inside on the rim |", "|---|---|---|---:|---|---|---:|---:|---|"]
    leak_rules = {lab: ("cand", FILL_KS) for lab in FILL_COLS if lab.startswith("fill rule /4-32")}
    leak_rules.update({lab: ("svc", MS_KS) for lab in FILL_COLS if lab.startswith("SVC fill-CV")})
    for r in rows:
        for label, (src, ks) in leak_rules.items():
            d, v = FILL_COLS[label](r)
            wider = [(w, r[src][w]["fill"]) for w in ks if w < d]
            if wider and max(t[1] for t in wider) - v >= 0.03:
                w, bv = max(wider, key=lambda t: t[1])
                c = r[src][d]
                out.append(f"| {r['name']} | {label} | /{d} | {v:.3f} | /{w} ({bv:.3f}) | {c['area']} -> {c['area_f']} | "
                           f"{c['pieces']} | {c['recall']:.3f} | {'yes' if c['rim'] else 'no'} |")
    rim = sum(r[src][k]["rim"] for r in rows for src, ks in (("svc", MS_KS), ("cand", FILL_KS)) for k in ks)
    out += ["", f"models whose f < 0 reaches the IoU raster's rim (the fill can only under-fill there): {rim} of "
            f"{len(rows) * (len(MS_KS) + len(FILL_KS))}"]
    gain8 = [r[src][k]["fill8"] - r[src][k]["fill"] for r in rows for src, ks in (("svc", MS_KS), ("cand", FILL_KS))
             for k in ks]
    out.append(f"8-connected outside instead of 4 (every model above): IoU filled changes by "
               f"{min(gain8):+.4f} .. {max(gain8):+.4f}, mean {np.mean(gain8):+.5f}")
    return out


def fill(out_dir: str, jobs: int) -> None:
    """Collect the pickles OUT lacks (in `jobs` processes), then print the tables."""
    print("\n".join(fill_table(collect_rows(out_dir, jobs, "fill", fill_datasets(), fill_one))))


SETS = ("default", "sparse", "six", "out")


def main(argv: list[str] | None = None) -> None:
    """The command line: `collect SETS OUT`, `rank OUT`, `multiscale OUT` or `fill OUT`; bad use exits 2 with one
    message (argparse)."""
    import argparse

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="command", required=True, metavar="{collect,rank,multiscale,fill}")
    c = sub.add_parser("collect", help="exact central solves per data set and candidate; one pickle per data set in OUT")
    c.add_argument("sets", help=f"comma-separated data sets, of {','.join(SETS)}")
    c.add_argument("out", help="an existing directory for the pickles")
    r = sub.add_parser("rank", help="every rule of the grid on the pickles in OUT")
    r.add_argument("out", help="the directory `collect` wrote")
    m = sub.add_parser("multiscale", help="issue 15: models beyond one width vs SVC-CV and the oracle")
    m.add_argument("out", help="an existing directory for the pickles (kept between calls)")
    m.add_argument("--jobs", type=int, default=2, help="data sets in parallel (processes)")
    fl = sub.add_parser("fill", help="issue 15: the inside region with its enclosed holes filled, vs SVC-CV and the oracle")
    fl.add_argument("out", help="an existing directory for the pickles (kept between calls)")
    fl.add_argument("--jobs", type=int, default=2, help="data sets in parallel (processes)")
    args = ap.parse_args(argv)
    if not Path(args.out).is_dir():
        ap.error(f"{args.out}: not a directory")
    if args.command in ("multiscale", "fill"):
        if args.jobs < 1:
            ap.error(f"--jobs must be >= 1, got {args.jobs}")
        (multiscale if args.command == "multiscale" else fill)(args.out, args.jobs)
        return
    if args.command == "rank":
        if not glob.glob(f"{args.out}/*.pkl"):
            ap.error(f"{args.out}: no .pkl files (run collect first)")
        rank(args.out)
        return
    wanted = [w for w in args.sets.split(",") if w]
    unknown = [w for w in wanted if w not in SETS]
    if unknown or not wanted:
        ap.error(f"unknown data set(s) {','.join(unknown) or repr(args.sets)}: choose from {','.join(SETS)}")
    for name, kw, pkw in datasets(wanted):
        t = time.time()
        row = one(name, kw, pkw)
        pickle.dump(row, open(f"{args.out}/{name}.pkl", "wb"))
        print(name, f"{time.time()-t:.0f}s", flush=True)


if __name__ == "__main__":
    main()
