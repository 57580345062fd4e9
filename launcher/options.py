"""Every option of every `shapefleet` command, once: the one table the rest is derived from.

From :data:`OPTIONS` come

* the argparse groups of each subcommand (:func:`add_arguments`, used by launcher/cli.py);
* the scenario-file schema: sections, keys, accepted TOML types and value checks
  (:data:`SECTIONS`, :func:`toml_value`, used by launcher/config.py);
* :class:`Options`, the dataclass `build_world` takes (launcher/world.py re-exports it), and
  :func:`options_from_args`, which fills it from a parsed command line;
* the typed parameters of each algorithm (:func:`algorithm_params`): the ``params`` of the fleet
  file, keyed by the fields of ADMMParams / CTADMMParams / AutoGridParams / NewtonParams;
* :func:`validate_options`, the one place each value is checked (the CLI, the TOML file and
  `build_world` all call the same ``check``).

How to add an option
--------------------
Append one :class:`Option` to :data:`OPTIONS`, next to its neighbours in the help::

    Option("sync", STR, "lockstep", "lockstep rounds or free-running robots", group=ALGORITHM,
           commands=FLEET_COMMANDS, section="algorithm", choices=("lockstep", "free"),
           feeds={"admm": "sync"})

* ``name``: the long flag without dashes; also the TOML key (in ``[section]``; ``section=None``:
  not in scenario files). ``dest`` defaults to the name with ``_`` (``max-grid-points`` ->
  ``max_grid_points``): the attribute on the argparse namespace and on :class:`Options`.
* ``kind``: how text becomes a value (INT, FLOAT, STR, PATH (text), FILE (a pathlib.Path),
  DURATION ("20ms" -> 0.02), PROBABILITY ("30%" -> 0.3), FLAG (store_true), LIST (repeatable))
  and which TOML types the key accepts.
* ``default``: the typed default (``None``: not given, something else decides -- say what in
  ``help``; ``FROM_PARAMS``: the default of the algorithm parameter it feeds, so that number is
  written only in the agents' *Params class). Help gets "(default ...)" appended automatically.
* ``check``: ``value -> None``, raises ValueError with a message saying what is wrong; the callers
  prefix ``--name:`` (CLI, build_world) or ``file: [section] name:`` (TOML), and strip a leading
  ``--name:`` the check may carry itself (so scenario.parse_grid serves as it is). ``choices``: a
  closed set of values (also shown by --help).
* ``commands``: the subcommands that have the flag (``SCENARIO_COMMANDS``, ``FLEET_COMMANDS``,
  ``CRASH_COMMANDS``, ``NODE_COMMANDS`` or your own tuple).
* ``target``: where the value lands: ``"options"`` (the default: a field of :class:`Options`, so
  ``build_world`` sees ``opts.<dest>``), ``"faults.<field>"`` (LinkFaults), ``"timing.<field>"``
  (Timing), or None (only on the argparse namespace; the command handler reads ``args.<dest>``).
* ``feeds``: ``{algorithm: parameter}``: the field of that algorithm's *Params class the value
  becomes in the fleet file (a None value: the parameter's own default). The field must exist
  (add it to the *Params class first). Parameters no option feeds keep their class default;
  values derived from the world (the graph's diameter) are added by build_world.
* ``group``: the --help section; ``metavar``, ``required``, ``exclusive`` (options sharing the name
  exclude each other, on the command line and in one TOML file) as in argparse.

tests/test_options.py checks that the CLI, the TOML keys, Options and the params agree with the
table, and that each FROM_PARAMS default equals every *Params default it feeds. It needs a valid,
non-default sample value of each option: INT, FLOAT, DURATION, PROBABILITY, FLAG and PATH get one
by their kind, an option with choices its last; a STR or LIST option with a check needs an entry
in its ``_TEXT``.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from agents.kernel import check_squarable_width
from agents.spec import ALGORITHMS, PARAMS_CLASSES, Timing
from launcher.scenario import DEFAULT_SHAPE, parse_bounds, parse_grid, shape_names
from launcher.topology import TOPOLOGIES
from protocol.keys import validate_fleet_id
from protocol.links import (
    DELAY_DISTRIBUTIONS,
    LinkFaults,
    parse_duration,
    parse_link_loss,
    parse_partition,
    parse_probability,
    parse_robot_loss,
)

# -- kinds: text -> value, and the TOML types a key accepts ---------------------------------------
INT, FLOAT, STR, PATH, FILE, DURATION, PROBABILITY, FLAG, LIST = (
    "int", "float", "str", "path", "file", "duration", "probability", "flag", "list",
)
KINDS = (INT, FLOAT, STR, PATH, FILE, DURATION, PROBABILITY, FLAG, LIST)  # PATH: text; FILE: a pathlib.Path

#: the paper's fixed grid and kernel width (``--preset paper``; admm/ct-admm without --grid/--sigma)
PAPER_GRID = "5x3"
PAPER_SIGMA = 1.0
PRESETS: dict[str, dict[str, Any]] = {"paper": {"grid": PAPER_GRID, "sigma": PAPER_SIGMA}}
#: --algorithm choices: "auto" resolves to admm (grid and sigma given) or autogrid
ALGORITHM_CHOICES = ("auto", *ALGORITHMS)

SCENARIO_COMMANDS = ("simulate", "launch", "central", "prepare", "gridstudy")
FAULT_COMMANDS = ("simulate", "launch", "prepare")
FLEET_COMMANDS = ("launch", "prepare")
NODE_COMMANDS = ("robot", "router")  # the processes of a fleet on other hosts
#: the robot id of a `shapefleet robot` process when --id is not given
ROBOT_ID_ENV = "SHAPEFLEET_ROBOT_ID"
CRASH_COMMANDS = ("simulate", "launch")


class _FromParams:
    """Marker default: the default of the first algorithm parameter the option feeds."""

    def __repr__(self) -> str:
        return "FROM_PARAMS"


FROM_PARAMS: Any = _FromParams()


def parse_int(text: str) -> int:
    try:
        if "_" in str(text):  # Python's digit separator: --robots 1_0 would silently be 10
            raise ValueError
        return int(str(text).strip())
    except ValueError:
        raise ValueError(f"{text!r} is not an integer") from None


def parse_float(text: str) -> float:
    try:
        if "_" in str(text):  # Python's digit separator: --sigma 1_0 would silently be 10
            raise ValueError
        value = float(text)
    except ValueError:
        raise ValueError(f"{text!r} is not a number") from None
    if not math.isfinite(value):
        raise ValueError(f"{text!r} is not a finite number")
    return value


def _strip_flag(exc: ValueError) -> str:
    """The protocol parsers name a flag first ("x: ..."): the table's callers add their own."""
    message = str(exc)
    return message.split(": ", 1)[1] if message.startswith("x: ") else message


