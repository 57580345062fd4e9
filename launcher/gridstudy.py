"""Grid-choice study (the paper's Fig. 5): a good grid and a coarse, shifted one, same data.

On the paper's 5x3 grid the hard-margin problem is feasible and the fleet's CT-ADMM learns
one outline that separates the data. On a coarser grid shifted by half a cell no function of
the grid separates the data: the centralized QP reports "infeasible", and the CT-ADMM -- which
has no dual solution to converge to -- keeps its primal bounded while its margin duals grow
linearly in time; the curves it draws no longer separate the data. The study says so in words
and draws both cases side by side from the fleet's last state.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from agents.problem import CentralSolution, solve_central
from agents.spec import FleetSpec
from launcher import scenario
from launcher.simulate import simulate_fleet
from launcher.world import Options, World, build_world


@dataclass
class GridCase:
    """One grid's outcome: the centralized verdict and what the fleet's CT-ADMM ended with."""

    label: str
    grid: np.ndarray
    bounds: tuple[float, float, float, float]
    central_status: str
    function_error: float | None  # largest over robots vs the central solution (None if infeasible)
    misclassified: int  # data points on the wrong side of at least one robot's curve
    worst_robot_misclassified: int  # the most any single robot's curve gets wrong
    n_points: int
    consensus_gap: float  # largest relative distance between two robots' (x, gamma)
    dual_norm_half: float  # largest |margin dual| at half the stop time
    dual_norm_end: float  # ... and at the stop time
    rounds: int
    robots: list[dict[str, Any]]  # the fleet's results (x, gamma per robot)

    @property
    def separates(self) -> bool:
        return self.misclassified == 0

    @property
    def duals_growing(self) -> bool:
        """Margin duals that keep growing (roughly linearly) signal that no dual solution exists."""
        return self.dual_norm_end > 1.5 * max(self.dual_norm_half, 1e-12)


@dataclass
class GridStudy:
    good: GridCase
    bad: GridCase
    message: str
    png: Path


def _consensus_gap(robots: list[dict[str, Any]]) -> float:
    vs = [np.append(np.asarray(r["x"], dtype=float), float(r["gamma"])) for r in robots]
    gap = 0.0
    for a in vs:
        for b in vs:
            gap = max(gap, float(np.linalg.norm(a - b)) / max(float(np.linalg.norm(a)), 1e-12))
    return gap


def _run_case(label: str, world: World, spec: FleetSpec, central: CentralSolution, stop_time: float) -> GridCase:
    """Run the fleet to half and to the full stop time: the dual norms show growth or not."""
    basis = spec.basis
    # params are CTADMMParams' own fields (launcher/options.py feeds --ct-stop-time to "stop_time"):
    # replacing the one key sets the stop time, whatever the dict held before
    half = dataclasses.replace(spec, params={**spec.params, "stop_time": stop_time / 2})
    full = dataclasses.replace(spec, params={**spec.params, "stop_time": stop_time})
    assert spec.algorithm == "ct-admm" and full.algorithm_params.stop_time == stop_time
    dual_half = max(r["dual_norm"] for r in simulate_fleet(half).robots)
    robots = simulate_fleet(full).robots
    pts, labels = world.points, world.labels
    wrong = np.zeros(len(labels), dtype=bool)
    worst, errors = 0, []
    for r in robots:
        c = basis.c_from_x(np.asarray(r["x"], dtype=float))
        mine = np.sign(basis.decision(pts, c, r["gamma"])) != labels
        wrong |= mine
        worst = max(worst, int(mine.sum()))
        if central.solved:
            errors.append(basis.function_error(c, r["gamma"], central.c, central.gamma))
    return GridCase(
        label=label,
        grid=spec.grid,
        bounds=world.bounds,
        central_status=central.status,
        function_error=max(errors) if errors else None,
        misclassified=int(wrong.sum()),
        worst_robot_misclassified=worst,
        n_points=len(labels),
        consensus_gap=_consensus_gap(robots),
        dual_norm_half=dual_half,
        dual_norm_end=max(r["dual_norm"] for r in robots),
        rounds=max(int(r["rounds"]) for r in robots),
        robots=robots,
    )


def _describe(case: GridCase, stop_time: float) -> str:
    if case.central_status == "solved":
        verdict = "the hard-margin problem is feasible"
        fleet = (
            f"CT-ADMM reaches function error {case.function_error:.1e} in {case.rounds} rounds and "
            + ("separates all" if case.separates else f"misclassifies {case.misclassified} of")
            + f" {case.n_points} points"
        )
    else:
        verdict = "the hard-margin problem is INFEASIBLE (no function on this grid separates the data)"
        growth = (
            f"its margin duals keep growing ({case.dual_norm_half:.3g} at {stop_time / 2:g} s, "
            f"{case.dual_norm_end:.3g} at {stop_time:g} s: no dual solution exists)"
            if case.duals_growing
            else f"its margin duals stay at {case.dual_norm_end:.3g}"
        )
        fleet = (
            f"CT-ADMM stays bounded but cannot converge: {growth}; after {stop_time:g} s "
            f"{case.misclassified} of {case.n_points} points lie on the wrong side of at least one "
            f"robot's curve (worst robot: {case.worst_robot_misclassified}; robots disagree by "
            f"{case.consensus_gap:.1e}); the picture shows that last state"
        )
    return f"grid {case.label}: {verdict}; {fleet}."


def _shifted_bounds(bounds: tuple[float, float, float, float], grid: str, shift: tuple[float, float]) -> str:
    nx, ny = scenario.parse_grid(grid)
    x0, x1, y0, y1 = bounds
    dx, dy = shift[0] * (x1 - x0) / nx, shift[1] * (y1 - y0) / ny
    return f"{x0 + dx!r},{x1 + dx!r},{y0 + dy!r},{y1 + dy!r}"


def run_grid_study(
    out_dir: str | Path,
    *,
    options: Options | None = None,
    good_grid: str = "5x3",
    bad_grid: str = "4x2",
    shift: tuple[float, float] = (0.5, 0.0),
    stop_time: float | None = None,
    quiet: bool = False,
) -> GridStudy:
    """Solve the same data on `good_grid` and on `bad_grid` shifted by `shift` cells; draw both.

    Writes out_dir/grid_study.png; returns both outcomes and the message (printed unless quiet).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    base = options or Options()
    base = dataclasses.replace(base, algorithm="ct-admm", fleet_id=base.fleet_id or "gridstudy")
    stop_time = base.ct_stop_time if stop_time is None else stop_time  # default: --ct-stop-time's
    good_world, good_spec = build_world(dataclasses.replace(base, grid=good_grid))
    bad_opts = dataclasses.replace(
        base, grid=bad_grid, grid_bounds=_shifted_bounds(good_world.bounds, bad_grid, shift)
    )
    bad_world, bad_spec = build_world(bad_opts)
    if not np.array_equal(good_world.points, bad_world.points):
        raise RuntimeError("the two grids must see the same data")
    cases = []
    for label, world, spec in (
        (good_grid, good_world, good_spec),
        (f"{bad_grid} shifted by ({shift[0]:g}, {shift[1]:g}) cells", bad_world, bad_spec),
    ):
        central = solve_central(spec.basis, world.points, world.labels, spec.C)
        cases.append((_run_case(label, world, spec, central, stop_time), world, spec))
    (good, _, _), (bad, _, _) = cases
    message = "\n".join(_describe(case, stop_time) for case, _, _ in cases)
    png = out / "grid_study.png"
    _draw(png, cases)
    if not quiet:
        print(message)
        print(f"wrote {png}")
    return GridStudy(good=good, bad=bad, message=message, png=png)


