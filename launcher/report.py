"""Measure a fleet's answer against the centralized solve, write result.json and draw it.

Shared by `simulate`, `launch` and `central`, so every run's folder reads the same way.
The schema of result.json is documented in docs/result-schema.md.

A fixed-grid run (admm, ct-admm, central) is measured on the fleet file's basis (`build_result`).
An autogrid fleet chose its own grid and sigma: each robot is measured on *its* final grid and
sigma against the centralized solve there (`autogrid_references`, `build_autogrid_result`).
A least-squares fleet's answer (`--algorithm lsq`, autogrid's model lsq) is its output region
(agents/lsq_model.py `output_region`): its IoU and its drawn outline are the region's; the raw
{f < 0} IoU is kept beside it (``iou_unfilled``).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import re
import threading
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from agents.kernel import GridBasis
from agents.lsq_model import OUTPUT_REACH, model_words, output_region, solve_central_lsq
from agents.problem import CentralSolution, solve_central
from launcher import scenario
from launcher.cores import runs_alone, usable_cores
from launcher.topology import components as connected_groups
from launcher.world import World

SCHEMA_VERSION = 1
#: the agreement tolerance of a run that does not say its own (the ADMM's default tol)
DEFAULT_AGREEMENT_TOL = 1e-3
#: a robot stopped for one of these reasons has no answer the fleet can stand behind
FAILED_STOPS = ("solver_error", "diverged", "isolated")
#: an agreed answer farther than this many tol from the exact answer of the participants' data is
#: a biased fixed point (a lost dual, a bug), not a solution: the run has not converged. The factor
#: leaves room for methods that stop on an estimate (ADMM's error at stop is <= 1.1e-4 for tol
#: 1e-3 on every benchmark fleet; the paper's CT-ADMM, stopped at its 10 s, 2.2e-3)
WRONG_ANSWER_FACTOR = 10.0


def _met_stopping_rule(robot: dict[str, Any], fleet_size: int) -> bool:
    """The robot's own ``converged``; or a fleet of one robot, which never had a neighbour and
    solved the whole problem exactly at round 0 (the cores mark it finished with residual 0 but
    have no stop flags to raise)."""
    if robot.get("converged"):
        return True
    alone = fleet_size == 1 and not robot.get("neighbours") and not robot.get("dropped")
    return alone and robot.get("residual") == 0.0 and robot.get("stopped", "finished") == "finished"


def agreement_verdict(
    robots: list[dict[str, Any]],
    pair_error: Callable[[dict[str, Any], dict[str, Any]], float],
    *,
    tol: float,
    absent: list[int] | tuple[int, ...] = (),
    exact_error: Callable[[dict[str, Any]], float | None] | None = None,
    lost: Mapping[int, str] | None = None,
) -> dict[str, Any]:
    """The one rule for ``converged`` (the project's contract: success means agreement).

    A run has converged only if (1) it has participants (robots with a result), (2) every one
    stopped by its stopping rule (``converged`` in its own result; not isolated, diverged or
    failed), (3) the graph of live links among them -- i--j when each still lists the other as a
    neighbour -- is connected, and (4) every live link's two robots agree: ``pair_error`` (the
    relative function error between the robots' *own* reported answers, both ways) within
    ``tol``. Robots absent for good (no result) are not participants: the survivors answer for
    their own data. (5) Where the testbed knows the exact answer of the participants' data
    (``exact_error``: a robot's relative function error against it, None if unknown), the agreed
    answer is within WRONG_ANSWER_FACTOR x tol of it: robots that agree on a biased point have not
    solved the problem. (6) No robot was lost unexpectedly (``lost``: robots whose process ended
    without a result and not by the crash plan -- a restart that failed, a robot that died of an
    error -- each with what happened): the run did not do what was asked. Returns ``converged`` and
    what went wrong (``verdict``: one line; which robots, which partition, since which round).
    """
    rows = {int(r["id"]): r for r in robots}
    graph = _live_links(rows)
    disagreement, worst = _worst_link(graph, rows, pair_error)
    components = connected_groups(graph)
    connected = len(components) == 1
    failed = [i for i, r in rows.items() if r.get("stopped") in FAILED_STOPS or r.get("error")]
    lost = {int(k): str(v) for k, v in (lost or {}).items()}
    not_converged = [i for i, r in rows.items() if not _met_stopping_rule(r, len(rows) + len(absent))]
    since = [int(k) for r in rows.values() for k in (r.get("dropped_at") or {}).values()]
    reasons = []
    if not rows:
        reasons.append("no robot produced a result")
    for i in failed:
        reasons.append(rows[i].get("error") or f"robot {i} stopped: {rows[i].get('stopped')}")
    reasons += [lost[i] for i in sorted(lost)]
    if rows and not connected:
        reasons.append(
            "the participants are split into " + " | ".join(str(c) for c in components)
            + (f" since round {min(since)}" if since else "")
        )
    if worst is not None and disagreement == math.inf:
        reasons.append(f"robots {worst[0]} and {worst[1]} hold no comparable answers (no function on a common "
                       "grid and sigma, e.g. stopped before the fleet agreed on one, or a non-finite one)")
    elif worst is not None and not disagreement <= tol:
        reasons.append(f"robots {worst[0]} and {worst[1]} disagree by {disagreement:.3g} > tol {tol:g}")
    wrong = _wrong_answer(rows, exact_error)
    if wrong is not None and wrong[1] > WRONG_ANSWER_FACTOR * tol:
        unfinished = wrong[0] in not_converged and wrong[0] not in failed
        reasons.append(
            f"robot {wrong[0]}'s answer is {wrong[1]:.3g} from the exact answer of the participants' data "
            f"(> {WRONG_ANSWER_FACTOR:g} x tol): "
            + ("it had not converged when it stopped" if unfinished else "the fleet settled on a biased point")
        )
    rest = [i for i in not_converged if i not in failed]
    if rest:
        how = sorted({str(rows[i].get("stopped")) for i in rest if rows[i].get("stopped") not in (None, "finished")})
        cap = {int(rows[i].get("rounds") or 0) for i in rest if rows[i].get("stopped") in (None, "finished")}
        when = f" within {max(cap)} rounds" if cap and max(cap) > 0 else ""
        reasons.append(f"robots {rest} did not meet their stopping rule{when}" + (f" (stopped: {', '.join(how)})" if how else ""))
    converged = not reasons
    return {
        "converged": converged,
        "verdict": "every participant agrees with its neighbours within tol, graph connected"
        if converged else "; ".join(reasons),
        "agreement": {
            "tol": tol,
            "disagreement": _num(disagreement) if worst is not None else 0.0,
            "connected": connected,
            "components": components,
            "failed": sorted(set(failed) | set(lost)),
            "not_converged": not_converged,
            "absent": sorted(int(a) for a in absent),
            "partition_since_round": min(since) if since and not connected else None,
            "error_vs_exact": None if wrong is None else _num(wrong[1]),
            "exact_bound": WRONG_ANSWER_FACTOR * tol,
        },
    }


def _live_links(rows: dict[int, dict[str, Any]]) -> dict[int, dict[int, None]]:
    """The participants, linked i--j where each still lists the other as a neighbour (adjacency
    dicts in insertion order, as a networkx graph keeps them: the same link order as before)."""
    graph: dict[int, dict[int, None]] = {i: {} for i in rows}
    for i, r in rows.items():
        for j in r.get("neighbours") or []:
            j = int(j)
            if j in rows and i in {int(n) for n in rows[j].get("neighbours") or []}:
                graph[i][j] = None
                graph[j][i] = None
    return graph


def _edges(graph: dict[int, dict[int, None]]) -> list[tuple[int, int]]:
    """Each link once, in networkx's order (by node, then by insertion)."""
    seen: set[int] = set()
    edges = []
    for i, near in graph.items():
        edges += [(i, j) for j in near if j not in seen]
        seen.add(i)
    return edges


def _worst_link(
    graph: dict[int, dict[int, None]],
    rows: dict[int, dict[str, Any]],
    pair_error: Callable[[dict[str, Any], dict[str, Any]], float],
) -> tuple[float, tuple[int, int] | None]:
    """The largest disagreement over the live links (both ways; non-finite counts as inf) and
    its link, the first one when none disagrees (None without links)."""
    disagreement = 0.0
    worst: tuple[int, int] | None = None
    for i, j in _edges(graph):
        e = max(float(pair_error(rows[i], rows[j])), float(pair_error(rows[j], rows[i])))
        if not np.isfinite(e):
            e = float("inf")
        if e > disagreement or worst is None:
            disagreement, worst = max(disagreement, e), (min(i, j), max(i, j))
    return disagreement, worst


def _wrong_answer(
    rows: dict[int, dict[str, Any]], exact_error: Callable[[dict[str, Any]], float | None] | None
) -> tuple[int, float] | None:
    """(robot, error) of the answer farthest from the exact one, or None when it is not known."""
    if exact_error is None:
        return None
    worst: tuple[int, float] | None = None
    for i, r in rows.items():
        e = exact_error(r)
        if e is None:
            continue
        e = float(e) if np.isfinite(e) else float("inf")
        if worst is None or e > worst[1]:
            worst = (i, e)
    return worst


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


def bytes_metrics(robots: list[dict[str, Any]]) -> dict[str, float | int | None]:
    """Encoded frame bytes each robot sent in the run (resends included): mean and max over robots,
    null when the rows carry no counter (old result files)."""
    sent = [int(r["bytes_sent"]) for r in robots if r.get("bytes_sent") is not None]
    if not sent or len(sent) != len(robots):
        return {"bytes_sent_per_robot": None, "bytes_sent_max": None}
    return {"bytes_sent_per_robot": sum(sent) / len(sent), "bytes_sent_max": max(sent)}


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
    tol: float = DEFAULT_AGREEMENT_TOL,
    model: str | None = None,
) -> dict[str, Any]:
    """The run's result.json content (see docs/result-schema.md); ``converged`` is
    :func:`agreement_verdict` of the robots' own answers with the run's ``tol``; ``model``: what
    the fleet fitted, in words (`FleetSpec.model`)."""
    fs = [(_robot_c(basis, r), float(r["gamma"])) for r in robots]
    function, consensus = _errors(basis, fs, central)
    pts, labels = world.points, world.labels
    accuracy = min((float(np.mean(np.sign(basis.decision(pts, c, g)) == labels)) for c, g in fs), default=None)
    least_squares = algorithm == "lsq"
    ious, unfilled = raster_ious(world, [(basis, c, g) for c, g in fs], least_squares=least_squares)
    robot_rows = []
    for r, (c, g) in zip(robots, fs, strict=True):
        row = {k: v for k, v in r.items() if k not in ("trace", "x", "round_times", "residuals")}
        row.update(id=int(r["id"]), c=c.tolist(), gamma=g)
        if central.solved:
            row["function_error"] = basis.function_error(c, g, central.c, central.gamma)
        robot_rows.append(row)
    rounds = max((int(r["rounds"]) for r in robots), default=0)
    own = {int(r["id"]): f for r, f in zip(robots, fs, strict=True)}

    def pair(a: dict[str, Any], b: dict[str, Any]) -> float:
        (ca, ga), (cb, gb) = own[int(a["id"])], own[int(b["id"])]
        return basis.function_error(ca, ga, cb, gb)

    def exact(r: dict[str, Any]) -> float | None:
        if not central.solved:
            return None
        c, g = own[int(r["id"])]
        return basis.function_error(c, g, central.c, central.gamma)

    verdict = agreement_verdict(robots, pair, tol=tol, absent=(extra or {}).get("absent", ()), exact_error=exact,
                                lost=(extra or {}).get("lost_unexpectedly"))
    result: dict[str, Any] = {
        "schema": SCHEMA_VERSION,
        **verdict,
        "rounds": rounds,
        "wall_s": wall_s,
        "algorithm": algorithm,
        **({} if model is None else {"model": model}),
        **({"output_region": OUTPUT_REGION_WORDS} if least_squares else {}),
        "sigma": basis.sigma,
        "C": C,
        "grid": basis.grid.tolist(),
        "grid_bounds": list(world.bounds),
        "world": None if world.lengths is None else world.lengths.as_dict(),
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
            "error_bound": _error_bound(robots),
            "train_accuracy": accuracy,
            "iou": min(ious, default=None),
            **({"iou_unfilled": min(unfilled, default=None)} if least_squares else {}),
            **bytes_metrics(robots),
        },
        "history": history(basis, robots, central),
    }
    result.update(extra or {})
    return result


