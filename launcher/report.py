"""Measure a fleet's answer against the centralized solve, write result.json and draw it.

Shared by `simulate`, `launch` and `central`, so every run's folder reads the same way.
The schema of result.json is documented in docs/result-schema.md.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from agents.kernel import GridBasis
from agents.problem import CentralSolution
from launcher import scenario
from launcher.world import World

SCHEMA_VERSION = 1


def _robot_c(basis: GridBasis, robot: dict[str, Any]) -> np.ndarray:
    return basis.c_from_x(np.asarray(robot["x"], dtype=float))


def _errors(basis: GridBasis, fs: list[tuple[np.ndarray, float]], central: CentralSolution) -> tuple[float, float]:
    """(largest function error vs the central solution, largest distance to the fleet mean)."""
    if not fs:
        return float("nan"), float("nan")
    c_mean = np.mean([c for c, _ in fs], axis=0)
    g_mean = float(np.mean([g for _, g in fs]))
    consensus = max(basis.function_error(c, g, c_mean, g_mean) for c, g in fs)
    if not central.solved:
        return float("nan"), consensus
    function = max(basis.function_error(c, g, central.c, central.gamma) for c, g in fs)
    return function, consensus


def history(basis: GridBasis, robots: list[dict[str, Any]], central: CentralSolution) -> list[dict[str, Any]]:
    """Per-round function and consensus errors over the robots that recorded that round."""
    traces = [{int(k): np.asarray(v) for k, v in r.get("trace", {}).items()} for r in robots]
    rounds = sorted(set().union(*[t.keys() for t in traces])) if traces else []
    out = []
    for k in rounds:
        values = [t[k] for t in traces if k in t]
        fs = [(basis.c_from_x(v[:-1]), float(v[-1])) for v in values]
        function, consensus = _errors(basis, fs, central)
        out.append({"round": k, "function_error": _num(function), "consensus_error": _num(consensus)})
    return out


def _num(value: float) -> float | None:
    """JSON has no NaN: unknown figures are null."""
    return None if value is None or not np.isfinite(value) else float(value)


def build_result(
    world: World,
    basis: GridBasis,
    central: CentralSolution,
    robots: list[dict[str, Any]],
    *,
    algorithm: str,
    C: float | None,
    wall_s: float,
    extra: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The run's result.json content (see docs/result-schema.md)."""
    fs = [(_robot_c(basis, r), float(r["gamma"])) for r in robots]
    function, consensus = _errors(basis, fs, central)
    pts, labels = world.points, world.labels
    accuracy = min((float(np.mean(np.sign(basis.decision(pts, c, g)) == labels)) for c, g in fs), default=None)
    iou = None
    if world.shape is not None and fs:
        x0, x1, y0, y1 = world.bounds
        ious = [
            scenario.iou_on_raster(world.shape, lambda p, c=c, g=g: basis.decision(p, c, g) < 0, (x0, x1, y0, y1))
            for c, g in fs
        ]
        iou = min(ious)
    robot_rows = []
    for r, (c, g) in zip(robots, fs, strict=True):
        row = {k: v for k, v in r.items() if k not in ("trace", "x", "round_times")}
        row.update(id=int(r["id"]), c=c.tolist(), gamma=g)
        if central.solved:
            row["function_error"] = basis.function_error(c, g, central.c, central.gamma)
        robot_rows.append(row)
    rounds = max((int(r["rounds"]) for r in robots), default=0)
    result: dict[str, Any] = {
        "schema": SCHEMA_VERSION,
        "converged": bool(robots) and all(bool(r.get("converged")) for r in robots),
        "rounds": rounds,
        "wall_s": wall_s,
        "algorithm": algorithm,
        "sigma": basis.sigma,
        "C": C,
        "grid": basis.grid.tolist(),
        "grid_bounds": list(world.bounds),
        "robots": robot_rows,
        "central": {
            "c": central.c.tolist() if central.solved else None,
            "gamma": central.gamma if central.solved else None,
            "status": central.status,
            "message": central.message,
        },
        "metrics": {
            "function_error": _num(function),
            "consensus_error": _num(consensus),
            "train_accuracy": accuracy,
            "iou": iou,
        },
        "history": history(basis, robots, central),
    }
    result.update(extra or {})
    return result


def write_json(path: Path, obj: Any) -> None:
    """Atomic JSON write: a reader never sees half a result."""
    tmp = Path(f"{path}.tmp")
    tmp.write_text(json.dumps(obj, indent=1, allow_nan=False))
    os.replace(tmp, path)


