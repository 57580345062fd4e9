"""`shapefleet simulate | launch | central | prepare | robot | router | collect` -- what a person runs.

Exit codes: 0 the fleet converged (every participant agrees with its neighbours within tol and
their graph is connected: launcher/report.py ``agreement_verdict``); 1 it did not, or a robot's
solve failed or diverged, or the machine failed (one line says why; result.json says more);
2 bad input (one line naming the flag or file; nothing is left behind); 128+N stopped by signal N
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

import numpy as np

from agents.spec import Timing
from launcher import scenario, topology
from launcher.world import (
    ALGORITHM_CHOICES,
    DEFAULT_MAX_ROUNDS,
    DEFAULT_MAX_TOTAL_ROUNDS,
    PAPER_GRID,
    PAPER_SIGMA,
    Options,
    World,
    build_world,
)
from protocol.links import LinkFaults, parse_duration, parse_probability

EXIT_BAD_INPUT = 2
EXIT_NOT_CONVERGED = 1


class UsageError(ValueError):
    """Bad input found after parsing; the message names the flag or file."""


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
        _fail(f"{message} (see {self.prog} --help)")


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


def _positive_int(flag: str) -> Callable[[str], int]:
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
        if value < 1:
            raise argparse.ArgumentTypeError(f"{text!r} must be at least 1")
        return value

    parse.__name__ = flag
    return parse


def _finite_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not np.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
    return value


def _algorithm_name(text: str) -> str:
    """--algorithm: a built-in name, a dotted path pkg.mod:Class or an entry-point name (the
    class itself is loaded, and its errors named, by launcher/world.py resolve_options)."""
    from launcher.world import _is_entry_point

    if text in ALGORITHM_CHOICES or ":" in text or _is_entry_point(text):
        return text
    raise argparse.ArgumentTypeError(f"{text!r} is not one of {', '.join(ALGORITHM_CHOICES)} "
                                     "(or a dotted path package.module:ClassName, or an installed entry point)")


def _max_grid_points(value: Any) -> int:
    """--max-grid-points: an integer of at least 4 (the core's smallest budget)."""
    try:
        n = int(str(value).strip())
    except ValueError:
        raise UsageError(f"--max-grid-points: {value!r} is not an integer") from None
    if n < 4:
        raise UsageError(f"--max-grid-points: {value!r} must be at least 4")
    return n


def _add_scenario_args(p: argparse.ArgumentParser) -> None:
    d = Options()
    p.add_argument("--config", type=Path, metavar="TOML", help="scenario file (docs/scenario-file.md); flags given here override it")
    world = p.add_argument_group("world and data")
    src = world.add_mutually_exclusive_group()
    src.add_argument("--shape", default=d.shape, help=f"built-in shape: {', '.join(scenario.shape_names())} (default {d.shape})")
    src.add_argument("--shape-file", metavar="CSV", help="object outline from a CSV file with header x,y")
    src.add_argument("--data", metavar="CSV", help="labelled data from a CSV file with header robot,x,y,label")
    world.add_argument("--robots", type=_positive_int("--robots"), default=d.robots, help=f"number of robots (default {d.robots})")
    world.add_argument("--points", type=_positive_int("--points"), default=d.points, help=f"labelled points per robot (default {d.points})")
    world.add_argument("--seed", type=int, default=d.seed, help="seed of LiDAR noise and network faults (default 0)")
    ref, L = scenario.REFERENCE_LENGTHS, scenario.REFERENCE_LENGTH
    follows = (f"times the object's scale: its bounding-box diagonal/{L:g} rounded to 1, 2, 5, 10, 20...; "
               "1 for the built-in shapes")
    world.add_argument(
        "--standoff", type=_finite_float,
        help=f"robot distance from the object's hull (default {ref['standoff']:g} {follows})",
    )
    world.add_argument(
        "--range", dest="lidar_range", type=_finite_float,
        help=f"LiDAR range (default {ref['range']:g} {follows})",
    )
    world.add_argument(
        "--offset", type=_finite_float,
        help=f"distance of labelled points from a LiDAR hit (default {ref['offset']:g} {follows})",
    )
    world.add_argument(
        "--noise", type=_finite_float,
        help=f"LiDAR range noise std (default {ref['noise']:g} {follows})",
    )
    model = p.add_argument_group("model (default: the fleet chooses grid and sigma itself)")
    model.add_argument(
        "--grid", metavar="NXxNY",
        help=f"fixed grid of NXxNY points (default: automatic; the paper's is {PAPER_GRID}). "
        "With --algorithm autogrid: the start grid the fleet refines",
    )
    model.add_argument(
        "--grid-bounds", metavar="X0,X1,Y0,Y1",
        help="region of the --grid points (default: the data's bounding box, padded)",
    )
    model.add_argument(
        "--sigma", type=_finite_float,
        help=f"Gaussian kernel width (default: chosen by the fleet; the paper's is {PAPER_SIGMA:g}). "
        "With --algorithm autogrid: kept fixed",
    )
    model.add_argument("--C", type=_finite_float, default=None, help="soft margin with this penalty (default: hard margin, the paper's)")
    model.add_argument(
        "--preset", metavar="NAME",
        help=f"'paper' = --grid {PAPER_GRID} --sigma {PAPER_SIGMA:g} --algorithm admm, the paper's fixed setting "
        "(flags given as well override it)",
    )
    model.add_argument(
        "--max-grid-points", metavar="N", default=str(d.max_grid_points),
        help=f"autogrid: budget of grid points, at least 4 (default {d.max_grid_points}); frames grow with it",
    )
    algo = p.add_argument_group("fleet and algorithm")
    algo.add_argument("--topology", default=d.topology, help=f"{' | '.join(topology.TOPOLOGIES)} (default {d.topology})")
    algo.add_argument(
        "--comm-range", type=_finite_float,
        help=f"link robots within this distance (geometric topology; default {ref['comm-range']:g} {follows})",
    )
    algo.add_argument(
        "--algorithm", default=d.algorithm, type=_algorithm_name, metavar="|".join(ALGORITHM_CHOICES) + "|PKG.MOD:CLASS",
        help="your own fleet algorithm: a dotted path package.module:ClassName or an entry-point name "
        "(agents/extension.py, docs/testing.md); auto (default): admm when --grid and --sigma are given, else autogrid; autogrid: the fleet agrees on "
        "its data's box, chooses sigma by a held-out vote and refines its grid; admm / ct-admm / newton (a "
        "distributed interior-point method, exact in tens of rounds): fixed grid, "
        f"the paper's ({PAPER_GRID}, sigma {PAPER_SIGMA:g}) unless --grid/--sigma say otherwise",
    )
    algo.add_argument("--rho", type=_finite_float, default=d.rho, help=f"ADMM penalty (default {d.rho})")
    algo.add_argument("--relax", type=_finite_float, default=d.relax, help=f"ADMM over-relaxation in (0, 2) (default {d.relax})")
    algo.add_argument("--tol", type=_finite_float, default=d.tol, help=f"stop when every robot's relative residual is below (default {d.tol:g})")
    algo.add_argument(
        "--max-rounds", type=_positive_int("--max-rounds"), default=d.max_rounds,
        help=f"round cap (default {DEFAULT_MAX_ROUNDS}; autogrid: the cap over all its phases, default "
        f"{DEFAULT_MAX_TOTAL_ROUNDS})",
    )
    algo.add_argument("--ct-step", default=f"{d.ct_step * 1e3:g}ms", help="ct-admm: integration step of the flow (default 1ms, the paper's)")
    algo.add_argument("--ct-period", default=f"{d.ct_period * 1e3:g}ms", help="ct-admm: communication period T_sp (default 10ms, the paper's)")
    algo.add_argument("--ct-stop-time", default=f"{d.ct_stop_time:g}s", help="ct-admm: stop time of the flow (default 10s, the paper's)")
    p.add_argument("--out", metavar="DIR", help="output folder (default: a new folder under runs/)")


def _add_fault_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("network faults (netem vocabulary, injected per directed link)")
    g.add_argument("--delay", default="0ms", help="one-way delay, e.g. 20ms or 0.5s")
    g.add_argument("--jitter", default="0ms", help="uniform jitter around the delay")
    g.add_argument("--loss", default="0", help="drop probability (the dropout), 0.3 or 30%%")
    g.add_argument("--duplicate", default="0", help="duplicate probability")
    g.add_argument("--reorder", default="0", help="probability that a frame is held back and overtaken")
    g.add_argument("--retransmit", default="20ms", help="resend the latest frame after this long without progress")


def _add_timing_args(g: argparse._ArgumentGroup) -> None:
    d = Timing()
    g.add_argument("--dead-after", metavar="DURATION", help=f"a robot gives up a neighbour silent this long, also at start (default {d.dead_after_s:g}s)")
    g.add_argument("--max-wall", metavar="DURATION", help=f"a robot stops after this long whatever happens (default {d.max_wall_s:g}s)")


def _faults(args: argparse.Namespace) -> LinkFaults:
    return LinkFaults(
        delay=parse_duration(args.delay, flag="--delay"),
        jitter=parse_duration(args.jitter, flag="--jitter"),
        loss=parse_probability(args.loss, flag="--loss"),
        duplicate=parse_probability(args.duplicate, flag="--duplicate"),
        reorder=parse_probability(args.reorder, flag="--reorder"),
    )


def _options(args: argparse.Namespace, **extra: Any) -> Options:
    timing_flags = {"retransmit": "retransmit_s", "dead_after": "dead_after_s", "max_wall": "max_wall_s"}
    try:
        faults = _faults(args) if hasattr(args, "delay") else LinkFaults.none()
        timing = Timing(**{
            field: parse_duration(getattr(args, dest), flag="--" + dest.replace("_", "-"))
            for dest, field in timing_flags.items()
            if getattr(args, dest, None) is not None
        })
        ct = {
            name: parse_duration(getattr(args, f"ct_{name}"), flag=f"--ct-{name.replace('_', '-')}")
            for name in ("step", "period", "stop_time")
        }
    except ValueError as exc:  # the parsers name their flag
        raise UsageError(str(exc)) from None
    for dest, field in timing_flags.items():
        if getattr(timing, field) <= 0:
            raise UsageError(f"--{dest.replace('_', '-')}: must be a positive duration")
    return Options(
        shape=args.shape,
        shape_file=args.shape_file,
        data=args.data,
        robots=args.robots,
        points=args.points,
        seed=args.seed,
        standoff=args.standoff,
        lidar_range=args.lidar_range,
        offset=args.offset,
        noise=args.noise,
        grid=args.grid,
        grid_bounds=args.grid_bounds,
        sigma=args.sigma,
        C=args.C,
        preset=args.preset,
        max_grid_points=_max_grid_points(args.max_grid_points),
        topology=args.topology,
        comm_range=args.comm_range,
        algorithm=args.algorithm,
        rho=args.rho,
        relax=args.relax,
        tol=args.tol,
        max_rounds=args.max_rounds,
        ct_step=ct["step"],
        ct_period=ct["period"],
        ct_stop_time=ct["stop_time"],
        faults=faults,
        timing=timing,
        **extra,
    )


def _robots_bound(args: argparse.Namespace) -> None:
    """--robots within what this machine runs as processes (launch), unless --max-robots says more."""
    from launcher.fleet import max_robots

    bound, why = max_robots()
    if args.max_robots is not None:
        bound, why = args.max_robots, "--max-robots"
    if args.robots > bound:
        raise UsageError(f"--robots: {args.robots} robot processes is more than this machine runs at once "
                         f"({bound}: {why}); use fewer, or --max-robots {args.robots} to insist")


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
    from rich.console import Console

    from launcher import report

    if spec.custom:
        from launcher.custom import finish_custom

        return finish_custom(out, world, spec, robots, wall_s=wall_s, extra=extra, quiet=quiet)
    bases = None
    if spec.fixed_grid:
        tol = float(spec.params.get("tol", report.DEFAULT_AGREEMENT_TOL))
        result = report.build_result(world, spec.basis, central, robots, algorithm=spec.algorithm, C=spec.C,
                                     wall_s=wall_s, extra=extra, tol=tol)
    else:
        references = _autogrid_references(world, spec, robots, extra)
        bases = {i: ref.basis for i, ref in references.items()}
        result = report.build_autogrid_result(world, robots, references, wall_s=wall_s, extra=extra)
    report.write_json(out / "result.json", result)
    report.plot_shapes(out / "shapes.png", world, spec.basis if bases is None else None, result, bases=bases)
    written = ["result.json", "data.csv", "shapes.png"]
    if result["history"]:
        report.plot_convergence(out / "convergence.png", result["history"])
        written.append("convergence.png")
    elif not spec.fixed_grid and robots and robots[0].get("residuals"):
        hist = report.autogrid_progress(robots[0], result["robots"][0].get("function_error"))
        report.plot_convergence(out / "convergence.png", hist, phases=robots[0].get("phases"))
        written.append("convergence.png")
    first = next((r for r in robots if r.get("trace")), None)
    if spec.algorithm == "ct-admm" and first is not None:
        from launcher.trajectory import plot_trajectory, trajectory_from_trace

        period = float(spec.params["ct_period"])
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
    return result


def _exit_code(result: dict[str, Any]) -> int:
    """0 only when the run converged (agreement, connected); 1 otherwise."""
    return 0 if result.get("converged") else EXIT_NOT_CONVERGED


def _autogrid_references(world: World, spec: Any, robots: list[dict[str, Any]], extra: dict[str, Any]) -> dict[int, Any]:
    """Each autogrid robot's reference: the central solve on its final grid and sigma, of all
    data -- or, with robots absent (`launch`), of the participants' data."""
    from launcher import report

    kept = world.robots
    if extra.get("absent"):
        kept = [r for r in world.robots if r.id in extra["participants"]]
    pts = np.vstack([r.points for r in kept])
    labels = np.concatenate([r.labels for r in kept])
    return report.autogrid_references(robots, pts, labels, C=spec.C, soft_C=spec.autogrid_params.soft_C)


def _round_budget(spec: Any) -> int:
    """Rounds the run is planned to take: the cap, for ct-admm the stop time in periods, for
    autogrid its phases' planned rounds (AutoGridParams.planned_rounds, not the 50,000 cap)."""
    if spec.algorithm == "ct-admm":
        from agents.ct_admm import CTADMMParams

        return CTADMMParams.from_params(spec.params).rounds
    if spec.algorithm == "autogrid":
        return spec.autogrid_params.planned_rounds
    return int(spec.params["max_rounds"])


def _prepare(args: argparse.Namespace, mode: str, options: Options | None = None,
             check: Callable[[Any], None] | None = None, **extra: Any) -> tuple[Path, World, Any, Any]:
    """The world, the fleet file, the run folder and -- for a fixed grid -- the central solve
    (an autogrid fleet's grid exists only after its run: central is None then).
    ``check(spec)`` validates what needs the fleet before anything is written (a refused run
    leaves nothing behind)."""
    from agents.problem import solve_central

    world, spec = build_world(options or _options(args, **extra))
    if check is not None:
        check(spec)
    out = _out_dir(args, mode)
    scenario.write_data_csv(out / "data.csv", world.robots)
    central = solve_central(spec.basis, world.points, world.labels, spec.C) if spec.fixed_grid else None
    return out, world, spec, central


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
    options = dataclasses.replace(options, preset=options.preset or "paper", algorithm="admm")
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

    t0 = time.perf_counter()
    out, world, spec, central = _prepare(args, "simulate")
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
            outcome = simulate_fleet(spec, progress=None if quiet else progress)
        except FleetFailure as exc:  # a local solve failed or an iterate diverged: no answer
            return RunReport(EXIT_NOT_CONVERGED, out, spec, world, message=f"the run failed: {exc}")
    extra = {"fleet": spec.fleet, "topology": args.topology, "virtual_s": outcome.virtual_s, "faults": _fault_dict(spec.faults), "links": outcome.link_stats}
    result = _finish(out, world, spec, central, outcome.robots, wall_s=time.perf_counter() - t0, extra=extra, quiet=quiet)
    return RunReport(_exit_code(result), out, spec, world, result=result, robots=outcome.robots)


def cmd_launch(args: argparse.Namespace) -> int:
    """The Zenoh fleet: a router and one process per robot on this machine."""
    return _say(run_launch(args), quiet=False)


def _launch_checks(args: argparse.Namespace) -> list[Any]:
    """The process flags checked before anything starts; the crash plans."""
    from launcher.fleet import _port_in_use, parse_crash

    try:
        crashes = [parse_crash(text) for text in args.crash]
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    if args.restart_after < 0:
        raise UsageError("--restart-after: must be a non-negative number of seconds")
    if args.zenoh_port is not None and not 1 <= args.zenoh_port <= 65535:
        raise UsageError(f"--zenoh-port: {args.zenoh_port} is not a TCP port (1-65535)")
    if args.max_robots is not None and args.max_robots < 1:
        raise UsageError(f"--max-robots: {args.max_robots} must be at least 1")
    _robots_bound(args)
    if args.zenoh_port is not None and _port_in_use(args.zenoh_port):
        raise UsageError(f"--zenoh-port {args.zenoh_port} is in use")
    return crashes


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


def run_launch(args: argparse.Namespace, *, quiet: bool = False, router: str | None = None) -> RunReport:
    """The Zenoh fleet on the parsed options; ``router``: a loopback router endpoint that
    already runs (launcher/pytest_plugin.py's ``zenoh_router``) instead of one of its own."""
    from launcher.fleet import LaunchError, launch_fleet

    crashes = _launch_checks(args)

    def check(spec: Any) -> None:
        unknown = [c.robot for c in crashes if c.robot not in spec.robots]
        if unknown:
            raise UsageError(f"--crash: robot {unknown[0]} is not in the fleet (robots {list(spec.robot_ids)})")
        budget = _round_budget(spec)
        late = [c for c in crashes if c.round >= budget]
        if late:
            raise UsageError(f"--crash: {late[0].robot}@{late[0].round} is at or past the run's last possible round "
                             f"({budget - 1}: the round cap is {budget}); it could never fire")

    t0 = time.perf_counter()
    out, world, spec, central = _prepare(args, "launch", check=check, fleet_id=args.fleet_id)
    if central is not None and not central.solved:
        _infeasible(out, world, spec, central)
    fleet_dir = out / "fleet"
    try:
        with _algorithm_importable(spec):
            outcome = launch_fleet(spec, workdir=fleet_dir, crashes=crashes, restart_after=args.restart_after,
                                   restart=not args.no_restart, zenoh_port=args.zenoh_port, progress=not quiet,
                                   router=router)
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
    }
    report.notes += [f"--crash {c.robot}@{c.round} never fired: robot {c.robot} stopped before round {c.round}"
                     for c in outcome.crashes_not_fired]
    report.notes += [str(r["error"]) for r in outcome.robots if r.get("error")]
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
    from agents.problem import solve_central

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
    kept = [r for r in world.robots if r.id in extra["participants"]]
    pts = np.vstack([r.points for r in kept])
    labels = np.concatenate([r.labels for r in kept])
    extra["reference"] = "central solution of the participants' data"
    return solve_central(spec.basis, pts, labels, spec.C)


