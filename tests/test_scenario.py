"""The world: shapes, polygon and data files, robot poses, simulated LiDAR, the grid, IoU."""

from __future__ import annotations

import contextlib
import math
import tempfile
from pathlib import Path

import numpy as np
import pytest
import shapely
from hypothesis import given, settings
from hypothesis import strategies as st
from shapely import affinity
from shapely.geometry import Point, Polygon

from launcher import scenario as sc
from launcher.scenario import RobotData, ScenarioError

DATA = Path(__file__).parent / "data"
EXAMPLES = Path(sc.__file__).parent / "shapes"
NON_CONVEX = ["blob", "star", "bean", "kidney", "crescent", "cross"]


def write(tmp_path: Path, text: str | bytes, name: str = "input.csv") -> Path:
    path = tmp_path / name
    if isinstance(text, bytes):
        path.write_bytes(text)
    else:
        path.write_text(text)
    return path


# ------------------------------------------------------------------------------------ shapes


@pytest.mark.parametrize("name", sc.shape_names())
def test_builtin_shapes_are_valid_and_sized_for_sigma_one(name: str) -> None:
    shape = sc.SHAPES[name]()
    assert isinstance(shape, Polygon) and shape.is_valid and shape.area > 0
    x0, x1, y0, y1 = sc.shape_bounds(shape)
    assert 3.0 <= x1 - x0 <= 5.0 and 2.0 <= y1 - y0 <= 4.0
    assert abs(shape.centroid.x) < 1e-9 and abs(shape.centroid.y) < 1e-9


@pytest.mark.parametrize("name", NON_CONVEX)
def test_claimed_non_convex_shapes_are(name: str) -> None:
    shape = sc.SHAPES[name]()
    assert shape.area < 0.99 * shape.convex_hull.area


def test_ellipse_is_convex_and_default_is_complex() -> None:
    ellipse = sc.SHAPES["ellipse"]()
    assert ellipse.area == pytest.approx(ellipse.convex_hull.area, rel=1e-12)
    assert sc.DEFAULT_SHAPE in sc.SHAPES and sc.DEFAULT_SHAPE in NON_CONVEX
    assert {*NON_CONVEX, "ellipse"} <= set(sc.shape_names())
    assert sc.shape_names() == sorted(sc.shape_names())


def test_get_shape_by_name_or_file_and_unknown() -> None:
    assert sc.get_shape("star").equals(sc.SHAPES["star"]())
    assert sc.get_shape(str(DATA / "notch.csv")).area == pytest.approx(6.0 - 1.2 * 3 / 2)
    with pytest.raises(ScenarioError, match=r"--shape: 'stra' .*crescent, cross"):
        sc.get_shape("stra")
    with pytest.raises(ScenarioError, match="no such file"):
        sc.get_shape("missing.csv")


def test_shape_bounds_are_x0_x1_y0_y1() -> None:
    assert sc.shape_bounds(shapely.box(1, 2, 3, 5)) == (1.0, 3.0, 2.0, 5.0)


# ------------------------------------------------------------------------------ polygon CSV


def test_polygon_csv_tolerates_whitespace_and_a_closing_vertex() -> None:
    shape = sc.load_polygon_csv(DATA / "notch.csv")
    assert list(shape.exterior.coords)[:-1] == [(0, 0), (3, 0), (3, 2), (1.5, 0.8), (0, 2)]
    assert shape.area < shape.convex_hull.area


