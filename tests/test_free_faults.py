"""Fault models of the link layer (issue 13): bursty loss, delay distributions, per-link and
per-robot loss, partition schedules -- seeded, serialisable in the fleet file, and what they do to
lockstep and free runs."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from agents.spec import FleetSpec
from launcher.simulate import simulate_fleet, simulate_free
from protocol.links import Link, LinkFaults, LinkLayer

from .conftest import make_run, max_function_error
from .test_links import fleet_and_robot_side_schedules


def _fates(faults: LinkFaults, n: int, seed: int = 1) -> np.ndarray:
    link = Link(faults, seed)
    lost = []
    for i in range(n):
        before = link.dropped
        link.send(b"x", float(i))
        lost.append(link.dropped > before)
    return np.array(lost)


def _mean_run(lost: np.ndarray) -> float:
    edges = np.diff(np.concatenate([[0], lost.astype(int), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    return float(np.mean(ends - starts))


def test_gilbert_elliott_keeps_the_loss_rate_and_makes_bursts():
    n = 60000
    bursty = _fates(LinkFaults(loss=0.3, loss_burst=5), n)
    plain = _fates(LinkFaults(loss=0.3), n)
    # 60000 frames in bursts of mean 5: ~3600 bursts, sd of the rate ~ 0.01
    assert abs(bursty.mean() - 0.3) < 0.03 and abs(plain.mean() - 0.3) < 0.01
    assert abs(_mean_run(bursty) - 5.0) < 0.4
    assert abs(_mean_run(plain) - 1 / 0.7) < 0.05


def test_loss_burst_too_short_for_the_loss_is_refused():
    with pytest.raises(ValueError, match="loss_burst"):
        LinkFaults(loss=0.9, loss_burst=2)


@pytest.mark.parametrize("dist", ["uniform", "normal", "exponential", "pareto"])
def test_delay_distributions_have_their_shape(dist):
    f = LinkFaults(delay=0.02, jitter=0.01, delay_dist=dist)
    u = (np.arange(20000) + 0.5) / 20000
    d = np.array([f.extra_delay(float(x)) for x in u])
    assert d.min() >= 0.0
    if dist == "uniform":
        assert d.min() >= 0.01 - 1e-9 and d.max() <= 0.03 + 1e-9 and abs(d.mean() - 0.02) < 1e-4
    elif dist == "normal":
        assert abs(d.mean() - 0.02) < 1e-3 and abs(d.std() - 0.01) < 1e-3
    else:  # one-sided, mean jitter on top of delay
        assert d.min() >= 0.02 and abs(d.mean() - 0.03) < 1.5e-3
    if dist == "pareto":
        assert d.max() > 0.02 + 10 * 0.01  # a heavy tail: rare long stalls


def test_per_link_and_per_robot_loss():
    f = LinkFaults(loss=0.0, link_loss=((0, 1, 1.0),), robot_loss=((3, 1.0),))
    layer = LinkLayer(f, seed=0)
    for i in range(50):
        for src, dst in ((0, 1), (1, 0), (3, 2), (2, 3), (1, 2)):
            layer.send(src, dst, b"x", i * 0.01)
    stats = layer.link_stats()
    assert stats[(0, 1)]["dropped"] == 50 and stats[(1, 0)]["dropped"] == 0
    assert stats[(3, 2)]["dropped"] == stats[(2, 3)]["dropped"] == 50 and stats[(1, 2)]["dropped"] == 0


def test_partition_cuts_both_ways_only_inside_its_window():
    f = LinkFaults(partitions=(((0, 1), (2, 3), 2.0, 5.0),))
    layer = LinkLayer(f, seed=0)
    t0 = 100.0  # the origin is the first frame's time
    for k in range(80):
        t = t0 + 0.1 * k
        layer.send(0, 2, t.hex().encode(), t)
        layer.send(3, 1, t.hex().encode(), t)
        layer.send(0, 1, t.hex().encode(), t)  # same side: never cut
    got = {(s, d, float.fromhex(p.decode()) - t0) for s, d, p in layer.deliver(math.inf)}
    for src, dst in ((0, 2), (3, 1)):
        times = sorted(t for s, d, t in got if (s, d) == (src, dst))
        assert times and all(t < 2.0 - 1e-9 or t >= 5.0 - 1e-9 for t in times)
        assert len(times) == 80 - 30
    assert sum(1 for s, d, _ in got if (s, d) == (0, 1)) == 80


def test_new_faults_survive_the_fleet_file(default_run):
    _, spec, _ = default_run
    f = LinkFaults(loss=0.2, loss_burst=4, delay_dist="pareto", jitter=0.01, link_loss=((0, 1, 0.5),),
                   robot_loss=((2, 0.4),), partitions=(((0,), (1, 2), 1.0, 2.5),))
    back = FleetSpec.from_json(json.loads(json.dumps(dataclasses.replace(spec, faults=f).to_json())))
    assert back.faults == f


def test_partition_until_five_seconds_lockstep_and_free_both_reach_the_exact_answer():
    """Robots {0,1} cut from {2,3} from 0.5 s to 5 s (shorter than dead_after 6 s): lockstep waits,
    free robots keep ticking on stale edge values; both end at the exact answer. (The cut starts early:
    uncut, the lockstep run -- a complete hard fleet, the exact end-game by default -- ends at 1.4 s.)"""
    world, spec, central = make_run(robots=4, seed=5, points=12)  # 12 points: the test in seconds
    cut = dataclasses.replace(spec, faults=LinkFaults(delay=0.01, partitions=(((0, 1), (2, 3), 0.5, 5.0),)))
    lock = simulate_fleet(cut)
    assert all(r["converged"] for r in lock.robots) and max_function_error(spec, central, lock.robots) < 1e-3
    assert lock.virtual_s > 5.0  # it did wait for the partition to heal
    uncut = simulate_fleet(dataclasses.replace(spec, faults=LinkFaults(delay=0.01)))
    assert uncut.virtual_s < 5.0 and [r["x"] for r in lock.robots] == [r["x"] for r in uncut.robots]  # the same bits
    free = simulate_free(cut, max_virtual_s=60.0)
    assert all(r["converged"] for r in free.robots) and max_function_error(spec, central, free.robots) < 1e-3
    assert free.virtual_s > 5.0 and free.link_stats["dropped"] > 0


def test_a_robot_side_layer_sees_the_simulators_new_faults_too():
    """Bursts, per-link / per-robot loss and delay shapes are per-link state: a robot process that
    passes only its incoming frames through its own layer sees the in-process fleet's schedule."""
    faults = LinkFaults(delay=0.01, jitter=0.008, loss=0.2, loss_burst=4, delay_dist="pareto",
                        link_loss=((0, 1, 0.6),), robot_loss=((2, 0.5),))
    into2, robot2, fleet = fleet_and_robot_side_schedules(faults, seed=7)
    assert into2 == robot2 and len(into2) > 100
    lost = {k: v["dropped"] / v["sent"] for k, v in fleet.link_stats().items() if v["sent"] > 50}
    # links 0->1, 1->3, 2->0, 3->2 carry the traffic; the per-link and per-robot losses are there
    assert min(lost[(0, 1)], lost[(2, 0)], lost[(3, 2)]) > lost[(1, 3)] + 0.15