ROBOT_ID_ENV = "SHAPEFLEET_ROBOT_ID"


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
    if result_path is None:
        print(json.dumps({"result": result}))
    if result.get("error"):
        print(f"shapefleet: {result['error']}", file=sys.stderr)
    return 0 if result.get("stopped") == "finished" and result.get("converged", True) is not False else 1


def cmd_router(args: argparse.Namespace) -> int:
    import zenoh

    from launcher.router import run_router

    if not 1 <= args.port <= 65535:
        raise UsageError(f"--port: {args.port} is not a TCP port (1-65535)")
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
    from agents.problem import solve_central
    from launcher import deploy

    try:
        wait_s = parse_duration(args.wait, flag="--wait")
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
    central = solve_central(spec.basis, world.points, world.labels, spec.C) if spec.fixed_grid else None
    extra: dict[str, Any] = {"fleet": spec.fleet, "topology": prepared.topology, "faults": _fault_dict(spec.faults)}
    central = _participants(world, spec, central, robots, extra)
    wall = max(float(r.get("wall_s") or 0.0) for r in robots)
    result = _finish(out, world, spec, central, robots, wall_s=wall, extra=extra)
    return _exit_code(result)


def cmd_gridstudy(args: argparse.Namespace) -> int:
    """The paper's Fig. 5: the same data on its grid and on a coarser, shifted one."""
    from launcher.gridstudy import run_grid_study

    options = _options(args)
    if args.bad_grid is not None:
        scenario.parse_grid(args.bad_grid)
    run_grid_study(
        _out_dir(args, "gridstudy"),
        options=options,
        good_grid=args.grid or PAPER_GRID,
        bad_grid=args.bad_grid or "4x2",
        stop_time=options.ct_stop_time,
    )
    return 0


