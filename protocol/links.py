"""Seeded fault-injecting links, sans-IO.

A :class:`Link` is told when a payload is sent and asked what is due by a given time; it never
reads a clock, so the in-process simulator drives it with a virtual clock and a Zenoh robot with
its event loop's clock, and both see the same faults for the same seed. Vocabulary follows
netem/toxiproxy (delay, jitter, loss, duplicate, reorder); the exact semantics are specified in
``docs/protocol.md``.
"""

from __future__ import annotations

import hashlib
import heapq
import itertools
import math
import re
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

# A held-back (reordered) copy waits max(REORDER_HOLD_FACTOR * (delay + jitter), REORDER_HOLD_MIN)
# on top of its own delay: long enough that frames sent shortly after it overtake it for sure.
REORDER_HOLD_FACTOR = 2.0
REORDER_HOLD_MIN = 0.001

_NUMBER = r"(?P<num>(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][-+]?\d+)?)"
_DURATION = re.compile(rf"\s*{_NUMBER}\s*(?P<unit>us|ms|s)?\s*")
_UNIT_SECONDS = {"us": 1e-6, "ms": 1e-3, "s": 1.0}
_PROBABILITY = re.compile(rf"\s*{_NUMBER}\s*(?P<pct>%?)\s*")
_COUNTERS = ("sent", "dropped", "duplicated", "reordered", "delivered")


def parse_duration(text: str, *, flag: str) -> float:
    """Seconds in ``text`` ("20ms", "0.5s", "1.5 s", "250us", "0"); ValueError names ``flag``.

    A bare number other than 0 is refused: "20" could mean seconds or milliseconds.
    """
    hint = "(use e.g. 20ms or 0.5s)"
    if not isinstance(text, str):
        raise ValueError(f"{flag}: expected text such as 20ms, got {type(text).__name__} {hint}")
    m = _DURATION.fullmatch(text)
    if m is None:
        if text.strip().startswith("-"):
            raise ValueError(f"{flag}: {text!r} is negative; a duration is >= 0 {hint}")
        raise ValueError(f"{flag}: {text!r} is not a duration {hint}")
    value = float(m["num"])
    if m["unit"] is None and value != 0.0:
        raise ValueError(f"{flag}: {text!r} has no unit {hint}")
    seconds = value * _UNIT_SECONDS[m["unit"] or "s"]
    if not math.isfinite(seconds):
        raise ValueError(f"{flag}: {text!r} is not a finite duration {hint}")
    return seconds


def parse_probability(text: str, *, flag: str) -> float:
    """Probability in ``text``, a fraction ("0.3") or a percentage ("30%").

    ValueError names ``flag`` and the accepted forms.
    """
    hint = "(use a fraction such as 0.3 or a percentage such as 30%)"
    if not isinstance(text, str):
        raise ValueError(f"{flag}: expected text such as 0.3, got {type(text).__name__} {hint}")
    m = _PROBABILITY.fullmatch(text)
    if m is None:
        if text.strip().startswith("-"):
            raise ValueError(f"{flag}: {text!r} is outside [0, 1] {hint}")
        raise ValueError(f"{flag}: {text!r} is not a probability {hint}")
    value = float(m["num"]) / (100.0 if m["pct"] else 1.0)
    if not 0.0 <= value <= 1.0:
        raise ValueError(f"{flag}: {text!r} is outside [0, 1] {hint}")
    return value