# -- pictures ---------------------------------------------------------------------------------
def _robot_colours(n: int) -> list[Any]:
    import matplotlib

    cmap = matplotlib.colormaps["tab10" if n <= 10 else "tab20"]
    return [cmap(i % cmap.N) for i in range(n)]


def plot_shapes(path: Path, world: World, basis: GridBasis, result: dict[str, Any], title: str = "") -> None:
    """The paper's Fig. 3: truth, each robot's data, grid points and every learned outline."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 6))
    x0, x1, y0, y1 = world.bounds
    pad = 0.05 * max(x1 - x0, y1 - y0)
    xs = np.linspace(x0 - pad, x1 + pad, 300)
    ys = np.linspace(y0 - pad, y1 + pad, 300)
    gx, gy = np.meshgrid(xs, ys)
    flat = np.column_stack([gx.ravel(), gy.ravel()])
    if world.shape is not None:
        bx, by = world.shape.exterior.xy
        ax.plot(bx, by, "--", color="magenta", lw=2, label="true outline")
    colours = _robot_colours(len(world.robots))
    rows = {int(r["id"]): r for r in result["robots"]}
    for colour, robot in zip(colours, world.robots, strict=True):
        out = robot.labels > 0
        ax.scatter(*robot.points[out].T, marker="o", facecolors="none", edgecolors=[colour], s=28)
        ax.scatter(*robot.points[~out].T, marker="x", color=colour, s=28)
        if robot.pose is not None:
            ax.scatter(*robot.pose, marker="^", color=colour, s=80, edgecolors="black", zorder=5)
        row = rows.get(robot.id)
        if row is None:
            continue
        f = basis.decision(flat, np.asarray(row["c"]), row["gamma"]).reshape(gx.shape)
        if f.min() < 0 < f.max():
            ax.contour(gx, gy, f, levels=[0.0], colors=[colour], linewidths=1.6)
        ax.plot([], [], color=colour, label=f"robot {robot.id}")
    ax.scatter(*basis.grid.T, marker="+", color="black", s=60, lw=1.2, label="grid points")
    ax.set_aspect("equal")
    ax.set_xlim(xs[0], xs[-1])
    ax.set_ylim(ys[0], ys[-1])
    ax.set_title(title or "learned outlines (solid), data: o outside, x inside")
    ax.legend(loc="upper right", fontsize=8, framealpha=0.8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_convergence(path: Path, hist: list[dict[str, Any]], tol: float | None = None) -> None:
    """Function error and consensus error against rounds, log scale."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.2))
    rounds = [h["round"] for h in hist]
    for key, label in (("function_error", "function error vs central"), ("consensus_error", "consensus error")):
        vals = [h[key] if h[key] is not None and h[key] > 0 else np.nan for h in hist]
        if not np.all(np.isnan(vals)):
            ax.semilogy(rounds, vals, label=label)
    ax.axhline(1e-3, color="grey", ls=":", lw=1, label="1e-3")
    ax.set_xlabel("round")
    ax.set_ylabel("error")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# -- terminal ---------------------------------------------------------------------------------
def summary_table(result: dict[str, Any]) -> Any:
    """A short rich table: one row per robot, then the fleet's figures."""
    from rich.table import Table

    m = result["metrics"]
    title = (
        f"{result['algorithm']}: {'converged' if result['converged'] else 'NOT converged'} in "
        f"{result['rounds']} rounds, {result['wall_s']:.2f} s"
    )
    table = Table(title=title)
    for col in ("robot", "rounds", "gamma", "f-error", "sent", "received", "lost", "rejected"):
        table.add_column(col, justify="right")
    for r in result["robots"]:
        fe = r.get("function_error")
        table.add_row(
            str(r["id"]),
            str(r["rounds"]),
            f"{r['gamma']:.4g}",
            "-" if fe is None else f"{fe:.2e}",
            str(r.get("frames_sent", "-")),
            str(r.get("frames_received", "-")),
            str(r.get("frames_lost", "-")),
            str(r.get("frames_rejected", "-")),
        )
    def fmt(value: float | None, spec: str) -> str:
        return "-" if value is None else format(value, spec)

    table.caption = (
        f"function error {fmt(m['function_error'], '.2e')}  consensus error {fmt(m['consensus_error'], '.2e')}  "
        f"train accuracy {fmt(m['train_accuracy'], '.3f')}  IoU {fmt(m['iou'], '.3f')}"
    )
    return table
