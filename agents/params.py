"""One way to read an algorithm's parameters from a fleet file's ``params``.

The launcher writes exactly the fields of the fleet's algorithm (launcher/options.py derives
them from its options table), so every reader is strict: a key that is not a field of the class
is an error naming it, never silently dropped or renamed. JSON arrays become tuples.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, TypeVar

P = TypeVar("P")


def params_from(cls: type[P], params: Mapping[str, Any], algorithm: str) -> P:
    """``cls(**params)``, with unknown keys refused by name (ValueError) and lists as tuples."""
    names = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(params) - names)
    if unknown:
        raise ValueError(f"unknown {algorithm} parameter {unknown[0]!r}; known: {', '.join(sorted(names))}")
    return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in params.items()})


#: stop flags carry one bit per hop of the diameter, and bit 0, in a 64-bit integer
MAX_DIAMETER = 62


def check_positive(params: Any, *names: str) -> None:
    """Refuse, by name, a field of ``params`` that is not positive: the same check and message
    for every algorithm's gains, penalties and tolerances."""
    for name in names:
        value = getattr(params, name)
        if not value > 0:
            raise ValueError(f"{name} must be positive, got {value}")


def check_counts(params: Any, *names: str) -> None:
    """Refuse, by name, a count field of ``params`` below 1 (None: no cap, allowed)."""
    for name in names:
        value = getattr(params, name)
        if value is not None and value < 1:
            raise ValueError(f"{name} must be at least 1, got {value}")


def check_diameter(diameter: int) -> None:
    """Refuse a diameter the stop flags cannot carry (bits 0..D of one frame's flags)."""
    if not 0 <= diameter <= MAX_DIAMETER:
        raise ValueError(f"diameter must be in [0, {MAX_DIAMETER}] (flag bits), got {diameter}")
