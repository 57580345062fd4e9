"""The round protocol's per-round helpers (agents/rounds.py) against their plain definitions."""

from __future__ import annotations

import numpy as np

from agents.rounds import DIVERGED_ABS, check_iterate


def _plain_check(values: np.ndarray) -> str | None:
    """check_iterate as first written: an isfinite test, then the largest |component|."""
    v = np.asarray(values, dtype=float)
    if not np.all(np.isfinite(v)):
        return "non-finite iterate (NaN or inf)"
    big = float(np.max(np.abs(v))) if v.size else 0.0
    if big > DIVERGED_ABS:
        return f"exploding iterate (largest component {big:.3g} > {DIVERGED_ABS:g})"
    return None


def test_check_iterate_gives_the_plain_verdicts():
    """One reduction instead of isfinite + all + abs + max: the same verdict and message on every
    mix of finite, huge, infinite and NaN components (a sum-based test would call 1e308 + 1e308
    non-finite: these vectors include that), and on empty and integer input."""
    rng = np.random.default_rng(11)
    specials = [np.nan, np.inf, -np.inf, 1e308, -1e308, DIVERGED_ABS, np.nextafter(DIVERGED_ABS, np.inf), -0.0, 5e-324]
    cases = [np.zeros(0), np.arange(5), np.array([1e308, 1e308]), np.array([np.inf, np.nan]), np.array([np.nan, -np.inf]),
             np.array([[1.0, 2e12], [3.0, 4.0]]), np.array([[1.0, np.nan], [3.0, 4.0]]), np.ones((2, 3)), [1.0, 2.0]]
    for _ in range(1500):
        v = rng.normal(scale=10.0 ** rng.integers(0, 14), size=rng.integers(1, 33))
        for i in rng.integers(0, len(v), size=rng.integers(0, 4)):
            v[i] = specials[rng.integers(len(specials))]
        cases.append(v)
    for v in cases:
        assert check_iterate(v) == _plain_check(v), v


def test_relative_gaps_keep_their_bits():
    """`relative_gaps` (the residual of every round) against its first form, bit for bit: the
    norm of v by math.sqrt instead of np.sqrt, rows given as one vector, a stack or a strided
    view (the hub passes the v-half of its frames), tiny and huge scales."""
    from agents.rounds import _TINY, relative_gaps

    def plain(v, w):
        d = np.atleast_2d(w) - v
        dx = np.sqrt(np.einsum("ij,ij->i", d[:, :-1], d[:, :-1])) / max(float(np.sqrt(v[:-1] @ v[:-1])), _TINY)
        return dx + np.abs(d[:, -1]) / max(1.0, abs(float(v[-1])))

    rng = np.random.default_rng(4)
    for _ in range(500):
        dim, n = int(rng.integers(2, 40)), int(rng.integers(1, 33))
        scale = 10.0 ** rng.integers(-150, 150)
        v = rng.normal(size=dim) * scale
        frames = rng.normal(size=(n, 2 * dim)) * scale
        for w in (frames[:, :dim], np.ascontiguousarray(frames[:, :dim]), frames[0, :dim]):
            assert relative_gaps(v, w).tobytes() == plain(v, w).tobytes()
    assert relative_gaps(np.zeros(3), np.ones((2, 3))).tobytes() == plain(np.zeros(3), np.ones((2, 3))).tobytes()