@dataclass(frozen=True)
class LinkFaults:
    """Faults of one directed link: durations in seconds, probabilities in [0, 1]."""

    delay: float = 0.0
    jitter: float = 0.0
    loss: float = 0.0
    duplicate: float = 0.0
    reorder: float = 0.0

    def __post_init__(self) -> None:
        for name in ("delay", "jitter", "loss", "duplicate", "reorder"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ValueError(f"{name} must be a number, got {type(value).__name__}")
            if not math.isfinite(value) or value < 0:
                raise ValueError(f"{name} must be finite and >= 0, got {value}")
            if name in ("loss", "duplicate", "reorder") and value > 1:
                raise ValueError(f"{name} is a probability, got {value} > 1")
            object.__setattr__(self, name, float(value))

    @classmethod
    def none(cls) -> LinkFaults:
        """A perfect link: every frame delivered once, at once, in order."""
        return cls()

    @property
    def is_clean(self) -> bool:
        """True when the link changes nothing."""
        return self == LinkFaults.none()

    @property
    def reorder_hold(self) -> float:
        """Extra wait of a held-back copy (see REORDER_HOLD_FACTOR)."""
        return max(REORDER_HOLD_FACTOR * (self.delay + self.jitter), REORDER_HOLD_MIN)


class Link:
    """One directed link with seeded faults.

    Every :meth:`send` consumes exactly six uniform draws, whatever the fault settings, so frame
    n's fate depends only on the seed and n; e.g. the frames lost at loss 0.1 are a subset of
    those lost at 0.2 with the same seed.
    """

    def __init__(self, faults: LinkFaults, seed: int) -> None:
        self.faults = faults
        self._rng = np.random.default_rng(seed)
        self._queue: list[tuple[float, int, bytes]] = []
        # Send-order stamps; LinkLayer shares one counter between its links to order ties.
        self._stamps: Iterator[int] = itertools.count()
        self.sent = 0
        self.dropped = 0
        self.duplicated = 0
        self.reordered = 0
        self.delivered = 0

    def send(self, payload: bytes, now: float) -> None:
        """Hand ``payload`` to the link at time ``now`` (seconds, any origin)."""
        if not math.isfinite(now):
            raise ValueError(f"now must be finite, got {now}")
        f = self.faults
        u_loss, u_dup, u_jit1, u_hold1, u_jit2, u_hold2 = self._rng.random(6).tolist()
        self.sent += 1
        if u_loss < f.loss:
            self.dropped += 1
            return
        copies = [(u_jit1, u_hold1)]
        if u_dup < f.duplicate:
            self.duplicated += 1
            copies.append((u_jit2, u_hold2))
        for u_jit, u_hold in copies:
            delay = max(0.0, f.delay + f.jitter * (2.0 * u_jit - 1.0))
            if u_hold < f.reorder:
                self.reordered += 1
                delay += f.reorder_hold
            heapq.heappush(self._queue, (now + delay, next(self._stamps), payload))

    def next_due(self) -> float | None:
        """Delivery time of the earliest payload in flight, or None if nothing is in flight."""
        return self._queue[0][0] if self._queue else None

    def deliver(self, now: float) -> list[bytes]:
        """Payloads due by ``now``, in delivery-time order (ties in send order)."""
        return [payload for _, _, payload in self._pop_due(now)]

    def _pop_due(self, now: float) -> list[tuple[float, int, bytes]]:
        out = []
        while self._queue and self._queue[0][0] <= now:
            out.append(heapq.heappop(self._queue))
        self.delivered += len(out)
        return out

    @property
    def in_flight(self) -> int:
        """Copies scheduled but not yet delivered."""
        return len(self._queue)

    def stats(self) -> dict[str, int]:
        """Counters; sent - dropped + duplicated == delivered + in_flight always holds."""
        counts = {name: getattr(self, name) for name in _COUNTERS}
        counts["in_flight"] = self.in_flight
        return counts


def link_seed(base_seed: int, src: int, dst: int) -> int:
    """Seed of the directed link src -> dst, derived from the fleet's seed.

    Each link draws from its own stream, so its schedule does not depend on which other links
    exist or carry traffic: a robot that owns only its incoming links sees exactly the faults
    the in-process simulator produces for them.
    """
    for name, value in (("base_seed", base_seed), ("src", src), ("dst", dst)):
        if type(value) is not int:
            raise ValueError(f"{name} must be an int, got {type(value).__name__}")
    digest = hashlib.blake2b(
        f"{base_seed}:{src}->{dst}".encode(), digest_size=8, person=b"shapefleet-link"
    ).digest()
    return int.from_bytes(digest, "little")


class LinkLayer:
    """All directed links of a fleet (or of one robot), created on first use."""

    def __init__(self, faults: LinkFaults, seed: int) -> None:
        self.faults = faults
        self.seed = seed
        self._links: dict[tuple[int, int], Link] = {}
        self._stamps = itertools.count()

    def link(self, src: int, dst: int) -> Link:
        """The link src -> dst, created (seeded with link_seed) if new."""
        link = self._links.get((src, dst))
        if link is None:
            link = Link(self.faults, link_seed(self.seed, src, dst))
            link._stamps = self._stamps  # ties across links break in layer-wide send order
            self._links[(src, dst)] = link
        return link

    def send(self, src: int, dst: int, payload: bytes, now: float) -> None:
        """Send ``payload`` from ``src`` to ``dst`` at time ``now``."""
        self.link(src, dst).send(payload, now)

    def next_due(self) -> float | None:
        """Earliest delivery time over all links, or None if nothing is in flight."""
        dues = [d for d in (link.next_due() for link in self._links.values()) if d is not None]
        return min(dues, default=None)

    def deliver(self, now: float) -> list[tuple[int, int, bytes]]:
        """(src, dst, payload) due by ``now`` on any link, by delivery time then send order."""
        due = [
            (t, stamp, src, dst, payload)
            for (src, dst), link in self._links.items()
            for t, stamp, payload in link._pop_due(now)
        ]
        due.sort(key=lambda item: (item[0], item[1]))
        return [(src, dst, payload) for _, _, src, dst, payload in due]

    def stats(self) -> dict[str, int]:
        """Counters summed over all links."""
        total = dict.fromkeys((*_COUNTERS, "in_flight"), 0)
        for link in self._links.values():
            for name, value in link.stats().items():
                total[name] += value
        return total

    def link_stats(self) -> dict[tuple[int, int], dict[str, int]]:
        """Counters of each link used so far, keyed by (src, dst)."""
        return {key: link.stats() for key, link in sorted(self._links.items())}
