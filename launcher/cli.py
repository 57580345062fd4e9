"""`shapefleet simulate | launch | central | prepare | robot | router | collect` -- what a person runs.

Exit codes: 0 the fleet converged (every participant agrees with its neighbours within tol and
their graph is connected: launcher/report.py ``agreement_verdict``); 1 it did not, or a robot's
solve failed or diverged, or the exact centralized solve failed, or no robot was left, or the
machine failed (one line says why; result.json says more);
2 bad input (one line naming the flag or file; nothing is left behind -- except for a fixed grid on which
the hard margin is infeasible: the run folder then holds data.csv, result.json and the shapes.png of the
paper's Fig. 5, which show why); 128+N stopped by signal N
(SIGINT 130, SIGHUP 129, SIGTERM 143; a partial result.json is written).
`--config scenario.toml` gives simulate/launch/central/prepare their flags from a scenario file
(launcher/config.py); flags on the command line override it.
"""

from __future__ import annotations

import argparse
import contextlib
import contextvars
import dataclasses
import os
import re
import sys
import time
from collections.abc import Callable, Sequence
from datetime import datetime
from pathlib import Path
from typing import Any, NoReturn

from launcher.router import EarlyRouter

#: `shapefleet launch` (the program, not a caller of main(argv)): its router starts now, before the
#: imports below (numpy, the world, the algorithms: ~0.3 s on one core), on the core they leave free
_EARLY_ROUTER = (EarlyRouter.for_command_line(sys.argv)
                 if __name__ == "__main__" or Path(sys.argv[0]).name == "shapefleet" else None)

import gc  # noqa: E402

#: the imports below create ~10^5 long-lived objects and no garbage worth a collection; the cyclic
#: collector's passes over them while they load (~60, the later ones over everything imported so
#: far) cost ~5 % of the launcher's start, on its critical path: paused for them, then as it was
_GC_WAS_ENABLED = gc.isenabled()
gc.disable()
try:
    import numpy as np

    from launcher import scenario, topology
    from launcher.options import (
        PAPER_GRID,
        PAPER_SIGMA,
        ROBOT_ID_ENV,
        Options,
        add_arguments,
        options_from_args,
    )
    from launcher.world import World, build_world
    from protocol.links import LinkFaults
finally:
    if _GC_WAS_ENABLED:
        gc.enable()

EXIT_BAD_INPUT = 2
EXIT_NOT_CONVERGED = 1


class UsageError(ValueError):
    """Bad input found after parsing; the message names the flag or file."""


class RunFailure(RuntimeError):
    """The run cannot go on for a reason that is not the input's form (exit 1, one line)."""


#: set by launcher/api.py: bad input raises UsageError instead of printing and exiting 2
_RAISE_USAGE: contextvars.ContextVar[bool] = contextvars.ContextVar("shapefleet_raise_usage", default=False)


def _fail(message: str) -> NoReturn:
    if _RAISE_USAGE.get():
        raise UsageError(message)
    print(f"shapefleet: error: {message}", file=sys.stderr)
    raise SystemExit(EXIT_BAD_INPUT)


# -- argument parsing -------------------------------------------------------------------------
class _Parser(argparse.ArgumentParser):
    """argparse with the project's rule for bad input: one line (no usage block), exit 2."""

    def error(self, message: str) -> NoReturn:
        # argparse says "argument --delay: ..."; the flag alone reads like every other message
        _fail(f"{message.removeprefix('argument ')} (see {self.prog} --help)")


_NEGATIVE_VALUE = re.compile(r"-[0-9.]")


def _join_negative_values(parser: argparse.ArgumentParser, argv: Sequence[str] | None) -> list[str]:
    """``--delay -5ms`` -> ``--delay=-5ms``: argparse would read ``-5ms`` as an unknown option and
    miss the flag's value; joined, the flag's own check says what is wrong with it."""
    args = list(sys.argv[1:] if argv is None else argv)
    if not args:
        return args
    try:
        sub = _subparser(parser, args[0])
    except KeyError:
        return args
    value_flags = {
        opt
        for action in sub._actions
        if isinstance(action, (argparse._StoreAction, argparse._AppendAction)) and action.nargs is None
        for opt in action.option_strings
    }
    out: list[str] = []
    i = 0
    while i < len(args):
        if args[i] in value_flags and i + 1 < len(args) and _NEGATIVE_VALUE.match(args[i + 1]):
            out.append(f"{args[i]}={args[i + 1]}")
            i += 2
        else:
            out.append(args[i])
            i += 1
    return out


def _options(args: argparse.Namespace, **extra: Any) -> Options:
    """The Options of a parsed command line (launcher/options.py: each flag's value went through
    the table's parse and check already; build_world checks the combinations)."""
    try:
        return options_from_args(args, **extra)
    except ValueError as exc:
        raise UsageError(str(exc)) from None


def _refuse_past_bound(args: argparse.Namespace, robots: int, what: str,
                       derived: Callable[[], tuple[int | None, str]]) -> None:
    """--robots within a bound, --max-robots's when given, else ``derived()``'s (bound, why): both
    shells refuse a fleet too large the same way (exit 2, naming the flag and the override)."""
    bound, why = (args.max_robots, "--max-robots") if args.max_robots is not None else derived()
    if bound is not None and robots > bound:
        raise UsageError(f"--robots: {robots} robots is more than {what} ({bound}: {why}); "
                         f"use fewer, or --max-robots {robots} to insist")


def _robots_bound(args: argparse.Namespace) -> None:
    """--robots within what this machine runs as processes (launch)."""
    from launcher.fleet import max_robots

    _refuse_past_bound(args, args.robots, "this machine runs at once", lambda: max_robots(args.robots_per_process))


def _simulate_bound(args: argparse.Namespace, options: Options) -> None:
    """--robots within what the in-process fleet holds in this machine's memory
    (launcher/simulate.py simulate_max_robots): checked before the world is built, so a fleet too
    large is refused before anything big is allocated."""
    from launcher.simulate import simulate_max_robots
    from launcher.world import resolve_options

    def derived() -> tuple[int | None, str]:
        resolved = resolve_options(options)
        rounds, grid_points = _rounds_and_grid(resolved)
        return simulate_max_robots(options.topology, resolved.algorithm, rounds=rounds, grid_points=grid_points)

    robots = options.robots if options.data is None else len(scenario.load_data_csv(options.data))
    _refuse_past_bound(args, robots, "simulate holds in this machine's memory", derived)


