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
    cases = [np.zeros(0), np.arange(5), np.array([1e308, 1e308]), np.array([np.inf, np.nan]), np.array([np.nan, -np.inf])]
    for _ in range(1500):
        v = rng.normal(scale=10.0 ** rng.integers(0, 14), size=rng.integers(1, 33))
        for i in rng.integers(0, len(v), size=rng.integers(0, 4)):
            v[i] = specials[rng.integers(len(specials))]
        cases.append(v)
    for v in cases:
        assert check_iterate(v) == _plain_check(v), v