def _duration(text: str) -> float:
    try:
        return parse_duration(text, flag="x")
    except ValueError as exc:
        raise ValueError(_strip_flag(exc)) from None


def _probability(text: str) -> float:
    try:
        return parse_probability(text, flag="x")
    except ValueError as exc:
        raise ValueError(_strip_flag(exc)) from None


_PARSE: dict[str, Callable[[str], Any]] = {
    INT: parse_int, FLOAT: parse_float, STR: str, PATH: str, FILE: Path, DURATION: _duration,
    PROBABILITY: _probability, LIST: str,
}


# -- checks: value -> None or ValueError (message without the flag) --------------------------------
def positive(value: float) -> None:
    if not value > 0:
        raise ValueError(f"{value!r} must be a positive number")


def kernel_width(value: float) -> None:
    """A positive width whose square 2 sigma^2 (the kernel's denominator) is a normal float."""
    positive(value)
    try:
        check_squarable_width(value)
    except ValueError as exc:
        raise ValueError(f"{exc}; rescale the data instead") from None


def at_least(low: int) -> Callable[[Any], None]:
    def check(value: Any) -> None:
        if value < low:
            raise ValueError(f"{str(value)!r} must be at least {low}")

    return check


def _open_interval(low: float, high: float) -> Callable[[float], None]:
    def check(value: float) -> None:
        if not low < value < high:
            raise ValueError(f"{value!r} must be in ({low:g}, {high:g})")

    return check


def _max_grid_points(value: int) -> None:
    from protocol.frames import MAX_DIM

    at_least(4)(value)
    if value + 2 > MAX_DIM:
        raise ValueError(f"{value} does not fit a frame (at most {MAX_DIM - 2})")


def _preset(value: str) -> None:
    if value not in PRESETS:
        raise ValueError(f"{value!r} is not a preset (choose from {', '.join(PRESETS)})")


def _algorithm(value: str) -> None:
    """A built-in name, or a user's fleet algorithm that loads (agents/extension.py): a dotted
    path package.module:ClassName or an entry point of group shapefleet.algorithms."""
    if value in ALGORITHM_CHOICES:
        return
    import importlib.metadata  # here, not at the top: ~25 ms of every command's start for this rare case

    from agents.extension import ENTRY_POINT_GROUP, load_algorithm

    if ":" not in value and not any(ep.name == value for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP)):
        raise ValueError(f"{value!r} is not one of {', '.join(ALGORITHM_CHOICES)} "
                         "(or a dotted path package.module:ClassName, or an installed entry point)")
    load_algorithm(value)  # ValueError names what is wrong with it


def _crash(value: str) -> None:
    from launcher.fleet import parse_crash

    parse_crash(value)


def _port(value: int) -> None:
    if not 1 <= value <= 65535:
        raise ValueError(f"{value} is not a TCP port (1-65535)")


def _robots_per_process(value: str) -> None:
    if str(value).strip() != "auto":
        try:
            n = int(str(value).strip())
        except ValueError:
            raise ValueError(f"{value!r} is not a number of robots or 'auto'") from None
        if n < 1:
            raise ValueError(f"{value!r} must be at least 1 or 'auto'")


def _non_negative(value: float) -> None:
    if not value >= 0:
        raise ValueError(f"{value!r} must be a non-negative number")


def _finite_positive(value: float) -> None:
    if not 0 < value < math.inf:
        raise ValueError(f"{value!r} must be a finite positive number")


def _finite_non_negative(value: float) -> None:
    if not 0 <= value < math.inf:
        raise ValueError(f"{value!r} must be a finite number >= 0")


def _durations(value: str) -> None:
    from launcher.sweep import parse_list

    parse_list(value, _duration, "delays")


def _probabilities(value: str) -> None:
    from launcher.sweep import parse_list

    parse_list(value, _probability, "losses")


