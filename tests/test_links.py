"""Fault-injecting links: exact clean behaviour, fault statistics, determinism, parsing.

Statistical checks use a 5-sigma binomial (or normal) bound: the runs are seeded, so they are
deterministic, and the bound documents how far from the nominal rate a correct link could be.
"""

import math

import pytest

from protocol.links import (
    REORDER_HOLD_MIN,
    Link,
    LinkFaults,
    LinkLayer,
    link_seed,
    parse_duration,
    parse_probability,
)

N = 20_000


def within_binomial(k: int, n: int, p: float, z: float = 5.0) -> bool:
    return abs(k - n * p) <= z * math.sqrt(n * p * (1 - p))


def run(link: Link, sends: list[tuple[float, bytes]]) -> list[tuple[float, bytes]]:
    """Send everything, then drain the link at each due time: (delivery time, payload)."""
    for t, payload in sends:
        link.send(payload, t)
    out = []
    while (t := link.next_due()) is not None:
        out.extend((t, p) for p in link.deliver(t))
    return out


def numbered(n: int, spacing: float = 0.001) -> list[tuple[float, bytes]]:
    return [(i * spacing, i.to_bytes(4, "big")) for i in range(n)]


def index(payload: bytes) -> int:
    return int.from_bytes(payload, "big")


def check_invariant(link_or_layer) -> None:
    s = link_or_layer.stats()
    assert s["sent"] - s["dropped"] + s["duplicated"] == s["delivered"] + s["in_flight"]


# ------------------------------------------------------------------------------------- parsing


@pytest.mark.parametrize(
    ("text", "seconds"),
    [("20ms", 0.02), ("0.5s", 0.5), ("1.5 s", 1.5), ("0", 0.0), ("0.0", 0.0), ("250us", 250e-6),
     (" 20ms ", 0.02), ("1e3ms", 1.0), (".5s", 0.5), ("0ms", 0.0), ("2s", 2.0)],
)
def test_parse_duration_accepts(text, seconds):
    assert parse_duration(text, flag="--delay") == pytest.approx(seconds, rel=1e-15)


# Rejected text, grouped by the verdict that follows the flag and the quoted text.
DURATION_REJECTIONS = {
    "is not a duration (use e.g. 20ms or 0.5s)": ["20 parsecs"],
    "is negative": ["-5ms"],
    "has no unit": ["20"],
    "is not a finite duration": ["1e400s"],
    "is not a duration": ["nan", "nanms", "infs", "", "ms", "20 ms s", "20MS"],
}
PROBABILITY_REJECTIONS = {
    "is outside [0, 1]": ["1.5", "101%", "-0.1", "-5%"],
    "is not a probability": ["nan", "inf", "a lot", "", "30%%"],
}
REJECTIONS = [
    (parse, flag, text, why)
    for parse, flag, table in ((parse_duration, "--jitter", DURATION_REJECTIONS),
                               (parse_probability, "--loss", PROBABILITY_REJECTIONS))
    for why, texts in table.items()
    for text in texts
]


@pytest.mark.parametrize(("parse", "flag", "text", "why"), REJECTIONS)
def test_parsers_reject_naming_the_flag_and_the_text(parse, flag, text, why):
    with pytest.raises(ValueError) as err:
        parse(text, flag=flag)
    assert str(err.value).startswith(f"{flag}: {text!r} {why}")


def test_parse_duration_requires_text():
    with pytest.raises(ValueError, match="--delay: expected text"):
        parse_duration(0.02, flag="--delay")


@pytest.mark.parametrize(
    ("text", "p"),
    [("0.3", 0.3), ("30%", 0.3), ("30 %", 0.3), ("0", 0.0), ("1", 1.0), ("100%", 1.0),
     ("0%", 0.0), ("1e-3", 0.001), (".25", 0.25), ("12.5%", 0.125)],
)
def test_parse_probability_accepts(text, p):
    assert parse_probability(text, flag="--loss") == p


def test_parse_probability_requires_text():
    with pytest.raises(ValueError, match="--loss: expected text"):
        parse_probability(0.3, flag="--loss")


# ---------------------------------------------------------------------------------- LinkFaults


def test_link_faults_none_is_clean():
    assert LinkFaults.none() == LinkFaults() and LinkFaults.none().is_clean
    assert LinkFaults(delay=0, jitter=0.0).is_clean
    for name in ("delay", "jitter", "loss", "duplicate", "reorder"):
        assert not LinkFaults(**{name: 0.1}).is_clean


@pytest.mark.parametrize(
    "kwargs",
    [dict(delay=-0.001), dict(jitter=math.nan), dict(delay=math.inf), dict(loss=1.01),
     dict(duplicate=-0.1), dict(reorder=2.0), dict(loss=True), dict(delay="20ms")],
)
def test_link_faults_validation(kwargs):
    with pytest.raises(ValueError, match=next(iter(kwargs))):
        LinkFaults(**kwargs)