def raster_ious(world: World, functions: list[tuple[GridBasis, np.ndarray, float]], *, least_squares: bool
                ) -> tuple[list[float], list[float]]:
    """(IoU, raw IoU) of each function (basis, c, gamma) against the truth on scenario.iou_on_raster's
    raster; both empty when the world has no shape (data from a file).

    The IoU is that of the answer: {f < 0} for the SVM; for a least-squares fleet (``least_squares``)
    its output region (agents/lsq_model.py `output_region`: within reach of a grid node, enclosed
    hollows filled). The raw IoU is {f < 0}'s (for the SVM the same figures). One raster kernel
    matrix per distinct basis (`SharedKernels`: bit for bit `GridBasis.decision`)."""
    if world.shape is None or not functions:
        return [], []
    shared = SharedKernels()
    shape = (scenario.IOU_RESOLUTION, scenario.IOU_RESOLUTION)

    def answer(points: np.ndarray, b: GridBasis, c: np.ndarray, g: float) -> np.ndarray:
        f = shared.decision(points, b, c, g)
        return output_region(f, points, shape, b.grid, b.sigma, b.widths) if least_squares else f < 0

    ious = [scenario.iou_on_raster(world.shape, lambda p, f=f: answer(p, *f), world.bounds) for f in functions]
    if not least_squares:
        return ious, ious
    raw = [scenario.iou_on_raster(world.shape, lambda p, f=f: shared.decision(p, *f) < 0, world.bounds)
           for f in functions]
    return ious, raw