def test_example_shapes_load() -> None:
    examples = sorted(EXAMPLES.glob("*.csv"))
    assert examples
    for path in examples:
        shape = sc.load_polygon_csv(path)
        assert shape.is_valid and shape.area > 0


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("", "empty file"),
        ("a,b\n0,0\n1,0\n0,1\n", "line 1: header is 'a,b', expected 'x,y'"),
        ("0,0\n1,0\n0,1\n", "line 1: header is '0,0', expected 'x,y'"),
        ("x,y\n0,0\n1,0\n0,abc\n", "line 4: y is 'abc', not a number"),
        ("x,y\n0,0\n\n1,0\nnan,1\n", "line 5: x is 'nan', must be finite"),
        ("x,y\n0,0\n1,0\n0,-inf\n", "line 4: y is '-inf', must be finite"),
        ("x,y\n0,0\n1,0,2\n0,1\n", "line 3: 3 fields, expected 2"),
        ("x,y\n0,0\n1,0\n0,0\n1,0\n", "2 distinct vertices, a polygon needs at least 3"),
        ("x,y\n", "0 distinct vertices"),
        ("x,y\n0,0\n1,1\n2,2\n3,3\n", "zero area, all 4 vertices lie on one line"),
        ("x,y\n0,0\n2,0\n1,0\n1,1\n", "self-intersecting"),
        ("x,y\n0,0\n" + "1" * 200_000 + ",0\n", "line 3: not valid CSV"),
    ],
)
def test_polygon_csv_errors_name_file_and_line(tmp_path: Path, text: str, expected: str) -> None:
    path = write(tmp_path, text)
    with pytest.raises(ScenarioError) as info:
        sc.load_polygon_csv(path)
    assert str(path) in str(info.value)
    assert expected in str(info.value)


def test_self_intersection_names_the_crossing_edges() -> None:
    with pytest.raises(ScenarioError) as info:
        sc.load_polygon_csv(DATA / "bowtie.csv")
    message = str(info.value)
    assert "bowtie.csv" in message and "self-intersecting" in message
    assert (
        "edge from line 2 to line 3 meets the edge from line 4 to line 5 at (0.5, 0.5)" in message
    )


def test_polygon_csv_unreadable_files(tmp_path: Path) -> None:
    with pytest.raises(ScenarioError, match=r"nowhere\.csv: no such file"):
        sc.load_polygon_csv(tmp_path / "nowhere.csv")
    with pytest.raises(ScenarioError, match="is a directory"):
        sc.load_polygon_csv(tmp_path)
    with pytest.raises(ScenarioError, match="not a UTF-8 text file"):
        sc.load_polygon_csv(write(tmp_path, b"x,y\n\xff\xfe,\x00\n"))


# ------------------------------------------------------------------------------ robot poses


@pytest.mark.parametrize("name", sc.shape_names())
def test_robots_ring_the_object_at_the_standoff(name: str) -> None:
    shape = sc.SHAPES[name]()
    poses = sc.place_robots(shape, 5, standoff=1.2)
    assert poses.shape == (5, 2)
    np.testing.assert_array_equal(poses, sc.place_robots(shape, 5, standoff=1.2))
    hull = shape.convex_hull
    for pose in poses:
        assert hull.distance(Point(pose)) == pytest.approx(1.2, abs=2e-3)
        assert shape.distance(Point(pose)) >= 1.2 - 2e-3
    bearings = np.arctan2(poses[:, 1], poses[:, 0])  # the centroid is at the origin
    np.testing.assert_allclose(np.unwrap(bearings), 2 * np.pi * np.arange(5) / 5, atol=1e-9)


def test_place_robots_rejects_bad_counts_and_standoffs() -> None:
    shape = sc.SHAPES["ellipse"]()
    for n in (0, -2, 2.5, True):
        with pytest.raises(ScenarioError, match="--robots"):
            sc.place_robots(shape, n)  # type: ignore[arg-type]
    for standoff in (0.0, -1.0, math.nan, math.inf):
        with pytest.raises(ScenarioError, match="--standoff"):
            sc.place_robots(shape, 3, standoff=standoff)


# ----------------------------------------------------------------------------------- LiDAR


