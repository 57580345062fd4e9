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


def test_log_axis_labels_are_plain_text_not_mathtext():
    from launcher.report import plain_log_label

    assert plain_log_label(r"$\mathdefault{10^{-5}}$") == "10\u207b\u2075"
    assert plain_log_label(r"$\mathdefault{2\times10^{-3}}$") == "2\u00d710\u207b\u00b3"
    assert plain_log_label(r"$\mathdefault{-10^{12}}$") == "\u221210\u00b9\u00b2"
    assert plain_log_label(r"$\mathdefault{0}$") == "0"
    assert plain_log_label("") == ""
    fractional = r"$\mathdefault{10^{-0.50}}$"  # not writable as plain text: kept for mathtext
    assert plain_log_label(fractional) == fractional


def test_convergence_picture_is_drawn_without_the_mathtext_parser(tmp_path, monkeypatch):
    """The decade labels of the log axis are plain text: drawing never builds the mathtext
    parser (~0.25 s the first time); the picture is still written."""
    import matplotlib.mathtext

    from launcher.report import plot_convergence

    def refuse(*_args, **_kwargs):
        raise AssertionError("mathtext used")

    monkeypatch.setattr(matplotlib.mathtext.MathTextParser, "parse", refuse)
    errors = np.logspace(0, -7, 60)
    hist = [{"round": k, "function_error": e, "consensus_error": e / 3} for k, e in enumerate(errors)]
    plot_convergence(tmp_path / "convergence.png", hist)
    assert (tmp_path / "convergence.png").stat().st_size > 20_000