#: result.json's ``output_region`` of a least-squares fleet: what its answer (and ``iou``) is, in words
OUTPUT_REGION_WORDS = f"{{f < 0}} within {OUTPUT_REACH:g} kernel widths of a grid node, enclosed holes filled"


def least_squares_result(result: dict[str, Any]) -> bool:
    """A least-squares fleet's result (`--algorithm lsq`, autogrid's model lsq, `central --algorithm
    lsq`; it says ``output_region``): its answer is the output region, not {f < 0}."""
    return "output_region" in result


def _error_bound(robots: list[dict[str, Any]]) -> float | None:
    """The fleet's certified bound on its function error (admm's hub form, agents/certificate.py):
    the largest robot's ``error_bound``, a proven upper bound against the exact optimum; None
    when a robot has none (another form or algorithm, a soft margin, a dropped robot)."""
    bounds = [r.get("error_bound") for r in robots]
    if not bounds or any(b is None for b in bounds):
        return None
    return float(max(bounds))


# -- autogrid: every robot measured on its own final grid and sigma -----------------------------
#: what autogrid adds at the top level of result.json, taken from robot 0's result
AUTOGRID_FIELDS = ("sigma_reason", "sigma_validation", "width_validation", "grid_history", "margin", "message",
                   "phases")


@dataclass(frozen=True)
class Reference:
    """What one autogrid robot is measured against: the central solve on its grid and sigma."""

    basis: GridBasis
    central: CentralSolution
    C: float | None  # the penalty of the problem the robot solved (None: hard margin)


def has_function(robot: dict[str, Any]) -> bool:
    """An autogrid robot that finished holds its grid, sigma and (c, gamma)."""
    return robot.get("grid") is not None and robot.get("c") is not None and robot.get("sigma") is not None


def robot_C(robot: dict[str, Any], C: float | None, soft_C: float) -> float | None:
    """The margin penalty of the answer: the hard margin, or the soft one it fell back to."""
    if robot.get("margin") != "soft":
        return None
    return C if C is not None else soft_C


def _references(robots: list[dict[str, Any]], penalty: Any, solve: Any) -> dict[int, Reference]:
    """Per robot id with a function: ``solve(basis, penalty)`` on its final grid, sigma (and widths),
    ``penalty(robot)`` the penalty of the problem it solved; robots that agree share one solve."""
    solved: dict[tuple[bytes, float, float | None, bytes | None], Reference] = {}
    out: dict[int, Reference] = {}
    for r in robots:
        if not has_function(r):
            continue
        grid = np.asarray(r["grid"], dtype=float).reshape(-1, 2)
        widths = None if r.get("widths") is None else np.asarray(r["widths"], dtype=float)
        key = (grid.tobytes(), float(r["sigma"]), penalty(r), None if widths is None else widths.tobytes())
        if key not in solved:
            basis = GridBasis(grid, float(r["sigma"]), widths=widths)
            solved[key] = Reference(basis, solve(basis, key[2]), key[2])
        out[int(r["id"])] = solved[key]
    return out


def autogrid_references(
    robots: list[dict[str, Any]], points: np.ndarray, labels: np.ndarray, *, C: float | None, soft_C: float
) -> dict[int, Reference]:
    """Per robot id with a function: the central solve of (points, labels) on its final grid and
    sigma, with its margin's penalty. Robots that agree share one solve. The solve is exact only
    when K_G keeps full numerical rank (basis.rank == M): `reference_exact` says so."""
    return _references(robots, lambda r: robot_C(r, C, soft_C),
                       lambda basis, penalty: solve_central(basis, points, labels, penalty))


def autogrid_lsq_references(robots: list[dict[str, Any]], points: np.ndarray, labels: np.ndarray,
                            robot_of: np.ndarray, lam: float) -> dict[int, Reference]:
    """`autogrid_references` of a least-squares fleet (model "lsq"): the exact least-squares fit
    (agents/lsq_model.py solve_central_lsq) of all rows on each robot's final grid and sigma."""
    return _references(robots, lambda r: None,
                       lambda basis, _: solve_central_lsq(basis, points, labels, lam, robot_of=robot_of))


def reference_exact(ref: Reference | None) -> bool:
    """True when the central solve dropped no eigenvalue of K_G (rank M): the exact QP optimum."""
    return ref is not None and ref.basis.rank == ref.basis.size


def robots_agree(robots: list[dict[str, Any]]) -> bool:
    """Every robot ended with the same grid, sigma, margin and (c, gamma), bit for bit. After the
    flood this holds by construction; `disagreement_before_flood` is the measured agreement."""
    if not robots or not all(has_function(r) for r in robots):
        return False
    first = robots[0]
    return all(
        r["grid"] == first["grid"] and r["sigma"] == first["sigma"] and r.get("margin") == first.get("margin")
        and r["c"] == first["c"] and r["gamma"] == first["gamma"]
        for r in robots[1:]
    )


def _autogrid_pair_error(a: dict[str, Any], b: dict[str, Any], references: dict[int, Reference]) -> float:
    """Disagreement of two autogrid robots' own answers: infinite unless both hold a function on
    the same grid and sigma; then the relative function error on that basis."""
    ra, rb = references.get(int(a["id"])), references.get(int(b["id"]))
    if ra is None or rb is None or ra.basis is not rb.basis:
        return float("inf")
    return ra.basis.function_error(np.asarray(a["c"], dtype=float), float(a["gamma"]),
                                   np.asarray(b["c"], dtype=float), float(b["gamma"]))