def _assert_labels_true(shape: Polygon, points: np.ndarray, labels: np.ndarray) -> None:
    outside = points[labels == 1]
    inside = points[labels == -1]
    assert not shapely.intersects_xy(shape, outside[:, 0], outside[:, 1]).any()
    assert shapely.contains_xy(shape, inside[:, 0], inside[:, 1]).all()


@pytest.mark.parametrize("name", sc.shape_names())
def test_lidar_labels_are_right_for_many_poses_and_seeds(name: str) -> None:
    shape = sc.SHAPES[name]()
    rng = np.random.default_rng(7)
    x0, x1, y0, y1 = sc.shape_bounds(shape)
    poses = list(sc.place_robots(shape, 4, standoff=0.3)) + list(
        sc.place_robots(shape, 3, standoff=2.0)
    )
    while len(poses) < 12:  # random outside poses, some deep in concavities
        pose = rng.uniform([x0 - 1, y0 - 1], [x1 + 1, y1 + 1])
        if not shape.intersects(Point(pose)):
            poses.append(pose)
    total = 0
    for seed, pose in enumerate(poses):
        for noise in (0.0, 0.03, 0.2):
            points, labels = sc.simulate_lidar(
                shape, pose, angular_res_deg=2.0, range_noise=noise, rng=seed
            )
            _assert_labels_true(shape, points, labels)
            np.testing.assert_array_equal(labels, np.tile([1, -1], len(labels) // 2))
            total += len(points)
    assert total > 1000


def test_lidar_pairs_straddle_the_outline_along_the_ray() -> None:
    shape = sc.SHAPES["blob"]()
    pose = np.array([4.0, 0.5])
    points, _ = sc.simulate_lidar(shape, pose, range_noise=0.0, offset=0.1, rng=0)
    outside, inside = points[0::2], points[1::2]
    np.testing.assert_allclose(np.hypot(*(inside - outside).T), 0.2, atol=1e-9)
    to_out, to_in = outside - pose, inside - pose
    np.testing.assert_allclose(
        to_out[:, 0] * to_in[:, 1] - to_out[:, 1] * to_in[:, 0], 0, atol=1e-9
    )
    hits = (outside + inside) / 2
    np.testing.assert_allclose(shapely.distance(shape.boundary, shapely.points(hits)), 0, atol=1e-9)


def test_lidar_honours_the_range_limit() -> None:
    shape = sc.SHAPES["ellipse"]()
    pose = np.array([3.5, 0.0])  # 1.5 from the nearest point, 5.5 from the far side
    for max_range in (1.7, 2.5, 4.0):
        points, _ = sc.simulate_lidar(shape, pose, max_range=max_range, range_noise=0.05, rng=3)
        hits = (points[0::2] + points[1::2]) / 2
        assert len(hits) and np.hypot(*(hits - pose).T).max() <= max_range
    points, labels = sc.simulate_lidar(shape, pose, max_range=1.4, rng=3)
    assert points.shape == (0, 2) and labels.shape == (0,)


def test_lidar_noise_is_seeded() -> None:
    shape = sc.SHAPES["star"]()
    pose = np.array([0.0, -3.5])
    first = sc.simulate_lidar(shape, pose, range_noise=0.02, rng=11)
    again = sc.simulate_lidar(shape, pose, range_noise=0.02, rng=np.random.default_rng(11))
    other = sc.simulate_lidar(shape, pose, range_noise=0.02, rng=12)
    np.testing.assert_array_equal(first[0], again[0])
    np.testing.assert_array_equal(first[1], again[1])
    assert not np.array_equal(first[0], other[0])


def test_lidar_field_of_view_faces_the_object() -> None:
    shape = sc.SHAPES["ellipse"]()
    pose = np.array([0.0, 3.0])
    points, _ = sc.simulate_lidar(shape, pose, fov_deg=40, range_noise=0.0, rng=0)
    off_axis = np.degrees(np.abs(np.arctan2(points[:, 0] - pose[0], pose[1] - points[:, 1])))
    assert len(points) and off_axis.max() <= 20 + 1e-9


def test_lidar_drops_a_ray_that_grazes_an_edge() -> None:
    square = shapely.box(0, 0, 1, 1)
    points, labels = sc.simulate_lidar(square, np.array([-1.0, 0.0]), range_noise=0.0, rng=0)
    _assert_labels_true(square, points, labels)
    assert not np.any(points[:, 1] == 0.0)  # the ray along y = 0 only touches the boundary


def test_lidar_rejects_bad_poses_and_parameters() -> None:
    shape = sc.SHAPES["ellipse"]()
    with pytest.raises(ScenarioError, match="inside the object"):
        sc.simulate_lidar(shape, np.array([0.0, 0.0]), rng=0)
    with pytest.raises(ScenarioError, match="two finite numbers"):
        sc.simulate_lidar(shape, np.array([np.nan, 5.0]), rng=0)
    for kwargs, flag in [
        ({"max_range": 0.0}, "--range"),
        ({"angular_res_deg": -1.0}, "angular_res_deg"),
        ({"fov_deg": 400.0}, "fov_deg"),
        ({"range_noise": -0.1}, "--noise"),
        ({"offset": math.nan}, "--offset"),
    ]:
        with pytest.raises(ScenarioError, match=flag):
            sc.simulate_lidar(shape, np.array([5.0, 0.0]), rng=0, **kwargs)


# ------------------------------------------------------------------------------ robot data


def test_default_scenario_gives_each_robot_balanced_pairs() -> None:
    shape = sc.SHAPES[sc.DEFAULT_SHAPE]()
    poses = sc.place_robots(shape, 3)
    robots = sc.sample_robot_data(shape, poses, rng=0)
    assert [robot.id for robot in robots] == [0, 1, 2]
    for robot, pose in zip(robots, poses, strict=True):
        assert robot.points.shape == (20, 2) and robot.points.dtype == np.float64
        assert (
            np.count_nonzero(robot.labels == 1) == 10 and np.count_nonzero(robot.labels == -1) == 10
        )
        np.testing.assert_array_equal(robot.pose, pose)
        _assert_labels_true(shape, robot.points, robot.labels)
    again = sc.sample_robot_data(shape, poses, rng=0)
    for a, b in zip(robots, again, strict=True):
        np.testing.assert_array_equal(a.points, b.points)


def test_kept_pairs_span_the_whole_scan() -> None:
    shape = sc.SHAPES["crescent"]()
    pose = sc.place_robots(shape, 1)
    (robot,) = sc.sample_robot_data(shape, pose, points_per_robot=7, rng=np.random.default_rng(4))
    points, _ = sc.simulate_lidar(shape, pose[0], rng=np.random.default_rng(4))
    np.testing.assert_array_equal(robot.points[:2], points[:2])  # first pair
    np.testing.assert_array_equal(robot.points[6], points[-2])  # last pair's outside point
    np.testing.assert_array_equal(robot.labels, [1, -1, 1, -1, 1, -1, 1])
    assert all((points == p).all(axis=1).any() for p in robot.points)


def test_a_robot_with_few_returns_keeps_them_all() -> None:
    shape = sc.SHAPES["ellipse"]()
    poses = sc.place_robots(shape, 2)
    robots = sc.sample_robot_data(shape, poses, points_per_robot=10_000, angular_res_deg=5.0, rng=1)
    for robot in robots:
        assert 2 <= len(robot.points) < 10_000 and len(robot.points) % 2 == 0


def test_a_blind_robot_is_named() -> None:
    shape = sc.SHAPES["ellipse"]()
    poses = np.array([[3.0, 0.0], [0.0, 9.0]])
    with pytest.raises(ScenarioError, match=r"robot 1 at \(0, 9\) .*--standoff.*--range"):
        sc.sample_robot_data(shape, poses, rng=0)
    with pytest.raises(ScenarioError, match="--points"):
        sc.sample_robot_data(shape, poses[:1], points_per_robot=0, rng=0)


def test_a_robot_that_sees_only_a_sliver_thinner_than_the_offset_is_told_to_lower_it() -> None:
    sliver = shapely.box(-2.0, -0.05, 2.0, 0.05)  # 0.1 thick: no pair with offset 0.3 straddles it
    with pytest.raises(ScenarioError, match=r"robot 0 .*sees the object \(\d+ LiDAR returns\).*lower --offset"):
        sc.sample_robot_data(sliver, np.array([[0.0, 1.0]]), rng=0, offset=0.3)
    assert len(sc.sample_robot_data(sliver, np.array([[0.0, 1.0]]), rng=0, offset=0.02, range_noise=0.001)[0].points)


def test_robot_data_validates_itself() -> None:
    with pytest.raises(ScenarioError, match="finite"):
        RobotData(id=1, points=np.array([[0.0, np.inf]]), labels=np.array([1]))
    with pytest.raises(ScenarioError, match="two finite numbers"):
        RobotData(id=1, points=np.zeros((1, 2)), labels=np.array([1]), pose=np.zeros(3))
    with pytest.raises(ScenarioError, match=r"robot 3: 2 points but labels of shape \(1,\)"):
        RobotData(id=3, points=np.zeros((2, 2)), labels=np.array([1]))
    with pytest.raises(ScenarioError, match="robot 0: labels must be -1"):
        RobotData(id=0, points=np.zeros((1, 2)), labels=np.array([0]))


# -------------------------------------------------------------------------------- data CSV


def test_data_csv_round_trip_is_bit_exact(tmp_path: Path) -> None:
    shape = sc.SHAPES["star"]()
    robots = sc.sample_robot_data(shape, sc.place_robots(shape, 4), rng=5)
    tricky = np.array([[-0.0, 5e-324], [0.1 + 0.2, 1e9], [-1 / 3, 2.0**-1074 * 3]])
    robots.append(RobotData(id=9, points=tricky, labels=np.array([1, -1, 1])))
    path = tmp_path / "data.csv"
    sc.write_data_csv(path, robots)
    loaded = sc.load_data_csv(path)
    assert [r.id for r in loaded] == [0, 1, 2, 3, 9]
    for original, copy in zip(robots, loaded, strict=True):
        assert copy.points.tobytes() == original.points.tobytes()
        np.testing.assert_array_equal(copy.labels, original.labels)
        assert copy.pose is None
    sc.write_data_csv(tmp_path / "again.csv", loaded)
    assert (tmp_path / "again.csv").read_bytes() == path.read_bytes()


def test_data_csv_groups_rows_by_robot_in_file_order() -> None:
    robots = sc.load_data_csv(DATA / "robots.csv")
    assert [r.id for r in robots] == [0, 1, 2]
    np.testing.assert_array_equal(robots[0].points, [[-1.0, 0.0], [1e-3, 2.5]])
    np.testing.assert_array_equal(robots[0].labels, [-1, 1])
    np.testing.assert_array_equal(robots[2].points, [[0.5, 0.25], [0.75, -0.5]])
    np.testing.assert_array_equal(robots[2].labels, [1, -1])
    assert robots[1].labels.tolist() == [1]


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("", "empty file"),
        ("robot,x,y\n0,1,2\n", "line 1: header is 'robot,x,y', expected 'robot,x,y,label'"),
        ("robot,x,y,label\n", "no data rows"),
        ("robot,x,y,label\n\n\n", "no data rows"),
        ("robot,x,y,label\n0,1,2\n", "line 2: 3 fields, expected 4"),
        (
            "robot,x,y,label\n0,1,2,1\n-1,1,2,1\n",
            "line 3: robot is '-1', not a non-negative integer",
        ),
        ("robot,x,y,label\n1.5,1,2,1\n", "line 2: robot is '1.5'"),
        ("robot,x,y,label\nr2,1,2,1\n", "line 2: robot is 'r2'"),
        ("robot,x,y,label\n0,abc,2,1\n", "line 2: x is 'abc', not a number"),
        ("robot,x,y,label\n0,1,nan,1\n", "line 2: y is 'nan', must be finite"),
        ("robot,x,y,label\n0,-2e9,0,1\n", "line 2: x is '-2e9', beyond +-1e+09"),
        ("robot,x,y,label\n0,1,2,0\n", "line 2: label is '0', must be +1 (outside) or -1 (inside)"),
        ("robot,x,y,label\n0,1,2,1.0\n", "line 2: label is '1.0'"),
        ("robot,x,y,label\n0,1,2,\n", "line 2: label is ''"),
        ("robot,x,y,label\n0,1,2,-2\n", "line 2: label is '-2'"),
    ],
)
def test_data_csv_errors_name_file_and_line(tmp_path: Path, text: str, expected: str) -> None:
    path = write(tmp_path, text, "data.csv")
    with pytest.raises(ScenarioError) as info:
        sc.load_data_csv(path)
    assert str(path) in str(info.value)
    assert expected in str(info.value)