def _syncs(value: str) -> None:
    from launcher.sweep import MODES

    bad = [m for m in value.split(",") if m.strip() not in MODES]
    if bad or not value.strip():
        raise ValueError(f"{value!r}: modes are {', '.join(MODES)}")


# -- the table ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class Option:
    """One option: its flag, TOML key, type, default, check, help and where its value goes."""

    name: str
    kind: str
    default: Any
    help: str
    group: str | None = None
    commands: tuple[str, ...] = SCENARIO_COMMANDS
    section: str | None = None
    check: Callable[[Any], None] | None = None
    feeds: Mapping[str, str] = field(default_factory=dict)
    dest: str = ""
    target: str | None = "options"
    metavar: str | None = None
    choices: tuple[str, ...] | None = None
    exclusive: str | None = None  # options sharing this name exclude each other (flag and file)
    required: bool = False
    show_default: bool = True

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"option {self.name}: unknown kind {self.kind!r}")
        if not self.dest:
            object.__setattr__(self, "dest", self.name.replace("-", "_"))
        if self.default is FROM_PARAMS:
            algorithm, param = next(iter(self.feeds.items()))
            object.__setattr__(self, "default", param_default(algorithm, param))

    @property
    def flag(self) -> str:
        return f"--{self.name}"

    def parse(self, text: Any) -> Any:
        """Text (a command-line word, or a TOML value as text) -> the checked value."""
        value = _PARSE[self.kind](text)
        self.validate(value)
        return value

    def validate(self, value: Any) -> None:
        """The option's choices and check; ValueError without the flag name."""
        if self.kind == PATH and not str(value).strip():  # "" would read as "not given" or as the folder "."
            raise ValueError("an empty path; give one or leave the option out")
        if self.choices is not None and value not in self.choices:
            raise ValueError(f"{value!r} is not one of {', '.join(self.choices)}")
        if self.check is not None:
            try:
                self.check(value)
            except ValueError as exc:  # the scenario parsers name the flag themselves
                raise ValueError(str(exc).removeprefix(f"{self.flag}: ")) from None


def param_default(algorithm: str, param: str) -> Any:
    """The default of one field of an algorithm's *Params class (the one place it is written)."""
    for f in dataclasses.fields(PARAMS_CLASSES[algorithm]):
        if f.name == param:
            return f.default
    raise KeyError(f"{PARAMS_CLASSES[algorithm].__name__} has no field {param!r}")


WORLD = "world and data"
MODEL = "model (default: the fleet chooses grid and sigma itself)"
ALGORITHM = "fleet and algorithm"
FAULTS = "network faults (netem vocabulary, injected per directed link)"
FLEET = "fleet"
PROCESSES = "crash injection (simulate: on the virtual clock; launch: SIGKILL)"
TLS = "TLS (tls/ endpoints, docs/deploy.md)"
SWEEP = "sweep grid (the default world on the paper's 5x3 grid; in-process on virtual time, or --over zenoh)"

_T = Timing()
_FOLLOWS = ("times the object's scale: its bounding-box diagonal/5 rounded to 1, 2, 5, 10, 20...; "
            "1 for the built-in shapes")
_ADMM_FAMILY = ("admm", "autogrid", "lsq")

