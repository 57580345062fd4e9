"""The least-squares model's output region (agents/lsq_model.py `output_region`): {f < 0} within
OUTPUT_REACH widths of a grid node, enclosed holes filled -- the answer whose IoU and outline a
least-squares run reports; an SVM run's stay {f < 0}. Its specification is the lead's rule 2
(benchmarks/lsq_emulation.py `output_mask`), checked equal here."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest
import shapely

from agents.kernel import GridBasis, lattice
from agents.lsq_model import OUTPUT_REACH, output_region
from launcher import report, scenario
from launcher.cli import main
from launcher.world import Options, build_world

from .conftest import ROOT

sys.path.insert(0, str(ROOT / "benchmarks"))
import lsq_emulation as emulation  # noqa: E402

BOX = (-1.0, 1.0, -1.0, 1.0)


def _raster(n: int = 61, bounds: tuple[float, float, float, float] = BOX) -> np.ndarray:
    return scenario.make_grid(n, n, bounds)


def test_a_ring_of_negative_f_fills_its_centre():
    q = _raster()
    r = np.hypot(q[:, 0], q[:, 1])
    values = np.where((r > 0.4) & (r < 0.8), -1.0, 1.0)  # a ring: raw {f < 0} is hollow
    region = output_region(values, q, (61, 61), lattice(9, 9, BOX), 0.25)
    assert not np.any((values < 0) & (r < 0.4))
    assert np.array_equal(region, r < 0.8)  # the centre no ray from outside reaches is inside


def test_gamma_below_zero_far_from_the_grid_stays_outside():
    q = _raster()
    grid = lattice(3, 3, (-0.2, 0.2, -0.2, 0.2))  # nodes near the centre only
    basis = GridBasis(grid, 0.1)
    values = basis.decision(q, np.zeros(basis.size), -0.01)  # f = gamma < 0 everywhere
    region = output_region(values, q, (61, 61), grid, basis.sigma)
    near = np.min(np.hypot(*(q[:, None, :] - grid[None, :, :]).transpose(2, 0, 1)), axis=1) <= OUTPUT_REACH * 0.1
    assert np.array_equal(region, near) and 0 < region.sum() < len(q) / 4


def test_a_full_lattice_and_no_hole_give_f_below_zero():
    q = _raster()
    values = q[:, 0] ** 2 + 2 * q[:, 1] ** 2 - 0.5  # an ellipse, no hole
    region = output_region(values, q, (61, 61), lattice(9, 9, BOX), 0.25)
    assert np.array_equal(region, values < 0)


def test_each_node_reaches_its_own_width():
    q = _raster()
    grid = np.array([[-0.5, 0.0], [0.5, 0.0]])
    widths = np.array([0.1, 0.2])  # the left node reaches 0.2, the right one 0.4
    region = output_region(-np.ones(len(q)), q, (61, 61), grid, 0.1, widths)
    d = np.hypot(q[:, None, 0] - grid[None, :, 0], q[:, None, 1] - grid[None, :, 1])
    assert np.array_equal(region, (d[:, 0] <= 0.2) | (d[:, 1] <= 0.4))
    assert np.array_equal(output_region(-np.ones(len(q)), q, (61, 61), grid, 0.1), np.min(d, axis=1) <= 0.2)


def test_a_raster_of_another_size_is_refused():
    q = _raster()
    with pytest.raises(ValueError, match="shape"):
        output_region(np.ones(len(q)), q, (60, 61), lattice(3, 3, BOX), 0.5)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_it_is_the_emulations_rule_2_output(seed):
    """The one definition agrees bit for bit with the frozen emulation's `output_mask` on grids that
    keep only some nodes (where the reach and the fill matter)."""
    assert emulation.MASK == OUTPUT_REACH
    rng = np.random.default_rng(seed)
    full = lattice(12, 12, BOX)
    grid = full[rng.random(len(full)) < 0.6]
    basis = GridBasis(grid, 0.15)
    c, gamma = rng.normal(size=basis.size), float(rng.normal(scale=0.1))
    q = scenario.make_grid(80, 70, (-1.2, 1.2, -1.1, 1.1))  # 80 x, 70 y: rows in y
    want = emulation.output_mask(lambda p: basis.decision(p, c, gamma), basis, q, (70, 80))
    got = output_region(basis.decision(q, c, gamma), q, (70, 80), basis.grid, basis.sigma)
    assert np.array_equal(got, want)
    assert not np.array_equal(got, basis.decision(q, c, gamma) < 0)  # (a case where the region matters)


# -- what a run reports ---------------------------------------------------------------------------
def _run(tmp_path, name: str, *flags: str) -> dict:
    out = tmp_path / name
    assert main(["simulate", *flags, "--out", str(out)]) == 0
    return json.loads((out / "result.json").read_text())


def _ious(world, result: dict, *, region: bool) -> list[float]:
    """Each robot's IoU computed here: the emulation's `output_mask` (``region``) or {f < 0}, on
    simulate's raster (200 x 200 of world.bounds, the truth by shapely)."""
    q = scenario.make_grid(200, 200, world.bounds)
    truth = shapely.contains_xy(world.shape, q[:, 0], q[:, 1])
    out = []
    for r in result["robots"]:
        basis = GridBasis(np.asarray(r.get("grid") or result["grid"]), r.get("sigma") or result["sigma"])
        c, gamma = np.asarray(r["c"], dtype=float), float(r["gamma"])
        f = lambda p, basis=basis, c=c, gamma=gamma: basis.decision(p, c, gamma)  # noqa: E731
        inside = emulation.output_mask(f, basis, q, (200, 200)) if region else f(q) < 0
        out.append(np.count_nonzero(truth & inside) / np.count_nonzero(truth | inside))
    return out


