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