OPTIONS: tuple[Option, ...] = (
    # -- every scenario command ------------------------------------------------------------
    Option("config", PATH, None, "scenario file (docs/scenario-file.md); flags given here override it",
           metavar="TOML", target=None),
    Option("shape", STR, DEFAULT_SHAPE, f"built-in shape: {', '.join(shape_names())}",
           group=WORLD, section="world", exclusive="source"),
    Option("shape-file", PATH, None, "object outline from a CSV file with header x,y", group=WORLD,
           section="world", metavar="CSV", exclusive="source"),
    Option("data", PATH, None, "labelled data from a CSV file with header robot,x,y,label", group=WORLD,
           section="world", metavar="CSV", exclusive="source"),
    Option("robots", INT, 3, "number of robots", group=WORLD, section="world", check=at_least(1)),
    Option("points", INT, 20, "labelled points per robot", group=WORLD, section="world", check=at_least(1)),
    Option("seed", INT, 0, "seed of LiDAR noise and network faults", group=WORLD, section="world",
           check=at_least(0)),  # numpy's generators take no negative seed
    Option("standoff", FLOAT, None, f"robot distance from the object's hull (default 1.5 {_FOLLOWS})",
           group=WORLD, section="world"),
    Option("range", FLOAT, None, f"LiDAR range (default 4 {_FOLLOWS})", group=WORLD, section="world",
           dest="lidar_range"),
    Option("offset", FLOAT, None, f"distance of labelled points from a LiDAR hit (default 0.3 {_FOLLOWS})",
           group=WORLD, section="world"),
    Option("noise", FLOAT, None, f"LiDAR range noise std (default 0.01 {_FOLLOWS})", group=WORLD,
           section="world"),
    Option("free-space", INT, 0, "outside points per kept LiDAR ray in the free space before its return (issue "
           "15: a ray certifies free space from the robot to the hit); 0 (default): none, the pairs alone", group=WORLD,
           section="world", check=at_least(0)),
    Option("grid", STR, None, f"fixed grid of NXxNY points (default: automatic; the paper's is {PAPER_GRID}). "
           "With --algorithm autogrid: the start grid the fleet refines", group=MODEL, section="model",
           metavar="NXxNY", check=parse_grid),
    Option("grid-bounds", STR, None, "region of the --grid points (default: the data's bounding box, padded)",
           group=MODEL, section="model", metavar="X0,X1,Y0,Y1", check=parse_bounds),
    Option("sigma", FLOAT, None, f"Gaussian kernel width (default: chosen by the fleet; the paper's is "
           f"{PAPER_SIGMA:g}). With --algorithm autogrid: kept fixed", group=MODEL, section="model",
           check=kernel_width),
    Option("C", FLOAT, None, "soft margin with this penalty (default: hard margin, the paper's)", group=MODEL,
           section="model", check=positive),
    Option("preset", STR, None, f"'paper' = --grid {PAPER_GRID} --sigma {PAPER_SIGMA:g} --algorithm admm, the "
           "paper's fixed setting (flags given as well override it)", group=MODEL, section="model",
           metavar="NAME", check=_preset),
    Option("max-grid-points", INT, FROM_PARAMS, "autogrid: budget of grid points, at least 4; frames grow with it",
           group=MODEL, section="model", metavar="N", check=_max_grid_points, feeds={"autogrid": "max_points"}),
    Option("narrow-ratio", FLOAT, FROM_PARAMS, "autogrid: the points refinement adds near the boundary have "
           "kernel width sigma / this, the level-0 lattice's sigma (issue 15: a width per grid level); 1 (default): "
           "one width", group=MODEL, section="model", check=at_least(1), feeds={"autogrid": "narrow_ratio"}),
    # (default None, not FROM_PARAMS: a fixed-grid run refuses --model only when it is given)
    Option("model", STR, None, "autogrid: what the fleet fits: lsq (default: the LiDAR least-squares model, "
           "--lsq-lambda: sigma by the held-out squared residual of whole pairs, one fit on its level-0 lattice) or svm "
           "(the margin, refined grids; label-only data, --C); docs/autogrid.md", group=MODEL, section="model",
           choices=("svm", "lsq"),
           feeds={"autogrid": "model"}),
    Option("topology", STR, "complete", " | ".join(TOPOLOGIES), group=ALGORITHM, section="algorithm",
           choices=TOPOLOGIES, metavar="TOPOLOGY"),
    Option("comm-range", FLOAT, None, f"link robots within this distance (geometric topology; default 12 "
           f"{_FOLLOWS})", group=ALGORITHM, section="algorithm"),
    Option("algorithm", STR, "auto", "auto (default): admm when --grid and --sigma are given, else autogrid; "
           "autogrid: the fleet agrees on its data's box, chooses sigma by a held-out vote and refines its grid; "
           "admm / ct-admm / newton (a distributed interior-point method, exact in tens of rounds) / lsq (the LiDAR "
           "least-squares model: outside +1, the return 0, inside -1, ridge --lsq-lambda; issue 15): fixed grid, "
           f"the paper's ({PAPER_GRID}, sigma {PAPER_SIGMA:g}) unless --grid/--sigma say otherwise; "
           "or your own fleet algorithm: a dotted path package.module:ClassName or an entry-point name "
           "(agents/extension.py, docs/testing.md)",
           group=ALGORITHM, section="algorithm", check=_algorithm, show_default=False,
           metavar="|".join(ALGORITHM_CHOICES) + "|PKG.MOD:CLASS"),
    Option("rho", FLOAT, None, f"ADMM penalty (default {param_default('admm', 'rho'):g}; lsq "
           f"{param_default('lsq', 'rho'):g}: its local curvature, 2 A'A, is of another scale)", group=ALGORITHM,
           section="algorithm", check=positive, show_default=False,
           feeds={a: "rho" for a in _ADMM_FAMILY}),
    Option("relax", FLOAT, FROM_PARAMS, "ADMM over-relaxation in (0, 2)", group=ALGORITHM, section="algorithm",
           check=_open_interval(0.0, 2.0), feeds={a: "relax" for a in _ADMM_FAMILY}),
    Option("tol", FLOAT, FROM_PARAMS, "admm/autogrid: stop when every robot's relative residual is below",
           group=ALGORITHM, section="algorithm", check=positive, feeds={a: "tol" for a in _ADMM_FAMILY}),
    Option("max-rounds", INT, None, f"round cap (default {param_default('admm', 'max_rounds')}; ct-admm: the "
           f"stop time in periods; autogrid: the cap over all its phases, default "
           f"{param_default('autogrid', 'max_total_rounds')})", group=ALGORITHM, section="algorithm",
           check=at_least(1), feeds={"admm": "max_rounds", "ct-admm": "max_rounds", "newton": "max_rounds", "lsq": "max_rounds",
                                     "autogrid": "max_total_rounds"}),
    Option("polish", FLAG, False, "admm on a complete graph, hard margin, grids of <= 24 points: the exact "
           "active-set end-game (docs/algorithm.md, \"An exact end-game\"): the run ends at the KKT-certified optimum, "
           "2-5x fewer rounds; its frames carry sums of each robot's active feature rows' outer products, as newton's",
           group=ALGORITHM, section="algorithm", show_default=False),
    Option("certify", FLOAT, None, "admm, hard margin: a stop also needs the fleet's proven bound on its error "
           "against the exact optimum <= CERTIFY x max(tol, 1e-3) (docs/algorithm.md, \"A certified stop\"; default "
           f"{param_default('admm', 'certify'):g} on the relay hub); 0: the stopping rule alone. A complete graph runs "
           "the exact end-game by default instead; giving --certify there keeps this guard",
           group=ALGORITHM, section="algorithm", check=_finite_non_negative, show_default=False),
    Option("lsq-lambda", FLOAT, FROM_PARAMS, "lsq and autogrid --model lsq: the ridge weight lam of the LiDAR least-squares model "
           "(docs/algorithm.md, \"The LiDAR least-squares model\"): sum of squared residuals + lam ||f||_H^2",
           group=ALGORITHM, section="algorithm", check=_finite_positive, feeds={"lsq": "lam", "autogrid": "lsq_lambda"}),
    Option("ct-step", DURATION, FROM_PARAMS, "ct-admm: integration step of the flow, the paper's",
           group=ALGORITHM, section="algorithm", check=positive, feeds={"ct-admm": "step"}),
    Option("ct-period", DURATION, FROM_PARAMS, "ct-admm: communication period T_sp, the paper's",
           group=ALGORITHM, section="algorithm", check=positive, feeds={"ct-admm": "period"}),
    Option("ct-stop-time", DURATION, FROM_PARAMS, "ct-admm: stop time of the flow, the paper's",
           group=ALGORITHM, section="algorithm", check=positive, feeds={"ct-admm": "stop_time"}),
    Option("ct-tol", FLOAT, FROM_PARAMS, "ct-admm: stop earlier when every robot's residual is below",
           group=ALGORITHM, section="algorithm", check=positive, feeds={"ct-admm": "tol"}),
    # issue 13: free-running robots (protocol/free.py, agents/pdmm.py, docs/robustness.md)
    Option("sync", STR, "lockstep", "lockstep: a round waits for every neighbour's exact value (resent until it "
           "arrives); free: every robot ticks each --period on its own clock with the newest values it holds and "
           "never waits (on a fixed grid: the free hub ADMM on a complete graph, else the relaxed ADMM; a --period "
           "of about a quarter of the one-way delay is fastest)", group=ALGORITHM, commands=("simulate", "launch"),
           section="algorithm", choices=("lockstep", "free"), target=None),
    Option("period", DURATION, 0.01, "free sync: each robot's tick period", group=ALGORITHM,
           commands=("simulate", "launch", "sweep"), section="algorithm", check=positive, target=None),
    Option("free-algorithm", STR, "auto", "free sync: the algorithm; auto: the free hub ADMM on a complete graph, "
           "else the relaxed ADMM; hub: the free hub ADMM (needs a complete graph); radmm: the relaxed ADMM",
           group=ALGORITHM, commands=("simulate", "launch"), section="algorithm", choices=("auto", "hub", "radmm"),
           target=None),
    # -- sweep (issue 13): delay x loss x sync, in-process ------------------------------------
    Option("delays", STR, None, "sweep: one-way delays, comma-separated (default 0ms,10ms,20ms,50ms; "
           "--over zenoh: 0ms,20ms)", group=SWEEP,
           commands=("sweep",), metavar="D1,D2,...", check=_durations, target=None),
    Option("losses", STR, None, "sweep: loss probabilities, comma-separated (default 0,0.1,0.3,0.5; "
           "--over zenoh: 0,0.3)", group=SWEEP,
           commands=("sweep",), metavar="P1,P2,...", check=_probabilities, target=None),
    Option("syncs", STR, "lockstep,free", "sweep: modes, comma-separated: lockstep (today's ADMM, the "
           "reference), free (as simulate --sync free: the free hub ADMM on a complete graph, else the relaxed ADMM), "
           "free-radmm (the relaxed ADMM), free-newest (today's ADMM fed the newest values: biased) or "
           "free-ct (CT-ADMM with held samples)", group=SWEEP, commands=("sweep",), metavar="MODES",
           check=_syncs, target=None),
    Option("jobs", INT, None, "sweep: worker processes (default: one per core)", group=SWEEP,
           commands=("sweep",), check=at_least(1), target=None),
    Option("over", STR, "inprocess", "sweep: inprocess (virtual time, parallel) or zenoh (spot checks: one "
           "router and robot processes per run, one run at a time, wall-clock seconds)", group=SWEEP,
           commands=("sweep",), choices=("inprocess", "zenoh"), target=None),
    Option("out", PATH, None, "output folder (default: a new folder under runs/)", metavar="DIR", target=None,
           commands=(*SCENARIO_COMMANDS, "collect", "sweep"), show_default=False),
    # -- network faults ------------------------------------------------------------------
    Option("delay", DURATION, 0.0, "one-way delay, e.g. 20ms or 0.5s", group=FAULTS, commands=FAULT_COMMANDS,
           section="faults", target="faults.delay"),
    Option("jitter", DURATION, 0.0, "uniform jitter around the delay", group=FAULTS, commands=FAULT_COMMANDS,
           section="faults", target="faults.jitter"),
    Option("loss", PROBABILITY, 0.0, "drop probability (the dropout), 0.3 or 30%%", group=FAULTS,
           commands=FAULT_COMMANDS, section="faults", target="faults.loss"),
    Option("duplicate", PROBABILITY, 0.0, "duplicate probability", group=FAULTS, commands=FAULT_COMMANDS,
           section="faults", target="faults.duplicate"),
    Option("reorder", PROBABILITY, 0.0, "probability that a frame is held back and overtaken", group=FAULTS,
           commands=FAULT_COMMANDS, section="faults", target="faults.reorder"),
    # issue 13: fault models beyond independent loss and uniform jitter (protocol/links.py)
    Option("loss-burst", FLOAT, 0.0, "mean length of a loss burst in frames (Gilbert-Elliott, with --loss as "
           "the long-run rate; 0: independent losses)", group=FAULTS, commands=FAULT_COMMANDS, section="faults",
           check=_non_negative, target="faults.loss_burst"),
    Option("delay-dist", STR, "uniform", "shape of the delay: uniform (--delay +- --jitter), normal (sd --jitter), "
           "exponential or pareto (--delay plus a one-sided extra of mean --jitter; pareto: heavy tail)",
           group=FAULTS, commands=FAULT_COMMANDS, section="faults", choices=DELAY_DISTRIBUTIONS,
           target="faults.delay_dist"),
    Option("link-loss", LIST, (), "loss of one directed link, e.g. 0-1:0.5 (repeatable; the largest "
           "applicable loss counts)", group=FAULTS, commands=FAULT_COMMANDS, section="faults",
           metavar="SRC-DST:P", check=parse_link_loss, target="faults.link_loss", show_default=False),
    Option("robot-loss", LIST, (), "loss of every link into and out of one robot, e.g. 2:0.3 (repeatable)",
           group=FAULTS, commands=FAULT_COMMANDS, section="faults", metavar="ID:P", check=parse_robot_loss,
           target="faults.robot_loss", show_default=False),
    Option("partition", LIST, (), "cut robots A,B from C,D between START and END after the first frame, "
           "e.g. 0,1/2,3@2s-5s (repeatable)", group=FAULTS, commands=FAULT_COMMANDS, section="faults",
           metavar="A,B/C,D@START-END", check=parse_partition, dest="partitions", target="faults.partitions",
           show_default=False),
    Option("retransmit", DURATION, _T.retransmit_s, "resend the latest frame after this long without progress",
           group=FAULTS, commands=FAULT_COMMANDS, section="faults", check=positive, target="timing.retransmit_s"),
    # -- the fleet on the network ---------------------------------------------------------
    Option("fleet-id", STR, None, "fleet id on the network (default: unique per run)", group=FLEET,
           commands=FLEET_COMMANDS, section="fleet", check=validate_fleet_id),
    Option("dead-after", DURATION, _T.dead_after_s, "a robot gives up a neighbour silent this long, also at start",
           group=FLEET, commands=("simulate", *FLEET_COMMANDS), section="fleet", metavar="DURATION", check=positive,
           target="timing.dead_after_s"),
    Option("max-wall", DURATION, _T.max_wall_s, "a robot stops after this long whatever happens", group=FLEET,
           commands=FLEET_COMMANDS, section="fleet", metavar="DURATION", check=positive,
           target="timing.max_wall_s"),
    # -- crash injection (simulate, launch) and robot processes (launch) -----------------------------------------------------------
    Option("crash", LIST, None, "SIGKILL robot ID when it reaches ROUND (repeatable)", group=PROCESSES,
           commands=CRASH_COMMANDS, section="launch", metavar="ID@ROUND", check=_crash, target=None),
    Option("restart-after", FLOAT, 1.0, "seconds before a crashed robot restarts from its checkpoint",
           group=PROCESSES, commands=CRASH_COMMANDS, section="launch", check=_non_negative, target=None),
    Option("no-restart", FLAG, False, "leave crashed robots dead: the others finish without them "
           "(sparse fleets then run the edge form, which can drop a dead robot)",
           group=PROCESSES, commands=CRASH_COMMANDS, section="launch", target=None, show_default=False),
    Option("zenoh-port", INT, None, "the router's loopback port (default: a free one)", group=PROCESSES,
           commands=("launch",), section="launch", check=_port, target=None),
    Option("max-robots", INT, None, "allow up to N robots (default: derived from this machine's memory, and for "
           "launch its cores; simulate: from the measured memory per robot of the topology and algorithm)",
           group=PROCESSES, commands=("simulate", "launch"), section="launch", metavar="N", check=at_least(1),
           target=None),
    Option("robots-per-process", STR, "auto", "robots run as asyncio tasks of one process, sharing one "
           "Zenoh session, each with its own key; auto: one process per robot when they fit the cores (or twice the cores, evenly), "
           "up to 4 robots in one process when they outnumber the cores, else one process per core "
           "(a robot with a --crash plan always runs alone)", group=PROCESSES, commands=("launch",),
           section="launch", metavar="N|auto", check=_robots_per_process, target=None),
    # -- gridstudy ----------------------------------------------------------------------
    Option("bad-grid", STR, None, "the coarse grid, shifted by half a cell (default 4x2)", commands=("gridstudy",),
           metavar="NXxNY", check=parse_grid, target=None),
    # -- robot, router, collect: the processes of a fleet on several hosts (docs/deploy.md) -----
    Option("fleet-file", FILE, None, "the fleet file (robot: written by launch or prepare; collect: the full "
           "fleet.json written by prepare, world.json beside it)", commands=("robot", "collect"), target=None,
           required=True),
    Option("id", INT, None, f"this robot's id (default: ${ROBOT_ID_ENV}, else the robot a per-robot fleet file is "
           "for)", commands=("robot",), target=None),
    Option("connect", LIST, None, "router endpoint, e.g. tcp/127.0.0.1:7447 or tls/10.0.0.1:7447",
           commands=("robot",), metavar="ENDPOINT", target=None, required=True),
    Option("checkpoint", FILE, None, "checkpoint file: written every round, resumed from on restart",
           commands=("robot",), target=None),
    Option("result", STR, None, "write the result JSON here, {id} is replaced by the robot id (default: stdout)",
           commands=("robot",), target=None, show_default=False),
    Option("port", INT, 7447, "TCP port", commands=("router",), check=_port, target=None),
    Option("host", STR, "127.0.0.1", "listen address", commands=("router",), target=None),
    Option("ready-file", FILE, None, "written once the router listens", commands=("router",), target=None),
    Option("allow-remote", FLAG, False, "accept non-loopback endpoints / listen on a non-loopback address "
           "(multi-host deployments)", commands=NODE_COMMANDS, target=None, show_default=False),
    Option("tls-ca", FILE, None, "the fleet's CA (robot: to verify the router; router: robots must show a "
           "certificate it signed, mutual TLS)", group=TLS, commands=NODE_COMMANDS, metavar="PEM", target=None),
    Option("tls-cert", FILE, None, "this node's certificate (router: naming the address robots connect to; "
           "robot: for a mutual-TLS router)", group=TLS, commands=NODE_COMMANDS, metavar="PEM", target=None),
    Option("tls-key", FILE, None, "this node's private key", group=TLS, commands=NODE_COMMANDS, metavar="PEM",
           target=None),
    Option("results", FILE, None, "folder of the robots' result files robot-<id>.json", commands=("collect",),
           metavar="DIR", target=None, required=True),
    Option("world", FILE, None, "world file (default: world.json beside the fleet file, if there)",
           commands=("collect",), target=None),
    Option("wait", DURATION, 0.0, "wait up to this long for every robot's result, e.g. 600s (0: do not wait)",
           commands=("collect",), metavar="DURATION", target=None),
)