def _autogrid_exact_error(robot: dict[str, Any], references: dict[int, Reference]) -> float | None:
    """A robot's error against the exact optimum on its own grid; None where the reference is
    not exact (rank-deficient K_G) or not solved."""
    ref = references.get(int(robot["id"]))
    if ref is None or not ref.central.solved or not reference_exact(ref):
        return None
    return ref.basis.function_error(np.asarray(robot["c"], dtype=float), float(robot["gamma"]),
                                    ref.central.c, ref.central.gamma)


def disagreement_before_flood(robots: list[dict[str, Any]]) -> float | None:
    """The largest relative gap between neighbours the robots measured before the last flood."""
    gaps = [r.get("disagreement_before_flood") for r in robots]
    return None if not gaps or any(g is None for g in gaps) else float(max(gaps))


def _autogrid_rows(
    world: World, robots: list[dict[str, Any]], references: dict[int, Reference], *, least_squares: bool
) -> tuple[list[dict[str, Any]], list[float], list[float], tuple[list[float], list[float]]]:
    """Each robot's row, measured on its own grid: the rows and the function errors, training
    accuracies and (IoUs, raw IoUs: `raster_ious`) of the robots whose reference exists."""
    pts, labels = world.points, world.labels
    rows, errors, accuracies = [], [], []
    measured = []  # (basis, c, gamma) of every robot with a reference: one raster for their IoUs
    for r in robots:
        row = {k: v for k, v in r.items() if k not in ("trace", "x", "round_times", "residuals")}
        row["id"] = int(r["id"])
        ref = references.get(int(r["id"]))
        if ref is not None:
            c, g = np.asarray(r["c"], dtype=float), float(r["gamma"])
            b = ref.basis
            measured.append((b, c, g))
            accuracies.append(float(np.mean(np.sign(b.decision(pts, c, g)) == labels)))
            if ref.central.solved:
                row["function_error"] = b.function_error(c, g, ref.central.c, ref.central.gamma)
                errors.append(row["function_error"])
        rows.append(row)
    return rows, errors, accuracies, raster_ious(world, measured, least_squares=least_squares)


def _autogrid_consensus(
    robots: list[dict[str, Any]],
    references: dict[int, Reference],
    ref0: Reference | None,
    agree: bool,
    gap: float | None,
) -> float:
    """The consensus error: robots identical after the flood by construction report what was
    measured before it; robots on one basis, their spread; else unknown (nan)."""
    if agree:
        return float("nan") if gap is None else gap
    if ref0 is not None and all(references.get(int(r["id"])) is not None and references[int(r["id"])].basis is ref0.basis for r in robots):
        fs = [(np.asarray(r["c"], dtype=float), float(r["gamma"])) for r in robots]
        return _errors(ref0.basis, fs, ref0.central)[1]
    return float("nan")


def build_autogrid_result(
    world: World,
    robots: list[dict[str, Any]],
    references: dict[int, Reference],
    *,
    wall_s: float,
    extra: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """result.json of an autogrid run (docs/result-schema.md): each robot measured on its own grid.

    The top-level grid, sigma, central solve and the autogrid fields are robot 0's (the first
    robot with a function); ``robots_agree`` says whether every robot holds the same grid, sigma
    and function bit for bit. No per-round ``history``: the exchanged vectors change meaning from
    phase to phase (bounds, sigma vote, ADMM on each grid, flood).
    """
    with_f = [r for r in robots if has_function(r)]
    first = with_f[0] if with_f else (robots[0] if robots else {})
    ref0 = references.get(int(first["id"])) if with_f else None
    least_squares = first.get("model") == "lsq"
    rows, errors, accuracies, (ious, unfilled) = _autogrid_rows(world, robots, references, least_squares=least_squares)
    agree = robots_agree(robots)
    gap = disagreement_before_flood(robots)
    consensus = _autogrid_consensus(robots, references, ref0, agree, gap)
    central = ref0.central if ref0 is not None else None
    result: dict[str, Any] = {
        "schema": SCHEMA_VERSION,
        **agreement_verdict(robots, lambda a, b: _autogrid_pair_error(a, b, references),
                            tol=DEFAULT_AGREEMENT_TOL, absent=(extra or {}).get("absent", ()),
                            exact_error=lambda r: _autogrid_exact_error(r, references),
                            lost=(extra or {}).get("lost_unexpectedly")),
        "rounds": max((int(r["rounds"]) for r in robots), default=0),
        "wall_s": wall_s,
        "algorithm": "autogrid",
        # the least-squares model's fleet says so (an SVM fleet's result is as it was: no model key)
        **({"model": model_words(first["lsq_lambda"]), "lsq_lambda": first["lsq_lambda"],
            "output_region": OUTPUT_REGION_WORDS} if least_squares else {}),
        "sigma": first.get("sigma"),
        "C": None if ref0 is None else ref0.C,
        "grid": first.get("grid") or [],
        "grid_bounds": list(world.bounds),
        "world": None if world.lengths is None else world.lengths.as_dict(),
        "robots_agree": agree,
        "disagreement_before_flood": _num(gap) if gap is not None else None,
        "reference_exact": reference_exact(ref0),
        "reference_note": (
            None if ref0 is None or reference_exact(ref0) else
            f"K_G has numerical rank {ref0.basis.rank} < M = {ref0.basis.size}: the central solve drops "
            "eigenvalues, the reference (and function_error) is not measured against the exact QP optimum"
        ),
        **{k: first.get(k) for k in AUTOGRID_FIELDS},
        "robots": rows,
        "central": {
            "c": central.c.tolist() if central is not None and central.solved else None,
            "gamma": central.gamma if central is not None and central.solved else None,
            "status": "no final grid" if central is None else central.status,
            "message": "no robot finished with a function" if central is None else central.message,
        },
        "metrics": {
            "function_error": _num(max(errors)) if errors and len(errors) == len(robots) else None,
            "consensus_error": _num(consensus),
            "train_accuracy": min(accuracies, default=None),
            "iou": min(ious, default=None),
            **({"iou_unfilled": min(unfilled, default=None)} if least_squares else {}),
            **bytes_metrics(robots),
        },
        "history": [],
    }
    result.update(extra or {})
    return result


def json_safe(obj: Any) -> Any:
    """``obj`` with every non-finite float as None (JSON null: not measured), so strict JSON can
    hold it: e.g. the residual of a robot that heard nobody in its only round is inf."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    return obj


def write_json(path: Path, obj: Any) -> None:
    """Atomic JSON write: a reader never sees half a result; non-finite numbers become null."""
    tmp = Path(f"{path}.tmp")
    tmp.write_text(json.dumps(json_safe(obj), indent=1, allow_nan=False))
    os.replace(tmp, path)


# -- pictures ---------------------------------------------------------------------------------
class SharedKernels:
    """Robots' functions on the same points with one kernel matrix per distinct (points, grid,
    sigma, widths), bit for bit `GridBasis.decision`: the robots of an agreed fleet share one matrix, and a
    raster of 40,000-90,000 points against a grid of 141-300 points costs 0.2-0.5 s per matrix."""

    def __init__(self) -> None:
        self._kernels: dict[tuple[bytes, bytes, float, bytes | None], np.ndarray] = {}

    def decision(self, points: np.ndarray, basis: GridBasis, c: np.ndarray, gamma: float) -> np.ndarray:
        """f(points) = k(points, G) c + gamma."""
        points = np.ascontiguousarray(points, dtype=float)
        widths = None if basis.widths is None else np.ascontiguousarray(basis.widths).tobytes()
        key = (points.tobytes(), np.ascontiguousarray(basis.grid).tobytes(), basis.sigma, widths)
        if key not in self._kernels:
            self._kernels[key] = basis.kernel_to_grid(points)
        return self._kernels[key] @ np.asarray(c, dtype=float) + float(gamma)


def decisions(points: np.ndarray, functions: list[tuple[GridBasis, np.ndarray, float]]) -> list[np.ndarray]:
    """f(points) of several robots' functions (basis, c, gamma), sharing kernel matrices."""
    shared = SharedKernels()
    return [shared.decision(points, b, c, g) for b, c, g in functions]


