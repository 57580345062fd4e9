"""Issue 15, step 6: central emulation of sigma rules (benchmarks/results/autogrid.md, "step 6").

`collect`: per data set (default run, the sparse five-shape test's data, the six benchmark shapes, the 12
development outlines), per candidate diag/{4, 6, 8, 12, 16, 24} and fold (5 folds, the fleet's units), one
exact central soft solve on the candidate's coarse lattice (held-out errors, hinge, solid strict / holes
allowed) and the IoU of the fleet's final pipeline at r = 1 and 3; SVC 5-fold CV and the oracle. One pickle
per data set in OUT. `rank`: every rule of the grid below on those pickles, the ones that keep the IoU rails
sorted by the outlines' mean. Never run it on the held-out-2 outlines.

    .venv/bin/python benchmarks/autogrid_rules_emulation.py collect default,sparse,six,out OUT
    .venv/bin/python benchmarks/autogrid_rules_emulation.py rank OUT
"""
import dataclasses, glob, itertools, pickle, sys, time
from pathlib import Path
import numpy as np
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
import autogrid as B
from agents.autogrid_rules import AutoGridParams, coarse_lattice, solid_on_raster
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
        lbox, _, grid = coarse_lattice(bounds, sigma, params.spacing_ratio, params.sweep_slot(d))
        basis = GridBasis(grid, sigma)
        fl = []
        for tp, tl, hp, hl in folds:
            sol = solve_central(basis, tp, tl, params.soft_C)
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


SETS = ("default", "sparse", "six", "out")


def main(argv: list[str] | None = None) -> None:
    """The command line: `collect SETS OUT` or `rank OUT`; bad use exits 2 with one message (argparse)."""
    import argparse

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="command", required=True, metavar="{collect,rank}")
    c = sub.add_parser("collect", help="exact central solves per data set and candidate; one pickle per data set in OUT")
    c.add_argument("sets", help=f"comma-separated data sets, of {','.join(SETS)}")
    c.add_argument("out", help="an existing directory for the pickles")
    r = sub.add_parser("rank", help="every rule of the grid on the pickles in OUT")
    r.add_argument("out", help="the directory `collect` wrote")
    args = ap.parse_args(argv)
    if not Path(args.out).is_dir():
        ap.error(f"{args.out}: not a directory")
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