def test_data_csv_unwritable_and_unreadable(tmp_path: Path) -> None:
    robot = RobotData(id=0, points=np.zeros((1, 2)), labels=np.array([1]))
    with pytest.raises(ScenarioError, match="cannot write"):
        sc.write_data_csv(tmp_path / "no" / "such" / "dir.csv", [robot])
    with pytest.raises(ScenarioError, match="no such file"):
        sc.load_data_csv(tmp_path / "gone.csv")


# ------------------------------------------------------------------------------------ grid


@pytest.mark.parametrize(
    ("text", "expected"), [("5x3", (5, 3)), ("5X3", (5, 3)), (" 1x100 ", (1, 100))]
)
def test_parse_grid(text: str, expected: tuple[int, int]) -> None:
    assert sc.parse_grid(text) == expected


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("5by3", "--grid: '5by3' is not NXxNY, e.g. 5x3"),
        ("", "is not NXxNY"),
        ("5.5x3", "is not NXxNY"),
        ("-1x3", "is not NXxNY"),
        ("x3", "is not NXxNY"),
        ("0x3", "--grid: '0x3' has 0 points along x, must be 1 to 100"),
        ("5x0", "0 points along y"),
        ("101x3", "101 points along x"),
    ],
)
def test_parse_grid_errors(text: str, expected: str) -> None:
    with pytest.raises(ScenarioError) as info:
        sc.parse_grid(text)
    assert expected in str(info.value)


