"""The world a fleet learns: object shapes, robot poses, simulated LiDAR, data files, the grid.

Everything here is deterministic given its inputs (and a seeded ``rng``), so a scenario can be
rebuilt bit for bit. Bad input (files, flags) raises :class:`ScenarioError` with one message
naming the file and line or the flag; the CLI turns it into exit code 2.

Bounds are always ``(x0, x1, y0, y1)`` -- the order of ``--grid-bounds`` -- never shapely's
``(minx, miny, maxx, maxy)``.

Sizes follow the paper: the Gaussian kernel has sigma = 1, so the built-in objects are about
4 units wide and 2-3 tall, centred (centroid) at the origin, and a 5x3 grid can describe them.

The world's lengths (robot standoff, LiDAR range, label offset, range noise, radio range) follow
the object's size, so an outline in millimetres gives the data of the same outline in metres,
scaled: see :func:`world_lengths` and :data:`REFERENCE_LENGTH`.
"""

from __future__ import annotations

import csv
import dataclasses
import math
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import shapely
from shapely import affinity
from shapely.geometry import Point, Polygon

from agents.kernel import lattice, padded_bounds

# ---------------------------------------------------------------------------------------------
# errors


class ScenarioError(ValueError):
    """Bad scenario input: one message naming the file and line, or the flag, and the problem."""


# ---------------------------------------------------------------------------------------------
# built-in shapes

#: vertices of the smooth built-in outlines: fine enough that the polygon is indistinguishable
#: from the curve at LiDAR offsets (~0.1), coarse enough that ray casting stays fast
_CURVE_VERTICES = 240


def _angles() -> np.ndarray:
    return np.linspace(0.0, 2.0 * np.pi, _CURVE_VERTICES, endpoint=False)


def _bump(t: np.ndarray, centre: float, width: float) -> np.ndarray:
    """A smooth periodic bump in angle: used to press dents into an outline."""
    return np.exp(-((np.angle(np.exp(1j * (t - centre))) / width) ** 2))


def _centred(polygon: Polygon) -> Polygon:
    """Move the centroid to the origin, where robots are placed around it."""
    c = polygon.centroid
    return affinity.translate(polygon, -c.x, -c.y)


def _polar(radius: np.ndarray, sx: float, sy: float) -> Polygon:
    t = _angles()
    return _centred(Polygon(np.column_stack([sx * radius * np.cos(t), sy * radius * np.sin(t)])))


def _blob() -> Polygon:
    """The default: an irregular smooth outline with two dents, like the paper's Fig. 3."""
    t = _angles()
    radius = 1.0 + 0.15 * np.cos(2 * t) + 0.12 * np.cos(3 * t + 0.9) - 0.3 * _bump(t, 1.6, 0.5)
    return _polar(radius, 1.9, 1.5)


def _star() -> Polygon:
    """Five smooth lobes: deep concavities between them, hard for a coarse grid."""
    t = _angles()
    return _polar(1.55 + 0.45 * np.cos(5 * t), 1.0, 1.0)


def _bean() -> Polygon:
    """A kidney: an ellipse bent along an arc, so its inner side is smoothly concave."""
    t = _angles()
    u, v, bend = 2.1 * np.cos(t), 0.95 * np.sin(t), 1.9
    x = (bend - v) * np.sin(u / bend)
    y = (bend - v) * np.cos(u / bend) - bend
    return _centred(Polygon(np.column_stack([x, y])))


def _crescent() -> Polygon:
    """A disc minus an offset disc: a deep concavity and two sharp, thin horns."""
    disc = Point(0.0, 0.0).buffer(1.8, quad_segs=64)
    bite = Point(0.9, 0.0).buffer(1.5, quad_segs=64)
    return _centred(affinity.rotate(disc.difference(bite), 90.0, origin=(0.0, 0.0)))


def _cross() -> Polygon:
    """A plus sign: straight edges and reflex corners."""
    return _centred(
        shapely.union(shapely.box(-2.0, -0.6, 2.0, 0.6), shapely.box(-0.6, -1.5, 0.6, 1.5))
    )


def _ellipse() -> Polygon:
    """The convex baseline."""
    return _polar(np.ones(_CURVE_VERTICES), 2.0, 1.25)


SHAPES: dict[str, Callable[[], Polygon]] = {
    "blob": _blob,
    "star": _star,
    "bean": _bean,
    "kidney": _bean,
    "crescent": _crescent,
    "cross": _cross,
    "ellipse": _ellipse,
}

DEFAULT_SHAPE = "blob"


def shape_names() -> list[str]:
    """Built-in shape names, sorted (for --help and error messages)."""
    return sorted(SHAPES)


