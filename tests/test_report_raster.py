"""The pictures' and IoU's raster values: one kernel matrix per distinct (grid, sigma), the same
bits as each robot's own `GridBasis.decision`."""

import numpy as np

from agents.kernel import GridBasis, lattice
from launcher.report import decisions


def test_shared_kernel_gives_each_robot_its_own_decision_bit_for_bit(monkeypatch):
    rng = np.random.default_rng(3)
    grid = lattice(5, 4, (0.0, 2.0, 0.0, 1.5))
    same_a, same_b = GridBasis(grid, 0.4), GridBasis(grid.copy(), 0.4)  # two robots, one final grid
    other = GridBasis(grid, 0.3)  # another sigma: its own matrix
    points = rng.uniform(-0.5, 2.5, size=(500, 2))
    functions = [(b, rng.normal(size=b.size), float(rng.normal())) for b in (same_a, same_b, other)]
    calls = []
    original = GridBasis.kernel_to_grid
    monkeypatch.setattr(GridBasis, "kernel_to_grid", lambda self, p: calls.append(self) or original(self, p))
    values = decisions(points, functions)
    assert len(calls) == 2
    monkeypatch.undo()
    for (b, c, g), v in zip(functions, values, strict=True):
        assert np.array_equal(v, b.decision(points, c, g))
