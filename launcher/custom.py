"""result.json of a user's fleet algorithm (agents/extension.py): measured against its own exact answer.

The built-in SVM runs are measured on a grid basis (launcher/report.py); a user algorithm says
what its answer is (``answer()`` of each robot, in its result row) and what the exact answer of
the data is (``reference(spec)``, computed in one place). The verdict is the project's one rule
(report.agreement_verdict): converged only if every participant met its stopping rule, the
graph of live links among them is connected, neighbours agree within the run's ``tol`` and the
agreed answer is within report.WRONG_ANSWER_FACTOR x tol of the exact one (agreeing on a biased
point is not converging).

Error of a robot's answer a against r: ||a - r|| / max(1, ||r||) (relative, absolute near 0).
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path
from typing import Any

import numpy as np

from agents.extension import load_algorithm
from launcher import report
from launcher.world import World


def relative_error(a: Any, r: Any) -> float:
    """||a - r|| / max(1, ||r||): the metric of a user algorithm's answers."""
    a, r = np.asarray(a, dtype=float), np.asarray(r, dtype=float)
    if a.shape != r.shape:
        return float("inf")
    return float(np.linalg.norm(a - r) / max(1.0, float(np.linalg.norm(r))))


def reference(spec: Any, participants: list[int] | None = None) -> np.ndarray | None:
    """The algorithm's exact answer of the participants' data (all robots' when None)."""
    cls = load_algorithm(spec.algorithm)
    kept = spec if participants is None else dataclasses.replace(
        spec, robots={i: r for i, r in spec.robots.items() if i in set(participants)})
    ref = cls.reference(kept)
    return None if ref is None else np.asarray(ref, dtype=float)


def build_custom_result(world: World, spec: Any, robots: list[dict[str, Any]], *, wall_s: float,
                        extra: dict[str, Any]) -> dict[str, Any]:
    """The run's result.json content: the robots' answers, errors against the exact answer,
    agreement verdict (the same keys as a fixed-grid run where they mean the same)."""
    absent = list(extra.get("absent", ()))
    ref = reference(spec, extra.get("participants") if absent else None)
    answers = {int(r["id"]): np.asarray(r.get("answer", []), dtype=float) for r in robots}
    rows = []
    for r in robots:
        row = {k: v for k, v in r.items() if k not in ("trace", "round_times", "residuals")}
        row["function_error"] = None if ref is None else report._num(relative_error(answers[int(r["id"])], ref))
        row["gamma"] = None  # the base layout's last entry: not a gamma here (see answer)
        rows.append(row)
    tol = float(spec.params.get("tol", report.DEFAULT_AGREEMENT_TOL))

    def pair(a: dict[str, Any], b: dict[str, Any]) -> float:
        return relative_error(answers[int(a["id"])], answers[int(b["id"])])

    def exact(r: dict[str, Any]) -> float | None:  # agreeing on a biased point is not converging
        return None if ref is None else relative_error(answers[int(r["id"])], ref)

    verdict = report.agreement_verdict(robots, pair, tol=tol, absent=absent, exact_error=exact,
                                       lost=extra.get("lost_unexpectedly"))
    errors = [e["function_error"] for e in rows if e["function_error"] is not None]
    mean = np.mean(list(answers.values()), axis=0) if answers else None
    consensus = max((relative_error(a, mean) for a in answers.values()), default=None)
    result: dict[str, Any] = {
        "schema": report.SCHEMA_VERSION,
        **verdict,
        "rounds": max((int(r["rounds"]) for r in robots), default=0),
        "wall_s": wall_s,
        "algorithm": spec.algorithm,
        "sigma": None,
        "C": None,
        "world": None if world.lengths is None else world.lengths.as_dict(),
        "robots": rows,
        "exact": {"answer": None if ref is None else ref.tolist(),
                      "of": "the participants' data" if absent else "all data"},
        "metrics": {
            "function_error": max(errors) if len(errors) == len(rows) and rows else None,
            "consensus_error": report._num(consensus) if consensus is not None else None,
            "train_accuracy": None,
            "iou": None,
        },
        "history": [],
    }
    result.update(extra)
    return result


def finish_custom(out: Path, world: World, spec: Any, robots: list[dict[str, Any]], *, wall_s: float,
                  extra: dict[str, Any], quiet: bool = False) -> dict[str, Any]:
    """Write result.json and print the summary (as launcher/cli.py's _finish does for the SVM)."""
    from rich.console import Console

    result = build_custom_result(world, spec, robots, wall_s=wall_s, extra=extra)
    report.write_json(out / "result.json", result)
    console = Console(quiet=quiet)
    console.print(report.summary_table(result))
    console.print(f"exact answer ({result['exact']['of']}): {result['exact']['answer']}", soft_wrap=True)
    console.print(f"wrote {out}/: result.json, data.csv")
    if not result["converged"] and not quiet:
        print(f"shapefleet: NOT converged: {result.get('verdict', 'see result.json')}", file=sys.stderr)
    return result