def raster_decisions(
    xs: np.ndarray, ys: np.ndarray, functions: list[tuple[GridBasis, np.ndarray, float]]
) -> list[np.ndarray]:
    """f on the raster xs x ys (an array of shape (len(ys), len(xs)), row j at ys[j]) of several
    robots' functions (basis, c, gamma): what the pictures contour.

    The Gaussian kernel factors over the coordinates, k(p, g) = exp(-(p_x - g_x)^2 / 2w^2)
    exp(-(p_y - g_y)^2 / 2w^2) (w: sigma, or the grid point's own width), so a raster costs
    (nx + ny) M exponentials and one (ny, M) @ (M, nx) product instead of nx ny M exponentials
    (`GridBasis.decision` on 90,000 points: 0.1 s per matrix at M = 141-300, six matrices in the
    default autogrid run). Equal to `GridBasis.decision` up to rounding, not bit for bit: for
    drawing only (result.json's IoU keeps `SharedKernels`)."""
    xs, ys = np.asarray(xs, dtype=float), np.asarray(ys, dtype=float)
    factors: dict[tuple[bytes, float, bytes | None], tuple[np.ndarray, np.ndarray]] = {}
    out = []
    for basis, c, gamma in functions:
        grid = np.asarray(basis.grid, dtype=float)
        widths = basis.widths
        key = (grid.tobytes(), basis.sigma, None if widths is None else np.asarray(widths).tobytes())
        if key not in factors:
            two_w2 = 2.0 * (basis.sigma if widths is None else np.asarray(widths, dtype=float)) ** 2
            factors[key] = (np.exp(-((xs[:, None] - grid[None, :, 0]) ** 2) / two_w2),
                            np.exp(-((ys[:, None] - grid[None, :, 1]) ** 2) / two_w2))
        kx, ky = factors[key]
        out.append((ky * np.asarray(c, dtype=float)) @ kx.T + float(gamma))
    return out


#: the pictures' resolution; figures are made at it, so text is measured once, as it is drawn
PICTURE_DPI = 110
#: where the axes sit (left, bottom, width, height as fractions of the figure): fixed, with room for
#: the tick labels (five characters on the left: -2000 of an outline in millimetres), the title and
#: the axis labels, instead of a tight_layout pass that measured every text before the drawing did
_SHAPES_RECT = (0.085, 0.055, 0.9, 0.885)
_CONVERGENCE_RECT = (0.105, 0.125, 0.875, 0.855)
#: superscript digits and minus: decade labels 10^-5 drawn as plain text (no mathtext parser)
_SUPERSCRIPT = str.maketrans("-0123456789", "\u207b\u2070\u00b9\u00b2\u00b3\u2074\u2075\u2076\u2077\u2078\u2079")
_MATHTEXT_LABEL = re.compile(r"\$\\mathdefault\{(-?)(.*)\}\$")
_POWER = re.compile(r"\^\{(-?\d+)\}")


def preload_pictures() -> None:
    """Import what the run's pictures need in a daemon thread, now, for later.

    `launch` calls it once its robots were handed over: the launcher then only waits for them, and
    the import (matplotlib ~0.25-0.4 s of CPU) runs while they do instead of after them (rich, for
    the summary, is imported at the end while shapes.png is drawn aside: launcher/cli.py ``_finish``). The first ``_figure`` call that needs the modules waits for the import
    (import_picture_modules' lock, then Python's module locks: nothing to join); a failed import
    fails again there, in the drawing thread."""

    def load() -> None:
        try:
            import_picture_modules()
        except Exception:  # noqa: BLE001 - reported by the drawing's own import
            pass

    global _PRELOAD
    _PRELOAD = threading.Thread(target=load, name="preload-pictures", daemon=True)
    _PRELOAD.start()


#: the thread of preload_pictures, once started (drawn_aside waits for it: no fork beside a thread)
_PRELOAD: threading.Thread | None = None
#: drawn_aside's bound on a forked drawing (then it is SIGKILLed and the picture drawn here)
ASIDE_WAIT_S = 60.0


@contextlib.contextmanager
def drawn_aside(draw: Callable[[], None]) -> Iterator[None]:
    """Run ``draw`` (one picture) in a forked child while the ``with`` block runs here.

    Why: the end of a run -- result.json and two pictures -- was serial on one core while the
    other idled (issue 14: ~0.4 s of `launch --preset paper`'s 1.6 s). The child is forked after the
    picture modules are imported (the preload thread is waited for) and only while this process has
    no other thread (a fork beside a running thread can copy a lock it holds); else, or when the
    child fails or outlasts ASIDE_WAIT_S, ``draw`` runs here after the block, as before. The child
    is this process's own: waited for by its PID on every path, SIGKILLed and reaped when the block
    raises (Ctrl-C included). Its picture is the same file as one drawn here."""
    pid = _fork_drawing(draw)
    try:
        yield
    except BaseException:
        if pid is not None:
            _kill_drawing(pid)
        raise
    if pid is None or _wait_drawing(pid) != 0:
        draw()