def _fault_dict(faults: LinkFaults) -> dict[str, float]:
    return dataclasses.asdict(faults)


# -- entry point ------------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="shapefleet", description="A robot fleet learns an object's outline together.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    p = sub.add_parser("simulate", help="all robots in this process (deterministic, fast)")
    _add_scenario_args(p)
    _add_fault_args(p)
    p.set_defaults(func=cmd_simulate)
    p = sub.add_parser("launch", help="one process per robot on Zenoh, with a fault-injecting network")
    _add_scenario_args(p)
    _add_fault_args(p)
    g = p.add_argument_group("processes")
    g.add_argument("--crash", action="append", default=[], metavar="ID@ROUND", help="SIGKILL robot ID when it reaches ROUND (repeatable)")
    g.add_argument("--restart-after", type=_finite_float, default=1.0, help="seconds before a crashed robot restarts from its checkpoint (default 1)")
    g.add_argument("--no-restart", action="store_true", help="leave crashed robots dead: the others finish without them")
    g.add_argument("--fleet-id", help="fleet id on the network (default: unique per run)")
    g.add_argument("--zenoh-port", type=int, help="the router's loopback port (default: a free one)")
    g.add_argument("--max-robots", type=int, metavar="N",
                   help="allow up to N robot processes (default: derived from this machine's cores and memory)")
    _add_timing_args(g)
    p.set_defaults(func=cmd_launch)
    p = sub.add_parser("central", help="solve the same problem with all data in one place")
    _add_scenario_args(p)
    p.set_defaults(func=cmd_central)
    p = sub.add_parser("prepare", help="write the fleet files for robots on other hosts (one per robot: its own data)")
    _add_scenario_args(p)
    _add_fault_args(p)
    g = p.add_argument_group("fleet")
    g.add_argument("--fleet-id", help="fleet id on the network (default: unique per run)")
    _add_timing_args(g)
    p.set_defaults(func=cmd_prepare)
    p = sub.add_parser("gridstudy", help="the paper's Fig. 5: a coarse, shifted grid leaves the hard margin infeasible")
    _add_scenario_args(p)
    p.add_argument("--bad-grid", metavar="NXxNY", help="the coarse grid, shifted by half a cell (default 4x2)")
    p.set_defaults(func=cmd_gridstudy)
    p = sub.add_parser("robot", help="run one robot process from a fleet file")
    p.add_argument("--fleet-file", type=Path, required=True, help="the fleet file written by launch or prepare")
    p.add_argument("--id", type=int, help=f"this robot's id (default: ${ROBOT_ID_ENV}, else the robot a per-robot fleet file is for)")
    p.add_argument("--connect", action="append", required=True, metavar="ENDPOINT", help="router endpoint, e.g. tcp/127.0.0.1:7447 or tls/10.0.0.1:7447")
    p.add_argument("--checkpoint", type=Path, help="checkpoint file: written every round, resumed from on restart")
    p.add_argument("--result", help="write the result JSON here, {id} is replaced by the robot id (default: stdout)")
    p.add_argument("--allow-remote", action="store_true", help="accept non-loopback endpoints (multi-host deployments)")
    _add_tls_args(p, node="robot")
    p.set_defaults(func=cmd_robot)
    p = sub.add_parser("router", help="a Zenoh router (loopback unless --allow-remote)")
    p.add_argument("--port", type=int, default=7447, help="TCP port (default 7447)")
    p.add_argument("--host", default="127.0.0.1", help="listen address (default 127.0.0.1)")
    p.add_argument("--ready-file", type=Path, help="written once the router listens")
    p.add_argument("--allow-remote", action="store_true", help="listen on a non-loopback address (multi-host deployments)")
    _add_tls_args(p, node="router")
    p.set_defaults(func=cmd_router)
    p = sub.add_parser("collect", help="gather robot result files into result.json and pictures")
    p.add_argument("--fleet-file", type=Path, required=True, help="the full fleet.json written by prepare (world.json beside it)")
    p.add_argument("--results", type=Path, required=True, metavar="DIR", help="folder of the robots' result files robot-<id>.json")
    p.add_argument("--world", type=Path, help="world file (default: world.json beside the fleet file, if there)")
    p.add_argument("--wait", default="0", metavar="DURATION", help="wait up to this long for every robot's result, e.g. 600s (default: do not wait)")
    p.add_argument("--out", metavar="DIR", help="output folder (default: a new folder under runs/)")
    p.set_defaults(func=cmd_collect)
    return parser