@pytest.mark.parametrize("flags", [(), ("--algorithm", "lsq", "--grid", "9x6", "--sigma", "0.25")],
                         ids=["default-autogrid-lsq", "fixed-grid-lsq"])
def test_a_least_squares_run_reports_its_regions_iou_and_the_raw_one(tmp_path, flags):
    result = _run(tmp_path, "run", *flags)
    options = {} if not flags else {"algorithm": "lsq", "grid": "9x6", "sigma": 0.25}
    world, _ = build_world(Options(**options))
    m = result["metrics"]
    assert result["output_region"] == report.OUTPUT_REGION_WORDS
    assert m["iou"] == min(_ious(world, result, region=True))
    assert m["iou_unfilled"] == min(_ious(world, result, region=False))
    if flags:  # a sparse grid (reach 0.5 < the lattice's gaps): the region differs from {f < 0}
        assert m["iou"] != m["iou_unfilled"]


def test_an_svm_run_reports_f_below_zero(tmp_path):
    result = _run(tmp_path, "svm", "--preset", "paper")
    world, _ = build_world(Options(preset="paper"))
    assert "output_region" not in result and "iou_unfilled" not in result["metrics"]
    assert result["metrics"]["iou"] == min(_ious(world, result, region=False))


def test_the_picture_draws_the_regions_boundary_for_least_squares_only(tmp_path, monkeypatch):
    """plot_shapes contours the region's mask (values -1 / +1) of a least-squares result, f of an SVM's."""
    import matplotlib.axes

    drawn = []
    monkeypatch.setattr(matplotlib.axes.Axes, "contour", lambda self, x, y, z, **kw: drawn.append(np.asarray(z)))
    world, spec = build_world(Options(algorithm="lsq", grid="9x6", sigma=0.25))
    rng = np.random.default_rng(0)
    row = {"id": 0, "c": rng.normal(size=spec.basis.size).tolist(), "gamma": -0.05}
    result = {"grid": spec.basis.grid.tolist(), "robots": [row]}
    report.plot_shapes(tmp_path / "svm.png", world, spec.basis, result)
    report.plot_shapes(tmp_path / "lsq.png", world, spec.basis, {**result, "output_region": "words"})
    svm, lsq = drawn
    assert set(np.unique(lsq)) == {-1.0, 1.0} and len(np.unique(svm)) > 2
