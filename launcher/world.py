"""From a person's options to a fleet: the world, each robot's data, the grid and the graph.

`build_world` is the one place the command-line options turn into a `FleetSpec` (what robots
are told) and a `World` (what only the launcher knows: the true shape, for drawing and IoU).
"""

from __future__ import annotations

import secrets
from dataclasses import dataclass, field
from typing import Any

import networkx as nx
import numpy as np
from shapely import Polygon

from agents.ct_admm import CTADMMParams
from agents.spec import FleetSpec, RobotSpec, Timing
from launcher import scenario, topology
from protocol.keys import validate_fleet_id
from protocol.links import LinkFaults


@dataclass
class Options:
    """Everything `simulate`, `launch` and `central` accept (their flags, with their defaults)."""

    shape: str = scenario.DEFAULT_SHAPE
    shape_file: str | None = None
    data: str | None = None
    robots: int = 3
    points: int = 20
    seed: int = 0
    standoff: float = 1.5
    lidar_range: float = 4.0
    offset: float = 0.3
    noise: float = 0.01
    grid: str = "5x3"
    grid_bounds: str | None = None
    sigma: float = 1.0
    C: float | None = None
    topology: str = "complete"
    comm_range: float | None = None
    algorithm: str = "admm"
    rho: float = 15.0
    relax: float = 1.95
    tol: float = 1e-3
    max_rounds: int = 5000
    ct_step: float = 1e-3  # ct-admm: Euler step of the flow (s), the paper's sampling period
    ct_period: float = 1e-2  # ct-admm: communication period T_sp (s)
    ct_stop_time: float = 10.0  # ct-admm: stop time (s)
    faults: LinkFaults = field(default_factory=LinkFaults.none)
    timing: Timing = field(default_factory=Timing)
    fleet_id: str | None = None


@dataclass
class World:
    """What the launcher knows beyond the robots: the truth, for pictures and IoU."""

    shape: Polygon | None
    robots: list[scenario.RobotData]
    grid: np.ndarray
    bounds: tuple[float, float, float, float]
    graph: nx.Graph

    @property
    def points(self) -> np.ndarray:
        return np.vstack([r.points for r in self.robots])

    @property
    def labels(self) -> np.ndarray:
        return np.concatenate([r.labels for r in self.robots])


def _check_positive(value: float, flag: str) -> None:
    if not (np.isfinite(value) and value > 0):
        raise scenario.ScenarioError(f"{flag}: {value!r} must be a positive number")


def build_world(opts: Options) -> tuple[World, FleetSpec]:
    """The scenario and the fleet file of one run; errors are ScenarioError / TopologyError."""
    _check_positive(opts.sigma, "--sigma")
    if opts.C is not None:
        _check_positive(opts.C, "--C")
    _check_positive(opts.rho, "--rho")
    _check_positive(opts.tol, "--tol")
    if not 0 < opts.relax < 2:
        raise scenario.ScenarioError(f"--relax: {opts.relax!r} must be in (0, 2)")
    if opts.max_rounds < 1:
        raise scenario.ScenarioError(f"--max-rounds: {opts.max_rounds!r} must be at least 1")
    nx_, ny_ = scenario.parse_grid(opts.grid)
    if opts.fleet_id is not None:
        try:
            validate_fleet_id(opts.fleet_id)
        except ValueError as exc:
            raise scenario.ScenarioError(f"--fleet-id: {exc}") from None

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
    else:
        shape = scenario.load_polygon_csv(opts.shape_file) if opts.shape_file else scenario.get_shape(opts.shape)
        poses = scenario.place_robots(shape, opts.robots, standoff=opts.standoff)
        robots = scenario.sample_robot_data(
            shape,
            poses,
            points_per_robot=opts.points,
            rng=opts.seed,
            max_range=opts.lidar_range,
            range_noise=opts.noise,
            offset=opts.offset,
        )
    points = np.vstack([r.points for r in robots])
    bounds = scenario.parse_bounds(opts.grid_bounds) if opts.grid_bounds else scenario.default_bounds(points)
    grid = scenario.make_grid(nx_, ny_, bounds)

    ids = [r.id for r in robots]
    positions = None
    if all(r.pose is not None for r in robots):
        positions = np.array([r.pose for r in robots])
    elif opts.topology == "geometric":  # data from a file has no poses: use each robot's data centroid
        positions = np.array([r.points.mean(axis=0) for r in robots])
    graph = topology.build_topology(opts.topology, ids, positions=positions, comm_range=opts.comm_range)
    neighbours = topology.neighbours(graph)

    params: dict[str, Any] = {
        "rho": opts.rho,
        "relax": opts.relax,
        "tol": opts.tol,
        "max_rounds": opts.max_rounds,
        "diameter": max(1, topology.diameter(graph)) if len(ids) > 1 else 0,
    }
    if opts.algorithm == "ct-admm":
        for flag, value in (("--ct-step", opts.ct_step), ("--ct-period", opts.ct_period), ("--ct-stop-time", opts.ct_stop_time)):
            _check_positive(value, flag)
        params.update(ct_step=opts.ct_step, ct_period=opts.ct_period, ct_stop_time=opts.ct_stop_time)
        try:
            CTADMMParams.from_params(params)
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
    return World(shape, robots, grid, bounds, graph), spec
