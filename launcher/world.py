"""From a person's options to a fleet: the world, each robot's data, the grid and the graph.

`build_world` is the one place the command-line options turn into a `FleetSpec` (what robots
are told) and a `World` (what only the launcher knows: the true shape, for drawing and IoU).

Grid and sigma are automatic by default: with neither given, `algorithm="auto"` runs the fleet
that chooses them itself (``autogrid``, agents/autogrid.py). `resolve_options` is the rule:

* ``preset="paper"`` fills grid 5x3 and sigma 1 where not given (the paper's setting);
* ``auto`` is ``admm`` when both grid and sigma are given, else ``autogrid``;
* ``admm`` and ``ct-admm`` need a fixed grid: without grid / sigma they use the paper's;
* ``autogrid`` takes a given grid as its start grid and a given sigma as fixed.

The world's lengths (standoff, range, offset, noise, comm-range) left None follow the object's
size (scenario.world_lengths): the paper's values times the bounding-box diagonal over
scenario.REFERENCE_LENGTH, rounded to the 1-2-5 series (exactly 1 for every built-in shape). The
values chosen are in ``World.lengths`` (result.json ``world``).
"""

from __future__ import annotations

import dataclasses
import secrets
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from shapely import Polygon

from agents.admm import ADMMParams
from agents.autogrid import AutoGridParams
from agents.autogrid_rules import AUTOGRID_MAX_DIAMETER
from agents.ct_admm import CTADMMParams
from agents.extension import ENTRY_POINT_GROUP, load_algorithm
from agents.lsq_model import lidar_pairs
from agents.params import MAX_DIAMETER
from agents.relay_hub import relay_cert_slot, relay_form
from agents.spec import ALGORITHMS, FleetSpec, RobotSpec
from launcher import scenario, topology
from launcher.options import (  # noqa: F401  (re-exported: Options and the presets are the table's)
    ALGORITHM_CHOICES,
    PAPER_GRID,
    PAPER_SIGMA,
    PRESETS,
    Options,
    algorithm_params,
    validate_options,
)
from protocol.frames import MAX_DIM

if TYPE_CHECKING:
    import networkx as nx


#: the autogrid fleet's budget of grid points (AutoGridParams.max_points)
DEFAULT_MAX_GRID_POINTS = AutoGridParams().max_points
#: autogrid's round cap over all its phases when --max-rounds is not given
DEFAULT_MAX_TOTAL_ROUNDS = AutoGridParams().max_total_rounds
#: the model autogrid fits when --model is not given (the least-squares model: docs/autogrid.md)
DEFAULT_MODEL = AutoGridParams().model
#: the admm / ct-admm round cap when --max-rounds is not given (autogrid: its own cap over all phases)
DEFAULT_MAX_ROUNDS = ADMMParams().max_rounds


@dataclass
class World:
    """What the launcher knows beyond the robots: the truth, for pictures and IoU."""

    shape: Polygon | None
    robots: list[scenario.RobotData]
    grid: np.ndarray  # the fixed grid; autogrid: the start grid, or empty (0, 2)
    bounds: tuple[float, float, float, float]  # the region drawn and rastered for IoU
    links: dict[int, tuple[int, ...]]  # each robot's neighbours (launcher/topology.py)
    lengths: scenario.WorldLengths | None = None  # the world's lengths used (None: not known, e.g. collect)
    positions: dict[int, np.ndarray] | None = None  # each robot's position (None: not known)

    @property
    def graph(self) -> nx.Graph:
        """The communication graph as a networkx graph (built on demand: networkx stays off the
        launch path)."""
        return topology.as_graph(self.links, self.positions)

    @property
    def points(self) -> np.ndarray:
        return np.vstack([r.points for r in self.robots])

    @property
    def labels(self) -> np.ndarray:
        return np.concatenate([r.labels for r in self.robots])