def test_parse_bounds() -> None:
    assert sc.parse_bounds("-2.5, 2.5,-1.5,1.5") == (-2.5, 2.5, -1.5, 1.5)
    for text, expected in [
        ("1,2,3", "is not x0,x1,y0,y1"),
        ("a,1,0,1", "x0 is 'a', not a number"),
        ("0,1,nan,1", "y0 is 'nan', must be finite"),
        ("0,inf,0,1", "x1 is 'inf', must be finite"),
        ("1,0,0,1", "x0 = 1 must be less than x1 = 0"),
        ("0,1,1,1", "y0 = 1 must be less than y1 = 1"),
    ]:
        with pytest.raises(ScenarioError) as info:
            sc.parse_bounds(text)
        assert str(info.value).startswith("--grid-bounds: ") and expected in str(info.value)


def test_default_bounds_pads_the_data() -> None:
    points = np.array([[0.0, 0.0], [10.0, 2.0]])
    assert sc.default_bounds(points) == pytest.approx((-1.5, 11.5, -0.3, 2.3))
    assert sc.default_bounds(points, pad=0.0) == pytest.approx((-0.1, 10.1, -0.1, 2.1))
    assert sc.default_bounds(np.array([[1.0, 1.0]])) == pytest.approx((0.9, 1.1, 0.9, 1.1))
    line = np.array([[0.0, 0.0], [5.0, 0.0]])  # the smallest pad is a world length: it scales
    assert sc.default_bounds(line) == pytest.approx((-0.75, 5.75, -0.1, 0.1))
    assert sc.default_bounds(1e-3 * line, scale=1e-3) == pytest.approx((-0.75e-3, 5.75e-3, -0.1e-3, 0.1e-3), rel=1e-12)
    with pytest.raises(ScenarioError):
        sc.default_bounds(np.zeros((0, 2)))
    with pytest.raises(ScenarioError):
        sc.default_bounds(points, pad=-1.0)


