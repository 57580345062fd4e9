"""Issue 15's sixth held-out set (benchmarks/outlines/heldout6/): the files the next evaluation runs on are
the ones make_outlines.py describes, valid outlines in their unit, and simulate takes them.

No fleet, SVC or emulation runs here (the set is fixed before anything is learned on it): only the
world a `simulate --shape-file X --robots 5 --points 40` would build.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from launcher import scenario as sc
from launcher.cli import _options, parse_args
from launcher.world import build_world
from tests.test_outlines_heldout4 import ROOT, _maker

FOLDER = ROOT / "benchmarks/outlines/heldout6"
#: outline -> (world scale, offset, pairs each of the 5 default robots keeps of the 20 asked). Every robot
#: keeps all 20: each stroke, tail and lobe is thicker than one offset (0.55 m against 0.3, 14 mm against 6),
#: so the inside point past a return square to it stays inside
WORLD = {
    "letter_g": (1.0, 0.3, [20] * 5),
    "digit_8": (1.0, 0.3, [20] * 5),
    "triskelion": (1.0, 0.3, [20] * 5),
    "ratchet_mm": (20.0, 6.0, [20] * 5),
    "dovetail_mm": (20.0, 6.0, [20] * 5),
    "fir_tree_mm": (20.0, 6.0, [20] * 5),
}


def test_the_files_are_what_make_outlines_writes(tmp_path: Path) -> None:
    """Byte for byte: an outline edited by hand (or a maker changed after the set was fixed) fails here."""
    maker = _maker()
    assert [make.__name__ for make, _ in maker.HELDOUT6] == list(WORLD)
    for make, digits in maker.HELDOUT6:
        maker.write(f"{make.__name__}.csv", make(), digits, tmp_path)
    written = {p.name: p.read_bytes() for p in tmp_path.glob("*.csv")}
    assert written == {p.name: p.read_bytes() for p in FOLDER.glob("*.csv")}


@pytest.mark.parametrize("name", list(WORLD))
def test_each_outline_is_one_simple_ring_whose_world_simulate_builds(name: str) -> None:
    """Metres keep the paper's world (scale 1); millimetres get the x20 world (6 mm offsets); the pairs per
    robot pin that no robot loses points, so the data are what a new user's simulate gives."""
    path = FOLDER / f"{name}.csv"
    shape = sc.load_polygon_csv(path)
    assert shape.is_valid and shape.exterior.is_simple and not shape.interiors
    assert 0.3 < shape.area / shape.envelope.area < 0.7  # notches and concavities, not a filled box
    world, spec = build_world(_options(parse_args(
        ["simulate", "--shape-file", str(path), "--robots", "5", "--points", "40"]), fleet_id="heldout6"))
    scale, offset, pairs = WORLD[name]
    assert (world.lengths.scale, world.lengths.offset) == (scale, offset)
    assert spec.algorithm == "autogrid"
    assert [int((r.labels < 0).sum()) for r in world.robots] == pairs
    assert [int((r.labels > 0).sum()) for r in world.robots] == pairs