def get_shape(name_or_path: str) -> Polygon:
    """A built-in shape by name, or a polygon CSV file (anything ending in .csv or that exists)."""
    if name_or_path in SHAPES:
        return SHAPES[name_or_path]()
    path = Path(name_or_path)
    if name_or_path.strip() and (path.suffix.lower() == ".csv" or path.exists()):  # "" is the folder "."
        return load_polygon_csv(path)
    raise ScenarioError(
        f"--shape: {name_or_path!r} is neither a built-in shape ({', '.join(shape_names())}) "
        "nor a polygon CSV file"
    )


def shape_bounds(shape: Polygon) -> tuple[float, float, float, float]:
    """The shape's bounding box as (x0, x1, y0, y1)."""
    minx, miny, maxx, maxy = shape.bounds
    return (float(minx), float(maxx), float(miny), float(maxy))


# ---------------------------------------------------------------------------------------------
# world lengths: the simulated world scales with the object

#: the object size the paper's world lengths below were chosen for: the built-in shapes are about
#: 4 by 3, a bounding-box diagonal of 5 (measured 4.4 to 5.3)
REFERENCE_LENGTH = 5.0
#: the world's lengths for an object of REFERENCE_LENGTH (today's and the paper's values): key =
#: the flag without dashes
REFERENCE_LENGTHS: dict[str, float] = {
    "standoff": 1.5,  # robot distance from the object's convex hull
    "range": 4.0,  # LiDAR range
    "offset": 0.3,  # labelled points before / past a LiDAR return
    "noise": 0.01,  # standard deviation of the LiDAR range noise
    # radio range of the geometric topology: more than the widest default ring (robots on the hull
    # buffered by the standoff: at most diagonal + 2 standoffs = 7.9 + 3 in a step, see
    # preferred_scale), so robots placed by default are always linked, every pair of them
    "comm-range": 12.0,
}
#: the 1-2-5 series of preferred numbers: log10 of the geometric midpoints between its steps
_STEPS = ((math.log10(math.sqrt(2.0)), 1), (0.5, 2), (math.log10(math.sqrt(50.0)), 5))


def preferred_scale(ratio: float) -> float:
    """`ratio` rounded (in log scale) to the 1-2-5 series: ..., 0.5, 1, 2, 5, 10, 20, ...

    Why round: every built-in shape and every outline in this repository (diagonals 3.6 to 5.3)
    lands on exactly 1, so they keep today's data bit for bit, with no special case for built-in
    shapes; an outline x10^k lands on exactly 10^k times the same step, so the same outline in
    metres and millimetres gets lengths exactly x1000 apart, in round numbers of its unit. Within a
    step an object is at most a factor sqrt(2.5) smaller or larger than the reference object.
    """
    if not (math.isfinite(ratio) and ratio > 0):
        raise ScenarioError(f"preferred_scale needs a positive finite ratio, got {ratio!r}")
    exponent = math.log10(ratio)
    decade = math.floor(exponent)
    fraction = exponent - decade
    step = next((step for bound, step in _STEPS if fraction < bound), 10)
    return step * 10.0**decade if decade >= 0 else step / 10.0 ** (-decade)