def test_make_grid_is_row_major_at_cell_centres() -> None:
    grid = sc.make_grid(4, 2, (0.0, 4.0, -1.0, 1.0))
    np.testing.assert_allclose(
        grid,
        [
            [0.5, -0.5],
            [1.5, -0.5],
            [2.5, -0.5],
            [3.5, -0.5],
            [0.5, 0.5],
            [1.5, 0.5],
            [2.5, 0.5],
            [3.5, 0.5],
        ],
    )
    np.testing.assert_allclose(sc.make_grid(1, 1, (0.0, 2.0, 0.0, 6.0)), [[1.0, 3.0]])
    with pytest.raises(ScenarioError, match="--grid"):
        sc.make_grid(0, 3, (0.0, 1.0, 0.0, 1.0))
    with pytest.raises(ScenarioError, match="x0 < x1"):
        sc.make_grid(2, 2, (1.0, 0.0, 0.0, 1.0))
    with pytest.raises(ScenarioError, match="four numbers"):
        sc.make_grid(2, 2, (0.0, 1.0, 0.0))  # type: ignore[arg-type]


# ------------------------------------------------------------------------------------- IoU


def test_iou_of_a_shape_with_itself_a_disjoint_one_and_a_half() -> None:
    shape = sc.SHAPES["crescent"]()
    far = affinity.translate(shape, 10.0, 0.0)
    bounds = (-3.0, 14.0, -3.0, 3.0)

    def inside_of(polygon: Polygon):
        return lambda p: shapely.contains_xy(polygon, p[:, 0], p[:, 1])

    assert sc.iou_on_raster(shape, inside_of(shape), bounds) == 1.0
    assert sc.iou_on_raster(shape, inside_of(far), bounds) == 0.0
    box = shapely.box(0.0, 0.0, 2.0, 1.0)
    assert (
        sc.iou_on_raster(box, lambda p: p[:, 0] < 1.0, (0.0, 2.0, 0.0, 1.0), resolution=50) == 0.5
    )
    assert sc.iou_on_raster(far, lambda p: np.zeros(len(p), bool), (-1.0, 1.0, -1.0, 1.0)) == 1.0