def _draw(path: Path, cases: list[tuple[GridCase, World, FleetSpec]]) -> None:
    """Side by side: truth, data, grid points and every robot's last curve."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(cases), figsize=(6.5 * len(cases), 5.6))
    cmap = matplotlib.colormaps["tab10"]
    for ax, (case, world, spec) in zip(np.atleast_1d(axes), cases, strict=True):
        basis = spec.basis
        x0, x1, y0, y1 = world.bounds
        gxs = np.concatenate([basis.grid[:, 0], [x0, x1]])
        gys = np.concatenate([basis.grid[:, 1], [y0, y1]])
        pad = 0.08 * max(x1 - x0, y1 - y0)
        xs = np.linspace(gxs.min() - pad, gxs.max() + pad, 260)
        ys = np.linspace(gys.min() - pad, gys.max() + pad, 260)
        gx, gy = np.meshgrid(xs, ys)
        flat = np.column_stack([gx.ravel(), gy.ravel()])
        if world.shape is not None:
            ax.plot(*world.shape.exterior.xy, "--", color="magenta", lw=2, label="true outline")
        rows = {int(r["id"]): r for r in case.robots}
        wrong = np.zeros(len(world.labels), dtype=bool)
        for i, robot in enumerate(world.robots):
            colour = cmap(i % cmap.N)
            out = robot.labels > 0
            ax.scatter(*robot.points[out].T, marker="o", facecolors="none", edgecolors=[colour], s=26)
            ax.scatter(*robot.points[~out].T, marker="x", color=colour, s=26)
            row = rows.get(robot.id)
            if row is None:
                continue
            c = basis.c_from_x(np.asarray(row["x"], dtype=float))
            f = basis.decision(flat, c, row["gamma"]).reshape(gx.shape)
            if f.min() < 0 < f.max():
                ax.contour(gx, gy, f, levels=[0.0], colors=[colour], linewidths=1.6)
            ax.plot([], [], color=colour, label=f"robot {robot.id}")
            wrong |= np.sign(basis.decision(world.points, c, row["gamma"])) != world.labels
        if wrong.any():
            ax.scatter(*world.points[wrong].T, s=120, facecolors="none", edgecolors="red", lw=1.4,
                       label="wrong side of some curve")
        ax.scatter(*basis.grid.T, marker="+", color="black", s=70, lw=1.3, label="grid points")
        if case.central_status == "solved":
            title = f"grid {case.label}: feasible\nCT-ADMM error {case.function_error:.1e}, "
            title += "all points separated" if case.separates else f"{case.misclassified} points wrong"
        else:
            title = (
                f"grid {case.label}: INFEASIBLE\nCT-ADMM last state: {case.misclassified}/{case.n_points} "
                f"points wrong (red), duals {'growing' if case.duals_growing else 'bounded'}"
            )
        ax.set_title(title, fontsize=10)
        ax.set_aspect("equal")
        ax.set_xlim(xs[0], xs[-1])
        ax.set_ylim(ys[0], ys[-1])
        ax.legend(loc="upper right", fontsize=7, framealpha=0.8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


if __name__ == "__main__":
    import sys

    run_grid_study(sys.argv[1] if len(sys.argv) > 1 else "runs/gridstudy")