def test_link_faults_stores_floats():
    f = LinkFaults(delay=1, loss=1)
    assert type(f.delay) is float and type(f.loss) is float


# ----------------------------------------------------------------------------------------- Link


def test_clean_link_delivers_at_send_time_in_order():
    link = Link(LinkFaults.none(), seed=1)
    assert link.next_due() is None and link.deliver(1e9) == []
    for i in range(100):
        now = 0.37 * i
        link.send(b"a%d" % i, now)
        link.send(b"b%d" % i, now)
        assert link.next_due() == now
        assert link.deliver(now) == [b"a%d" % i, b"b%d" % i]
        assert link.next_due() is None
    assert link.stats() == dict(sent=200, dropped=0, duplicated=0, reordered=0, delivered=200,
                                in_flight=0)


def test_nothing_is_delivered_early():
    link = Link(LinkFaults(delay=0.02), seed=1)
    link.send(b"x", 1.0)
    assert link.deliver(1.0199) == [] and link.in_flight == 1
    assert link.next_due() == pytest.approx(1.02)
    assert link.deliver(5.0) == [b"x"]


def test_send_refuses_non_finite_time():
    with pytest.raises(ValueError):
        Link(LinkFaults.none(), seed=1).send(b"x", math.nan)


@pytest.mark.parametrize("p", [0.01, 0.3, 0.9])
def test_loss_rate(p):
    link = Link(LinkFaults(loss=p), seed=7)
    delivered = run(link, numbered(N))
    assert within_binomial(link.dropped, N, p)
    assert len(delivered) == N - link.dropped == link.delivered
    assert [index(x) for _, x in delivered] == sorted(index(x) for _, x in delivered)
    check_invariant(link)


def test_loss_extremes():
    assert run(Link(LinkFaults(loss=1.0), seed=1), numbered(1000)) == []
    assert len(run(Link(LinkFaults(loss=0.0), seed=1), numbered(1000))) == 1000


def test_loss_is_monotone_in_probability_for_one_seed():
    """Common random numbers: raising loss only adds losses, so sweeps compare like with like."""
    kept = {
        p: {x for _, x in run(Link(LinkFaults(loss=p, jitter=0.01), seed=3), numbered(5000))}
        for p in (0.1, 0.2, 0.5)
    }
    assert kept[0.5] < kept[0.2] < kept[0.1]


@pytest.mark.parametrize(("delay", "jitter"), [(0.02, 0.0), (0.02, 0.005), (0.1, 0.1)])
def test_delay_and_jitter_bounds(delay, jitter):
    n = 5000
    sends = numbered(n, spacing=0.0003)
    link = Link(LinkFaults(delay=delay, jitter=jitter), seed=11)
    sent_at = dict((x, t) for t, x in sends)
    latency = [t - sent_at[x] for t, x in run(link, sends)]
    assert len(latency) == n
    eps = 1e-9
    assert min(latency) >= delay - jitter - eps and max(latency) <= delay + jitter + eps
    mean = sum(latency) / n
    sd = jitter / math.sqrt(3)  # of U(-jitter, jitter)
    assert abs(mean - delay) <= 5 * sd / math.sqrt(n) + eps
    if jitter:  # the whole window is used, not just its middle
        assert min(latency) < delay - 0.95 * jitter and max(latency) > delay + 0.95 * jitter


def test_jitter_larger_than_delay_is_clipped_at_zero():
    delay, jitter = 0.001, 0.004
    sends = numbered(N, spacing=0.01)
    sent_at = dict((x, t) for t, x in sends)
    latency = [t - sent_at[x] for t, x in run(Link(LinkFaults(delay=delay, jitter=jitter), 5),
                                              sends)]
    assert min(latency) >= 0 and max(latency) <= delay + jitter + 1e-12
    p_zero = (jitter - delay) / (2 * jitter)  # P(delay + U(-jitter, jitter) <= 0)
    assert within_binomial(sum(1 for d in latency if d == 0.0), N, p_zero)


def test_constant_delay_keeps_order():
    out = run(Link(LinkFaults(delay=0.05), seed=2), numbered(1000, spacing=0.0))
    assert [index(x) for _, x in out] == list(range(1000))


@pytest.mark.parametrize("p", [0.05, 0.5])
def test_duplicate_rate(p):
    link = Link(LinkFaults(duplicate=p, delay=0.01, jitter=0.005), seed=13)
    out = run(link, numbered(N))
    copies: dict[bytes, int] = {}
    for _, x in out:
        copies[x] = copies.get(x, 0) + 1
    assert len(copies) == N and set(copies.values()) <= {1, 2}
    twice = sum(1 for c in copies.values() if c == 2)
    assert twice == link.duplicated and within_binomial(twice, N, p)
    assert link.delivered == N + twice
    check_invariant(link)