def _fork_drawing(draw: Callable[[], None]) -> int | None:
    """The PID of a child running ``draw`` then exiting (0: drawn), None when not safe to fork."""
    if not hasattr(os, "fork"):
        return None
    if _PRELOAD is not None:
        _PRELOAD.join(ASIDE_WAIT_S)
    try:
        import_picture_modules()  # once, here: both processes draw with it
        if not runs_alone() or not _core_idle():  # a thread (ours or a library's) runs
            return None
        pid = os.fork()
    except Exception:  # noqa: BLE001 -- no /proc, no fork, a failed import: draw here (its error shows there)
        return None
    if pid:
        return pid
    code = 1
    try:
        import gc

        gc.disable()  # a short-lived child: its collections would only copy the parent's pages
        draw()
        code = 0
    except BaseException:  # noqa: BLE001 -- the parent draws it again and shows the error
        pass
    finally:
        os._exit(code)


def _core_idle() -> bool:
    """A core runs nothing but us now (/proc/loadavg's runnable count, this process included).

    Why: the child costs ~0.06 s of CPU more than drawing here (the fork, and the pages both
    processes then copy as they write); with a core idle that buys ~0.1 s of wall, on a machine
    whose cores are busy it only adds the cost (measured at load 4: 0.45 -> 0.6 s)."""
    try:
        with open("/proc/loadavg") as fh:
            runnable = int(fh.read().split()[3].split("/")[0])
    except (OSError, ValueError, IndexError):
        return False
    return runnable < usable_cores()


def _wait_drawing(pid: int) -> int:
    """The child's exit code (-1 when it outlasted ASIDE_WAIT_S: then it was SIGKILLed and reaped)."""
    import time

    end = time.monotonic() + ASIDE_WAIT_S
    while time.monotonic() < end:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            return os.waitstatus_to_exitcode(status)
        time.sleep(0.002)
    _kill_drawing(pid)
    return -1


def _kill_drawing(pid: int) -> None:
    """SIGKILL the drawing child by its PID (not yet reaped: it is still ours) and reap it."""
    import signal

    try:
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
    except ChildProcessError:
        pass


def import_picture_modules() -> None:
    """Import matplotlib's figure, Agg canvas and tickers without one cost of matplotlib's import
    that no picture reads: the docstring of every Artist subclass's ``set``, a table of its
    properties built by inspecting the class (`matplotlib.artist.kwdoc`, ~30 % of the import's
    CPU). kwdoc is a stub only while these modules are imported the first time and is put back
    after, so a caller's own ``kwdoc`` calls are unchanged (the cyclic garbage collector is paused
    for that import too, then as it was); the ``set`` docstrings of the classes
    defined meanwhile (and matplotlib's ``%(Line2D:kwdoc)s``-style docstring entries filled
    meanwhile) say less. Nothing else in matplotlib reads them."""
    import gc
    import sys

    with _PICTURE_IMPORT:  # the preload thread and the drawing one: one swaps kwdoc, the other waits
        if "matplotlib.figure" in sys.modules:
            return
        collecting = gc.isenabled()
        gc.disable()  # long-lived objects, no garbage: the collector's ~110 passes were ~20 % more
        try:
            import matplotlib.artist

            kwdoc = getattr(matplotlib.artist, "kwdoc", None)  # None: another matplotlib, import as is
            if kwdoc is not None:
                matplotlib.artist.kwdoc = _no_kwdoc
            try:
                import matplotlib.backends.backend_agg  # noqa: F401
                import matplotlib.figure  # noqa: F401
                import matplotlib.ticker  # noqa: F401
            finally:
                if kwdoc is not None:
                    matplotlib.artist.kwdoc = kwdoc
        finally:
            if collecting:
                gc.enable()


#: held while the picture modules are first imported (import_picture_modules)
_PICTURE_IMPORT = threading.Lock()


def _no_kwdoc(artist: Any) -> str:
    """`matplotlib.artist.kwdoc` while the picture modules are first imported: no property table."""
    return ""


def _figure(size: tuple[float, float], rect: tuple[float, float, float, float]) -> tuple[Any, Any]:
    """A figure on the Agg canvas with one axes at ``rect``.

    Not pyplot and not tight_layout: a picture is drawn once and written, so pyplot's figure
    manager and backend switch buy nothing, and tight_layout measured every tick label in a pass of
    its own before the drawing measured them again (with the pyplot import, ~0.5 s of the 1 s the
    two pictures of `launch --preset paper` took)."""
    import_picture_modules()
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=size, dpi=PICTURE_DPI)
    FigureCanvasAgg(fig)
    return fig, fig.add_axes(rect)


#: zlib level of the pictures' PNG files: 1 encodes the 825x660 shapes picture in ~0.03 s instead of
#: ~0.06 s at PIL's default 6, for files ~20 % larger (55 -> 66 kB)
PNG_COMPRESS_LEVEL = 1


def save_picture(fig: Any, path: Path) -> None:
    """Write ``fig`` as a PNG at PICTURE_DPI, with the fast zlib level (PNG_COMPRESS_LEVEL)."""
    fig.savefig(path, dpi=PICTURE_DPI, pil_kwargs={"compress_level": PNG_COMPRESS_LEVEL})


def plain_log_label(label: str) -> str:
    """matplotlib's log-axis label ``$\\mathdefault{2\\times10^{-3}}$`` as the plain text
    ``2\u00d710\u207b\u00b3``: the same label without mathtext, whose parser costs ~0.25 s the first
    time it is used. A label it cannot write plainly is returned as it came."""
    m = _MATHTEXT_LABEL.fullmatch(label)
    if m is None:
        return label
    body = _POWER.sub(lambda p: p.group(1).translate(_SUPERSCRIPT), m.group(2).replace("\\times", "\u00d7"))
    if any(ch in body for ch in "\\^{}$"):
        return label
    return ("\u2212" if m.group(1) else "") + body


def _plain_log_formatter(*, label_only_base: bool) -> Any:
    """The log axis's own formatter (LogFormatterSciNotation: which ticks get a label) writing
    its labels as plain text (:func:`plain_log_label`)."""
    from matplotlib.ticker import LogFormatterSciNotation

    class PlainLogFormatter(LogFormatterSciNotation):
        def __call__(self, x: float, pos: int | None = None) -> str:
            return plain_log_label(super().__call__(x, pos))

    return PlainLogFormatter(10, labelOnlyBase=label_only_base)