def resolve_options(opts: Options) -> Options:
    """The options with the preset applied and the algorithm, grid and sigma settled (module doc).

    The result has ``preset=None`` and a concrete algorithm; grid and sigma are None only for
    autogrid (chosen by the fleet). ScenarioError names a bad --preset / --algorithm.
    """
    grid, sigma = opts.grid, opts.sigma
    if opts.preset is not None:
        if opts.preset not in PRESETS:
            raise scenario.ScenarioError(f"--preset: {opts.preset!r} is not a preset (choose from {', '.join(PRESETS)})")
        preset = PRESETS[opts.preset]
        grid = preset["grid"] if grid is None else grid
        sigma = preset["sigma"] if sigma is None else sigma
    algorithm = opts.algorithm
    if algorithm == "auto":
        algorithm = "admm" if grid is not None and sigma is not None else "autogrid"
    if algorithm not in ALGORITHMS:  # a user's fleet algorithm (agents/extension.py), or a typo
        if ":" not in algorithm and not _is_entry_point(algorithm):
            raise scenario.ScenarioError(f"--algorithm: {algorithm!r} is not one of {', '.join(ALGORITHM_CHOICES)}, "
                                         "a dotted path package.module:ClassName or an installed entry point")
        try:
            load_algorithm(algorithm)
        except ValueError as exc:
            raise scenario.ScenarioError(f"--algorithm: {exc}") from None
    if algorithm != "autogrid":  # a fixed basis: the paper's where not given
        grid = PAPER_GRID if grid is None else grid
        sigma = PAPER_SIGMA if sigma is None else sigma
    return dataclasses.replace(opts, grid=grid, sigma=sigma, algorithm=algorithm, preset=None)


def _is_entry_point(name: str) -> bool:
    import importlib.metadata

    return any(ep.name == name for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP))


def build_world(opts: Options) -> tuple[World, FleetSpec]:
    """The scenario and the fleet file of one run; errors are ScenarioError / TopologyError."""
    opts = resolve_options(opts)
    autogrid = opts.algorithm == "autogrid"
    try:
        validate_options(opts)  # each value's check, from the options table (launcher/options.py)
    except ValueError as exc:
        raise scenario.ScenarioError(str(exc)) from None
    grid_shape = None if opts.grid is None else scenario.parse_grid(opts.grid)
    given_bounds = scenario.parse_bounds(opts.grid_bounds) if opts.grid_bounds else None
    if given_bounds is not None and grid_shape is None:
        raise scenario.ScenarioError(
            "--grid-bounds: places the grid of --grid, and none is given (the automatic grid covers the data "
            "by itself); give --grid too, or --preset paper"
        )

    if opts.data is None and topology.known_diameter(opts.topology, opts.robots) is not None:
        _checked_diameter(opts, opts.robots)  # a ring of 10^4 robots: refused before their data is drawn (20 s)
    shape, robots, lengths = _robots_and_lengths(opts)
    points = np.vstack([r.points for r in robots])
    bounds = given_bounds if given_bounds is not None else scenario.default_bounds(points, scale=lengths.scale)
    grid = np.zeros((0, 2)) if grid_shape is None else scenario.make_grid(*grid_shape, bounds)

    ids = [r.id for r in robots]
    positions = None
    if all(r.pose is not None for r in robots):
        positions = np.array([r.pose for r in robots])
    elif opts.topology == "geometric":  # data from a file has no poses: use each robot's data centroid
        positions = np.array([r.points.mean(axis=0) for r in robots])
    neighbours = topology.links(opts.topology, ids, positions=positions, comm_range=lengths.comm_range)
    diameter = max(1, _checked_diameter(opts, len(ids), neighbours)) if len(ids) > 1 else 0
    params = algorithm_params(opts, opts.algorithm, diameter=diameter)
    if opts.polish and opts.algorithm == "admm":  # written only when asked: other fleets' files stay as they were
        params["polish"] = True
    if opts.certify is not None and opts.algorithm == "admm":  # (likewise)
        params["certify"] = float(opts.certify)
    if opts.algorithm == "ct-admm":
        try:
            CTADMMParams(**params)
        except ValueError as exc:  # e.g. a period that is not a whole number of steps
            raise scenario.ScenarioError(f"--ct-period/--ct-step: {exc}") from None
    spec = FleetSpec(
        fleet=opts.fleet_id or f"run-{secrets.token_hex(4)}",
        algorithm=opts.algorithm,
        sigma=opts.sigma,
        C=opts.C,
        grid=grid,
        robots={
            r.id: RobotSpec(r.id, neighbours[r.id], r.points, np.asarray(r.labels, dtype=int)) for r in robots
        },
        params=params,
        faults=opts.faults,
        seed=opts.seed,
        timing=opts.timing,
    )
    if opts.model == "lsq" and not autogrid:
        raise scenario.ScenarioError(
            f"--model lsq: the model autogrid fits; this run is --algorithm {opts.algorithm} on a fixed grid (for the "
            "least-squares model there: --algorithm lsq)")
    if autogrid and (opts.model or DEFAULT_MODEL) == "lsq":  # (the default model: its refusals name the SVM's flag)
        _check_lsq(opts, robots, svm_fix=SVM_FIX)
        if opts.narrow_ratio is not None and opts.narrow_ratio != 1:
            raise scenario.ScenarioError("--narrow-ratio: the lsq model fits on one level-0 lattice of one width "
                                         f"(no refinement); drop --narrow-ratio, {SVM_FIX}")
        if opts.rho is not None:  # (--rho feeds the SVM model's penalty; the lsq model's is lsq_rho, of another scale)
            raise scenario.ScenarioError("--rho: autogrid's lsq model runs its own penalty (lsq_rho, 1: a least-squares "
                                         f"step's curvature is of another scale than the margin's); drop --rho, {SVM_FIX}")
    if autogrid:
        _check_autogrid(opts, spec)
    if opts.algorithm == "newton" and spec.dim > MAX_DIM:
        raise scenario.ScenarioError(
            f"--grid: {opts.grid} is {len(grid)} points; newton's frames would carry {spec.dim} numbers (the upper "
            f"triangle of a {len(grid) + 1}-square matrix per contribution), more than a frame holds ({MAX_DIM}); "
            "use a coarser --grid or --algorithm admm"
        )
    if opts.algorithm == "lsq":
        _check_lsq(opts, robots)
    if opts.polish:
        _check_polish(opts, spec)
    if opts.certify is not None:
        _check_certify(opts, spec)
    where = None if positions is None else dict(zip(ids, positions))
    return World(shape, robots, grid, bounds, neighbours, lengths, where), spec