def test_duplicates_get_their_own_delay():
    link = Link(LinkFaults(duplicate=1.0, delay=0.01, jitter=0.005), seed=13)
    out = run(link, numbered(200, spacing=1.0))
    times: dict[bytes, list[float]] = {}
    for t, x in out:
        times.setdefault(x, []).append(t)
    assert all(len(ts) == 2 for ts in times.values())
    assert sum(1 for a, b in times.values() if a != b) > 190


def test_clean_duplicate_copies_arrive_together_in_send_order():
    link = Link(LinkFaults(duplicate=1.0), seed=1)
    link.send(b"a", 0.0)
    link.send(b"b", 0.0)
    assert link.deliver(0.0) == [b"a", b"a", b"b", b"b"]


@pytest.mark.parametrize(("delay", "jitter"), [(0.0, 0.0), (0.01, 0.0), (0.01, 0.004)])
def test_reorder_holds_frames_back_so_later_ones_overtake(delay, jitter):
    p, spacing, n = 0.1, 0.0002, N
    faults = LinkFaults(delay=delay, jitter=jitter, reorder=p)
    link = Link(faults, seed=17)
    sends = numbered(n, spacing)
    out = run(link, sends)
    assert within_binomial(link.reordered, n, p)
    order = [index(x) for _, x in out]
    assert order != sorted(order) and sorted(order) == list(range(n))
    # Documented guarantee: an unheld frame sent less than hold - (delay + jitter) after a held
    # frame is delivered before it.
    assert faults.reorder_hold == max(2 * (delay + jitter), REORDER_HOLD_MIN)
    window = faults.reorder_hold - (delay + jitter)
    arrival = {index(x): t for t, x in out}
    sent_at = {index(x): t for t, x in sends}
    latency = {i: arrival[i] - sent_at[i] for i in arrival}
    held = {i for i, d in latency.items() if d > delay + jitter + 1e-12}
    assert within_binomial(len(held), n, p)
    for i in list(held)[:300]:
        for j in range(i + 1, min(n, i + int(window / spacing))):
            if j not in held and sent_at[j] - sent_at[i] < window - 1e-12:
                assert arrival[j] < arrival[i]


def test_same_seed_same_schedule_different_seed_differs():
    faults = LinkFaults(delay=0.02, jitter=0.01, loss=0.2, duplicate=0.1, reorder=0.1)
    sends = numbered(2000)
    a = run(Link(faults, seed=42), sends)
    b = run(Link(faults, seed=42), sends)
    c = run(Link(faults, seed=43), sends)
    assert a == b and a != c


def test_schedule_does_not_depend_on_when_deliver_is_called():
    faults = LinkFaults(delay=0.02, jitter=0.01, duplicate=0.1, reorder=0.1)
    sends = numbered(3000)
    reference = run(Link(faults, seed=9), sends)
    link, out = Link(faults, seed=9), []
    for t, x in sends:  # interleaved: deliver everything due before each send
        out.extend((t, p) for p in link.deliver(t))
        link.send(x, t)
        check_invariant(link)
    while (t := link.next_due()) is not None:
        out.extend((t, p) for p in link.deliver(t))
    assert [x for _, x in out] == [x for _, x in reference]


# --------------------------------------------------------------------------- seeds and layers


def test_link_seed_deterministic_and_distinct():
    seeds = {link_seed(base, s, d) for base in range(4) for s in range(40) for d in range(40)}
    assert len(seeds) == 4 * 40 * 40
    assert link_seed(7, 1, 2) == link_seed(7, 1, 2) != link_seed(7, 2, 1)
    assert link_seed(-1, 0, 0) != link_seed(1, 0, 0)
    assert all(0 <= s < 2**64 for s in seeds)


@pytest.mark.parametrize("args", [(1.0, 1, 2), (1, True, 2), (1, 2, "3")])
def test_link_seed_requires_ints(args):
    with pytest.raises(ValueError):
        link_seed(*args)


def test_layer_merges_links_by_time_then_send_order():
    layer = LinkLayer(LinkFaults.none(), seed=0)
    layer.send(2, 1, b"first", 0.0)
    layer.send(0, 1, b"second", 0.0)
    layer.send(1, 0, b"third", 0.0)
    assert layer.next_due() == 0.0
    assert layer.deliver(0.0) == [(2, 1, b"first"), (0, 1, b"second"), (1, 0, b"third")]
    assert layer.next_due() is None

    layer = LinkLayer(LinkFaults(delay=0.01, jitter=0.005), seed=0)
    for i in range(300):
        layer.send(i % 3, (i + 1) % 3, i.to_bytes(2, "big"), i * 0.001)
    times = []
    while (t := layer.next_due()) is not None:
        delivered = layer.deliver(t)
        assert delivered
        times.extend([t] * len(delivered))
    assert times == sorted(times) and len(times) == 300


