"""shapefleet as a Python API: build a scenario, run a fleet, get a typed result (issue 17).

The API is the command line without the shell: every keyword is one of the CLI's own options
(the flag without its dashes, ``-`` written ``_``: ``loss=0.3``, ``delay="20ms"``,
``crash="1@40"`` or ``crash=["0@10", "2@30"]``, ``no_restart=True``, ``config="scenario.toml"``)
and goes through the CLI's own parser, checks, TOML loading (launcher/config.py), world building
(launcher/world.py) and reports (launcher/report.py): one option, one default, one check.
``option_names(mode)`` lists what a mode accepts.

    from launcher import api

    r = api.run("launch", robots=4, loss=0.3, delay="20ms", crash="1@40", out="runs/demo")
    assert r.converged, r.verdict
    print(r.rounds, r.error, r.participants, r.robot(1).counters["restarts"])

    r = await api.run_async("simulate", algorithm="mypkg.consensus:Average", tol=1e-9)

Bad input raises :class:`UsageError` (a ValueError) with the CLI's one line naming the flag or
file; a run that does not converge is *not* an exception: ``converged`` is False and ``verdict``
says why (the CLI's exit code is ``exit_code``). ``launch`` leaves no process behind: the
launcher stops every process it started by PID (``Result.pids`` lists them).

``run_async`` runs the same function in a worker thread (``asyncio.to_thread``): the event loop
stays free while the fleet runs. Cancelling the awaiting task does not stop a run already
started; it ends within its own bound (``max_wall``, default 600 s; the pytest fixtures use 60 s).
"""

from __future__ import annotations

import argparse
import asyncio
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from launcher import cli, scenario, topology
from launcher.cli import UsageError
from launcher.options import options_of
from launcher.world import World, build_world

__all__ = ["MODES", "UsageError", "RobotResult", "Result", "Scenario", "option_names", "build", "run",
           "run_async", "simulate", "launch"]

#: the commands the API runs (the CLI's ``simulate`` and ``launch``)
MODES = ("simulate", "launch")
_COUNTERS = ("frames_sent", "frames_received", "frames_lost", "frames_duplicated", "frames_accepted",
             "frames_deduplicated", "frames_rejected", "frames_rejected_by_reason", "restarts",
             "neighbours_dropped", "dropped_at", "wall_s", "round_ms")


@dataclass(frozen=True)
class RobotResult:
    """One robot's end of a run (the result row of the CLI's result.json, typed)."""

    id: int
    rounds: int
    converged: bool  # met its stopping rule (not the fleet's verdict)
    stopped: str | None  # "finished", "time_bound", "signal", "diverged", ...
    values: np.ndarray  # its final exchanged vector: (x, gamma) for the SVM, the user core's otherwise
    answer: np.ndarray | None  # a user algorithm's answer() (None for the built-in SVM)
    error: float | None  # relative error against the exact centralized answer
    counters: dict[str, Any]  # frames sent/received/lost/duplicated/rejected, restarts, drops...
    trace: dict[int, np.ndarray]  # round -> exchanged vector (what it recorded)
    row: dict[str, Any] = field(repr=False)  # everything, as in result.json


@dataclass(frozen=True)
class Result:
    """A run: the fleet's verdict, its figures and every robot's row (docs/result-schema.md)."""

    mode: str
    converged: bool  # every participant agrees within tol, graph connected (the CLI's exit 0)
    verdict: str  # what happened, in one line
    exit_code: int  # the CLI's: 0 converged, 1 not, 128+N stopped by signal N
    rounds: int
    algorithm: str
    robots: tuple[RobotResult, ...]
    participants: tuple[int, ...]
    absent: tuple[int, ...]  # robots dead for good: the reference is the participants' data
    error: float | None  # largest robot error against the exact answer
    consensus_error: float | None
    out: Path  # the run folder: result.json, data.csv, pictures, fleet/ (launch)
    wall_s: float
    pids: tuple[int, ...] = ()  # launch: every process started (router first), all stopped
    states: dict[int, str] = field(default_factory=dict)  # launch: each robot's last state
    raw: dict[str, Any] | None = field(default=None, repr=False)  # result.json content

    def robot(self, robot_id: int) -> RobotResult:
        """The row of robot ``robot_id`` (KeyError names the robots there are)."""
        for r in self.robots:
            if r.id == robot_id:
                return r
        raise KeyError(f"robot {robot_id} has no result (robots {[r.id for r in self.robots]})")


@dataclass(frozen=True)
class Scenario:
    """What a run is given: the world (truth, data) and the fleet file (what robots are told)."""

    world: World
    spec: Any  # agents.spec.FleetSpec


def _parser(mode: str) -> argparse.ArgumentParser:
    if mode not in MODES:
        raise UsageError(f"mode: {mode!r} is not one of {', '.join(MODES)}")
    return cli._subparser(cli.build_parser(), mode)


def _keyword(name: str) -> str:
    return name.replace("-", "_")


def _actions(mode: str) -> dict[str, argparse.Action]:
    """keyword -> the CLI action of that option (``range`` -> ``--range``, dest lidar_range)."""
    by_flag = {f: a for a in _parser(mode)._actions for f in a.option_strings}
    return {_keyword(o.name): by_flag[o.flag] for o in options_of(mode)}


