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
from typing import Any
from dataclasses import dataclass, replace
from statistics import NormalDist

import numpy as np

# A held-back (reordered) copy waits max(REORDER_HOLD_FACTOR * (delay + jitter), REORDER_HOLD_MIN)
# on top of its own delay: long enough that frames sent shortly after it overtake it for sure.
REORDER_HOLD_FACTOR = 2.0
REORDER_HOLD_MIN = 0.001
# A faulty link takes its draws from its stream this many sends at a time (see Link._six_draws).
DRAW_BATCH = 16

_NUMBER = r"(?P<num>(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][-+]?\d+)?)"
_DURATION = re.compile(rf"\s*{_NUMBER}\s*(?P<unit>us|ms|s)?\s*")
_UNIT_SECONDS = {"us": 1e-6, "ms": 1e-3, "s": 1.0}
_PROBABILITY = re.compile(rf"\s*{_NUMBER}\s*(?P<pct>%?)\s*")
_COUNTERS = ("sent", "dropped", "duplicated", "reordered", "delivered")
_DURATION_HINT = "(use e.g. 20ms or 0.5s)"
_PROBABILITY_HINT = "(use a fraction such as 0.3 or a percentage such as 30%)"


def _match(pattern: re.Pattern[str], text: Any, *, flag: str, example: str, noun: str, negative: str,
           hint: str) -> re.Match[str]:
    """``text`` matched by ``pattern``; else ValueError naming ``flag``, what is wrong and ``hint``
    (the one wording every option parser here gives)."""
    if not isinstance(text, str):
        raise ValueError(f"{flag}: expected text such as {example}, got {type(text).__name__} {hint}")
    m = pattern.fullmatch(text)
    if m is None:
        if text.strip().startswith("-"):
            raise ValueError(f"{flag}: {text!r} {negative} {hint}")
        raise ValueError(f"{flag}: {text!r} is not a {noun} {hint}")
    return m


def parse_duration(text: str, *, flag: str) -> float:
    """Seconds in ``text`` ("20ms", "0.5s", "1.5 s", "250us", "0"); ValueError names ``flag``.

    A bare number other than 0 is refused: "20" could mean seconds or milliseconds.
    """
    m = _match(_DURATION, text, flag=flag, example="20ms", noun="duration",
               negative="is negative; a duration is >= 0", hint=_DURATION_HINT)
    value = float(m["num"])
    if m["unit"] is None and value != 0.0:
        raise ValueError(f"{flag}: {text!r} has no unit {_DURATION_HINT}")
    seconds = value * _UNIT_SECONDS[m["unit"] or "s"]
    if not math.isfinite(seconds):
        raise ValueError(f"{flag}: {text!r} is not a finite duration {_DURATION_HINT}")
    return seconds


def parse_probability(text: str, *, flag: str) -> float:
    """Probability in ``text``, a fraction ("0.3") or a percentage ("30%").

    ValueError names ``flag`` and the accepted forms.
    """
    m = _match(_PROBABILITY, text, flag=flag, example="0.3", noun="probability",
               negative="is outside [0, 1]", hint=_PROBABILITY_HINT)
    value = float(m["num"]) / (100.0 if m["pct"] else 1.0)
    if not 0.0 <= value <= 1.0:
        raise ValueError(f"{flag}: {text!r} is outside [0, 1] {_PROBABILITY_HINT}")
    return value


DELAY_DISTRIBUTIONS = ("uniform", "normal", "exponential", "pareto")
PARETO_SHAPE = 2.5  # tail index of the pareto delay: finite mean and variance, rare long stalls


