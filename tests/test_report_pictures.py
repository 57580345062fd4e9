"""The pictures' cheap paths draw the same content: the raster values the outlines are contoured
from, and the convergence picture's log axis (decades, minor grid, trace values)."""

import numpy as np
import pytest

from agents.kernel import GridBasis, lattice
from launcher.report import convergence_figure, raster_decisions


@pytest.mark.parametrize("widths", [None, "two levels"])
def test_raster_values_equal_each_robots_decision_on_the_raster(widths):
    rng = np.random.default_rng(5)
    grid = lattice(6, 5, (0.0, 3.0, 0.0, 2.0))
    w = None if widths is None else np.where(np.arange(len(grid)) % 2 == 0, 0.5, 0.25)
    basis = GridBasis(grid, 0.5, widths=w)
    xs, ys = np.linspace(-0.4, 3.4, 37), np.linspace(-0.3, 2.3, 23)
    functions = [(basis, rng.normal(size=basis.size), float(rng.normal())) for _ in range(2)]
    gx, gy = np.meshgrid(xs, ys)
    points = np.column_stack([gx.ravel(), gy.ravel()])
    for (b, c, g), values in zip(functions, raster_decisions(xs, ys, functions), strict=True):
        exact = b.decision(points, c, g).reshape(gx.shape)
        assert values.shape == (len(ys), len(xs))
        np.testing.assert_allclose(values, exact, rtol=0, atol=1e-12 * np.abs(exact).max())


def _trace(decades: float, rounds: int = 80, consensus: float = 1 / 7) -> list[dict]:
    errors = np.logspace(0.2, 0.2 - decades, rounds)
    return [{"round": k, "function_error": e, "consensus_error": e * consensus} for k, e in enumerate(errors)]


def test_convergence_axis_shows_the_trace_at_its_decades_with_a_minor_grid():
    hist = _trace(6.5)
    fig = convergence_figure(hist)
    ax = fig.axes[0]
    fig.canvas.draw()
    assert ax.get_yscale() == "log"
    lo, hi = ax.get_ylim()
    values = [h[k] for h in hist for k in ("function_error", "consensus_error")]
    assert lo <= min(values) and max(values) <= hi
    plotted = {line.get_label(): np.asarray(line.get_ydata(), dtype=float) for line in ax.get_lines()}
    np.testing.assert_array_equal(plotted["function error vs central"], [h["function_error"] for h in hist])
    np.testing.assert_array_equal(plotted["consensus error"], [h["consensus_error"] for h in hist])
    # a labelled major tick at every decade in view, written 10^k in plain text
    labels = {round(np.log10(t.get_loc())): t.label1.get_text() for t in ax.yaxis.get_major_ticks()
              if lo <= t.get_loc() <= hi and t.label1.get_visible()}
    decades = range(int(np.ceil(np.log10(lo))), int(np.floor(np.log10(hi))) + 1)
    assert sorted(labels) == list(decades)
    sup = str.maketrans("-0123456789", "\u207b\u2070\u00b9\u00b2\u00b3\u2074\u2075\u2076\u2077\u2078\u2079")
    assert all(labels[k] == "10" + str(k).translate(sup) for k in decades)
    # the minor grid: 2..9 x 10^k inside the view, one horizontal line each, unlabelled
    minor = sorted(float(seg[0][1]) for coll in ax.collections for seg in coll.get_segments())
    expected = sorted(m * 10.0**k for k in range(int(np.floor(np.log10(lo))), int(np.ceil(np.log10(hi))))
                      for m in range(2, 10) if lo <= m * 10.0**k <= hi)
    np.testing.assert_allclose(minor, expected, rtol=1e-12)
    assert len(ax.yaxis.get_minor_ticks()) == 0  # no Tick objects (what made the picture slow)


def test_convergence_axis_of_less_than_a_decade_keeps_labelled_minor_ticks():
    fig = convergence_figure(_trace(0.5, consensus=1.0), tol=1.0)
    ax = fig.axes[0]
    fig.canvas.draw()
    minor = [t.label1.get_text() for t in ax.yaxis.get_minor_ticks() if t.label1.get_visible()]
    assert any(minor)  # matplotlib's own minor ticks, some with labels
    assert not ax.collections


def test_picture_imports_skip_only_the_set_docstrings_and_restore_kwdoc():
    """import_picture_modules leaves matplotlib's kwdoc as it was (a fresh interpreter: the stub
    acts only during the first import), and the figures still work."""
    import subprocess
    import sys

    code = (
        "from launcher.report import import_picture_modules, _figure\n"
        "import_picture_modules()\n"
        "import matplotlib.artist, matplotlib.lines\n"
        "assert matplotlib.artist.kwdoc(matplotlib.lines.Line2D).startswith('Properties:')\n"
        "assert 'Properties' not in (matplotlib.lines.Line2D.set.__doc__ or '')\n"
        "fig, ax = _figure((1, 1), (0.1, 0.1, 0.8, 0.8)); ax.plot([0, 1]); fig.canvas.draw()\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