@dataclass(frozen=True)
class WorldLengths:
    """The lengths of one run's world, in the outline's unit, and where they come from.

    ``length`` is the object's characteristic length (the diagonal of the bounding box of the
    outline, or of a data file's points; ``basis`` says which) and ``scale`` the
    :func:`preferred_scale` of ``length / REFERENCE_LENGTH``: every default is its reference value
    times ``scale``. ``given`` names the flags the person gave (kept as given, in the outline's
    unit). A length the run does not use is None (the LiDAR's with a data file, the radio range
    outside the geometric topology).
    """

    length: float
    basis: str
    scale: float
    standoff: float | None
    lidar_range: float | None
    offset: float | None
    noise: float | None
    comm_range: float | None
    given: tuple[str, ...] = ()

    def as_dict(self) -> dict[str, object]:
        """The ``world`` object of result.json (docs/result-schema.md): the fields in their order,
        ``lidar_range`` under its flag's name ``range``, ``given`` as a list."""
        row = {"range" if f.name == "lidar_range" else f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        return {**row, "given": list(self.given)}


def characteristic_length(shape: Polygon | None = None, points: np.ndarray | None = None) -> float:
    """The size the world's default lengths follow: the diagonal of the bounding box of the
    outline if one is given, else of the points (a data file)."""
    if shape is not None:
        minx, miny, maxx, maxy = shape.bounds
    elif points is not None and len(points):
        points = np.asarray(points, dtype=np.float64)
        (minx, miny), (maxx, maxy) = points.min(axis=0), points.max(axis=0)
    else:
        raise ScenarioError("characteristic_length needs an outline or points")
    return float(math.hypot(maxx - minx, maxy - miny))


def world_lengths(
    length: float,
    basis: str,
    *,
    standoff: float | None = None,
    lidar_range: float | None = None,
    offset: float | None = None,
    noise: float | None = None,
    comm_range: float | None = None,
    lidar: bool = True,
    radio: bool = True,
) -> WorldLengths:
    """The lengths of a world whose object has characteristic `length`: each one given, or its
    reference value times ``preferred_scale(length / REFERENCE_LENGTH)``.

    ``lidar=False`` (a data file) and ``radio=False`` (a topology without radio range) leave those
    lengths None. A flag given is kept, in the outline's unit.
    """
    given = {"standoff": standoff, "range": lidar_range, "offset": offset, "noise": noise, "comm-range": comm_range}
    used = {"standoff": lidar, "range": lidar, "offset": lidar, "noise": lidar, "comm-range": radio}
    if not (math.isfinite(length) and length >= 0):
        raise ScenarioError(f"characteristic length {length!r} must be a finite, non-negative number")
    scale = preferred_scale(length / REFERENCE_LENGTH) if length > 0 else 1.0
    values: dict[str, float | None] = {}
    for key, value in given.items():
        if not used[key]:
            values[key] = None
        elif value is not None:
            values[key] = float(value)
        elif length > 0:
            values[key] = REFERENCE_LENGTHS[key] * scale
        else:  # all the data in one point: nothing to scale from
            raise ScenarioError(f"--{key}: the data has no extent to scale a default from; give --{key}")
    return WorldLengths(
        length=float(length),
        basis=basis,
        scale=scale,
        standoff=values["standoff"],
        lidar_range=values["range"],
        offset=values["offset"],
        noise=values["noise"],
        comm_range=values["comm-range"],
        given=tuple(k for k, v in given.items() if v is not None and used[k]),
    )


# ---------------------------------------------------------------------------------------------
# CSV helpers


def _open_rows(path: Path) -> tuple[list[tuple[int, list[str]]], str]:
    """Non-blank rows of a CSV file with their line numbers; the file's display name."""
    name = str(path)
    try:
        with open(path, newline="", encoding="utf-8-sig") as handle:
            reader = csv.reader(handle)
            rows = [(reader.line_num, row) for row in reader if any(cell.strip() for cell in row)]
    except FileNotFoundError:
        raise ScenarioError(f"{name}: no such file") from None
    except IsADirectoryError:
        raise ScenarioError(f"{name}: is a directory, not a CSV file") from None
    except UnicodeDecodeError:
        raise ScenarioError(f"{name}: not a UTF-8 text file") from None
    except csv.Error as exc:
        raise ScenarioError(f"{name} line {reader.line_num}: not valid CSV ({exc})") from None
    except OSError as exc:
        raise ScenarioError(f"{name}: cannot read ({exc.strerror or exc})") from None
    return rows, name


def _check_header(name: str, rows: list[tuple[int, list[str]]], expected: list[str]) -> None:
    want = ",".join(expected)
    if not rows:
        raise ScenarioError(f"{name}: empty file, expected the header '{want}' and data rows")
    line, header = rows[0]
    if [cell.strip() for cell in header] != expected:
        raise ScenarioError(
            f"{name} line {line}: header is {','.join(header)!r}, expected '{want}'"
        )


def _check_width(name: str, line: int, row: list[str], expected: list[str]) -> None:
    if len(row) != len(expected):
        want = ",".join(expected)
        raise ScenarioError(
            f"{name} line {line}: {len(row)} fields, expected {len(expected)} ({want})"
        )


#: coordinates past this are a unit mistake, and their squares would overflow in geometry
MAX_COORDINATE = 1e9


def _finite(text: str, where: str) -> float:
    """A finite float, or a ScenarioError saying ``where`` (a flag's part, a file's field) and why."""
    try:
        value = float(text)
    except ValueError:
        value = None
    if value is None or not math.isfinite(value):
        raise ScenarioError(f"{where} is {text.strip()!r}, {'not a number' if value is None else 'must be finite'}")
    return value


def _number(name: str, line: int, field: str, text: str) -> float:
    """A finite float, or a ScenarioError naming file, line and field."""
    value = _finite(text, f"{name} line {line}: {field}")
    if abs(value) > MAX_COORDINATE:
        raise ScenarioError(
            f"{name} line {line}: {field} is {text.strip()!r}, "
            f"beyond +-{MAX_COORDINATE:g} (wrong units?)"
        )
    return value


# ---------------------------------------------------------------------------------------------
# polygon files


def load_polygon_csv(path: str | Path) -> Polygon:
    """An object outline from a CSV file: header ``x,y``, one vertex a row, in order around it.

    A closing vertex equal to the first is allowed. The outline must be a simple polygon with
    area: the learned classifier is judged against it, so it has to have a clear inside.
    """
    rows, name = _open_rows(Path(path))
    expected = ["x", "y"]
    _check_header(name, rows, expected)
    vertices: list[tuple[float, float]] = []
    lines: list[int] = []
    for line, row in rows[1:]:
        _check_width(name, line, row, expected)
        vertex = (_number(name, line, "x", row[0]), _number(name, line, "y", row[1]))
        if not vertices or vertex != vertices[-1]:  # a repeated vertex adds no edge
            vertices.append(vertex)
            lines.append(line)
    while len(vertices) > 1 and vertices[0] == vertices[-1]:  # the optional closing vertex
        vertices.pop()
        lines.pop()
    distinct = len(set(vertices))
    if distinct < 3:
        raise ScenarioError(f"{name}: {distinct} distinct vertices, a polygon needs at least 3")
    coords = np.asarray(vertices)
    if shapely.MultiPoint(coords).convex_hull.geom_type != "Polygon":  # a segment: collinear
        raise ScenarioError(f"{name}: zero area, all {len(vertices)} vertices lie on one line")
    polygon = Polygon(coords)
    if not polygon.is_valid:
        raise ScenarioError(_self_intersection_message(name, coords, lines))
    return polygon


def _self_intersection_message(name: str, coords: np.ndarray, lines: list[int]) -> str:
    """Say where the outline crosses itself, by the file lines of two edges that meet.

    With repeated vertices removed and at least 4 vertices (a triangle is valid unless flat),
    an invalid ring has two non-adjacent edges that meet; the GEOS reason is the fallback for
    the degenerate coordinates (~1e-300) where GEOS's robust predicates and ours disagree.
    """
    advice = "list the vertices in order around the outline"
    n = len(coords)
    edges = shapely.linestrings(np.stack([coords, np.roll(coords, -1, axis=0)], axis=1))
    with np.errstate(all="ignore"):  # subnormal coordinates make GEOS divide by ~0; harmless
        for i in range(n - 2):
            later = np.arange(i + 2, n - 1 if i == 0 else n)  # edge n-1 is adjacent to edge 0
            for j in later[shapely.intersects(edges[i], edges[later])].tolist():
                meeting = shapely.intersection(edges[i], edges[j])
                if meeting.is_empty:
                    continue
                at = meeting.representative_point()
                return (
                    f"{name}: the outline is self-intersecting: the edge from line {lines[i]} "
                    f"to line {lines[i + 1]} meets the edge from line {lines[j]} to line "
                    f"{lines[(j + 1) % n]} at ({at.x:.6g}, {at.y:.6g}); {advice}"
                )
        reason = shapely.is_valid_reason(Polygon(coords))
    return f"{name}: the outline is self-intersecting ({reason}); {advice}"


# ---------------------------------------------------------------------------------------------
# robots and their data


@dataclass(eq=False)
class RobotData:
    """One robot's labelled points: +1 outside the object, -1 inside; pose None if unknown."""

    id: int
    points: np.ndarray
    labels: np.ndarray
    pose: np.ndarray | None = None

    def __post_init__(self) -> None:
        points = np.asarray(self.points, dtype=np.float64)
        labels = np.asarray(self.labels)
        if points.ndim != 2 or points.shape[1] != 2 or not np.all(np.isfinite(points)):
            raise ScenarioError(
                f"robot {self.id}: points must be an (n, 2) array of finite numbers"
            )
        if labels.shape != (len(points),):
            raise ScenarioError(
                f"robot {self.id}: {len(points)} points but labels of shape {labels.shape}"
            )
        if not np.all(np.isin(labels, (-1, 1))):
            raise ScenarioError(f"robot {self.id}: labels must be -1 (inside) or +1 (outside)")
        self.points = points
        self.labels = labels.astype(np.int64)
        if self.pose is not None:
            self.pose = _as_pose(self.pose)


def _as_pose(pose: np.ndarray) -> np.ndarray:
    pose = np.asarray(pose, dtype=np.float64)
    if pose.shape != (2,) or not np.all(np.isfinite(pose)):
        raise ScenarioError(f"a pose must be two finite numbers (x, y), got {pose.tolist()!r}")
    return pose


def _positive_int(value: object, message: str) -> int:
    """value as an int if it is a positive integer (not a bool), else ScenarioError(message)."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ScenarioError(message)
    return int(value)


def place_robots(shape: Polygon, n: int, *, standoff: float = 1.5) -> np.ndarray:
    """n robot poses, evenly spaced in angle around the centroid, robot 0 due east (+x).

    Each robot sits `standoff` outside the object's convex hull along its bearing: the hull
    (unlike the object) is crossed exactly once by every ray from the centroid, so every robot
    is at least `standoff` from the outline, whatever the concavities.
    """
    n = _positive_int(n, f"--robots: {n!r} is not a positive number of robots")
    if not (math.isfinite(standoff) and standoff > 0):
        raise ScenarioError(f"--standoff: {standoff!r} must be a positive distance")
    centre = np.array([shape.centroid.x, shape.centroid.y])
    ring = shape.convex_hull.buffer(standoff, quad_segs=32).exterior
    minx, miny, maxx, maxy = shape.bounds
    # rays from the centroid long enough to cross the ring whatever the shape
    reach = 2.0 * (math.hypot(maxx - minx, maxy - miny) + standoff)
    bearing = 2.0 * np.pi * np.arange(n) / n
    direction = np.column_stack([np.cos(bearing), np.sin(bearing)])
    rays = shapely.linestrings(
        np.stack([np.broadcast_to(centre, (n, 2)), centre + reach * direction], axis=1)
    )
    coords, index = shapely.get_coordinates(shapely.intersection(rays, ring), return_index=True)
    distance = np.full(n, -np.inf)
    np.maximum.at(distance, index, np.hypot(*(coords - centre).T))
    return centre + distance[:, None] * direction


def simulate_lidar(
    shape: Polygon, pose: np.ndarray, *, rng: np.random.Generator | int, **lidar: float
) -> tuple[np.ndarray, np.ndarray]:
    """Scan the object from `pose`; every return becomes an outside (+1) / inside (-1) pair.

    Rays are cast with shapely; the first boundary crossing is the return, measured with
    Gaussian range noise and dropped beyond `max_range`. The +1 point lies `offset` before the
    return along the ray, the -1 point `offset` past it. A pair whose points are not really on
    their sides of the true outline (thin horns, grazing rays, noise larger than the offset)
    is dropped, so every label is right. With fov < 360 the sensor faces the centroid.
    ``lidar``: the sensor's settings, by their names in `_scan` (max_range, angular_res_deg,
    fov_deg, range_noise, offset), each defaulting as there.
    Returns points (2k, 2) and labels (2k,), pairs consecutive, in ray order.
    """
    points, labels, _, _ = _scan(shape, pose, rng=rng, **lidar)
    return points, labels


def _scan(
    shape: Polygon,
    pose: np.ndarray,
    *,
    max_range: float = 4.0,
    angular_res_deg: float = 1.0,
    fov_deg: float = 360.0,
    range_noise: float = 0.01,
    offset: float = 0.1,
    rng: np.random.Generator | int,
) -> tuple[np.ndarray, np.ndarray, int, np.ndarray]:
    """simulate_lidar, how many rays returned within range (kept pairs or not), and each kept
    pair's ray as (direction x, direction y, measured range) rows, in pair order."""
    pose = _as_pose(pose)
    for flag, value, ok, need in (
        ("--range", max_range, max_range > 0, "a positive distance"),
        ("angular_res_deg", angular_res_deg, 0 < angular_res_deg <= 360, "in (0, 360]"),
        ("fov_deg", fov_deg, 0 < fov_deg <= 360, "in (0, 360]"),
        ("--noise", range_noise, range_noise >= 0, "a non-negative standard deviation"),
        ("--offset", offset, offset > 0, "a positive distance"),
    ):
        if not (math.isfinite(value) and ok):
            raise ScenarioError(f"{flag}: {value!r} must be {need}")
    if shape.intersects(Point(pose)):
        raise ScenarioError(f"pose ({pose[0]:.3g}, {pose[1]:.3g}) is on or inside the object")
    rng = np.random.default_rng(rng)

    if fov_deg >= 360.0:
        bearing = np.deg2rad(np.arange(0.0, 360.0, angular_res_deg))
    else:
        heading = math.atan2(shape.centroid.y - pose[1], shape.centroid.x - pose[0])
        count = math.floor(fov_deg / angular_res_deg + 1e-9) + 1
        bearing = heading + np.deg2rad(np.linspace(-fov_deg / 2, fov_deg / 2, count))
    direction = np.column_stack([np.cos(bearing), np.sin(bearing)])
    k = len(bearing)
    rays = shapely.linestrings(
        np.stack([np.broadcast_to(pose, (k, 2)), pose + max_range * direction], axis=1)
    )
    coords, index = shapely.get_coordinates(
        shapely.intersection(rays, shape.boundary), return_index=True
    )
    true_range = np.full(k, np.inf)
    np.minimum.at(true_range, index, np.hypot(*(coords - pose).T))
    measured = true_range + rng.normal(0.0, range_noise, size=k)
    hit = measured <= max_range  # misses stay inf; noise can push a far return out of range
    outside = pose + (measured[hit] - offset)[:, None] * direction[hit]
    inside = pose + (measured[hit] + offset)[:, None] * direction[hit]
    good = ~shapely.intersects_xy(shape, outside[:, 0], outside[:, 1]) & shapely.contains_xy(
        shape, inside[:, 0], inside[:, 1]
    )
    points = np.stack([outside[good], inside[good]], axis=1).reshape(-1, 2)
    labels = np.tile(np.array([1, -1], dtype=np.int64), int(good.sum()))
    rays_kept = np.column_stack([direction[hit][good], measured[hit][good]])
    return points, labels, int(hit.sum()), rays_kept