def _add_tls_args(p: argparse.ArgumentParser, *, node: str) -> None:
    g = p.add_argument_group("TLS (tls/ endpoints, docs/deploy.md)")
    if node == "router":
        g.add_argument("--tls-cert", type=Path, metavar="PEM", help="the router's certificate (naming the address robots connect to)")
        g.add_argument("--tls-key", type=Path, metavar="PEM", help="the router's private key")
        g.add_argument("--tls-ca", type=Path, metavar="PEM", help="the fleet's CA: robots must show a certificate it signed (mutual TLS)")
    else:
        g.add_argument("--tls-ca", type=Path, metavar="PEM", help="the fleet's CA, to verify the router")
        g.add_argument("--tls-cert", type=Path, metavar="PEM", help="this robot's certificate (for a mutual-TLS router)")
        g.add_argument("--tls-key", type=Path, metavar="PEM", help="this robot's private key")


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
        return args
    try:
        scenario_file = config.load_scenario(args.config)
        defaults = config.defaults_for(_subparser(parser, args.command), scenario_file, _given_on_command_line(args.command, argv))
    except config.ConfigError as exc:
        _fail(str(exc))
    _subparser(parser, args.command).set_defaults(**defaults)
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (UsageError, scenario.ScenarioError, topology.TopologyError) as exc:
        _fail(str(exc))
    except KeyboardInterrupt:
        print("shapefleet: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    raise SystemExit(main())