def _checked_diameter(opts: Options, n_robots: int, neighbours: dict[int, tuple[int, ...]] | None = None) -> int:
    """The graph's diameter, checked: the round protocol's stop flags reach MAX_DIAMETER hops
    (autogrid's AUTOGRID_MAX_DIAMETER), a sparser fleet could never agree to stop, so it is refused
    before anything runs -- ring, line and complete by their closed form (no graph needed), a
    geometric graph at its first robot that is too far from another."""
    limit = AUTOGRID_MAX_DIAMETER if opts.algorithm == "autogrid" else MAX_DIAMETER
    diameter = topology.known_diameter(opts.topology, n_robots)
    exact = diameter is not None
    if diameter is None:
        assert neighbours is not None, "a geometric graph's diameter needs the graph"
        diameter = topology.diameter(neighbours, beyond=limit)
    if diameter > limit:
        raise topology.TopologyError(
            f"--topology {opts.topology}: the {n_robots} robots' graph has a diameter of {'' if exact else 'at least '}"
            f"{diameter} hops, more than the round protocol's stop flags reach ({limit}); use a denser topology "
            "(complete, or geometric with a larger --comm-range) or fewer robots")
    return diameter


#: what autogrid's lsq refusals suggest: the SVM model, which has a margin (--C, --rho, --narrow-ratio) and fits
#: label-only data
SVM_FIX = "or add --model svm (autogrid's margin model)"


def _check_lsq(opts: Options, robots: list[scenario.RobotData], *, svm_fix: str | None = None) -> None:
    """The least-squares model reads LiDAR pairs and has no margin: a --C, or data without a single
    pair (consecutive +1, -1 rows of one robot), is refused by name instead of fitting labels alone.
    `svm_fix`: autogrid's way out (the SVM model), else the fixed-grid one (--algorithm admm)."""
    if opts.C is not None:
        raise scenario.ScenarioError("--C: the lsq model has no margin (its weight is --lsq-lambda); drop --C"
                                     + (f", {svm_fix}" if svm_fix else ""))
    if not any(len(lidar_pairs(r.labels)) for r in robots):
        source = opts.data if opts.data is not None else "the scan"
        fix = ("add --model svm, which fits label-only data" if svm_fix
               else "use --algorithm admm for labelled points alone")
        raise scenario.ScenarioError(
            f"{source}: no LiDAR pair (a +1 row followed by a -1 row of the same robot) in the data: the lsq model "
            f"fits the returns between pairs; {fix}")


def _check_polish(opts: Options, spec: FleetSpec) -> None:
    """--polish exists for admm's hub form, hard margin, small grids (FleetSpec.polish_refusal says
    why not): say so instead of running without it."""
    if opts.algorithm != "admm":
        raise scenario.ScenarioError(f"--polish: the exact end-game is built for --algorithm admm only (this run: "
                                     f"{opts.algorithm}); give --grid and --sigma, or --preset paper")
    reason = spec.polish_refusal()
    if reason is not None:
        raise scenario.ScenarioError(f"--polish: {reason}")


