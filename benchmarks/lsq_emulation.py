"""Issue 15: the LiDAR least-squares model in central emulation, against SVC (benchmarks/results/autogrid.md,
"the LiDAR least-squares model").

Every LiDAR pair a robot keeps (consecutive rows: outside +1 at `offset` before the return, inside -1 at
`offset` past it) says three things: the outside point is outside, the inside point inside, and the return
-- the pair's midpoint -- is ON the outline. The model fits all three as rows with targets +1, 0, -1 on the
fleet's grid basis (agents/kernel.py GridBasis: f = phi' x + gamma, |x|^2 = ||f||_H^2):

    minimise  sum_rows (phi(p_i)' x + gamma - t_i)^2 + LAM |x|^2          (gamma free)

The rule, frozen before any held-out set was read (the values below are its whole definition):
- grid: the candidate's level-0 lattice (`coarse_lattice`) at spacing SPACING x sigma, within the budget;
- sigma = diag / k, k in CANDIDATES, diag the data box's diagonal;
- the width: 5 folds of whole pairs (fold = (pair index in its robot + robot id) mod 5), the smallest mean
  held-out squared residual over a held-out pair's three rows; ties -> the larger sigma;
- the output: {f < 0} on the IoU raster (also reported with enclosed holes filled, not used by the rule).
Rule 2 ("near"), frozen after rule 1's held-out evaluations, on development data only, before held-out 6 was
read (benchmarks/results/autogrid.md, "rule 2"): the same model, lam, folds, score and ties; what changes is
where the grid is and which widths are tried:
- grid: the candidate's level-0 lattice at spacing SPACING x sigma, keeping only the nodes within NEAR x sigma
  of a data point (the fleet's near-data marks); a candidate whose kept lattice exceeds the budget is not
  tried (none fits: the widest candidate's lattice coarsened as rule 1's);
- sigma = diag / k, k in CANDIDATES_NEAR (narrower widths fit the budget once the lattice follows the data);
- the output: {f < 0} within MASK x sigma of a grid node (far from every node f is only gamma, which says
  nothing), with every enclosed hole filled (an outside region no LiDAR ray from outside can reach is inside).
References (as in the earlier sections): SVC (RBF, C = 1e6) at diag/k, k in SVC_KS; "SVC-CV" = best 5-fold
CV accuracy (stratified, shuffled, seed 0; ties -> the larger sigma), "oracle" = best IoU against the truth.
IoU on the 200 x 200 raster of the outline's box widened by 20 % (benchmarks/autogrid.py padded_bounds).
Exact solves (closed form, no iteration): deterministic.

    .venv/bin/python benchmarks/lsq_emulation.py dev OUT [--jobs 2]       # development data only
    .venv/bin/python benchmarks/lsq_emulation.py heldout4 OUT             # the one evaluation
    .venv/bin/python benchmarks/lsq_emulation.py heldout5 OUT
    .venv/bin/python benchmarks/lsq_emulation.py heldout6 OUT             # rule 2's one evaluation
"""
from __future__ import annotations

import argparse
import pickle
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
import agents  # noqa: F401,E402  (one OpenBLAS thread, before numpy)
import numpy as np  # noqa: E402

LAM = 0.1
SPACING = 1.0
CANDIDATES = (4, 6, 8, 12, 16)
NEAR = 1.5
CANDIDATES_NEAR = (4, 6, 8, 12, 16, 24, 32)
MASK = 2.0
FOLDS = 5
SVC_KS = (2, 3, 4, 6, 8, 12, 16, 24, 32)
RES = 200


def lidar_rows(robots) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(outside points, inside points, fold of each pair) over all robots' consecutive (+1, -1) pairs."""
    outside, inside, fold = [], [], []
    for r in robots:
        k = 0
        for j in range(0, len(r.points) - 1, 2):
            if r.labels[j] == 1 and r.labels[j + 1] == -1:
                outside.append(r.points[j]); inside.append(r.points[j + 1]); fold.append((k + r.id) % FOLDS)
                k += 1
    return np.array(outside), np.array(inside), np.array(fold)