def _robot_colours(n: int) -> list[Any]:
    import matplotlib

    cmap = matplotlib.colormaps["tab10" if n <= 10 else "tab20"]
    return [cmap(i % cmap.N) for i in range(n)]


def plot_shapes(
    path: Path,
    world: World,
    basis: GridBasis | None,
    result: dict[str, Any],
    title: str = "",
    bases: dict[int, GridBasis] | None = None,
) -> None:
    """The paper's Fig. 3: truth, each robot's data, grid points and every learned outline.

    ``bases`` (autogrid): each robot's own final basis; the grid drawn is ``result["grid"]`` (the
    final grid) and, when the fleet started from a given grid, that start grid too. A least-squares
    fleet's outline is the boundary of its output region (`least_squares_result`), an SVM's f = 0.
    """
    fig, ax = _figure((7.5, 6), _SHAPES_RECT)
    x0, x1, y0, y1 = world.bounds
    grid = np.asarray(result.get("grid") or [], dtype=float).reshape(-1, 2)
    if len(grid):  # an automatic grid may reach beyond the data's box: show all of it
        x0, x1 = min(x0, grid[:, 0].min()), max(x1, grid[:, 0].max())
        y0, y1 = min(y0, grid[:, 1].min()), max(y1, grid[:, 1].max())
    pad = 0.05 * max(x1 - x0, y1 - y0)
    xs = np.linspace(x0 - pad, x1 + pad, 300)
    ys = np.linspace(y0 - pad, y1 + pad, 300)
    gx, gy = np.meshgrid(xs, ys)
    if world.shape is not None:
        bx, by = world.shape.exterior.xy
        ax.plot(bx, by, "--", color="magenta", lw=2, label="true outline")
    colours = _robot_colours(len(world.robots))
    rows = {int(r["id"]): r for r in result["robots"]}
    drawn = {}
    for robot in world.robots:
        row, b = rows.get(robot.id), (basis if bases is None else bases.get(robot.id))
        if row is not None and b is not None and row.get("c") is not None:
            drawn[robot.id] = (b, np.asarray(row["c"], dtype=float), float(row["gamma"]))
    values = dict(zip(drawn, raster_decisions(xs, ys, list(drawn.values())), strict=True))
    if least_squares_result(result):  # the region's boundary: its mask as -1 inside, +1 outside, contoured at 0
        raster = np.column_stack([gx.ravel(), gy.ravel()])
        values = {i: np.where(output_region(f, raster, f.shape, drawn[i][0].grid, drawn[i][0].sigma,
                                            drawn[i][0].widths).reshape(f.shape), -1.0, 1.0)
                  for i, f in values.items()}
    for colour, robot in zip(colours, world.robots, strict=True):
        out = robot.labels > 0
        ax.scatter(*robot.points[out].T, marker="o", facecolors="none", edgecolors=[colour], s=28)
        ax.scatter(*robot.points[~out].T, marker="x", color=colour, s=28)
        if robot.pose is not None:
            ax.scatter(*robot.pose, marker="^", color=colour, s=80, edgecolors="black", zorder=5)
        if robot.id not in values:
            continue
        f = values[robot.id]
        if f.min() < 0 < f.max():
            ax.contour(gx, gy, f, levels=[0.0], colors=[colour], linewidths=1.6)
        ax.plot([], [], color=colour, label=f"robot {robot.id}")
    if bases is not None and len(world.grid):
        ax.scatter(*world.grid.T, marker="s", facecolors="none", edgecolors="grey", s=70, lw=1.0, label="start grid")
    if len(grid):
        label = "grid points" if bases is None else f"final grid ({len(grid)} points)"
        ax.scatter(*grid.T, marker="+", color="black", s=60 if len(grid) < 80 else 25, lw=1.2 if len(grid) < 80 else 0.8, label=label)
    ax.set_aspect("equal")
    ax.set_xlim(xs[0], xs[-1])
    ax.set_ylim(ys[0], ys[-1])
    ax.set_title(title or "learned outlines (solid), data: o outside, x inside")
    ax.legend(loc="upper right", fontsize=8, framealpha=0.8)
    save_picture(fig, path)


def plot_convergence(
    path: Path,
    hist: list[dict[str, Any]],
    tol: float | None = None,
    phases: list[tuple[str, int]] | None = None,
) -> None:
    """Function error, consensus error and (autogrid) the ADMM residual against rounds, log
    scale; autogrid's phase boundaries as vertical lines labelled with the phase."""
    save_picture(convergence_figure(hist, tol, phases), path)


def convergence_figure(
    hist: list[dict[str, Any]],
    tol: float | None = None,
    phases: list[tuple[str, int]] | None = None,
) -> Any:
    """The figure :func:`plot_convergence` writes (its axes: ``figure.axes[0]``)."""
    fig, ax = _figure((7, 4.2), _CONVERGENCE_RECT)
    rounds = [h["round"] for h in hist]
    for key, label in (
        ("function_error", "function error vs central"),
        ("consensus_error", "consensus error"),
        ("residual", "ADMM residual (sweep: its largest)"),
    ):
        vals = [h.get(key) if h.get(key) is not None and h[key] > 0 else np.nan for h in hist]
        if hist and not np.all(np.isnan(vals)):
            single = int(np.sum(~np.isnan(vals))) == 1  # autogrid: the final error only
            ax.semilogy(rounds, vals, label=label, lw=1, marker="o" if single else None)
    ax.axhline(1e-3 if tol is None else tol, color="grey", ls=":", lw=1, label=f"{1e-3 if tol is None else tol:g}")
    for name, start in phases or []:
        if name in ("validate", "admm", "seed", "done"):
            ax.axvline(start, color="tab:red", lw=0.6, alpha=0.5)
            ax.text(start, 1.0, f" {name}", rotation=90, va="top", fontsize=7, transform=ax.get_xaxis_transform())
    ax.set_xlabel("round")
    ax.set_ylabel("error")
    ax.grid(True, which="both", alpha=_GRID_ALPHA)
    if ax.get_yscale() == "log":
        ax.yaxis.set_major_formatter(_plain_log_formatter(label_only_base=True))
        ax.yaxis.set_minor_formatter(_plain_log_formatter(label_only_base=False))
        _light_minor_ticks(ax)
    ax.legend(fontsize=8)
    return fig