BY_NAME: dict[str, Option] = {o.name: o for o in OPTIONS}


def options_of(command: str) -> list[Option]:
    """The options of one subcommand, in the table's order."""
    return [o for o in OPTIONS if command in o.commands]


# -- (a) argparse ---------------------------------------------------------------------------------
def _format_default(option: Option) -> str:
    if option.kind == DURATION:
        value = option.default
        return f"{value * 1e3:g}ms" if 0 < value < 1 else f"{value:g}s"
    return f"{option.default:g}" if isinstance(option.default, float) else str(option.default)


def _argparse_type(option: Option) -> Callable[[str], Any]:
    def parse(text: str) -> Any:
        try:
            return option.parse(text)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None

    parse.__name__ = option.flag
    return parse


def add_arguments(parser: argparse.ArgumentParser, command: str) -> None:
    """The flags of ``command`` from the table, in argparse groups named by each option's group."""
    groups: dict[str | None, Any] = {None: parser}
    exclusive: dict[tuple[str | None, str], Any] = {}
    for option in options_of(command):
        if option.group not in groups:
            groups[option.group] = parser.add_argument_group(option.group)
        target = groups[option.group]
        if option.exclusive is not None:
            key = (option.group, option.exclusive)
            if key not in exclusive:
                exclusive[key] = target.add_mutually_exclusive_group()
            target = exclusive[key]
        help_text = option.help
        if option.show_default and option.default is not None and "(default" not in help_text:
            help_text += f" (default {_format_default(option)})"
        kw: dict[str, Any] = {"dest": option.dest, "help": help_text}
        if option.metavar:
            kw["metavar"] = option.metavar
        if option.required:
            kw["required"] = True
        if option.kind == FLAG:
            target.add_argument(option.flag, action="store_true", default=option.default, **kw)
        elif option.kind == LIST:
            default = None if option.required else []  # argparse appends to a default list
            target.add_argument(option.flag, action="append", default=default, type=_argparse_type(option), **kw)
        else:
            choices = {"choices": option.choices} if option.choices else {}
            target.add_argument(option.flag, type=_argparse_type(option), default=option.default, **choices, **kw)


