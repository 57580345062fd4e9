"""Writes the complex test outlines of issue 15 (CSV, header x,y, one vertex a row).

Each is built from boxes, strokes and discs with shapely and rounded to 1e-4 of its unit, so the
files are the data (this script only says how they were made):

- letter_e.csv     (m)  an E: three arms, two notches 0.7 wide and 2.1 deep
- digit_3.csv      (m)  a 3 drawn with a 0.55-wide stroke: two deep concavities on its left
- wrench_mm.csv    (mm) an open-end wrench: a 210 mm handle, a jaw with a 32 mm slot
- gear_mm.csv      (mm) an 8-tooth gear: teeth 14 mm wide, 18 mm long, gaps ~25 mm at the rim
- fork_mm.csv      (mm) a fork of a machine part: three tines 40 mm wide, two slots 30 mm wide

    .venv/bin/python benchmarks/outlines/make_outlines.py
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import shapely
from shapely.geometry import LineString, Point, Polygon

HERE = Path(__file__).resolve().parent


def letter_e() -> Polygon:
    body = shapely.box(0.0, 0.0, 3.0, 4.0)
    notch = 0.7
    arm = (4.0 - 2 * notch) / 3.0
    for k in (1, 2):
        y0 = k * arm + (k - 1) * notch
        body = body.difference(shapely.box(0.9, y0, 3.01, y0 + notch))
    return body


def digit_3() -> Polygon:
    t1 = np.linspace(math.radians(150), math.radians(-90), 25)
    t2 = np.linspace(math.radians(90), math.radians(-150), 25)
    upper = np.column_stack([1.2 * np.cos(t1), 1.0 + 1.0 * np.sin(t1)])
    lower = np.column_stack([1.35 * np.cos(t2), -1.1 + 1.1 * np.sin(t2)])
    stroke = LineString(np.vstack([upper, lower])).buffer(0.275, quad_segs=4)
    return stroke


def wrench_mm() -> Polygon:
    handle = shapely.box(0.0, -15.0, 210.0, 15.0)
    head = Point(235.0, 0.0).buffer(40.0, quad_segs=16)
    slot = shapely.box(228.0, -16.0, 290.0, 16.0)
    return handle.union(head).difference(slot)


def gear_mm() -> Polygon:
    body = Point(0.0, 0.0).buffer(45.0, quad_segs=24)
    for k in range(8):
        tooth = shapely.box(35.0, -7.0, 63.0, 7.0)
        body = body.union(shapely.affinity.rotate(tooth, 45.0 * k, origin=(0.0, 0.0)))
    return body


def fork_mm() -> Polygon:
    base = shapely.box(0.0, 0.0, 180.0, 60.0)
    tines = [shapely.box(x, 59.0, x + 40.0, 200.0) for x in (0.0, 70.0, 140.0)]
    return shapely.union_all([base, *tines])


def write(name: str, polygon: Polygon, digits: int) -> None:
    polygon = shapely.set_precision(polygon.simplify(10.0 ** -digits), 10.0 ** -digits)
    assert polygon.geom_type == "Polygon" and polygon.is_valid and not polygon.interiors, name
    coords = np.asarray(polygon.exterior.coords)[:-1]
    text = "x,y\n" + "".join(f"{x:.{digits}f},{y:.{digits}f}\n" for x, y in coords)
    (HERE / name).write_text(text)


if __name__ == "__main__":
    write("letter_e.csv", letter_e(), 4)
    write("digit_3.csv", digit_3(), 4)
    write("wrench_mm.csv", wrench_mm(), 2)
    write("gear_mm.csv", gear_mm(), 2)
    write("fork_mm.csv", fork_mm(), 2)
