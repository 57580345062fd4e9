"""Issue 15's sixth held-out set (benchmarks/outlines/heldout6/): the files the next evaluation runs on are
the ones make_outlines.py describes, valid outlines in their unit, and simulate takes them.

No fleet, SVC or emulation runs here (the set is fixed before anything is learned on it): only the
world a `simulate --shape-file X --robots 5 --points 40` would build.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.test_outlines_heldout4 import ROOT
from tests.test_outlines_heldout5 import (
    assert_folder_is_what_make_outlines_writes,
    assert_one_ring_whose_world_simulate_builds,
)

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
    assert_folder_is_what_make_outlines_writes("HELDOUT6", FOLDER, list(WORLD), tmp_path)


@pytest.mark.parametrize("name", list(WORLD))
def test_each_outline_is_one_simple_ring_whose_world_simulate_builds(name: str) -> None:
    """Metres keep the paper's world (scale 1); millimetres get the x20 world (6 mm offsets); the pairs per
    robot pin that no robot loses points, so the data are what a new user's simulate gives."""
    assert_one_ring_whose_world_simulate_builds(FOLDER / f"{name}.csv", *WORLD[name])