#: the convergence picture's grid lines (major and minor)
_GRID_ALPHA = 0.3
#: a log axis spanning more decades than this labels none of its minor ticks (the first of
#: matplotlib's LogFormatter ``minor_thresholds``)
_MINOR_LABEL_DECADES = 1.0


def _light_minor_ticks(ax: Any) -> None:
    """The log y axis's minor tick marks and grid lines drawn as two artists (one line of tick
    markers, one line collection) instead of a matplotlib Tick per position.

    The same positions (the axis's own minor locator, called once) in the same style (rcParams:
    tick size, width and colour; grid colour, style, width; ``_GRID_ALPHA``). A Tick is five
    artists built by copying properties, and the ~60 minor ones of a run over 7 decades were
    half of the picture's drawing time. Only when the axis spans more than
    ``_MINOR_LABEL_DECADES``: then the formatter labels no minor tick and nothing is lost; an axis
    of fewer decades keeps matplotlib's (few, partly labelled) minor ticks."""
    from matplotlib import rcParams
    from matplotlib.collections import LineCollection
    from matplotlib.lines import TICKLEFT, Line2D
    from matplotlib.ticker import NullLocator

    lo, hi = sorted(ax.get_ylim())
    if not (lo > 0 and np.log10(hi / lo) > _MINOR_LABEL_DECADES):
        return
    locs = [float(y) for y in ax.yaxis.get_minor_locator()() if lo <= y <= hi]
    ax.set_ylim(ax.get_ylim())  # the view the positions were taken for: no later autoscale
    ax.yaxis.set_minor_locator(NullLocator())
    if not locs:
        return
    grid = LineCollection([[(0.0, y), (1.0, y)] for y in locs], transform=ax.get_yaxis_transform(which="grid"),
                          colors=rcParams["grid.color"], linestyles=rcParams["grid.linestyle"],
                          linewidths=rcParams["grid.linewidth"], alpha=_GRID_ALPHA,
                          zorder=ax.yaxis.get_zorder())
    ax.add_collection(grid, autolim=False)
    marks = Line2D([0.0] * len(locs), locs, transform=ax.get_yaxis_transform(which="tick1"), linestyle="none",
                   marker=TICKLEFT, markersize=rcParams["ytick.minor.size"],
                   markeredgewidth=rcParams["ytick.minor.width"], color=rcParams["ytick.color"],
                   clip_on=False, zorder=ax.yaxis.get_zorder())
    ax.add_artist(marks)


def autogrid_progress(robot: dict[str, Any], function_error: float | None) -> list[dict[str, Any]]:
    """Per round of one autogrid robot: its residual (nan outside ADMM rounds); the last round
    also carries the final function error against the central solve."""
    res = robot.get("residuals") or []
    hist = [{"round": k + 1, "residual": r} for k, r in enumerate(res)]
    if hist and function_error is not None:
        hist[-1]["function_error"] = function_error
    return hist


# -- terminal ---------------------------------------------------------------------------------
def _endgame_phrase(robots: list[dict[str, Any]]) -> str:
    """The summary line's word on admm's exact end-game (robots' `endgame`, docs/result-schema.md): on its
    certified optimum when every robot's run ended there; not certified when one ran and did not end the
    run; nothing when none ran."""
    ends = {r.get("endgame") for r in robots} - {None}
    if not ends:
        return ""
    return " on the certified exact optimum" if ends == {"certified"} else " (exact end-game not certified)"


def summary_table(result: dict[str, Any]) -> Any:
    """A short rich table: one row per robot, then the fleet's figures."""
    from rich import box
    from rich.table import Table

    m = result["metrics"]
    title = (
        f"{result['algorithm']}: {'converged' if result['converged'] else 'NOT converged'} in "
        f"{result['rounds']} rounds{_endgame_phrase(result['robots'])}, {result['wall_s']:.2f} s"
    )
    # a simple head rule and no vertical lines: the nine columns fit an 80-column terminal whole
    # (with the default box rich cut the numbers to "7.92e-...")
    table = Table(title=title, box=box.SIMPLE_HEAD, pad_edge=False)
    for col in ("robot", "rounds", "gamma", "f-error", "sent", "bytes", "received", "lost", "rejected"):
        table.add_column(col, justify="right", no_wrap=True)
    for r in result["robots"]:
        fe = r.get("function_error")
        table.add_row(
            str(r["id"]),
            str(r["rounds"]),
            "-" if r.get("gamma") is None else f"{r['gamma']:.4g}",
            "-" if fe is None else f"{fe:.2e}",
            str(r.get("frames_sent", "-")),
            str(r.get("bytes_sent", "-")),
            str(r.get("frames_received", "-")),
            str(r.get("frames_lost", "-")),
            str(r.get("frames_rejected", "-")),
        )
    def fmt(value: float | None, spec: str) -> str:
        return "-" if value is None else format(value, spec)

    table.caption_justify = "left"
    table.caption = (
        f"function error {fmt(m['function_error'], '.2e')}, consensus error {fmt(m['consensus_error'], '.2e')}\n"
        f"train accuracy {fmt(m['train_accuracy'], '.3f')}, IoU {fmt(m['iou'], '.3f')}"
        + (f" (output region; raw {{f < 0}} {fmt(m['iou_unfilled'], '.3f')})" if "iou_unfilled" in m else "")
    )
    if result.get("model"):
        table.caption += f"\nmodel: {result['model']}"
    if m.get("error_bound") is not None:  # proven: the function error is at most this (agents/certificate.py)
        table.caption += f"\ncertified: function error <= {m['error_bound']:.2e} (duality-gap bound)"
    w = result.get("world")
    if w:
        lengths = ", ".join(f"{k.replace('_', '-')} {w[k]:.6g}{'' if k.replace('_', '-') in w['given'] else '*'}"
                            for k in ("standoff", "range", "offset", "noise", "comm_range") if w.get(k) is not None)
        table.caption += f"\nworld: {lengths or '-'} (* = default: the paper's x {w['scale']:.4g}, the scale of {w['basis']} {w['length']:.4g})"
    if result["algorithm"] == "autogrid":
        sizes = " -> ".join(str(h["size"]) for h in result.get("grid_history") or [])
        table.caption += (
            f"\nsigma {fmt(result['sigma'], '.4g')}, grids {sizes or '-'} points, "
            f"{'least-squares fit' if result.get('margin') == 'lsq' else str(result.get('margin')) + ' margin'}, "
            f"robots {'agree bit for bit' if result.get('robots_agree') else 'DO NOT agree'}"
        )
        if result.get("message"):
            table.caption += f"\n{result['message']}"
    return table