def option_names(mode: str = "simulate") -> frozenset[str]:
    """Every keyword ``run(mode, ...)`` accepts: the options table's options of ``mode``
    (launcher/options.py), each name with ``-`` written ``_`` -- the CLI's flags and the TOML keys."""
    if mode not in MODES:
        raise UsageError(f"mode: {mode!r} is not one of {', '.join(MODES)}")
    return frozenset(_keyword(o.name) for o in options_of(mode))


def argv(mode: str, options: Mapping[str, Any]) -> list[str]:
    """The command line equal to ``options`` (UsageError names an unknown keyword)."""
    actions = _actions(mode)
    line = [mode]
    for key, value in options.items():
        action = actions.get(key)
        if action is None:
            raise UsageError(f"{key}: not an option of {mode} (see launcher.api.option_names({mode!r}))")
        flag = next(f for f in action.option_strings if f.startswith("--"))
        if value is None:
            continue
        if isinstance(action, argparse._StoreTrueAction):
            if not isinstance(value, bool):
                raise UsageError(f"{flag}: expected True or False, got {value!r}")
            line += [flag] if value else []
        elif isinstance(action, argparse._AppendAction):
            items = [value] if isinstance(value, (str, Path)) else list(value)
            line += [f"{flag}={item}" for item in items]
        else:
            line.append(f"{flag}={value}")
    return line


def _parse(mode: str, options: Mapping[str, Any]) -> argparse.Namespace:
    token = cli._RAISE_USAGE.set(True)
    try:
        return cli.parse_args(argv(mode, options))
    finally:
        cli._RAISE_USAGE.reset(token)


def build(mode: str = "simulate", **options: Any) -> Scenario:
    """The scenario ``run(mode, **options)`` would run (nothing is written, nothing started)."""
    args = _parse(mode, options)
    token = cli._RAISE_USAGE.set(True)
    try:
        world, spec = build_world(cli._options(args))
    except (scenario.ScenarioError, topology.TopologyError) as exc:
        raise UsageError(str(exc)) from None
    finally:
        cli._RAISE_USAGE.reset(token)
    return Scenario(world, spec)


def run(mode: str = "simulate", *, quiet: bool = True, router: str | None = None, **options: Any) -> Result:
    """Run a fleet in-process (``simulate``) or as processes over Zenoh (``launch``).

    ``options``: the CLI's (module doc). ``quiet``: no terminal output (the CLI prints its
    summary). ``router``: a loopback endpoint of a router that already runs (``launch`` only; the
    pytest fixture ``zenoh_router``), instead of a router of the run's own.
    """
    if router is not None and mode != "launch":
        raise UsageError("router: only launch connects to a router")
    args = _parse(mode, options)
    token = cli._RAISE_USAGE.set(True)
    try:
        report = cli.run_simulate(args, quiet=quiet) if mode == "simulate" else cli.run_launch(
            args, quiet=quiet, router=router)
    except (scenario.ScenarioError, topology.TopologyError) as exc:
        raise UsageError(str(exc)) from None
    finally:
        cli._RAISE_USAGE.reset(token)
    return _result(mode, report)


async def run_async(mode: str = "simulate", **kwargs: Any) -> Result:
    """``run`` for code inside an event loop: the run goes to a worker thread (module doc)."""
    return await asyncio.to_thread(run, mode, **kwargs)


def simulate(**options: Any) -> Result:
    """``run("simulate", **options)``: every robot in this process, deterministic."""
    return run("simulate", **options)


def launch(**options: Any) -> Result:
    """``run("launch", **options)``: a router and one process per robot on loopback."""
    return run("launch", **options)


def _robot(row: dict[str, Any], shown: dict[str, Any] | None) -> RobotResult:
    values = np.asarray([*row.get("x", []), row.get("gamma", np.nan)], dtype=float)
    err = (shown or {}).get("function_error")
    return RobotResult(
        id=int(row["id"]),
        rounds=int(row.get("rounds", 0)),
        converged=bool(row.get("converged")),
        stopped=row.get("stopped"),
        values=values,
        answer=None if "answer" not in row else np.asarray(row["answer"], dtype=float),
        error=None if err is None else float(err),
        counters={k: row[k] for k in _COUNTERS if k in row},
        trace={int(k): np.asarray(v, dtype=float) for k, v in (row.get("trace") or {}).items()},
        row={**row, **(shown or {})},
    )


def _result(mode: str, report: cli.RunReport) -> Result:
    res = report.result or {}
    shown = {int(r["id"]): r for r in res.get("robots", [])}
    robots = tuple(sorted((_robot(r, shown.get(int(r["id"]))) for r in report.robots), key=lambda r: r.id))
    metrics = res.get("metrics") or {}
    participants = res.get("participants", [r.id for r in robots])
    return Result(
        mode=mode,
        converged=bool(res.get("converged")) and report.code == 0,
        verdict=report.message or str(res.get("verdict", "no result")),
        exit_code=report.code,
        rounds=int(res.get("rounds", max((r.rounds for r in robots), default=0))),
        algorithm=str(res.get("algorithm", report.spec.algorithm)),
        robots=robots,
        participants=tuple(int(i) for i in participants),
        absent=tuple(int(i) for i in res.get("absent", [])),
        error=metrics.get("function_error"),
        consensus_error=metrics.get("consensus_error"),
        out=Path(report.out),
        wall_s=float(res.get("wall_s", 0.0)),
        pids=tuple(report.pids),
        states=dict(report.states),
        raw=report.result,
    )