def test_iou_rejects_a_wrong_sized_answer() -> None:
    with pytest.raises(ScenarioError, match="inside"):
        sc.iou_on_raster(shapely.box(0, 0, 1, 1), lambda p: np.zeros(3, bool), (0.0, 1.0, 0.0, 1.0))


# ------------------------------------------------------------ no other exception escapes


def _load_text(loader, text: str):
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "fuzz.csv"
        path.write_text(text)
        try:
            return loader(path)
        except ScenarioError as exc:
            assert str(path) in str(exc)
            return None


CSV_ALPHABET = st.sampled_from(list('0123456789-+.,xyrobotlabeinf \n"e'))


@settings(max_examples=150, deadline=None)
@given(st.text(CSV_ALPHABET, max_size=60) | st.text(max_size=30))
def test_any_text_is_a_polygon_or_a_scenario_error(text: str) -> None:
    shape = _load_text(sc.load_polygon_csv, text)
    assert shape is None or (shape.is_valid and shape.area > 0)


@settings(max_examples=150, deadline=None)
@given(st.lists(st.tuples(st.integers(-3, 3), st.integers(-3, 3)), max_size=7))
def test_any_vertex_list_is_a_valid_polygon_or_a_scenario_error(
    vertices: list[tuple[int, int]],
) -> None:
    text = "x,y\n" + "".join(f"{x},{y}\n" for x, y in vertices)
    shape = _load_text(sc.load_polygon_csv, text)
    assert shape is None or (shape.is_valid and shape.area > 0)


