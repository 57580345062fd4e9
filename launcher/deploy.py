"""The fleet on several hosts: what `shapefleet prepare` hands out and `shapefleet collect` gathers.

`prepare` writes a *fleet folder*::

    fleet.json              the full fleet file (every robot's data): for `collect` (and `launch`)
    world.json              what only the launcher knows: true outline, robot poses, grid bounds,
                            topology -- so `collect` draws and measures exactly as `launch` does
    data.csv                every robot's labelled points (re-runnable with --data)
    robot-<id>/fleet.json   robot <id>'s fleet file: the shared problem, every robot's neighbour
                            list, and robot <id>'s data only (FleetSpec.for_robot)

Each robot host gets its own ``robot-<id>/fleet.json`` (and nothing of the other robots' data),
runs ``shapefleet robot --fleet-file fleet.json --connect tcp/ROUTER:7447 --allow-remote
--result robot-<id>.json`` and sends the result file back. `collect` reads the result files of a
folder, checks they belong to this fleet, and writes result.json and the pictures through the same
code as `launch` (launcher.cli._finish).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from agents.spec import FleetSpec
from launcher import scenario
from launcher.world import World

WORLD_SCHEMA = 1
POLL_S = 0.25  # collect --wait: how often the results folder is looked at


def robot_fleet_file(folder: Path, robot_id: int) -> Path:
    return Path(folder) / f"robot-{int(robot_id)}" / "fleet.json"


def result_file(folder: Path, robot_id: int) -> Path:
    """Where a robot's result is expected in a results folder (the name `launch` uses too)."""
    return Path(folder) / f"robot-{int(robot_id)}.json"


def _write_text_atomic(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text)
    tmp.replace(path)


def world_to_json(world: World, spec: FleetSpec, topology: str | None) -> dict[str, Any]:
    from shapely.geometry import mapping

    return {
        "schema": WORLD_SCHEMA,
        "fleet": spec.fleet,
        "topology": topology,
        "shape": None if world.shape is None else mapping(world.shape),
        "bounds": [float(v) for v in world.bounds],
        "poses": {str(r.id): None if r.pose is None else [float(v) for v in r.pose] for r in world.robots},
    }


def write_prepared(folder: Path, world: World, spec: FleetSpec, *, topology: str | None) -> dict[str, Path]:
    """Write the fleet folder (see the module doc); returns the files by role."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    written = {"fleet": folder / "fleet.json", "world": folder / "world.json"}
    spec.save(written["fleet"])
    _write_text_atomic(written["world"], json.dumps(world_to_json(world, spec, topology)))
    for i in spec.robot_ids:
        path = robot_fleet_file(folder, i)
        path.parent.mkdir(exist_ok=True)
        spec.for_robot(i).save(path)
        written[f"robot-{i}"] = path
    return written


@dataclass
class Prepared:
    """A fleet folder read back: the full fleet file and the world it came from."""

    spec: FleetSpec
    world: World
    topology: str | None


def load_prepared(fleet_file: Path, world_file: Path | None = None) -> Prepared:
    """Read the full fleet file and its ``world.json`` (default: beside the fleet file).

    Without a world file (e.g. the fleet file of a `launch` run) the pictures have no true outline
    and no poses, and the grid region is the data's padded bounding box. ValueError names the file.
    """
    spec = FleetSpec.load(fleet_file)
    if spec.owner is not None:
        raise ValueError(
            f"{fleet_file}: this is robot {spec.owner}'s fleet file (its own data only); "
            "give the full fleet.json that `shapefleet prepare` wrote"
        )
    explicit = world_file is not None
    world_file = Path(world_file) if explicit else Path(fleet_file).with_name("world.json")
    info: dict[str, Any] = {}
    if explicit or world_file.exists():
        try:
            info = json.loads(world_file.read_text())
            if not isinstance(info, dict) or info.get("schema") != WORLD_SCHEMA:
                raise ValueError(f"not a shapefleet world file (schema {WORLD_SCHEMA})")
            if info.get("fleet") != spec.fleet:
                raise ValueError(f"it belongs to fleet {info.get('fleet')!r}, the fleet file to {spec.fleet!r}")
        except OSError as exc:
            raise ValueError(f"{world_file}: cannot read world file ({exc.strerror})") from None
        except ValueError as exc:
            raise ValueError(f"{world_file}: {exc}") from None
    return Prepared(spec, world_from_json(spec, info), info.get("topology"))


def world_from_json(spec: FleetSpec, info: dict[str, Any]) -> World:
    from shapely.geometry import shape as to_shape

    poses = info.get("poses") or {}
    robots = [
        scenario.RobotData(
            i,
            spec.robots[i].points,
            spec.robots[i].labels,
            None if poses.get(str(i)) is None else np.asarray(poses[str(i)], dtype=float),
        )
        for i in spec.robot_ids
    ]
    points = np.vstack([r.points for r in robots])
    bounds = tuple(float(v) for v in info["bounds"]) if info.get("bounds") else scenario.default_bounds(points)
    links = {i: tuple(spec.robots[i].neighbours) for i in spec.robot_ids}
    shape = to_shape(info["shape"]) if info.get("shape") else None
    return World(shape, robots, spec.grid, bounds, links)  # type: ignore[arg-type]


def _read_result(path: Path, spec: FleetSpec, robot_id: int) -> tuple[dict[str, Any] | None, str | None]:
    """(result, None), or (None, why it is not usable yet)."""
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        return None, "missing"
    except (OSError, ValueError) as exc:
        return None, f"unreadable ({exc})"
    if not isinstance(data, dict) or "x" not in data or "gamma" not in data:
        return None, "not a robot result"
    if data.get("fleet") != spec.fleet:
        return None, f"belongs to fleet {data.get('fleet')!r}, not {spec.fleet!r} (an older run?)"
    if int(data.get("id", data.get("robot", -1))) != robot_id:
        return None, f"is robot {data.get('id')}'s result"
    return data, None


def read_results(
    spec: FleetSpec, folder: Path, *, wait_s: float = 0.0, clock: Any = time.monotonic, sleep: Any = time.sleep
) -> tuple[list[dict[str, Any]], dict[int, str]]:
    """The usable result of each robot in ``folder`` (``robot-<id>.json``), sorted by id, and why
    the others are absent. Waits at most ``wait_s`` seconds for all of them to appear."""
    from launcher.fleet import _normalise  # the row `launch` makes of a result file: same code path

    deadline = clock() + max(0.0, wait_s)
    while True:
        found: dict[int, dict[str, Any]] = {}
        absent: dict[int, str] = {}
        for i in spec.robot_ids:
            data, why = _read_result(result_file(folder, i), spec, i)
            if data is None:
                absent[i] = str(why)
            else:
                found[i] = data
        if not absent or clock() >= deadline:
            break
        sleep(min(POLL_S, max(0.0, deadline - clock())))
    return [_normalise(found[i]) for i in sorted(found)], absent