def sample_robot_data(
    shape: Polygon,
    poses: np.ndarray,
    *,
    points_per_robot: int = 20,
    rng: np.random.Generator | int,
    free_space: int = 0,
    **lidar_kwargs: float,
) -> list[RobotData]:
    """Scan from every pose and keep `points_per_robot` points per robot (robot ids 0..n-1).

    Whole pairs are kept, evenly spaced over the robot's returns, so the points spread along
    the part of the outline it sees; an odd count drops the last pair's inside point. A robot
    with fewer returns keeps them all. One generator serves all robots in order, so an int
    seed gives different noise per robot and the same scenario every run.
    """
    points_per_robot = _positive_int(
        points_per_robot, f"--points: {points_per_robot!r} is not a positive number of points"
    )
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 2 or poses.shape[1] != 2:
        raise ScenarioError(f"poses must be an (n, 2) array, got shape {poses.shape}")
    if not np.all(np.isfinite(poses)):
        raise ScenarioError(
            f"robot {int(np.argmax(~np.isfinite(poses).all(axis=1)))}: pose is not finite"
        )
    rng = np.random.default_rng(rng)
    pairs_wanted = (points_per_robot + 1) // 2
    robots = []
    for robot_id, pose in enumerate(poses):
        points, labels, returns, rays = _scan(shape, pose, rng=rng, **lidar_kwargs)
        pairs = len(points) // 2
        if pairs == 0 and returns:  # it sees the object, but no pair straddles the outline
            offset, noise = lidar_kwargs.get("offset", 0.1), lidar_kwargs.get("range_noise", 0.01)
            raise ScenarioError(
                f"robot {robot_id} at ({pose[0]:.3g}, {pose[1]:.3g}) sees the object ({returns} LiDAR returns) "
                f"but none gives a correctly labelled pair: the object is thinner than 2 x --offset "
                f"{offset:.3g} where it looks, or --noise {noise:.3g} swamps the offset; lower --offset"
            )
        if pairs == 0:
            raise ScenarioError(
                f"robot {robot_id} at ({pose[0]:.3g}, {pose[1]:.3g}) sees no part of the object; "
                f"move it closer (--standoff) or raise the LiDAR range (--range, "
                f"{lidar_kwargs.get('max_range', 4.0):.3g} here)"
            )
        chosen = np.floor(np.linspace(0, pairs - 1, min(pairs, pairs_wanted)) + 0.5).astype(int)
        rows = (2 * chosen[:, None] + np.array([0, 1])).reshape(-1)[:points_per_robot]
        points, labels = points[rows], labels[rows]
        if free_space > 0:
            free = free_space_samples(
                shape, pose, rays[chosen], free_space, offset=lidar_kwargs.get("offset", 0.1)
            )
            points = np.vstack([points, free])
            labels = np.concatenate([labels, np.ones(len(free), dtype=np.int64)])
        robots.append(RobotData(id=robot_id, points=points, labels=labels, pose=pose.copy()))
    return robots