# -- (b) the scenario-file schema ---------------------------------------------------------------
SECTIONS: dict[str, tuple[str, ...]] = {}
for _o in OPTIONS:
    if _o.section is not None:
        SECTIONS.setdefault(_o.section, ())
        SECTIONS[_o.section] += (_o.name,)
SECTION_OF: dict[str, str] = {key: section for section, keys in SECTIONS.items() for key in keys}


def _type_name(value: Any) -> str:
    return {bool: "a boolean", int: "an integer", float: "a number", str: "a string", list: "an array",
            dict: "a table"}.get(type(value), type(value).__name__)


def toml_value(option: Option, value: Any) -> Any:
    """A TOML value of ``option`` -> the checked value; ValueError (message without the key)."""

    def wrong(expected: str) -> ValueError:
        return ValueError(f"expected {expected}, got {_type_name(value)} {value!r}")

    if option.kind == FLAG:
        if not isinstance(value, bool):
            raise wrong("true or false")
        return value
    if option.kind == INT:
        if isinstance(value, bool) or not isinstance(value, int):
            raise wrong("an integer")
        option.validate(value)
        return value
    if option.kind == FLOAT:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise wrong("a number")
        if not math.isfinite(value):
            raise ValueError(f"{value!r} is not a finite number")
        option.validate(float(value))
        return float(value)
    if option.kind == PROBABILITY:
        if isinstance(value, bool) or not isinstance(value, (int, float, str)):
            raise wrong('a probability such as 0.3 or "30%"')
        return option.parse(value if isinstance(value, str) else repr(float(value)))
    if option.kind == LIST:
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            raise wrong('an array of strings such as ["1@40"]')
        return [option.parse(v) for v in value]
    if not isinstance(value, str):
        raise wrong('a duration such as "20ms"' if option.kind == DURATION else "a string")
    return option.parse(value)


