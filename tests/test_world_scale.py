"""Any unit, any size: the simulated world's lengths follow the outline it is given (issue 19).

Standoff, LiDAR range, label offset, range noise and the geometric radio range default to the
paper's values times the outline's bounding-box diagonal over scenario.REFERENCE_LENGTH, rounded
to the 1-2-5 series: the built-in shapes (and the repository's outline files) keep today's data
bit for bit, and an outline drawn in millimetres gives the data of the same outline in metres,
x1000, and the same learned shape.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from launcher import scenario as sc
from launcher.cli import _autogrid_references
from launcher.report import build_autogrid_result
from launcher.simulate import simulate_fleet
from launcher.world import Options, build_world

ROOT = Path(__file__).resolve().parents[1]
CSV_OUTLINES = [
    ROOT / "launcher/shapes/l_block.csv",
    ROOT / "tests/data/notch.csv",
    ROOT / "benchmarks/data/bracket_mm.csv",
]
REF = sc.REFERENCE_LENGTHS
PAPER_FLAGS = {"standoff": REF["standoff"], "lidar_range": REF["range"], "offset": REF["offset"], "noise": REF["noise"]}


def scaled_csv(source: Path, factor: float, folder: Path) -> Path:
    """The outline of `source` with every coordinate times `factor` (written bit-exact)."""
    vertices = np.loadtxt(source, delimiter=",", skiprows=1)
    path = folder / f"{source.stem}_x{factor:g}.csv"
    path.write_text("x,y\n" + "".join(f"{float(x) * factor!r},{float(y) * factor!r}\n" for x, y in vertices))
    return path


def world_of(**kwargs):
    kwargs.setdefault("fleet_id", "scale")
    kwargs.setdefault("preset", "paper")  # the world is the point here, not the learning
    return build_world(Options(**kwargs))


# -- the built-in shapes keep today's world --------------------------------------------------
@pytest.mark.parametrize("name", sc.shape_names())
def test_builtin_shapes_keep_the_paper_lengths_and_data_bit_for_bit(name: str) -> None:
    world, _ = world_of(shape=name, robots=4, topology="geometric")
    lengths = world.lengths
    assert (lengths.standoff, lengths.lidar_range, lengths.offset, lengths.noise, lengths.comm_range) == (
        1.5, 4.0, 0.3, 0.01, 12.0,
    )
    assert lengths.scale == 1.0 and lengths.basis == "outline diagonal" and lengths.given == ()
    assert 4.0 < lengths.length < 5.5
    explicit, _ = world_of(shape=name, robots=4, topology="geometric", comm_range=12.0, **PAPER_FLAGS)
    assert world.points.tobytes() == explicit.points.tobytes()
    np.testing.assert_array_equal(world.labels, explicit.labels)
    assert sorted(world.graph.edges) == sorted(explicit.graph.edges)
    assert explicit.lengths.given == ("standoff", "range", "offset", "noise", "comm-range")


def test_bracket_mm_gets_the_millimetre_lengths_and_its_metre_twin_the_paper_ones(tmp_path: Path) -> None:
    """bracket_mm.csv is 4000 x 3000 (diagonal 5000): x1000 the reference, exactly."""
    mm, _ = world_of(shape_file=str(CSV_OUTLINES[2]))
    assert (mm.lengths.standoff, mm.lengths.lidar_range, mm.lengths.offset, mm.lengths.noise) == (1500.0, 4000.0, 300.0, 10.0)
    assert mm.lengths.basis == "outline diagonal" and mm.lengths.length == 5000.0 and mm.lengths.comm_range is None
    metres, _ = world_of(shape_file=str(scaled_csv(CSV_OUTLINES[2], 1e-3, tmp_path)))
    assert (metres.lengths.standoff, metres.lengths.lidar_range, metres.lengths.offset, metres.lengths.noise) == (
        pytest.approx(1.5, rel=1e-15), pytest.approx(4.0, rel=1e-15), pytest.approx(0.3, rel=1e-15), pytest.approx(0.01, rel=1e-15),
    )


# -- the same outline in any unit gives the same data, scaled -----------------------------------
@pytest.mark.parametrize("source", CSV_OUTLINES, ids=lambda p: p.name)
@pytest.mark.parametrize("factor", [1e-3, 1e3])
def test_an_outline_in_another_unit_gives_the_same_data_scaled(tmp_path: Path, source: Path, factor: float) -> None:
    base, spec = world_of(shape_file=str(source), robots=5, topology="geometric")
    other, other_spec = world_of(shape_file=str(scaled_csv(source, factor, tmp_path)), robots=5, topology="geometric")
    for key in ("length", "standoff", "lidar_range", "offset", "noise", "comm_range"):
        assert getattr(other.lengths, key) == pytest.approx(factor * getattr(base.lengths, key), rel=1e-12), key
    np.testing.assert_array_equal(other.labels, base.labels)
    np.testing.assert_allclose(other.points, factor * base.points, rtol=1e-9, atol=1e-9 * factor)
    np.testing.assert_allclose(np.array(other.bounds), factor * np.array(base.bounds), rtol=1e-9, atol=1e-9 * factor)
    np.testing.assert_allclose(other_spec.grid, factor * spec.grid, rtol=1e-9, atol=1e-9 * factor)
    assert sorted(other.graph.edges) == sorted(base.graph.edges)


def test_explicit_flags_keep_their_meaning_in_the_outline_unit(tmp_path: Path) -> None:
    mm = str(scaled_csv(ROOT / "launcher/shapes/l_block.csv", 1000.0, tmp_path))
    # a hair's breadth in mm, as asked (without noise: the default 10 mm of noise would swamp it)
    world, _ = world_of(shape_file=mm, offset=0.3, noise=0.0, comm_range=7000.0, topology="geometric")
    assert (world.lengths.offset, world.lengths.noise, world.lengths.comm_range) == (0.3, 0.0, 7000.0)
    assert world.lengths.standoff == pytest.approx(1500.0, rel=1e-12)
    assert world.lengths.given == ("offset", "noise", "comm-range")
    pairs = world.robots[0].points.reshape(-1, 2, 2)
    assert np.allclose(np.hypot(*(pairs[:, 1] - pairs[:, 0]).T), 0.6, rtol=1e-6)
    # yesterday's defaults given in a millimetre world mean millimetres: each robot sees a 4 mm patch
    tiny, _ = world_of(shape_file=mm, **PAPER_FLAGS)
    for robot in tiny.robots:
        assert np.hypot(*(robot.points - robot.pose).T).max() <= 4.0 + 0.3 + 0.1


def test_a_data_file_scales_the_radio_range_by_its_points(tmp_path: Path) -> None:
    world, _ = world_of(shape_file=str(CSV_OUTLINES[2]), robots=4)
    data = tmp_path / "data.csv"
    sc.write_data_csv(data, world.robots)
    again, _ = world_of(data=str(data), topology="geometric")
    span = world.points.max(axis=0) - world.points.min(axis=0)
    assert again.lengths.basis == "data diagonal" and again.lengths.length == pytest.approx(np.hypot(*span), rel=1e-12)
    assert np.hypot(*span) > 5000 and again.lengths.scale == 1000.0 and again.lengths.comm_range == 12000.0
    assert again.lengths.standoff is None and again.lengths.noise is None  # no LiDAR simulated
    single = tmp_path / "one.csv"
    single.write_text("robot,x,y,label\n0,1,1,1\n1,1,1,-1\n")
    with pytest.raises(sc.ScenarioError, match="--comm-range: the data has no extent"):
        world_of(data=str(single), topology="geometric")


# -- robots placed by default always see the object --------------------------------------------
OUTLINES = [("builtin", name) for name in sc.shape_names() if name != "kidney"] + [
    ("csv", path) for path in CSV_OUTLINES
]


@pytest.mark.parametrize("kind, source", OUTLINES, ids=lambda v: getattr(v, "name", v))
def test_robots_placed_by_default_see_the_object_at_any_size(tmp_path: Path, kind: str, source) -> None:
    """No 'sees no part of the object' for 1..16 robots, the outline at ten sizes spread over a
    decade (every place within the 1-2-5 steps) and in millimetres; and the default radio range
    links every pair of robots placed by default (the geometric topology is complete)."""
    if kind == "builtin":
        shape = sc.get_shape(source)
        source = tmp_path / f"{source}.csv"
        source.write_text("x,y\n" + "".join(f"{x!r},{y!r}\n" for x, y in shape.exterior.coords))
    unit = 1e-3 if source.name == "bracket_mm.csv" else 1.0
    for factor in [unit * 10 ** (i / 10) for i in range(10)] + [1e3 * unit]:
        outline = str(scaled_csv(source, factor, tmp_path))
        for robots in (1, 2, 3, 5, 8, 16):
            world, _ = world_of(shape_file=outline, robots=robots, topology="geometric", free_space=0)  # the pairs
            assert all(len(r.points) == 20 for r in world.robots), (outline, robots)
            assert world.graph.number_of_edges() == robots * (robots - 1) // 2, (outline, robots)


COMPLEX = sorted((ROOT / "benchmarks/outlines").glob("*.csv"))


@pytest.mark.parametrize("source", COMPLEX, ids=lambda p: p.name)
def test_complex_outlines_placed_by_default_see_the_object(tmp_path: Path, source: Path) -> None:
    """Issue 15's outlines (notches, thin parts, metres and millimetres) as a new user runs them:
    every robot placed by default sees the object and gets its points, in the file's unit and x1000
    or /1000, and the geometric topology links every pair. A robot may keep fewer points than asked
    where pairs straddling a part thinner than 2 offsets are dropped (the wrench's 30 mm handle
    with its 15 mm offset, 8 robots: 38), never none; 5 robots (issue 15's runs) get all 40."""
    assert len(COMPLEX) >= 5
    factor = 1e-3 if source.stem.endswith("_mm") else 1e3
    for outline in (str(source), str(scaled_csv(source, factor, tmp_path))):
        for robots in (1, 3, 5, 8):
            world, _ = world_of(shape_file=outline, robots=robots, points=40, topology="geometric", free_space=0)
            assert all(len(r.points) >= (40 if robots <= 5 else 30) for r in world.robots), (outline, robots)
            assert world.graph.number_of_edges() == robots * (robots - 1) // 2, (outline, robots)


def test_preferred_scale_is_the_1_2_5_series_and_exact_across_decades() -> None:
    assert [sc.preferred_scale(r) for r in (0.7, 0.72, 1.0, 1.41, 1.42, 3.16, 3.17, 7.07, 7.08)] == [
        0.5, 1.0, 1.0, 1.0, 2.0, 2.0, 5.0, 5.0, 10.0,
    ]
    for ratio in (0.72, 1.063, 1.5, 4.0, 6.9):
        base = sc.preferred_scale(ratio)
        assert sc.preferred_scale(1000 * ratio) == 1000 * base
        assert sc.preferred_scale(ratio / 1000) == pytest.approx(base / 1000, rel=1e-15)
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(sc.ScenarioError):
            sc.preferred_scale(bad)


# -- the whole run: same learned shape in metres and millimetres -------------------------------
def _autogrid_run(outline: str) -> dict:
    """An autogrid simulate with default world and learning flags (3 robots, 20 points each)."""
    world, spec = build_world(Options(shape_file=outline, robots=3, points=20, fleet_id="scale"))
    outcome = simulate_fleet(spec)
    extra: dict = {}
    references = _autogrid_references(world, spec, outcome.robots, extra)
    return build_autogrid_result(world, outcome.robots, references, wall_s=0.0, extra=extra)


@pytest.fixture(scope="module")
def metres_and_mm(tmp_path_factory) -> tuple[dict, dict]:
    folder = tmp_path_factory.mktemp("outlines")
    source = ROOT / "tests/data/notch.csv"
    return _autogrid_run(str(source)), _autogrid_run(str(scaled_csv(source, 1000.0, folder)))


def test_metres_and_millimetres_learn_the_same_shape(metres_and_mm: tuple[dict, dict]) -> None:
    m, mm = metres_and_mm
    assert m["robots_agree"] and mm["robots_agree"]
    iou_m, iou_mm = m["metrics"]["iou"], mm["metrics"]["iou"]
    print(f"IoU metres {iou_m:.6f}, millimetres {iou_mm:.6f}; sigma {m['sigma']:.6g} / {mm['sigma']:.6g}; "
          f"grids {[h['size'] for h in m['grid_history']]}; rounds {m['rounds']} / {mm['rounds']}")
    assert iou_m > 0.7  # a shape was learned (measured 0.764 on the notch: 3 robots, 20 points)
    assert abs(iou_mm - iou_m) <= 0.005
    assert m["converged"] and mm["converged"] and mm["margin"] == m["margin"]
    assert mm["sigma"] == pytest.approx(1000.0 * m["sigma"], rel=1e-9)
    # the grids: the same size and nodes (exactly the same grid, scaled, and the same rounds: the next test)
    ours = {tuple(np.round(np.asarray(p) / m["world"]["scale"], 6)) for p in m["grid"]}
    theirs = {tuple(np.round(np.asarray(p) / mm["world"]["scale"], 6)) for p in mm["grid"]}
    assert len(ours) == len(theirs) and len(ours & theirs) >= 0.99 * len(ours)
    assert [h["size"] for h in mm["grid_history"]] == [h["size"] for h in m["grid_history"]]
    assert mm["world"]["scale"] == pytest.approx(1000.0 * m["world"]["scale"], rel=1e-12)
    assert mm["world"]["offset"] == pytest.approx(300.0 * m["world"]["scale"], rel=1e-12)


def test_metres_and_millimetres_same_grid_and_rounds(metres_and_mm: tuple[dict, dict]) -> None:
    m, mm = metres_and_mm
    assert mm["rounds"] == m["rounds"]
    np.testing.assert_allclose(np.array(mm["grid"]), 1000.0 * np.array(m["grid"]), rtol=1e-6, atol=1e-6 * 1000)


def test_the_summary_and_result_json_say_the_chosen_lengths(tmp_path: Path) -> None:
    out = tmp_path / "run"
    proc = subprocess.run(
        [sys.executable, "-m", "launcher.cli", "simulate", "--shape-file", str(CSV_OUTLINES[2]), "--preset", "paper",
         "--sigma", "1000", "--noise", "5", "--out", str(out)],
        capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    world = json.loads((out / "result.json").read_text())["world"]
    assert world == {
        "length": 5000.0, "basis": "outline diagonal", "scale": 1000.0, "standoff": 1500.0, "range": 4000.0,
        "offset": 300.0, "noise": 5.0, "comm_range": None, "given": ["noise"],
    }
    assert "world: standoff 1500*, range 4000*, offset 300*, noise 5 " in " ".join(proc.stdout.split())