@dataclass(frozen=True)
class LinkFaults:
    """Faults of one directed link (or, with the per-link / per-robot / partition entries, of a
    fleet's links): durations in seconds, probabilities in [0, 1].

    ``loss_burst`` > 1 makes loss bursty (Gilbert-Elliott: a two-state chain whose bad state loses
    every frame, with stationary loss ``loss`` and mean burst length ``loss_burst`` frames).
    ``delay_dist`` shapes the extra delay: uniform in delay +- jitter (netem's default), normal
    (sd jitter), exponential or pareto (mean jitter, one-sided; pareto has a heavy tail).
    ``link_loss`` ((src, dst, p), ...) and ``robot_loss`` ((robot, p), ...) raise the loss of some
    links (the largest applicable probability counts); ``partitions`` ((group_a, group_b, start_s,
    end_s), ...) cut every link between the two groups, both ways, in [start_s, end_s) measured
    from the link layer's origin (its first frame).
    """

    delay: float = 0.0
    jitter: float = 0.0
    loss: float = 0.0
    duplicate: float = 0.0
    reorder: float = 0.0
    loss_burst: float = 0.0
    delay_dist: str = "uniform"
    link_loss: tuple[tuple[int, int, float], ...] = ()
    robot_loss: tuple[tuple[int, float], ...] = ()
    partitions: tuple[tuple[tuple[int, ...], tuple[int, ...], float, float], ...] = ()

    def __post_init__(self) -> None:
        for name in ("delay", "jitter", "loss", "duplicate", "reorder", "loss_burst"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ValueError(f"{name} must be a number, got {type(value).__name__}")
            if not math.isfinite(value) or value < 0:
                raise ValueError(f"{name} must be finite and >= 0, got {value}")
            if name in ("loss", "duplicate", "reorder") and value > 1:
                raise ValueError(f"{name} is a probability, got {value} > 1")
            object.__setattr__(self, name, float(value))
        if self.delay_dist not in DELAY_DISTRIBUTIONS:
            raise ValueError(f"delay_dist must be one of {', '.join(DELAY_DISTRIBUTIONS)}, got {self.delay_dist!r}")
        if self.loss_burst > 1 and 0 < self.loss < 1 and self.good_to_bad > 1:
            raise ValueError(f"loss_burst (--loss-burst) {self.loss_burst:g} is too short for loss {self.loss:g} "
                             f"(needs loss <= loss_burst / (loss_burst + 1))")
        link_loss = [parse_link_loss(e) if isinstance(e, str) else e for e in self.link_loss]
        robot_loss = [parse_robot_loss(e) if isinstance(e, str) else e for e in self.robot_loss]
        object.__setattr__(self, "link_loss", tuple((_rid(a), _rid(b), _prob("link_loss", p)) for a, b, p in link_loss))
        object.__setattr__(self, "robot_loss", tuple((_rid(a), _prob("robot_loss", p)) for a, p in robot_loss))
        parts = []
        for entry in self.partitions:
            parts.append(parse_partition(entry) if isinstance(entry, str) else _check_partition(*entry))
        object.__setattr__(self, "partitions", tuple(parts))

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

    @property
    def good_to_bad(self) -> float:
        """Gilbert-Elliott: probability per frame of entering a loss burst."""
        return self.loss / ((1.0 - self.loss) * self.loss_burst)

    def extra_delay(self, u: float) -> float:
        """The delay of a copy from one uniform draw ``u`` in [0, 1), never below 0."""
        j = self.jitter
        if self.delay_dist == "uniform":
            extra = j * (2.0 * u - 1.0)
        elif self.delay_dist == "normal":
            extra = j * NormalDist().inv_cdf(min(max(u, 1e-12), 1.0 - 1e-12))
        elif self.delay_dist == "exponential":
            extra = -j * math.log1p(-u)
        else:  # pareto with mean j
            extra = j * (PARETO_SHAPE - 1.0) * ((1.0 - u) ** (-1.0 / PARETO_SHAPE) - 1.0)
        return max(0.0, self.delay + extra)

    def for_link(self, src: int, dst: int) -> LinkFaults:
        """The faults of the one link src -> dst (fleet-wide entries resolved, partitions kept out)."""
        loss = max([self.loss] + [p for a, b, p in self.link_loss if (a, b) == (src, dst)]
                   + [p for r, p in self.robot_loss if r in (src, dst)])
        return replace(self, loss=loss, link_loss=(), robot_loss=(), partitions=())

    def cut(self, src: int, dst: int, t: float) -> bool:
        """True when a partition separates src and dst at ``t`` seconds after the origin."""
        for a, b, t0, t1 in self.partitions:
            if t0 <= t < t1 and ((src in a and dst in b) or (src in b and dst in a)):
                return True
        return False


def _ids(text: str, what: str) -> tuple[int, ...]:
    try:
        return tuple(int(t) for t in text.split(","))
    except ValueError:
        raise ValueError(f"{what}: {text!r} is not a comma-separated list of robot ids") from None


def parse_link_loss(text: str) -> tuple[int, int, float]:
    """"SRC-DST:P" (e.g. "0-1:0.5" or "0-1:50%"): the loss of the directed link SRC -> DST."""
    link, sep, prob = text.partition(":")
    src, dash, dst = link.partition("-")
    if not (sep and dash):
        raise ValueError(f"{text!r} is not SRC-DST:P (e.g. 0-1:0.5)")
    (a,), (b,) = _ids(src, "link loss"), _ids(dst, "link loss")
    return a, b, parse_probability(prob, flag="link loss")


def parse_robot_loss(text: str) -> tuple[int, float]:
    """"ID:P" (e.g. "2:0.3"): the loss of every link into and out of robot ID."""
    rid, sep, prob = text.partition(":")
    if not sep:
        raise ValueError(f"{text!r} is not ID:P (e.g. 2:0.3)")
    (r,) = _ids(rid, "robot loss")
    return r, parse_probability(prob, flag="robot loss")


def parse_partition(text: str) -> tuple[tuple[int, ...], tuple[int, ...], float, float]:
    """"A,B/C,D@START-END" (e.g. "0,1/2,3@2s-5s"): robots {A,B} cut from {C,D} in [START, END)."""
    groups, sep, window = text.partition("@")
    left, slash, right = groups.partition("/")
    start, dash, end = window.partition("-")
    if not (sep and slash and dash):
        raise ValueError(f"{text!r} is not A,B/C,D@START-END (e.g. 0,1/2,3@2s-5s)")
    return _check_partition(_ids(left, "partition"), _ids(right, "partition"),
                            parse_duration(start, flag="partition start"), parse_duration(end, flag="partition end"))


def _check_partition(a: Any, b: Any, t0: Any, t1: Any) -> tuple[tuple[int, ...], tuple[int, ...], float, float]:
    ga, gb = tuple(sorted(_rid(i) for i in a)), tuple(sorted(_rid(i) for i in b))
    if not ga or not gb or set(ga) & set(gb):
        raise ValueError(f"partitions: two non-empty disjoint groups needed, got {ga} and {gb}")
    t0, t1 = float(t0), float(t1)
    if not (math.isfinite(t0) and math.isfinite(t1) and 0 <= t0 < t1):
        raise ValueError(f"partitions: need 0 <= start < end, got {t0:g}..{t1:g}")
    return ga, gb, t0, t1


def _rid(value: object) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise ValueError(f"robot ids in faults must be ints >= 0, got {value!r}")
    return value


def _prob(name: str, value: object) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 <= value <= 1:
        raise ValueError(f"{name}: a probability in [0, 1] is needed, got {value!r}")
    return float(value)


class Link:
    """One directed link with seeded faults.

    Every :meth:`send` consumes exactly six uniform draws, whatever the fault settings, so frame
    n's fate depends only on the seed and n (a link that leaves nothing to chance takes none:
    they could change nothing); e.g. the frames lost at loss 0.1 are a subset of
    those lost at 0.2 with the same seed.
    """

    def __init__(self, faults: LinkFaults, seed: int) -> None:
        self._faults = faults
        # the generator is made at the first draw, from the same seed (the same stream): a link that
        # takes no draws (below) has none -- ~1.2 kB each, N^2 links in a complete in-process fleet
        self._seed = seed
        self._rng: np.random.Generator | None = None
        # A link whose faults leave nothing to chance (no loss, duplicate, reorder or jitter)
        # delays every copy by exactly ``delay``: its draws could change nothing, so it takes
        # none (they cost ~1 us per frame, ~10 % of a 32-robot in-process fleet's time).
        self._fixed_delay: float | None = (
            faults.delay if faults.loss == 0 and faults.duplicate == 0 and faults.reorder == 0
            and faults.jitter == 0 else None)
        self._draws: list[float] = []  # uniform draws taken from _rng in batches, in stream order
        self._drawn = 0  # how many of them were used
        self._queue: list[tuple[float, int, bytes]] = []
        # Send-order stamps; LinkLayer shares one counter between its links to order ties.
        self._stamps: Iterator[int] = itertools.count()
        self._bad = False  # Gilbert-Elliott state (only with loss_burst > 1)
        self.bytes_sent = 0  # payload bytes handed to the link (lost ones included)
        self.sent = 0
        self.dropped = 0
        self.duplicated = 0
        self.reordered = 0
        self.delivered = 0

    @property
    def faults(self) -> LinkFaults:
        """The link's faults (fixed at construction: the draw schedule depends on them)."""
        return self._faults

    def _six_draws(self) -> list[float]:
        """The next six uniform draws of the link's stream: taken DRAW_BATCH sends at a time (one
        numpy call instead of one per frame; the stream, hence every frame's fate, is the same)."""
        i = self._drawn
        if i >= len(self._draws):
            if self._rng is None:
                self._rng = np.random.default_rng(self._seed)
            self._draws, i = self._rng.random(6 * DRAW_BATCH).tolist(), 0
        self._drawn = i + 6
        return self._draws[i : i + 6]

    def send(self, payload: bytes, now: float, *, cut: bool = False) -> None:
        """Hand ``payload`` to the link at time ``now`` (seconds, any origin); ``cut``: a
        partition swallows it (the draws are still taken, so the schedule after it is unchanged)."""
        if not math.isfinite(now):
            raise ValueError(f"now must be finite, got {now}")
        self.sent += 1
        self.bytes_sent += len(payload)
        fixed = self._fixed_delay
        if fixed is not None:  # nothing left to chance (see __init__): one copy, after `delay`
            if cut:
                self.dropped += 1
            else:
                heapq.heappush(self._queue, (now + fixed, next(self._stamps), payload))
            return
        f = self._faults
        u_loss, u_dup, u_jit1, u_hold1, u_jit2, u_hold2 = self._six_draws()
        if f.loss_burst > 1 and 0 < f.loss < 1:  # Gilbert-Elliott: the draw moves the chain
            self._bad = u_loss >= 1.0 / f.loss_burst if self._bad else u_loss < f.good_to_bad
            lost = self._bad
        else:
            lost = u_loss < f.loss
        if lost or cut:
            self.dropped += 1
            return
        copies = [(u_jit1, u_hold1)]
        if u_dup < f.duplicate:
            self.duplicated += 1
            copies.append((u_jit2, u_hold2))
        for u_jit, u_hold in copies:
            delay = f.extra_delay(u_jit)
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

    def __init__(self, faults: LinkFaults, seed: int, *, origin: float | None = None) -> None:
        """``origin``: time 0 of the partition schedule (None: the time of the first frame)."""
        self.faults = faults
        self.seed = seed
        self.origin = origin
        self._links: dict[tuple[int, int], Link] = {}
        self._stamps = itertools.count()

    def link(self, src: int, dst: int) -> Link:
        """The link src -> dst, created (seeded with link_seed) if new."""
        link = self._links.get((src, dst))
        if link is None:
            link = Link(self.faults.for_link(src, dst), link_seed(self.seed, src, dst))
            link._stamps = self._stamps  # ties across links break in layer-wide send order
            self._links[(src, dst)] = link
        return link

    def send(self, src: int, dst: int, payload: bytes, now: float) -> None:
        """Send ``payload`` from ``src`` to ``dst`` at time ``now``."""
        if self.origin is None:
            self.origin = now
        cut = bool(self.faults.partitions) and self.faults.cut(src, dst, now - self.origin)
        link = self._links.get((src, dst))  # (the link made already: every frame but a link's first)
        (link or self.link(src, dst)).send(payload, now, cut=cut)

    def next_due(self) -> float | None:
        """Earliest delivery time over all links, or None if nothing is in flight."""
        dues = [d for d in (link.next_due() for link in self._links.values()) if d is not None]
        return min(dues, default=None)

    def deliver(self, now: float) -> list[tuple[int, int, bytes]]:
        """(src, dst, payload) due by ``now`` on any link, by delivery time then send order."""
        due = [
            (t, stamp, src, dst, payload)
            for (src, dst), link in self._links.items()
            if link._queue and link._queue[0][0] <= now  # (Link.next_due, inline: ~1000 links a call)
            for t, stamp, payload in link._pop_due(now)
        ]
        due.sort()  # by time, then send order: the stamps are unique, so nothing after them is compared
        return [(src, dst, payload) for _, _, src, dst, payload in due]

    def stats(self) -> dict[str, int]:
        """Counters summed over all links."""
        total = dict.fromkeys((*_COUNTERS, "in_flight"), 0)
        for link in self._links.values():
            for name, value in link.stats().items():
                total[name] += value
        return total

    def bytes_sent(self) -> int:
        """Payload bytes handed to every link (what the robots put on the air, lost or not)."""
        return sum(link.bytes_sent for link in self._links.values())

    def link_stats(self) -> dict[tuple[int, int], dict[str, int]]:
        """Counters of each link used so far, keyed by (src, dst)."""
        return {key: link.stats() for key, link in sorted(self._links.items())}