def test_layer_stats_aggregate_links():
    layer = LinkLayer(LinkFaults(loss=0.3, duplicate=0.2, reorder=0.1, delay=0.01), seed=5)
    for i in range(3000):
        layer.send(i % 4, (i // 4) % 4, b"x", i * 0.001)
    layer.deliver(1.5)
    check_invariant(layer)
    per_link = layer.link_stats()
    assert set(per_link) == {(s, d) for s in range(4) for d in range(4)}
    total = layer.stats()
    for name, value in total.items():
        assert value == sum(s[name] for s in per_link.values())
    assert total["sent"] == 3000 and total["in_flight"] > 0
    layer.deliver(math.inf)
    assert layer.stats()["in_flight"] == 0
    assert LinkLayer(LinkFaults.none(), seed=0).stats() == dict(
        sent=0, dropped=0, duplicated=0, reordered=0, delivered=0, in_flight=0)


def fleet_and_robot_side_schedules(faults: LinkFaults, seed: int) -> tuple[list, list, LinkLayer]:
    """2000 frames among 5 robots through one fleet-wide layer (the in-process simulator) and,
    for the frames into robot 2, through robot 2's own layer (a robot process): the deliveries
    into robot 2 of each, as (time, *item), and the fleet's layer (for its link statistics)."""
    fleet, robot2 = LinkLayer(faults, seed=seed), LinkLayer(faults, seed=seed)
    for i in range(2000):
        src, dst, t = i % 5, (i * 7 + 1) % 5, i * 0.002
        if src == dst:
            continue
        fleet.send(src, dst, i.to_bytes(2, "big"), t)
        if dst == 2:
            robot2.send(src, dst, i.to_bytes(2, "big"), t)

    def drain(layer):
        out = []
        while (t := layer.next_due()) is not None:
            out.extend((t, *item) for item in layer.deliver(t))
        return out

    return [item for item in drain(fleet) if item[2] == 2], drain(robot2), fleet


def test_robot_side_layer_sees_the_simulators_faults():
    """A robot passing only its incoming frames through its own layer gets the same schedule
    for those links as the in-process simulator that carries every link of the fleet."""
    faults = LinkFaults(delay=0.01, jitter=0.008, loss=0.2, duplicate=0.1, reorder=0.1)
    into2, robot2, _ = fleet_and_robot_side_schedules(faults, seed=99)
    assert into2 == robot2 and len(into2) > 200


def test_batched_draws_give_each_frame_the_fate_of_its_own_six():
    """The link takes its uniforms DRAW_BATCH sends at a time; frame n still gets draws 6n..6n+5
    of its seed's stream (docs/protocol.md): the schedule equals one written from six draws per send."""
    import numpy as np

    from protocol.links import DRAW_BATCH, Link, LinkFaults

    faults = LinkFaults(delay=0.01, jitter=0.004, loss=0.3, duplicate=0.2, reorder=0.1)
    link, ref = Link(faults, seed=11), np.random.default_rng(11)
    want = []
    for n in range(3 * DRAW_BATCH + 5):
        now = 0.001 * n
        link.send(n.to_bytes(2, "little"), now)
        u = ref.random(6).tolist()
        if u[0] < faults.loss:
            continue
        for k in (0, 1) if u[1] < faults.duplicate else (0,):
            hold = faults.reorder_hold if u[3 + 2 * k] < faults.reorder else 0.0
            want.append((now + faults.extra_delay(u[2 + 2 * k]) + hold, n))
    got = sorted((t, int.from_bytes(p, "little")) for t, _, p in link._queue)
    assert got == sorted(want) and link.dropped > 0 and link.duplicated > 0 and link.reordered > 0


def test_a_link_that_leaves_nothing_to_chance_delivers_like_the_drawn_schedule():
    """No loss, duplicate, reorder or jitter: the link takes no draws, and every frame is due at
    send time + delay, in send order, as a link that draws (a tiny loss never hit) schedules it."""
    from protocol.links import Link, LinkFaults

    fixed, drawn = Link(LinkFaults(delay=0.02), seed=3), Link(LinkFaults(delay=0.02, loss=1e-300), seed=3)
    for n in range(40):
        for link in (fixed, drawn):
            link.send(bytes([n]), 0.005 * (n // 3), cut=n == 7)
    assert fixed._queue == drawn._queue and fixed.stats() == drawn.stats() and fixed.dropped == 1
    assert fixed._draws == [] and drawn._draws  # the fixed link never drew