def stacked(outside: np.ndarray, inside: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The model's rows: outside +1, return (midpoint) 0, inside -1."""
    n = len(outside)
    return (np.vstack([outside, (outside + inside) / 2, inside]),
            np.concatenate([np.ones(n), np.zeros(n), -np.ones(n)]))


def fit(basis, points: np.ndarray, targets: np.ndarray, lam: float = LAM):
    """The exact least-squares solution (normal equations, gamma unregularised); returns f as a function."""
    from scipy import linalg
    a = np.hstack([basis.features(points), np.ones((len(points), 1))])
    p = a.T @ a
    p[:-1, :-1] += lam * np.eye(a.shape[1] - 1)
    v = linalg.solve(p, a.T @ targets, assume_a="sym")
    return lambda q: basis.features(q) @ v[:-1] + v[-1]


def near_lattice(bounds, sigma: float, points: np.ndarray) -> np.ndarray:
    """Rule 2's grid: the level-0 lattice at SPACING sigma, the nodes within NEAR sigma of a data point."""
    from scipy.spatial import cKDTree

    from agents.autogrid_rules import lattice, lattice_box
    nodes = lattice(lattice_box(bounds, sigma), SPACING * sigma, 0)
    distance, _ = cKDTree(points).query(nodes)
    return nodes[distance <= NEAR * sigma]


def output_mask(f, basis, q: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Rule 2's output on a raster q (row-major, `shape`): {f < 0} within MASK sigma of a grid node, holes filled."""
    from scipy import ndimage
    from scipy.spatial import cKDTree
    distance, _ = cKDTree(basis.grid).query(q)
    inside = (f(q) < 0) & (distance <= MASK * basis.sigma)
    return ndimage.binary_fill_holes(inside.reshape(shape)).ravel()


def scored(basis, outside: np.ndarray, inner: np.ndarray, fold: np.ndarray) -> tuple[object, float]:
    """(the fit on all rows, the mean held-out squared residual over the folds' held-out pairs)."""
    sq = []
    for h in range(FOLDS):
        g = fit(basis, *stacked(outside[fold != h], inner[fold != h]))
        o, i = outside[fold == h], inner[fold == h]
        sq += list((g(o) - 1) ** 2 + g((o + i) / 2) ** 2 + (g(i) + 1) ** 2)
    return fit(basis, *stacked(outside, inner)), float(np.mean(sq))


def one(item: tuple[str, dict, dict]) -> dict:
    """One data set: each rule's IoU and score per candidate, SVC per width (IoU, CV accuracy)."""
    import shapely
    from scipy import ndimage
    from sklearn.model_selection import StratifiedKFold, cross_val_score
    from sklearn.svm import SVC

    import autogrid as B
    from agents.autogrid_rules import coarse_lattice
    from agents.kernel import GridBasis
    from autogrid_rules_emulation import dataset_world
    from launcher import scenario

    name, world, spec, params, bounds, diag = dataset_world(item)
    p, y = world.points, world.labels
    q = scenario.make_grid(RES, RES, B.padded_bounds(world.shape))
    truth = shapely.contains_xy(world.shape, q[:, 0], q[:, 1])

    def iou(inside: np.ndarray) -> float:
        return float(np.count_nonzero(truth & inside) / max(1, np.count_nonzero(truth | inside)))

    outside, inner, fold = lidar_rows(world.robots)
    row = {"name": name, "n": len(y), "pairs": len(outside), "lsq": {}, "near": {}, "svc": {}}
    for k in CANDIDATES:
        sigma = diag / k
        _, _, grid = coarse_lattice(bounds, sigma, SPACING, params.max_points)
        basis = GridBasis(grid, sigma)
        f, score = scored(basis, outside, inner, fold)
        inside = f(q) < 0
        filled = ndimage.binary_fill_holes(inside.reshape(RES, RES)).ravel()
        row["lsq"][k] = {"iou": iou(inside), "iou_filled": iou(filled), "score": score, "grid": len(grid)}
    for k in CANDIDATES_NEAR:
        sigma = diag / k
        grid = near_lattice(bounds, sigma, p)
        if len(grid) > params.max_points:
            row["near"][k] = {"grid": len(grid), "fits": False}
            continue
        basis = GridBasis(grid, sigma)
        f, score = scored(basis, outside, inner, fold)
        row["near"][k] = {"grid": len(grid), "fits": True, "score": score, "iou_raw": iou(f(q) < 0),
                          "iou": iou(output_mask(f, basis, q, (RES, RES)))}
    if not any(e["fits"] for e in row["near"].values()):  # nothing fits: rule 1's coarsened widest lattice
        k = CANDIDATES_NEAR[0]
        _, _, grid = coarse_lattice(bounds, diag / k, SPACING, params.max_points)
        basis = GridBasis(grid, diag / k)
        f, score = scored(basis, outside, inner, fold)
        row["near"][k] = {"grid": len(grid), "fits": True, "score": score, "iou_raw": iou(f(q) < 0),
                          "iou": iou(output_mask(f, basis, q, (RES, RES)))}
    cv = StratifiedKFold(5, shuffle=True, random_state=0)
    for k in SVC_KS:
        gamma = k * k / (2 * diag * diag)
        clf = SVC(kernel="rbf", C=1e6, gamma=gamma).fit(p, y)
        row["svc"][k] = {"iou": iou(clf.decision_function(q) < 0),
                         "cv": float(cross_val_score(SVC(kernel="rbf", C=1e6, gamma=gamma), p, y, cv=cv).mean())}
    return row


def choice(row: dict) -> int:
    """The frozen rule: the smallest held-out squared residual, ties -> the larger sigma (smaller k)."""
    return min(CANDIDATES, key=lambda k: (row["lsq"][k]["score"], k))


def choice_near(row: dict) -> int:
    """Rule 2: among the candidates whose near-data lattice fits, the smallest score, ties -> the larger sigma."""
    fits = [k for k in CANDIDATES_NEAR if row["near"][k]["fits"]]
    return min(fits, key=lambda k: (row["near"][k]["score"], k))


def svc_cv(row: dict) -> int:
    return min(SVC_KS, key=lambda k: (-row["svc"][k]["cv"], k))


def table(rows: list[dict]) -> list[str]:
    out = ["| data set | points (pairs) | rule 1: sigma (diag/k), grid, IoU | rule 2: sigma, grid, IoU raw | rule 2 IoU "
           "| SVC-CV (diag/k) | oracle (diag/k) | rule 2 - SVC-CV | rule 2 - oracle |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        k, n, c = choice(r), choice_near(r), svc_cv(r)
        o = max(SVC_KS, key=lambda j: r["svc"][j]["iou"])
        e, m = r["lsq"][k], r["near"][n]
        out.append(f"| {r['name']} | {r['n']} ({r['pairs']}) | /{k}, {e['grid']}, {e['iou']:.3f} "
                   f"| /{n}, {m['grid']}, {m['iou_raw']:.3f} | **{m['iou']:.3f}** "
                   f"| {r['svc'][c]['iou']:.3f} (/{c}) | {r['svc'][o]['iou']:.3f} (/{o}) "
                   f"| {m['iou'] - r['svc'][c]['iou']:+.3f} | {m['iou'] - r['svc'][o]['iou']:+.3f} |")
    return out


def summary(rows: list[dict], label: str) -> str:
    one = [r["lsq"][choice(r)]["iou"] for r in rows]
    two = [r["near"][choice_near(r)]["iou"] for r in rows]
    cv = [r["svc"][svc_cv(r)]["iou"] for r in rows]
    orc = [max(r["svc"][k]["iou"] for k in SVC_KS) for r in rows]
    count = lambda xs, ref: f"{sum(a >= b for a, b in zip(xs, ref))} of {len(rows)}"  # noqa: E731
    return (f"| {label} ({len(rows)}) | {np.mean(one):.3f} | **{np.mean(two):.3f}** | {np.mean(cv):.3f} | {np.mean(orc):.3f} "
            f"| {count(one, cv)} / {count(two, cv)} | {count(one, orc)} / {count(two, orc)} |")


def datasets(which: str) -> list[tuple[str, dict, dict]]:
    """dev: the development data of the earlier sections (autogrid_rules_emulation.fill_datasets); heldoutN:
    the folder's outlines as a new user runs them (5 robots x 40 points, simulate's defaults)."""
    if which == "dev":
        import autogrid_rules_emulation as E
        return E.fill_datasets()
    folder = ROOT / "benchmarks" / "outlines" / which
    files = sorted(folder.glob("*.csv"))
    if not files:
        raise SystemExit(f"lsq_emulation: {folder}: no outlines")
    return [(f"{which}_{f.stem}", dict(robots=5, points=40, shape_file=str(f)), {}) for f in files]


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sets", choices=["dev", "heldout4", "heldout5", "heldout6"])
    ap.add_argument("out", type=Path, help="folder for one pickle per data set (kept: a second call only prints)")
    ap.add_argument("--jobs", type=int, default=2)
    args = ap.parse_args(argv)
    if args.jobs < 1:
        ap.error(f"--jobs must be >= 1, got {args.jobs}")
    if args.out.exists() and not args.out.is_dir():
        ap.error(f"{args.out}: not a directory")
    args.out.mkdir(parents=True, exist_ok=True)
    items = datasets(args.sets)
    todo = [it for it in items if not (args.out / f"{it[0]}.pkl").exists()]
    if todo:
        import multiprocessing as mp
        with mp.get_context("spawn").Pool(max(1, args.jobs)) as pool:
            for row in pool.imap_unordered(one, todo):
                (args.out / f"{row['name']}.pkl").write_bytes(pickle.dumps(row))
                print("done", row["name"], file=sys.stderr, flush=True)
    rows = [pickle.loads((args.out / f"{n}.pkl").read_bytes()) for n, _, _ in items]
    print("\n".join(table(rows)))
    print("\n| set | rule 1 mean IoU | rule 2 | SVC-CV | oracle | >= SVC-CV (rule 1 / 2) | >= oracle (rule 1 / 2) |\n"
          "|---|---|---|---|---|---|---|")
    groups = {"24 development outlines": ("dev_", "ho2_", "ho3_"), "six shapes": ("six_",), "default run": ("default",),
              "sparse five": ("sparse_",)} if args.sets == "dev" else {args.sets: (args.sets,)}
    for label, prefixes in groups.items():
        sel = [r for r in rows if r["name"].startswith(prefixes)]
        if sel:
            print(summary(sel, label))


if __name__ == "__main__":
    main()