def _check_certify(opts: Options, spec: FleetSpec) -> None:
    """--certify sets admm's certified stop guard, which exists for the hub form on hard margins
    (docs/algorithm.md, "A certified stop"): a value that would change nothing says so instead."""
    if opts.algorithm != "admm":
        raise scenario.ScenarioError(f"--certify: the certified stop guard is built for --algorithm admm only (this run: "
                                     f"{opts.algorithm}); give --grid and --sigma, or --preset paper")
    if opts.certify == 0:
        return
    if spec.C is not None:
        raise scenario.ScenarioError("--certify: the guard's bound needs a hard margin; drop --C (or give --certify 0)")
    if opts.polish:
        raise scenario.ScenarioError("--certify: with --polish the end-game certifies the stop itself; drop one of them")
    params, dim = spec.algorithm_params, len(spec.grid) + 1
    if spec._hub_form(params):
        return
    if not relay_form(params, spec.graph, dim):
        raise scenario.ScenarioError(
            f"--certify: the guard needs a complete graph (the hub form) or the relay hub (a sparse graph of 3 to 16 "
            f"robots); this graph of {spec.n_robots} robots runs the edge form, which stops by its rule alone "
            "(docs/algorithm.md)")
    if not relay_cert_slot(params, spec.n_robots, dim):
        raise scenario.ScenarioError(
            f"--certify: the relay hub carries the guard's payload only while N (M + 1 + 6) floats fit the frame "
            f"budget; {spec.n_robots} robots on {dim - 1} grid points do not, and stop by the rule alone "
            "(docs/algorithm.md)")


def _robots_and_lengths(opts: Options) -> tuple[Polygon | None, list[scenario.RobotData], scenario.WorldLengths]:
    """Each robot's data (from --data, or LiDAR on the shape) and the world's lengths used."""
    radio = opts.topology == "geometric"
    if opts.data is not None:
        shape = None
        robots = scenario.load_data_csv(opts.data)
        ids = [r.id for r in robots]
        gaps = sorted(set(range(max(ids) + 1)) - set(ids))
        if gaps:
            raise scenario.ScenarioError(
                f"{opts.data}: robot {gaps[0]} has no data (robot ids must run 0..{max(ids)} without gaps; "
                f"the file has {', '.join(map(str, ids))})"
            )
        length = scenario.characteristic_length(points=np.vstack([r.points for r in robots]))
        lengths = scenario.world_lengths(length, "data diagonal", comm_range=opts.comm_range, lidar=False, radio=radio)
    else:
        shape = scenario.load_polygon_csv(opts.shape_file) if opts.shape_file else scenario.get_shape(opts.shape)
        lengths = scenario.world_lengths(
            scenario.characteristic_length(shape), "outline diagonal", standoff=opts.standoff,
            lidar_range=opts.lidar_range, offset=opts.offset, noise=opts.noise, comm_range=opts.comm_range, radio=radio,
        )
        assert lengths.standoff is not None and lengths.lidar_range is not None
        assert lengths.offset is not None and lengths.noise is not None
        poses = scenario.place_robots(shape, opts.robots, standoff=lengths.standoff)
        robots = scenario.sample_robot_data(
            shape,
            poses,
            points_per_robot=opts.points,
            rng=opts.seed,
            max_range=lengths.lidar_range,
            range_noise=lengths.noise,
            offset=lengths.offset,
            free_space=opts.free_space,
        )
    return shape, robots, lengths


def _check_autogrid(opts: Options, spec: FleetSpec) -> None:
    """What AdaptiveGridCore would refuse on the robots, said here in terms of the flags."""
    if len(spec.grid) > opts.max_grid_points:
        raise scenario.ScenarioError(
            f"--grid: {opts.grid} is {len(spec.grid)} start points, more than --max-grid-points {opts.max_grid_points}"
        )
    try:
        params = spec.autogrid_params
    except ValueError as exc:
        raise scenario.ScenarioError(f"autogrid: {exc}") from None
    ids = spec.robot_ids
    if params.validates and max(ids) >= params.tally_slots:
        need = AutoGridParams.points_for_robot_ids(max(ids))
        raise scenario.ScenarioError(
            f"--max-grid-points: {opts.max_grid_points} leaves room for robot ids below {params.tally_slots} in the "
            f"fleet's sigma vote (one tally slot per robot id, in frames sized by max-grid-points); robot {max(ids)} "
            f"needs --max-grid-points {need} or more, or give --sigma"
        )