# -- (c) Options, and the algorithms' typed parameters ---------------------------------------------
_PY_TYPES = {INT: int, FLOAT: float, STR: str, PATH: str, FILE: Path, DURATION: float, PROBABILITY: float,
             FLAG: bool, LIST: list}


def _options_fields() -> list[tuple[str, Any, Any]]:
    fields_: list[tuple[str, Any, Any]] = []
    for option in OPTIONS:
        if option.target == "options":
            kind = _PY_TYPES[option.kind]
            fields_.append((option.dest, kind | None if option.default is None else kind,
                            field(default=option.default)))
    fields_.append(("faults", LinkFaults, field(default_factory=LinkFaults.none)))
    fields_.append(("timing", Timing, field(default_factory=Timing)))
    return fields_


Options = dataclasses.make_dataclass("Options", _options_fields())
Options.__module__ = __name__
Options.__doc__ = ("Everything `build_world` takes: one field per option of the table whose target is "
                   "'options', plus the composite faults (LinkFaults) and timing (Timing). Derived from "
                   "launcher/options.py OPTIONS: add an option there, not here.")


def options_from_args(args: argparse.Namespace, **extra: Any) -> Any:
    """:class:`Options` from a parsed command line (the flags a command lacks keep their default)."""
    given = vars(args)
    plain: dict[str, Any] = {}
    faults: dict[str, Any] = {}
    timing: dict[str, Any] = {}
    for option in OPTIONS:
        if option.target is None or option.dest not in given:
            continue
        value = given[option.dest]
        if option.target == "options":
            plain[option.dest] = value
        elif option.target.startswith("faults."):
            faults[option.target.removeprefix("faults.")] = value
        elif option.target.startswith("timing."):
            timing[option.target.removeprefix("timing.")] = value
    plain.update(extra)  # e.g. fleet_id=... from a command handler
    return Options(**plain, faults=LinkFaults(**faults), timing=Timing(**timing))


