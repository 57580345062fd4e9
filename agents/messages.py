"""The message an algorithm core exchanges with its neighbours, apart from any wire format.

A core produces and consumes :class:`StateUpdate` values; it never sees bytes, msgpack, Zenoh
keys or authentication. The codec (``protocol/frames.py``) turns these messages into frames and
back; the session (``protocol/session.py``) moves them. The checks here are the message's own
invariants (ids and rounds in range, finite-size real vectors, no round -1), so a malformed
message is refused wherever it is built.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

MAX_ROBOT_ID = 2**31 - 1
MAX_ROUND = 2**31 - 1
MAX_FLAGS = 2**63 - 1


def check_int(name: str, value: Any, hi: int) -> int:
    """``value`` if it is an int (never a bool) in [0, hi], else TypeError / ValueError."""
    if type(value) is not int:
        raise TypeError(f"{name} must be an int, got {type(value).__name__}")
    if not 0 <= value <= hi:
        raise ValueError(f"{name} {value} is outside [0, {hi}]")
    return value


def as_vector(name: str, value: Any) -> np.ndarray:
    """``value`` as a non-empty 1-D float64 vector (no copy when it already is one)."""
    arr = np.asarray(value)
    if arr.dtype.kind not in "iuf":
        raise TypeError(f"{name} must be real numbers, got dtype {arr.dtype}")
    if arr.ndim != 1 or arr.size == 0:
        raise ValueError(f"{name} must be a non-empty 1-D vector, got shape {arr.shape}")
    return arr.astype(np.float64, copy=False)


def check_robot_id(robot: Any) -> int:
    """``robot`` if it is an int (never a bool) in [0, MAX_ROBOT_ID], else ValueError: the one
    rule for a robot id, in messages and in Zenoh keys (protocol/keys.py) alike."""
    if type(robot) is not int:
        raise ValueError(f"robot id must be an int, got {type(robot).__name__}")
    if not 0 <= robot <= MAX_ROBOT_ID:
        raise ValueError(f"robot id {robot} is outside [0, {MAX_ROBOT_ID}]")
    return robot


def gone_problem(sender: int, gone: Any, prev_gone: Any) -> str | None:
    """Why a message's lists of robots dropped for good cannot be believed, or None: each must be
    a tuple of robot ids in strictly ascending order without the sender (a robot that sends is not
    gone), and ``prev_gone`` a subset of ``gone`` (what a robot knows to be gone only grows)."""
    for name, ids in (("gone", gone), ("prev_gone", prev_gone)):
        if type(ids) is not tuple or not all(type(j) is int and 0 <= j <= MAX_ROBOT_ID for j in ids):
            return f"{name} must be a tuple of robot ids"
        if any(a >= b for a, b in zip(ids, ids[1:])):
            return f"{name} {list(ids)[:8]} is not strictly ascending"
        if sender in ids:
            return f"{name} names its own sender {sender}"
    if not set(prev_gone).issubset(gone):
        return f"prev_gone {list(prev_gone)[:8]} is not a subset of gone {list(gone)[:8]}"
    return None


@dataclass(frozen=True, eq=False)
class StateUpdate:
    """One robot's consensus vector for one round, as the algorithm core sees it.

    ``prev_values`` are the sender's values of ``round - 1``: a receiver that lost that frame
    recovers the exact value from the next one instead of reusing a stale one (which would bias
    ADMM). Consequently it must be None at round 0, and ``prev_flags`` must be 0 without it.
    Equality compares the arrays element-wise (``np.array_equal``); instances are unhashable.
    """

    sender: int
    round: int
    values: np.ndarray
    flags: int
    prev_values: np.ndarray | None
    prev_flags: int = 0
    gone: tuple[int, ...] = ()
    prev_gone: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        check_robot_id(self.sender)
        check_int("round", self.round, MAX_ROUND)
        check_int("flags", self.flags, MAX_FLAGS)
        check_int("prev_flags", self.prev_flags, MAX_FLAGS)
        values = as_vector("values", self.values)
        object.__setattr__(self, "values", values)
        if self.gone or self.prev_gone:
            why = gone_problem(self.sender, self.gone, self.prev_gone)
            if why is not None:
                raise ValueError(why)
        if self.prev_values is None:
            if self.prev_flags:
                raise ValueError("prev_flags must be 0 when prev_values is None")
            if self.prev_gone:
                raise ValueError("prev_gone must be empty when prev_values is None")
            return
        if self.round == 0:
            raise ValueError("prev_values must be None at round 0 (there is no round -1)")
        prev = as_vector("prev_values", self.prev_values)
        if prev.shape != values.shape:
            raise ValueError(
                f"prev_values has {prev.size} entries but values has {values.size}"
            )
        object.__setattr__(self, "prev_values", prev)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, StateUpdate):
            return NotImplemented
        if (self.sender, self.round, self.flags, self.prev_flags, self.gone, self.prev_gone) != (
            other.sender,
            other.round,
            other.flags,
            other.prev_flags,
            other.gone,
            other.prev_gone,
        ):
            return False
        if not np.array_equal(self.values, other.values):
            return False
        if self.prev_values is None or other.prev_values is None:
            return self.prev_values is None and other.prev_values is None
        return np.array_equal(self.prev_values, other.prev_values)

    __hash__ = None  # type: ignore[assignment]  # holds mutable arrays