#: free-space samples lie at least this many label offsets before a LiDAR return: beyond the
#: pair's own outside point (1 offset), so they never crowd the outline the pairs describe
FREE_MIN_GAP = 2.0
#: ... and at most this share of the way from there back to the robot
FREE_REACH = 0.5
#: the golden ratio's fractional part: spreads the samples' gaps evenly over successive rays
_GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0


def free_space_samples(
    shape: Polygon, pose: np.ndarray, rays: np.ndarray, per_ray: int, *, offset: float
) -> np.ndarray:
    """Outside (+1) points along LiDAR rays: a ray certifies free space from the robot to its return.

    `rays` are (direction x, direction y, measured range) rows. Sample k of ray i lies a gap
    g = offset * (FREE_MIN_GAP + u (r / offset - FREE_MIN_GAP) FREE_REACH) before the return,
    u = frac((per_ray i + k + 1) golden ratio): a deterministic, scale-free spread (lengths in
    units of the label offset and the range) that needs no random numbers, so the scan's noise
    is the same with or without them. A sample the truth puts inside the object (range noise
    far beyond the offset) is dropped, as simulate_lidar drops a wrong pair.
    """
    pose = _as_pose(pose)
    if per_ray < 1 or len(rays) == 0:
        return np.zeros((0, 2))
    index = np.arange(len(rays) * per_ray)
    ray = rays[index // per_ray]
    u = np.mod((index + 1) * _GOLDEN, 1.0)
    room = np.maximum(ray[:, 2] / offset - FREE_MIN_GAP, 0.0)
    gap = offset * (FREE_MIN_GAP + u * room * FREE_REACH)
    points = pose + (ray[:, 2] - gap)[:, None] * ray[:, :2]
    keep = (ray[:, 2] - gap > 0) & ~shapely.intersects_xy(shape, points[:, 0], points[:, 1])
    return points[keep]


# ---------------------------------------------------------------------------------------------
# data files

_DATA_HEADER = ["robot", "x", "y", "label"]
_LABEL_TEXT = {"1": 1, "+1": 1, "-1": -1}


def load_data_csv(path: str | Path) -> list[RobotData]:
    """Robots' labelled points from a CSV file with header ``robot,x,y,label``.

    Robot ids are non-negative integers, labels the integers -1 (inside) or +1 (outside),
    coordinates finite. Rows may come in any order; robots are returned sorted by id with
    their points in file order, and no pose (a data file records what was seen, not where from).
    """
    rows, name = _open_rows(Path(path))
    _check_header(name, rows, _DATA_HEADER)
    if len(rows) == 1:
        raise ScenarioError(f"{name}: no data rows after the header")
    grouped: dict[int, tuple[list[tuple[float, float]], list[int]]] = {}
    for line, row in rows[1:]:
        _check_width(name, line, row, _DATA_HEADER)
        robot_text = row[0].strip()
        if not re.fullmatch(r"[0-9]+", robot_text):
            raise ScenarioError(
                f"{name} line {line}: robot is {robot_text!r}, not a non-negative integer id"
            )
        x = _number(name, line, "x", row[1])
        y = _number(name, line, "y", row[2])
        label = _LABEL_TEXT.get(row[3].strip())
        if label is None:
            raise ScenarioError(
                f"{name} line {line}: label is {row[3].strip()!r}, "
                "must be +1 (outside) or -1 (inside)"
            )
        points, labels = grouped.setdefault(int(robot_text), ([], []))
        points.append((x, y))
        labels.append(label)
    kinds = {label for _, labels in grouped.values() for label in labels}
    if len(kinds) == 1:  # every function positive (or negative) everywhere fits: no outline to learn
        only = "+1 (outside)" if kinds == {1} else "-1 (inside)"
        count = sum(len(labels) for _, labels in grouped.values())
        raise ScenarioError(f"{name}: all {count} points are labelled {only}; an outline needs points of both labels")
    return [
        RobotData(id=robot_id, points=np.array(points, dtype=np.float64), labels=np.array(labels))
        for robot_id, (points, labels) in sorted(grouped.items())
    ]


def write_data_csv(path: str | Path, robots: list[RobotData]) -> None:
    """Write robots' points in the :func:`load_data_csv` format, floats as repr (bit-exact)."""
    try:
        with open(path, "w", newline="", encoding="utf-8") as handle:
            writer = csv.writer(handle, lineterminator="\n")
            writer.writerow(_DATA_HEADER)
            for robot in robots:
                for (x, y), label in zip(robot.points, robot.labels, strict=True):
                    writer.writerow([robot.id, repr(float(x)), repr(float(y)), int(label)])
    except OSError as exc:
        raise ScenarioError(f"{path}: cannot write ({exc.strerror or exc})") from None


# ---------------------------------------------------------------------------------------------
# grid

#: more grid points per axis than this makes the M x M kernel matrices and the frames too big
MAX_GRID_PER_AXIS = 100


def parse_grid(text: str) -> tuple[int, int]:
    """'5x3' -> (5, 3): grid points along x and along y."""
    match = re.fullmatch(r"\s*([0-9]+)\s*[xX]\s*([0-9]+)\s*", text)
    if not match:
        raise ScenarioError(f"--grid: {text!r} is not NXxNY, e.g. 5x3")
    nx, ny = int(match.group(1)), int(match.group(2))
    for axis, count in (("x", nx), ("y", ny)):
        if not 1 <= count <= MAX_GRID_PER_AXIS:
            raise ScenarioError(
                f"--grid: {text!r} has {count} points along {axis}, "
                f"must be 1 to {MAX_GRID_PER_AXIS}"
            )
    return nx, ny


def parse_bounds(text: str) -> tuple[float, float, float, float]:
    """'x0,x1,y0,y1' -> (x0, x1, y0, y1) with x0 < x1 and y0 < y1."""
    parts = text.split(",")
    if len(parts) != 4:
        raise ScenarioError(f"--grid-bounds: {text!r} is not x0,x1,y0,y1, e.g. -2.5,2.5,-1.5,1.5")
    x0, x1, y0, y1 = (_finite(part, f"--grid-bounds: {label}") for label, part in zip(("x0", "x1", "y0", "y1"), parts))
    if not x0 < x1:
        raise ScenarioError(f"--grid-bounds: x0 = {x0:g} must be less than x1 = {x1:g}")
    if not y0 < y1:
        raise ScenarioError(f"--grid-bounds: y0 = {y0:g} must be less than y1 = {y1:g}")
    return x0, x1, y0, y1


#: smallest padding per side of default_bounds, so data on a line still gets a 2-D box; a world
#: length like the others (REFERENCE_LENGTHS): times the world's scale
MIN_PAD = 0.1


def default_bounds(points: np.ndarray, pad: float = 0.15, *, scale: float = 1.0) -> tuple[float, float, float, float]:
    """The data's bounding box widened on each side by `pad` times its size, at least MIN_PAD
    times `scale` (WorldLengths.scale: the same box for the same data in any unit)."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 2 or len(points) == 0:
        raise ScenarioError(
            f"default_bounds needs an (n, 2) array of points, got shape {points.shape}"
        )
    if not np.all(np.isfinite(points)) or not (math.isfinite(pad) and pad >= 0):
        raise ScenarioError("default_bounds needs finite points and a non-negative pad")
    if not (math.isfinite(scale) and scale > 0):
        raise ScenarioError(f"default_bounds needs a positive scale, got {scale!r}")
    return padded_bounds(points, pad, MIN_PAD * scale)


def make_grid(nx: int, ny: int, bounds: tuple[float, float, float, float]) -> np.ndarray:
    """nx*ny grid points at the centres of an nx-by-ny split of `bounds`, row-major.

    Cell centres (not corners) keep every point strictly inside the region, the lattice the
    paper draws, and make a 1-wide axis sit in the middle. Point j*nx + i is (x_i, y_j): x
    varies fastest, rows go up in y.
    """
    nx = _positive_int(nx, f"--grid: {nx!r} points along x is not a positive integer")
    ny = _positive_int(ny, f"--grid: {ny!r} points along y is not a positive integer")
    return lattice(nx, ny, _check_bounds(bounds))


def _check_bounds(bounds: tuple[float, float, float, float]) -> tuple[float, float, float, float]:
    try:
        x0, x1, y0, y1 = (float(b) for b in bounds)
    except (TypeError, ValueError):
        raise ScenarioError(
            f"bounds must be four numbers (x0, x1, y0, y1), got {bounds!r}"
        ) from None
    if not (all(map(math.isfinite, (x0, x1, y0, y1))) and x0 < x1 and y0 < y1):
        raise ScenarioError(f"bounds {bounds!r} must be finite with x0 < x1 and y0 < y1")
    return x0, x1, y0, y1


#: points per side of the IoU raster (`iou_on_raster`): result.json's ``iou`` is measured on it
IOU_RESOLUTION = 200


def iou_on_raster(
    true_shape: Polygon,
    inside: Callable[[np.ndarray], np.ndarray],
    bounds: tuple[float, float, float, float],
    resolution: int = IOU_RESOLUTION,
) -> float:
    """Intersection over union of the true interior and {x : inside(x)} on a raster of `bounds`.

    `inside` gets all raster points at once as an (m, 2) array (make_grid's order: a
    (resolution, resolution) raster, rows in y) and returns m booleans. Both sets empty counts as a
    perfect match (1.0).
    """
    resolution = _positive_int(resolution, f"resolution {resolution!r} is not a positive integer")
    points = make_grid(resolution, resolution, bounds)
    truth = shapely.contains_xy(true_shape, points[:, 0], points[:, 1])
    predicted = np.asarray(inside(points))
    if predicted.shape != truth.shape:
        raise ScenarioError(
            f"inside() returned shape {predicted.shape} for {len(points)} raster points, "
            f"expected ({len(points)},)"
        )
    predicted = predicted.astype(bool)
    union = int(np.count_nonzero(truth | predicted))
    if union == 0:
        return 1.0
    return int(np.count_nonzero(truth & predicted)) / union