def validate_options(opts: Any) -> None:
    """Run every option's check on ``opts`` (the one place values are checked); ValueError
    ``--flag: message`` naming the first bad one. Options built in code get the same checks as
    the command line and the scenario file."""
    for option in OPTIONS:
        if option.target != "options":
            continue
        value = getattr(opts, option.dest)
        if value is None:
            continue
        kind = _PY_TYPES[option.kind]
        if kind is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if isinstance(value, bool) != (kind is bool) or not isinstance(value, kind):
            raise ValueError(f"{option.flag}: {value!r} is not {_type_name(kind())}")
        try:
            option.validate(value)
        except ValueError as exc:
            raise ValueError(f"{option.flag}: {exc}") from None


def algorithm_params(opts: Any, algorithm: str, **derived: Any) -> dict[str, Any]:
    """The fleet file's ``params`` of ``algorithm``: each option that feeds it, under the parameter's
    own name (an option left None gets the parameter's own default, left out if that is None too),
    plus ``derived`` values
    (e.g. the graph's diameter) that the algorithm has a field for. Checked by the typed class."""
    if algorithm not in PARAMS_CLASSES:
        return _fleet_algorithm_params(opts, algorithm, derived)
    names = {f.name for f in dataclasses.fields(PARAMS_CLASSES[algorithm])}
    params = {k: v for k, v in derived.items() if k in names}
    for option in OPTIONS:
        param = option.feeds.get(algorithm)
        if param is None or option.target != "options":
            continue
        value = getattr(opts, option.dest)
        if value is None:  # not given: the algorithm's own default, written out in the fleet file
            value = param_default(algorithm, param)
        if value is not None:
            params[param] = value
    return params


def _fleet_algorithm_params(opts: Any, algorithm: str, derived: Mapping[str, Any]) -> dict[str, Any]:
    """A user's fleet algorithm (agents/extension.py): each field of its ``params_class`` from the
    option that feeds the admm parameter of that name (tol, max_rounds, rho, relax) when given,
    or from ``derived`` (the diameter); the other fields keep the class's default."""
    from agents.extension import load_algorithm

    names = {f.name for f in dataclasses.fields(load_algorithm(algorithm).params_class)}
    params = {k: v for k, v in derived.items() if k in names}
    for option in OPTIONS:
        param = option.feeds.get("admm")
        if param in names and option.target == "options" and getattr(opts, option.dest) is not None:
            params[param] = getattr(opts, option.dest)
    return params


def fed_parameters() -> Iterable[tuple[Option, str, str]]:
    """(option, algorithm, parameter) for every feed of the table (for tests and docs)."""
    for option in OPTIONS:
        for algorithm, param in option.feeds.items():
            yield option, algorithm, param


__all__ = [
    "OPTIONS", "Option", "Options", "SECTIONS", "SECTION_OF", "BY_NAME", "PRESETS", "PAPER_GRID", "PAPER_SIGMA",
    "ALGORITHM_CHOICES", "add_arguments", "options_of", "options_from_args", "validate_options",
    "algorithm_params", "toml_value", "param_default", "fed_parameters",
]