def _rounds_and_grid(options: Options) -> tuple[int, int]:
    """The run's round cap (autogrid: its planned rounds) and grid points (autogrid: its budget),
    from the options alone (the memory bound is checked before the world exists)."""
    from agents.spec import PARAMS_CLASSES
    from launcher.options import algorithm_params

    algorithm = options.algorithm
    if algorithm not in PARAMS_CLASSES:  # a user's fleet algorithm: admm's cap, the grid given
        algorithm = "admm"
    try:
        params = PARAMS_CLASSES[algorithm].from_params(algorithm_params(options, algorithm, diameter=1))
    except ValueError:  # e.g. a --ct-period that is no whole number of steps: build_world says so, by its flag
        params = PARAMS_CLASSES[algorithm]()
    if algorithm == "autogrid":
        return int(params.planned_rounds), int(params.max_points)
    rounds = int(params.rounds if algorithm == "ct-admm" else params.max_rounds)
    if options.grid is None:
        return rounds, 0
    nx, ny = scenario.parse_grid(options.grid)
    return rounds, nx * ny


def _out_dir(args: argparse.Namespace, mode: str) -> Path:
    if args.out:
        out = Path(args.out)
    else:
        stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
        out = Path("runs") / f"{stamp}-{mode}"
        n = 1
        while out.exists():
            n += 1
            out = Path("runs") / f"{stamp}-{mode}-{n}"
    if out.exists() and not out.is_dir():
        raise UsageError(f"--out: {out} exists and is not a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UsageError(f"--out: cannot create {out} ({exc.strerror})") from None
    return out


# -- jobs -------------------------------------------------------------------------------------
def _finish(out: Path, world: World, spec: Any, central: Any, robots: list[dict[str, Any]], *, wall_s: float,
            extra: dict[str, Any], quiet: bool = False) -> dict[str, Any]:
    """result.json, the pictures and the summary of a run. `central` is the reference of a
    fixed-grid run; an autogrid run (central None) is measured per robot on its final grid; a
    user algorithm's against its own ``reference`` (launcher/custom.py). ``quiet``: no terminal output."""
    from launcher import report

    if spec.custom:
        from launcher.custom import finish_custom

        return finish_custom(out, world, spec, robots, wall_s=wall_s, extra=extra, quiet=quiet)
    bases = None
    if spec.fixed_grid:
        tol = float(getattr(spec.algorithm_params, "tol", report.DEFAULT_AGREEMENT_TOL))
        result = report.build_result(world, spec.basis, central, robots, algorithm=spec.algorithm, C=spec.C,
                                     wall_s=wall_s, extra=extra, tol=tol, model=spec.model)
    else:
        references = _autogrid_references(world, spec, robots, extra)
        bases = {i: ref.basis for i, ref in references.items()}
        result = report.build_autogrid_result(world, robots, references, wall_s=wall_s, extra=extra)
    written = ["result.json", "data.csv", "shapes.png"]
    with report.drawn_aside(lambda: report.plot_shapes(out / "shapes.png", world, spec.basis if bases is None else None,
                                                       result, bases=bases)):
        report.write_json(out / "result.json", result)  # meanwhile, on the other core
        if result["history"]:
            report.plot_convergence(out / "convergence.png", result["history"])
            written.append("convergence.png")
        elif not spec.fixed_grid and robots and robots[0].get("residuals"):
            hist = report.autogrid_progress(robots[0], result["robots"][0].get("function_error"))
            report.plot_convergence(out / "convergence.png", hist, phases=robots[0].get("phases"))
            written.append("convergence.png")
        from rich.console import Console  # the summary's imports (~0.08 s) while shapes.png is drawn aside
        from rich.table import Table  # noqa: F401
    first = next((r for r in robots if r.get("trace")), None)
    if spec.algorithm == "ct-admm" and first is not None:
        from launcher.trajectory import plot_trajectory, trajectory_from_trace

        period = float(spec.algorithm_params.period)
        reference = np.append(central.x, central.gamma) if central.solved else None
        plot_trajectory(out / "trajectory.png", *trajectory_from_trace(first["trace"], period), reference=reference)
        written.append("trajectory.png")
    console = Console(quiet=quiet)
    console.print(report.summary_table(result))
    if not spec.fixed_grid and result.get("sigma_reason"):
        console.print(f"sigma: {result['sigma_reason']}", soft_wrap=True)
    console.print(f"wrote {out}/: {', '.join(written)}")
    if not result["converged"] and not quiet:
        print(f"shapefleet: NOT converged: {result.get('verdict', 'see result.json')}", file=sys.stderr)
        hint = _round_cap_hint(spec, result)
        if hint:
            print(f"shapefleet: hint: {hint}", file=sys.stderr)
    return result


def _round_cap_hint(spec: Any, result: dict[str, Any]) -> str | None:
    """What to try when a fixed-grid admm fleet only ran out of rounds: nothing failed, the fleet
    stayed connected, and every robot that did not meet its stopping rule used the whole cap. Barely
    separable data (star or cross on the 5x3 grid at 8 robots: an exact answer with |c| ~ 1e4) keep
    the ADMM far from the optimum for 5000 rounds, where newton solves them in 49-83 rounds
    (benchmarks/results/polish-sweep.md); otherwise a slow fleet only needs a larger cap."""
    if spec.algorithm != "admm" or not spec.fixed_grid:
        return None
    agreement, cap = result.get("agreement") or {}, _round_cap(spec)
    late = set(agreement.get("not_converged") or [])
    if not late or agreement.get("failed") or not agreement.get("connected"):
        return None
    if any(int(r.get("rounds") or 0) < cap for r in result.get("robots", []) if int(r["id"]) in late):
        return None
    return (f"the ADMM did not settle within its cap of {cap} rounds; --max-rounds raises the cap, and "
            "--algorithm newton solves the same problem exactly in far fewer rounds")


def _exit_code(result: dict[str, Any]) -> int:
    """0 only when the run converged (agreement, connected); 1 otherwise."""
    return 0 if result.get("converged") else EXIT_NOT_CONVERGED


def _autogrid_references(world: World, spec: Any, robots: list[dict[str, Any]], extra: dict[str, Any]) -> dict[int, Any]:
    """Each autogrid robot's reference: the central solve on its final grid and sigma, of all
    data -- or, with robots absent (`launch`), of the participants' data."""
    from launcher import report

    params = spec.autogrid_params
    if params.lsq:  # the least-squares model's exact fit, each robot's pairs read in its own data
        kept = _participants_robots(world, extra)
        robot_of = np.concatenate([np.full(len(lab), i) for i, _, lab in kept])
        return report.autogrid_lsq_references(robots, np.vstack([p for _, p, _ in kept]),
                                              np.concatenate([lab for _, _, lab in kept]), robot_of, params.lsq_lambda)
    pts, labels = _participants_data(world, extra)
    return report.autogrid_references(robots, pts, labels, C=spec.C, soft_C=params.soft_C)


def _participants_data(world: World, extra: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """The points and labels of the robots that took part to the end (all of them when none is
    absent): the data the fleet's answer is measured against."""
    kept = _participants_robots(world, extra)
    return np.vstack([p for _, p, _ in kept]), np.concatenate([lab for _, _, lab in kept])


def _participants_robots(world: World, extra: dict[str, Any]) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """(id, points, labels) of each robot that took part to the end (`_participants_data`)."""
    kept = world.robots
    if extra.get("absent"):
        kept = [r for r in world.robots if r.id in extra["participants"]]
    if not kept:  # e.g. every robot crashed with --no-restart: nobody's answer to measure
        raise RunFailure(f"no robot took part to the end (robots {extra['absent']} all lost): no answer to measure")
    return _robot_data(kept)


def _robot_data(robots: list[Any]) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """(id, points, labels) per robot: what `FleetSpec.central` measures a fleet's model against."""
    return [(r.id, r.points, r.labels) for r in robots]


def _round_budget(spec: Any) -> int:
    """Rounds the run is planned to take (a progress bar's total): the cap, for ct-admm the stop
    time in periods, for autogrid its phases' planned rounds (AutoGridParams.planned_rounds, an
    estimate: a run with a soft-margin fallback or a second refinement lasts longer)."""
    if spec.algorithm == "autogrid":
        return int(spec.algorithm_params.planned_rounds)
    return _round_cap(spec)


def _round_cap(spec: Any) -> int:
    """Rounds the run can last at most: the cap (autogrid: max_total_rounds, not its plan), for
    ct-admm the stop time in periods."""
    params = spec.algorithm_params
    if spec.algorithm == "ct-admm":
        return int(params.rounds)
    if spec.algorithm == "autogrid":
        return int(params.max_total_rounds)
    return int(params.max_rounds)


def _prepare(args: argparse.Namespace, mode: str, options: Options | None = None,
             check: Callable[[Any], None] | None = None, **extra: Any) -> tuple[Path, World, Any, Any]:
    """The world, the fleet file, the run folder and -- for a fixed grid -- the central solve
    (an autogrid fleet's grid exists only after its run: central is None then).
    ``check(spec)`` validates what needs the fleet before anything is written (a refused run
    leaves nothing behind)."""
    from agents.problem import SolverError

    world, spec = build_world(options or _options(args, **extra))
    _fault_robots_check(spec)
    if check is not None:
        check(spec)
    out = _out_dir(args, mode)
    scenario.write_data_csv(out / "data.csv", world.robots)
    try:
        central = spec.central(_robot_data(world.robots)) if spec.fixed_grid else None
    except SolverError as exc:  # e.g. --C 1e300: the reference every figure is measured against has no answer
        raise RunFailure(f"the exact centralized solve failed ({exc}) with --C {spec.C:g} on the "
                         f"{args_grid(spec)} grid: no reference to measure the fleet against; wrote {out}/data.csv") from None
    return out, world, spec, central


def _fault_robots_check(spec: Any) -> None:
    """--link-loss / --robot-loss / --partition name robots of this fleet: an entry for a robot it
    lacks would be ignored without a word, and the run measured under faults it never had."""
    faults = getattr(spec, "faults", None)
    if faults is None:
        return
    known = set(spec.robot_ids)
    named = ([("--link-loss", r) for a, b, _ in faults.link_loss for r in (a, b)]
             + [("--robot-loss", r) for r, _ in faults.robot_loss]
             + [("--partition", r) for a, b, _, _ in faults.partitions for r in (*a, *b)])
    for flag, robot in named:
        if robot not in known:
            raise UsageError(f"{flag}: robot {robot} is not in the fleet (robots {sorted(known)})")


def _infeasible(out: Path, world: World, spec: Any, central: Any) -> NoReturn:
    """Say it in words (the paper's Fig. 5) and show the data and grid, not a wrong curve."""
    from launcher import report

    result = report.build_result(world, spec.basis, central, [], algorithm=spec.algorithm, C=spec.C, wall_s=0.0, extra={})
    report.write_json(out / "result.json", result)
    report.plot_shapes(out / "shapes.png", world, spec.basis, result, title="no separating function on this grid")
    _fail(f"--grid {args_grid(spec)}: {central.message}. Wrote {out}/shapes.png")


def args_grid(spec: Any) -> str:
    if not spec.fixed_grid:
        start = f", start grid {len(spec.grid)} points" if len(spec.grid) else ""
        return f"automatic (at most {spec.autogrid_params.max_points} points{start})"
    xs = np.unique(np.round(spec.grid[:, 0], 9))
    ys = np.unique(np.round(spec.grid[:, 1], 9))
    return f"{len(xs)}x{len(ys)}"


def cmd_central(args: argparse.Namespace) -> int:
    """All data in one QP on a fixed grid. Without --grid / --sigma: the paper's (said so); the
    automatic grid and sigma are the fleet's own choice, made by simulate / launch."""
    t0 = time.perf_counter()
    options = _options(args)
    missing = [flag for flag, value in (("--grid", options.grid), ("--sigma", options.sigma)) if value is None]
    if missing and options.preset is None:
        print(
            f"central: no {' / '.join(missing)} given: solving on the paper's setting (--preset paper: grid "
            f"{PAPER_GRID}, sigma {PAPER_SIGMA:g}); the automatic grid and sigma are chosen by the fleet "
            "(shapefleet simulate / launch)"
        )
    model = "lsq" if options.algorithm == "lsq" else "admm"  # the least-squares model's own central fit, else the QP
    options = dataclasses.replace(options, preset=options.preset or "paper", algorithm=model)
    out, world, spec, central = _prepare(args, "central", options=options)
    if not central.solved:
        _infeasible(out, world, spec, central)
    robot = {"id": 0, "x": central.x.tolist(), "gamma": central.gamma, "rounds": 0, "converged": True}
    result = _finish(out, world, spec, central, [robot], wall_s=time.perf_counter() - t0, extra={"algorithm": "central"})
    return _exit_code(result)


@dataclasses.dataclass
class RunReport:
    """What one `simulate` / `launch` run produced: shared by the CLI and launcher/api.py.

    ``code`` is the CLI's exit code; ``result`` the content of result.json (None when the run
    produced no answer: ``message`` says why in one line); ``robots`` every robot's raw result
    row (with its per-round ``trace``); ``notes`` the one-line warnings the CLI prints."""

    code: int
    out: Path
    spec: Any
    world: World
    result: dict[str, Any] | None = None
    robots: list[dict[str, Any]] = dataclasses.field(default_factory=list)
    message: str | None = None
    notes: list[str] = dataclasses.field(default_factory=list)
    pids: list[int] = dataclasses.field(default_factory=list)
    states: dict[int, str] = dataclasses.field(default_factory=dict)  # launch: each robot's last state


def _say(report: RunReport, quiet: bool) -> int:
    """Print a run's failure line as the CLI always did; its exit code."""
    if not quiet and report.message is not None:
        print(f"shapefleet: {report.message}", file=sys.stderr)
    return report.code


def cmd_simulate(args: argparse.Namespace) -> int:
    return _say(run_simulate(args), quiet=False)


def run_simulate(args: argparse.Namespace, *, quiet: bool = False) -> RunReport:
    """The in-process fleet on the parsed options (bad input: UsageError / ScenarioError)."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from launcher.simulate import FleetFailure, simulate_fleet

    if getattr(args, "sync", "lockstep") == "free":
        return _simulate_free(args, quiet=quiet)
    crashes = _crash_plan(args)
    t0 = time.perf_counter()
    options = _options(args)
    _simulate_bound(args, options)
    out, world, spec, central = _prepare(args, "simulate", options=options, check=_crash_check(crashes))
    if central is not None and not central.solved:
        _infeasible(out, world, spec, central)
    with Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("residual {task.fields[residual]}"),
        TimeElapsedColumn(),
        transient=True,
        disable=quiet,
    ) as bar:
        planned = _round_budget(spec)
        task = bar.add_task(f"{spec.n_robots} robots, {spec.algorithm}", total=planned, residual="-")

        def progress(rnd: int, residual: float) -> None:
            # autogrid's plan is an estimate: the bar grows past it rather than stopping at 100 %
            bar.update(task, completed=rnd, total=max(planned, rnd), residual=f"{residual:.2e}")

        try:
            outcome = simulate_fleet(spec, progress=None if quiet else progress, crashes=crashes,
                                     restart=not args.no_restart, restart_after=args.restart_after)
        except FleetFailure as exc:  # a local solve failed or an iterate diverged: no answer
            return RunReport(EXIT_NOT_CONVERGED, out, spec, world, message=f"the run failed: {exc}")
    extra = {"fleet": spec.fleet, "topology": args.topology, "virtual_s": outcome.virtual_s, "faults": _fault_dict(spec.faults), "links": outcome.link_stats}
    report = RunReport(1, out, spec, world, robots=outcome.robots)
    if crashes:
        extra["crashes"] = outcome.crash_log
        report.notes += [f"--crash {c['robot']}@{c['planned_round']} never fired: robot {c['robot']} stopped before "
                         f"round {c['planned_round']}" for c in outcome.crash_log if not c["fired"]]
        for line in [] if quiet else report.notes:
            print(f"shapefleet: {line}", file=sys.stderr)
        central = _participants(world, spec, central, outcome.robots, extra)
    report.result = _finish(out, world, spec, central, outcome.robots, wall_s=time.perf_counter() - t0, extra=extra,
                            quiet=quiet)
    report.code = _exit_code(report.result)
    return report


def cmd_launch(args: argparse.Namespace) -> int:
    """The Zenoh fleet: a router and one process per robot on this machine."""
    global _EARLY_ROUTER
    early, _EARLY_ROUTER = _EARLY_ROUTER, None  # handed on once
    try:
        return _say(run_launch(args, early_router=early), quiet=False)
    finally:
        if early is not None:
            early.discard()  # when launch_fleet did not adopt it


def _free_algorithm(args: argparse.Namespace) -> str:
    """--free-algorithm (auto where the command has no such flag)."""
    return getattr(args, "free_algorithm", "auto")


def _free_check(args: argparse.Namespace) -> Callable[[Any], None]:
    """What --sync free refuses before anything is written: autogrid (its fleet-wide phases are
    lockstep), another fixed-grid algorithm, crash injection (a free robot has no checkpoint), the
    hub on a graph that is not complete."""
    from agents.pdmm import free_algorithm_for

    def check(spec: Any) -> None:
        if args.crash:
            raise UsageError("--crash: crash injection is lockstep only (a free robot has no checkpoint to resume)")
        if spec.algorithm != "admm":
            raise UsageError(f"--sync free: runs on a fixed grid (the free hub ADMM on a complete graph, else the relaxed "
                             f"ADMM), not {spec.algorithm}; give "
                             "--preset paper (or --grid and --sigma) and --algorithm admm or auto")
        if _free_algorithm(args) == "hub" and free_algorithm_for(spec) != "hub":
            raise UsageError("--free-algorithm hub: the free hub ADMM needs a complete graph (every robot a neighbour "
                             "of every other); use --topology complete, or --free-algorithm radmm or auto")

    return check


def _simulate_free(args: argparse.Namespace, *, quiet: bool = False) -> RunReport:
    """`simulate --sync free`: every robot on its own virtual clock (protocol/free.py), no waiting."""
    from rich.console import Console

    from launcher.simulate import FleetFailure, simulate_free

    t0 = time.perf_counter()
    options = _options(args)
    _simulate_bound(args, options)
    out, world, spec, central = _prepare(args, "simulate", options=options, check=_free_check(args))
    if not central.solved:
        _infeasible(out, world, spec, central)
    console = Console(stderr=True, quiet=quiet)
    with console.status(f"{spec.n_robots} robots, free sync every {args.period * 1e3:g} ms "
                        f"({_free_extra(args, spec)['free_algorithm']})"):
        try:
            outcome = simulate_free(spec, period=args.period, algorithm=_free_algorithm(args))
        except FleetFailure as exc:
            return RunReport(EXIT_NOT_CONVERGED, out, spec, world, message=f"the run failed: {exc}")
    spec = dataclasses.replace(spec, algorithm="admm")
    extra = {"fleet": spec.fleet, "topology": args.topology, **_free_extra(args, spec), "virtual_s": outcome.virtual_s,
             "faults": _fault_dict(spec.faults), "links": outcome.link_stats}
    report = RunReport(1, out, spec, world, robots=outcome.robots)
    report.result = _finish(out, world, spec, central, outcome.robots, wall_s=time.perf_counter() - t0, extra=extra,
                            quiet=quiet)
    report.code = _exit_code(report.result)
    return report


def _free_extra(args: argparse.Namespace, spec: Any) -> dict[str, Any]:
    """What result.json says of a free run (simulate and launch alike)."""
    from agents.pdmm import free_algorithm_for

    return {"sync": "free", "period_s": args.period, "free_algorithm": free_algorithm_for(spec, _free_algorithm(args))}


def _launch_free(args: argparse.Namespace) -> dict[str, Any]:
    """`launch --sync free`: launch_fleet's arguments that start free robot processes
    (agents/free_robot.py: each ticks every --period on its own clock, never waits); the rest of
    the launch -- router, fault links, result files, agreement verdict -- is lockstep launch's."""
    return {"robot_argv": ("-m", "agents.free_robot", "--period", repr(float(args.period)),
                           "--free-algorithm", _free_algorithm(args))}


def cmd_sweep(args: argparse.Namespace) -> int:
    """`shapefleet sweep`: the robustness map (launcher/sweep.py); exit 0 when every run finished
    within 1e-3 of the exact answer in agreement, 1 otherwise (the table says which)."""
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from launcher import sweep
    from protocol.links import parse_duration, parse_probability

    default_delays, default_losses = sweep.DEFAULT_GRID[args.over]
    delays = sweep.parse_list(args.delays or default_delays, lambda t: parse_duration(t, flag="--delays"), "--delays")
    losses = sweep.parse_list(args.losses or default_losses, lambda t: parse_probability(t, flag="--losses"),
                              "--losses")
    syncs = [m.strip() for m in args.syncs.split(",") if m.strip()]
    try:
        grid = sweep.cells(delays, losses, syncs, period=args.period, over=args.over)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    out = _out_dir(args, "sweep")
    t0 = time.perf_counter()
    with Progress(TextColumn("[bold]sweep"), BarColumn(), MofNCompleteColumn(), TextColumn("{task.fields[last]}"),
                  TimeElapsedColumn(), console=Console(stderr=True)) as bar:
        task = bar.add_task("sweep", total=len(grid), last="")

        def progress(row: dict[str, Any]) -> None:
            bar.update(task, advance=1, last=f"{row['sync']} {row['delay_s'] * 1e3:g} ms loss {row['loss']:g}")

        rows = sweep.run_sweep(grid, jobs=args.jobs, progress=progress)
    wall = time.perf_counter() - t0
    sweep.write_csv(out / "sweep.csv", rows)
    sweep.plot(out / "robustness.png", rows, delays, losses, syncs)
    console = Console()
    console.print(sweep.summary(rows))
    bad = [r for r in rows if not (r["converged"] and r["error"] < sweep.CLAIM)]
    jobs = args.jobs or os.cpu_count() or 1
    cpu = sum(r["cpu_s"] for r in rows)
    cost = (f"on {jobs} processes ({cpu:.0f} s of CPU: {cpu / jobs:.0f} s on {jobs} idle cores; the difference is "
            "other load)") if args.over == "inprocess" else "over Zenoh, one fleet of processes at a time"
    console.print(f"{len(rows)} runs in {wall:.0f} s wall {cost}; wrote {out}/: sweep.csv, robustness.png")
    if bad:
        print(f"shapefleet: {len(bad)} runs did not end in agreement within {sweep.CLAIM:g} of the exact answer "
              "(see sweep.csv)", file=sys.stderr)
    return 0 if not bad else EXIT_NOT_CONVERGED


def _crash_plan(args: argparse.Namespace) -> list[Any]:
    """--crash ID@ROUND ... as CrashPlans (each already checked by the options table)."""
    from launcher.fleet import parse_crash

    return [parse_crash(text) for text in args.crash]


def _crash_check(crashes: list[Any]) -> Callable[[Any], None]:
    """The fleet-dependent checks of a crash plan (simulate and launch): a known robot, a round
    the run can reach."""

    def check(spec: Any) -> None:
        unknown = [c.robot for c in crashes if c.robot not in spec.robots]
        if unknown:
            raise UsageError(f"--crash: robot {unknown[0]} is not in the fleet (robots {list(spec.robot_ids)})")
        cap = _round_cap(spec)
        late = [c for c in crashes if c.round >= cap]
        if late:
            raise UsageError(f"--crash: {late[0].robot}@{late[0].round} is at or past the run's last possible round "
                             f"({cap - 1}: the round cap is {cap}); it could never fire")

    return check


@contextlib.contextmanager
def _algorithm_importable(spec: Any) -> Any:
    """A user algorithm's module root on the robot processes' PYTHONPATH for the launch."""
    from agents.extension import import_root

    root = import_root(spec.algorithm) if spec.custom else None
    before = os.environ.get("PYTHONPATH")
    if root is not None and str(root) not in (before or "").split(os.pathsep):
        os.environ["PYTHONPATH"] = os.pathsep.join(p for p in (str(root), before or "") if p)
    try:
        yield
    finally:
        if before is None:
            os.environ.pop("PYTHONPATH", None)
        else:
            os.environ["PYTHONPATH"] = before


def _preload_pictures(_endpoint: str) -> None:
    """launch_fleet's ``on_running``: the picture modules' import thread, once the robots run."""
    from launcher.report import preload_pictures

    preload_pictures()


def run_launch(args: argparse.Namespace, *, quiet: bool = False, router: str | None = None,
               early_router: EarlyRouter | None = None) -> RunReport:
    """The Zenoh fleet on the parsed options; ``router``: a loopback router endpoint that
    already runs (launcher/pytest_plugin.py's ``zenoh_router``) instead of one of its own;
    ``early_router``: the router `shapefleet launch` started before its imports (adopted when it
    fits, else stopped). The robot processes are forked from this process when it runs no other
    thread (launcher/fleet.py ``fork_robot``), else spawned."""
    from launcher.fleet import LaunchError, _port_in_use, launch_fleet

    crashes = _crash_plan(args)
    _robots_bound(args)
    if args.zenoh_port is not None and _port_in_use(args.zenoh_port):
        raise UsageError(f"--zenoh-port {args.zenoh_port} is in use")
    free = getattr(args, "sync", "lockstep") == "free"
    check = _free_check(args) if free else _crash_check(crashes)

    t0 = time.perf_counter()
    out, world, spec, central = _prepare(args, "launch", check=check, fleet_id=args.fleet_id)
    if central is not None and not central.solved:
        _infeasible(out, world, spec, central)
    fleet_dir = out / "fleet"
    # the pictures' imports run while the launcher only waits for its robots, from the hand-over on
    # (started before it, the import thread and the hand-over shared the GIL)
    preload = None if spec.custom else _preload_pictures
    try:
        with _algorithm_importable(spec):
            outcome = launch_fleet(spec, workdir=fleet_dir, crashes=crashes, restart_after=args.restart_after,
                                   restart=not args.no_restart, zenoh_port=args.zenoh_port, progress=not quiet,
                                   router=router, robots_per_process=args.robots_per_process, on_running=preload,
                                   early_router=early_router,
                                   **(_launch_free(args) if free else {}))
    except ValueError as exc:  # e.g. --zenoh-port in use: the message names the flag
        raise UsageError(str(exc)) from None
    except LaunchError as exc:  # the machine, not the input: say it in one line, exit 1
        return RunReport(1, out, spec, world, message=f"launch failed: {exc} (logs in {fleet_dir})")
    report = RunReport(1, out, spec, world, robots=outcome.robots, pids=list(outcome.pids), states=dict(outcome.states))
    if not outcome.robots and outcome.interrupted is None:
        report.message = f"launch failed: no robot produced a result (logs in {fleet_dir})"
        return report
    extra: dict[str, Any] = {
        "fleet": spec.fleet,
        "topology": args.topology,
        "faults": _fault_dict(spec.faults),
        "crashes": [dataclasses.asdict(c) for c in outcome.crashes],
        "crashes_not_fired": [dataclasses.asdict(c) for c in outcome.crashes_not_fired],
        "router_restarts": outcome.router_restarts,
        "interrupted": outcome.interrupted,
        "timed_out": outcome.timed_out,
        "lost_unexpectedly": {str(i): why for i, why in sorted(outcome.lost_unexpectedly.items())},
    }
    if free:
        extra.update(_free_extra(args, spec), virtual_s=outcome.wall_s)
    report.notes += [f"--crash {c.robot}@{c.round} never fired: robot {c.robot} stopped before round {c.round}"
                     for c in outcome.crashes_not_fired]
    report.notes += [str(r["error"]) for r in outcome.robots if r.get("error")]
    report.notes += list(extra["lost_unexpectedly"].values())
    for line in [] if quiet else report.notes:  # before the summary, as the CLI always printed them
        print(f"shapefleet: {line}", file=sys.stderr)
    central = _participants(world, spec, central, outcome.robots, extra)
    report.result = _finish(out, world, spec, central, outcome.robots, wall_s=time.perf_counter() - t0,
                            extra=extra, quiet=quiet)
    report.code = _exit_code(report.result)
    if outcome.interrupted is not None:
        import signal as _signal

        report.message = (f"stopped by {outcome.interrupted}: partial result in {out / 'result.json'}, "
                          f"per-robot results in {fleet_dir}/robot-<id>.json, logs in {fleet_dir}/robot-<id>.log")
        report.code = 128 + int(getattr(_signal, outcome.interrupted))
    return report


def _participants(world: World, spec: Any, central: Any, robots: list[dict[str, Any]], extra: dict[str, Any]) -> Any:
    """Record who took part; with robots absent, the reference is the central solve of the
    participants' data (they solved the problem of *their* data: measure them against that).

    A robot took part if it wrote a result or if a robot that did still lists it as a neighbour
    at the end (its data is in their answer: only its result file is missing, ``results_missing``).
    ``absent``: robots dropped for good by everyone who wrote a result (or that never came)."""
    with_result = {int(r["id"]) for r in robots}
    linked = {int(j) for r in robots for j in (r.get("neighbours") or [])}
    extra["participants"] = sorted(with_result | (linked & set(spec.robot_ids)))
    extra["absent"] = sorted(set(spec.robot_ids) - set(extra["participants"]))
    extra["results_missing"] = sorted(set(extra["participants"]) - with_result)
    if not spec.fixed_grid:  # measured per robot on its own grid (_autogrid_references)
        if extra["absent"]:
            extra["reference"] = "central solution of the participants' data"
        return None
    if not extra["absent"]:
        return central
    kept = _participants_robots(world, extra)
    extra["reference"] = "central solution of the participants' data"
    return spec.central(kept)




def _tls_files(args: argparse.Namespace) -> Any:
    """TLSFiles of --tls-ca/--tls-cert/--tls-key (each must be a readable file), or None."""
    from protocol.zenoh_config import TLSFiles

    given = {name: getattr(args, f"tls_{name}") for name in ("ca", "cert", "key")}
    if all(v is None for v in given.values()):
        return None
    for name, path in given.items():
        if path is not None and not os.access(path, os.R_OK):
            raise UsageError(f"--tls-{name}: cannot read {path}")
    if (given["cert"] is None) != (given["key"] is None):
        raise UsageError("--tls-cert/--tls-key: give both (this node's certificate and its private key) or neither")
    return TLSFiles(**{k: None if v is None else str(v) for k, v in given.items()})


def _robot_id(args: argparse.Namespace, spec: Any) -> int:
    """--id, else $SHAPEFLEET_ROBOT_ID, else the robot a per-robot fleet file is for."""
    rid, source = args.id, "--id"
    if rid is None and os.environ.get(ROBOT_ID_ENV, "").strip():
        source = ROBOT_ID_ENV
        try:
            rid = int(os.environ[ROBOT_ID_ENV])
        except ValueError:
            raise UsageError(f"{ROBOT_ID_ENV}: {os.environ[ROBOT_ID_ENV]!r} is not a robot id (an integer)") from None
    if rid is None:
        if spec.owner is None:
            raise UsageError(f"--id: which robot? {args.fleet_file} holds robots {list(spec.robot_ids)} (or set {ROBOT_ID_ENV})")
        return int(spec.owner)
    if rid not in spec.robots:
        raise UsageError(f"{source}: robot {rid} is not in {args.fleet_file} (robots {list(spec.robot_ids)})")
    if spec.owner is not None and rid != spec.owner:
        raise UsageError(f"{source}: {args.fleet_file} is robot {spec.owner}'s fleet file (its data only), not robot {rid}'s")
    return int(rid)


def _remote_hint(exc: ValueError) -> str:
    return str(exc).replace("pass loopback_only=False to allow it", "add --allow-remote for a multi-host deployment")


def cmd_robot(args: argparse.Namespace) -> int:
    """One robot process (started by `launch`, or by hand on another host)."""
    import asyncio
    import json
    import logging

    import zenoh

    from agents.problem import InfeasibleError, SolverError
    from agents.robot import run_robot
    from agents.spec import FleetSpec
    from protocol.zenoh_config import robot_config_dict

    logging.basicConfig(level=logging.WARNING, format="robot %(message)s", stream=sys.stderr)
    try:
        spec = FleetSpec.load(args.fleet_file)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    rid = _robot_id(args, spec)
    tls = _tls_files(args)
    try:
        session = robot_config_dict(args.connect, loopback_only=not args.allow_remote, tls=tls)
    except ValueError as exc:
        raise UsageError(f"--connect: {_remote_hint(exc)}") from None
    result_path = None if args.result is None else Path(str(args.result).replace("{id}", str(rid)))
    try:
        result = asyncio.run(
            run_robot(
                spec,
                rid,
                connect=session["connect"]["endpoints"],
                checkpoint_path=args.checkpoint,
                result_path=result_path,
                handle_signals=True,
                zenoh_config=session,
            )
        )
    except zenoh.ZError as exc:
        print(f"shapefleet: robot {rid}: no Zenoh session with {', '.join(args.connect)}: {exc}", file=sys.stderr)
        return 1
    except (SolverError, InfeasibleError) as exc:  # the first local solve (building the core)
        print(f"shapefleet: robot {rid} round 0: local solver failed: {exc}", file=sys.stderr)
        return 1
    except ValueError as exc:  # agents/robot.py refuses a --checkpoint that is no checkpoint of this robot's
        if args.checkpoint is not None and str(args.checkpoint) in str(exc):
            raise UsageError(f"--checkpoint: {exc}") from None
        raise
    if result_path is None:
        print(json.dumps({"result": result}))
    if result.get("error"):
        print(f"shapefleet: {result['error']}", file=sys.stderr)
    return 0 if result.get("stopped") == "finished" and result.get("converged", True) is not False else 1


def cmd_router(args: argparse.Namespace) -> int:
    import zenoh

    from launcher.router import run_router

    tls = _tls_files(args)
    if tls is not None and tls.cert is None:
        raise UsageError("--tls-cert/--tls-key: a TLS router needs its certificate and private key")
    try:
        run_router(args.port, host=args.host, ready_file=args.ready_file, loopback_only=not args.allow_remote, tls=tls)
    except ValueError as exc:
        raise UsageError(f"--host: {_remote_hint(exc)}") from None
    except zenoh.ZError as exc:
        print(f"shapefleet: router: cannot listen on {args.host}:{args.port}: {exc}", file=sys.stderr)
        return 1
    return 0


def cmd_prepare(args: argparse.Namespace) -> int:
    """Write the fleet folder for robots on other hosts (launcher/deploy.py)."""
    from launcher import deploy

    out, world, spec, central = _prepare(args, "prepare", fleet_id=args.fleet_id)
    if central is not None and not central.solved:
        _infeasible(out, world, spec, central)
    written = deploy.write_prepared(out, world, spec, topology=args.topology)
    print(f"fleet {spec.fleet}: {spec.n_robots} robots, {spec.algorithm}, grid {args_grid(spec)}")
    print(f"wrote {written['fleet']} (every robot's data: for collect), {written['world']}, {out / 'data.csv'}")
    for i in spec.robot_ids:
        print(f"robot {i}: copy {written[f'robot-{i}']} to its host, then run there:")
        print(f"  shapefleet robot --fleet-file fleet.json --connect tcp/ROUTER:7447 --allow-remote --result robot-{i}.json")
    return 0


def cmd_collect(args: argparse.Namespace) -> int:
    """Gather robot result files into result.json and pictures, as `launch` writes them."""
    from launcher import deploy

    wait_s = args.wait  # seconds (the options table parsed the duration)
    try:
        prepared = deploy.load_prepared(args.fleet_file, args.world)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    if not args.results.is_dir():
        raise UsageError(f"--results: {args.results} is not a folder")
    world, spec = prepared.world, prepared.spec
    robots, absent = deploy.read_results(spec, args.results, wait_s=wait_s)
    if not robots:
        raise UsageError(f"--results: no result of fleet {spec.fleet} in {args.results} (robot-<id>.json)")
    for i, why in absent.items():
        print(f"robot {i}: no result ({deploy.result_file(args.results, i)}: {why})", file=sys.stderr)
    out = _out_dir(args, "collect")
    scenario.write_data_csv(out / "data.csv", world.robots)
    central = spec.central(_robot_data(world.robots)) if spec.fixed_grid else None
    extra: dict[str, Any] = {"fleet": spec.fleet, "topology": prepared.topology, "faults": _fault_dict(spec.faults)}
    central = _participants(world, spec, central, robots, extra)
    wall = max(float(r.get("wall_s") or 0.0) for r in robots)
    result = _finish(out, world, spec, central, robots, wall_s=wall, extra=extra)
    return _exit_code(result)


def cmd_gridstudy(args: argparse.Namespace) -> int:
    """The paper's Fig. 5: the same data on its grid and on a coarser, shifted one."""
    from launcher.gridstudy import run_grid_study

    options = _options(args)
    run_grid_study(
        _out_dir(args, "gridstudy"),
        options=options,
        good_grid=args.grid or PAPER_GRID,
        bad_grid=args.bad_grid or "4x2",
    )
    return 0


def _fault_dict(faults: LinkFaults) -> dict[str, float]:
    return dataclasses.asdict(faults)


# -- entry point ------------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="shapefleet", description="A robot fleet learns an object's outline together.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    commands = (
        ("simulate", "all robots in this process (deterministic, fast)", cmd_simulate),
        ("launch", "one process per robot on Zenoh, with a fault-injecting network", cmd_launch),
        ("central", "solve the same problem with all data in one place", cmd_central),
        ("prepare", "write the fleet files for robots on other hosts (one per robot: its own data)", cmd_prepare),
        ("gridstudy", "the paper's Fig. 5: a coarse, shifted grid leaves the hard margin infeasible", cmd_gridstudy),
        ("sweep", "delay x loss x sync grid of in-process runs: sweep.csv, robustness.png", cmd_sweep),
    )
    for name, help_text, func in commands:  # their flags: launcher/options.py
        p = sub.add_parser(name, help=help_text)
        add_arguments(p, name)
        p.set_defaults(func=func)
    commands = (
        ("robot", "run one robot process from a fleet file", cmd_robot),
        ("router", "a Zenoh router (loopback unless --allow-remote)", cmd_router),
        ("collect", "gather robot result files into result.json and pictures", cmd_collect),
    )
    for name, help_text, func in commands:
        p = sub.add_parser(name, help=help_text)
        add_arguments(p, name)
        p.set_defaults(func=func)
    return parser


def _subparser(parser: argparse.ArgumentParser, command: str) -> argparse.ArgumentParser:
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return action.choices[command]


def _given_on_command_line(command: str, argv: Sequence[str] | None) -> set[str]:
    """The dests the command line sets (parsed again with every default suppressed)."""
    parser = build_parser()
    for action in _subparser(parser, command)._actions:
        action.default = argparse.SUPPRESS
    return set(vars(parser.parse_args(_join_negative_values(parser, argv)))) - {"command", "func"}


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    """Parse the command line; with --config, the scenario file's values become the defaults."""
    from launcher import config

    parser = build_parser()
    argv = _join_negative_values(parser, argv)
    args = parser.parse_args(argv)
    if getattr(args, "config", None) is None:
        _data_conflicts(args, argv)
        return args
    try:
        scenario_file = config.load_scenario(args.config)
        defaults = config.defaults_for(_subparser(parser, args.command), scenario_file, _given_on_command_line(args.command, argv))
    except config.ConfigError as exc:
        _fail(str(exc))
    _subparser(parser, args.command).set_defaults(**defaults)
    args = parser.parse_args(argv)
    _data_conflicts(args, argv)
    return args


#: the flags that shape the simulated LiDAR world: a --data run has none (its file holds the points)
_LIDAR_FLAGS = ("robots", "points", "standoff", "range", "offset", "noise", "free-space")


def _data_conflicts(args: argparse.Namespace, argv: Sequence[str] | None) -> None:
    """--data with a LiDAR-world flag on the command line (--robots 5, --noise 0.5, ...): the flag
    would be ignored without a word and the run made on the file's robots and points. (Such keys
    beside ``data`` in one scenario file stay allowed: docker/scenario.toml is such a template.)"""
    if getattr(args, "data", None) is None:
        return
    from launcher.options import BY_NAME

    given = _given_on_command_line(args.command, argv)
    for name in _LIDAR_FLAGS:
        if BY_NAME[name].dest in given:
            _fail(f"--{name}: not used with --data {args.data} (the file holds the robots and their points; "
                  f"no LiDAR is simulated): drop --{name}")


def main(argv: Sequence[str] | None = None) -> int:
    """The `shapefleet` program (``argv`` None: the command line; the process ends after it)."""
    try:
        args = parse_args(argv)
        return int(args.func(args) or 0)
    except (UsageError, scenario.ScenarioError, topology.TopologyError) as exc:
        _fail(str(exc))
    except RunFailure as exc:
        print(f"shapefleet: error: {exc}", file=sys.stderr)
        return EXIT_NOT_CONVERGED
    except KeyboardInterrupt:
        print("shapefleet: interrupted", file=sys.stderr)
        return 130
    finally:
        if _EARLY_ROUTER is not None and argv is None:  # not handed to a launch (bad input, --help)
            _EARLY_ROUTER.discard()
        if argv is None:
            freeze_before_exit()


def freeze_before_exit() -> None:
    """The process is about to end: put every object in the garbage collector's permanent
    generation, so that the interpreter's shutdown does not walk them all in its last collections.

    Measured: 0.3-0.5 s (load 12) from the end of `launch` to the process's exit with matplotlib's
    objects alive, 0.05 s frozen; memory goes back to the OS with the process either way. Only
    for a process that ends next (a caller of ``main(argv)`` keeps collecting)."""
    import gc

    gc.freeze()


if __name__ == "__main__":
    raise SystemExit(main())