@settings(max_examples=150, deadline=None)
@given(st.text(CSV_ALPHABET, max_size=60).map(lambda body: "robot,x,y,label\n" + body))
def test_any_data_text_is_robots_or_a_scenario_error(text: str) -> None:
    robots = _load_text(sc.load_data_csv, text)
    assert robots is None or all(len(r.points) == len(r.labels) > 0 for r in robots)


@settings(max_examples=200, deadline=None)
@given(st.text(max_size=20))
def test_flag_parsers_only_raise_scenario_errors(text: str) -> None:
    for parse in (sc.parse_grid, sc.parse_bounds):
        with contextlib.suppress(ScenarioError):
            parse(text)


# -- free space along LiDAR rays (issue 15) ------------------------------------------------------


@pytest.mark.parametrize("name", ["crescent", "cross"])
def test_free_space_samples_lie_outside_on_their_rays_before_the_return(name: str) -> None:
    """Every free-space sample is +1, truly outside, on the segment from the robot to one of the
    robot's kept returns and at least FREE_MIN_GAP offsets before it; the pairs come first and
    are exactly the data without free space (the scan's noise does not depend on them)."""
    shape = sc.SHAPES[name]()
    poses = sc.place_robots(shape, 3)
    plain = sc.sample_robot_data(shape, poses, rng=3, offset=0.3)
    free = sc.sample_robot_data(shape, poses, rng=3, offset=0.3, free_space=2)
    for a, b, pose in zip(plain, free, poses, strict=True):
        n = len(a.points)
        np.testing.assert_array_equal(b.points[:n], a.points)
        np.testing.assert_array_equal(b.labels[:n], a.labels)
        extra, labels = b.points[n:], b.labels[n:]
        assert len(extra) == 2 * (n // 2) and np.all(labels == 1)  # two per kept ray: none dropped here
        _assert_labels_true(shape, extra, labels)
        returns = a.points[0::2] - pose  # each pair's outside point lies on its ray
        unit = returns / np.hypot(*returns.T)[:, None]
        for p in extra:
            d = p - pose
            along = unit @ d  # distance along each kept ray
            across = np.abs(unit[:, 0] * d[1] - unit[:, 1] * d[0])  # distance off it
            ray = int(np.argmin(across - (along > 0)))
            assert across[ray] < 1e-9 * np.hypot(*d) and along[ray] > 0
            hit = np.hypot(*returns[ray]) + 0.3  # the measured return: the outside point is 1 offset before it
            assert along[ray] <= hit - sc.FREE_MIN_GAP * 0.3 + 1e-9


def test_free_space_samples_are_scale_free() -> None:
    """The outline x1000 with every length x1000 gives the same data x1000 (to round-off)."""
    shape = sc.SHAPES["bean"]()
    big = affinity.scale(shape, 1000.0, 1000.0, origin=(0, 0))
    poses = sc.place_robots(shape, 2)
    small = sc.sample_robot_data(shape, poses, rng=1, offset=0.3, range_noise=0.01, free_space=1)
    large = sc.sample_robot_data(big, poses * 1000.0, rng=1, offset=300.0, range_noise=10.0, max_range=4000.0,
                                 free_space=1)
    for a, b in zip(small, large, strict=True):
        np.testing.assert_array_equal(a.labels, b.labels)
        np.testing.assert_allclose(b.points, 1000.0 * a.points, rtol=1e-9, atol=1e-6)
