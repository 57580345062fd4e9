"""The free hub ADMM (agents/free_hub.py): its fixed point is the exact optimum, old packets are old
values (dropped by sequence number), Anderson leaves the answer where it is, and free runs under
loss and delay stop within the tolerance of the exact answer."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from agents.free_hub import FreeHubADMM, FreeHubParams
from agents.pdmm import Packet, build_free_core, free_algorithm_for
from launcher.simulate import simulate_free
from protocol.links import LinkFaults

from .conftest import make_run, max_function_error

BOUND = 1e-3


def _lockstep(cores: list[FreeHubADMM], ticks: int) -> None:
    """Every robot ticks, then every packet arrives (no loss, no delay)."""
    for _ in range(ticks):
        sent = [c.tick() for c in cores]
        for c, packets in zip(cores, sent):
            for p, j in zip(packets, c.neighbours):
                cores[j].receive(p)


@pytest.mark.parametrize("anderson, options", [(0, {}), (30, {}), (30, {"hub_every_tick": True, "hub_step_cap": 10.0})])
def test_the_fixed_point_is_the_exact_optimum(default_run, anderson, options):
    """At the fixed point every x_i is one z, mean_i t_i = z (so sum_i P (t_i - z) = 0: the
    subgradients P (t_i - z) of the f_i at z sum to zero) and z is the central solution; the
    every-tick step and the step cap leave it there."""
    _, spec, central = default_run
    params = {"tol": 1e-12, "max_ticks": 10**6, "hub_anderson": anderson, "hub_relax": 1.0 if anderson else 1.9,
              **options}
    cores = [build_free_core(spec, r, params, "hub") for r in spec.robot_ids]
    _lockstep(cores, 300 if anderson else 450)
    z = np.mean([c.values for c in cores], axis=0)
    scale = np.linalg.norm(z)
    assert max(np.linalg.norm(c.values - z) for c in cores) < 1e-7 * scale
    assert np.linalg.norm(np.mean([c._t for c in cores], axis=0) - z) < 1e-7 * scale
    rows = [{"x": c.values[:-1], "gamma": c.values[-1]} for c in cores]
    assert max_function_error(spec, central, rows) < 1e-6


def test_old_packets_are_dropped_and_the_newest_value_is_held(default_run):
    _, spec, _ = default_run
    core = build_free_core(spec, 0, {}, "hub")
    core.tick()
    j = core.neighbours[0]
    v = np.ones(core.dim)
    assert core.receive(Packet(j, 5, v, 2.0 * v, 0))
    assert not core.receive(Packet(j, 5, v, 7.0 * v, 0))  # duplicate
    assert not core.receive(Packet(j, 3, v, 9.0 * v, 0))  # overtaken by a newer one
    assert np.array_equal(core._held[j], 2.0 * v) and core.stale == 2
    assert core.receive(Packet(j, 6, v, 4.0 * v, 0))
    assert np.array_equal(core._held[j], 4.0 * v)  # the newest value, as it was sent


def test_the_hub_needs_a_complete_graph_and_auto_picks_it_only_there():
    _, ring, _ = make_run(robots=4, topology="ring")
    _, full, _ = make_run(robots=4)
    assert free_algorithm_for(ring) == "radmm" and free_algorithm_for(full) == "hub"
    assert free_algorithm_for(full, "radmm") == "radmm"
    me = ring.robots[0]
    with pytest.raises(ValueError, match="complete graph"):
        FreeHubADMM(ring.share(0), FreeHubParams())
    with pytest.raises(ValueError, match="hub_relax"):
        FreeHubParams(hub_relax=2.0)


def test_free_hub_under_loss_and_delay_stops_within_tol_of_the_exact_answer():
    """Seed 1 at a 5 ms period (test_free.py's loss-and-delay run covers seed 0 at 10 ms: auto is the hub)."""
    _, spec, central = make_run(seed=1)
    faulty = dataclasses.replace(spec, faults=LinkFaults(loss=0.3, delay=0.02))
    out = simulate_free(faulty, period=0.005, max_virtual_s=30.0)
    assert all(r["algorithm"] == "hub" for r in out.robots)
    assert all(r["stopped"] == "finished" and r["converged"] for r in out.robots), [r["stopped"] for r in out.robots]
    assert max_function_error(spec, central, out.robots) < BOUND
    assert out.link_stats["dropped"] > 0.2 * out.link_stats["sent"]


def test_the_stop_window_spans_robot_clock_time_from_the_period_alone(default_run):
    """hub_window: 0.2 s of the robot's clock, 20 to 40 ticks; a window given in params wins; the
    relaxed ADMM keeps its own window. (Stops within tol at 10 ms: test_free.py's loss-and-delay run.)"""
    from agents.free_hub import hub_window

    _, spec, _ = default_run
    assert [hub_window(p) for p in (0.002, 0.005, 0.0075, 0.01, 0.05)] == [40, 40, 27, 20, 20]
    assert build_free_core(spec, 0, {}, "hub", 0.01).params.window == 20
    assert build_free_core(spec, 0, {}, "hub", 0.005).params.window == 40
    assert build_free_core(spec, 0, {"window": 33}, "hub", 0.01).params.window == 33
    assert build_free_core(spec, 0, {}, "radmm", 0.01).params.window == 40


def _heard_everyone(spec, params: dict) -> list[FreeHubADMM]:
    """The default fleet's hub cores after two lockstep ticks: every robot holds every neighbour's a_j."""
    cores = [build_free_core(spec, r, params, "hub") for r in spec.robot_ids]
    _lockstep(cores, 2)
    return cores


@pytest.mark.parametrize("every", [True, False])
def test_a_tick_without_news_steps_only_when_stepping_every_tick(default_run, every):
    """Without a packet the robot's own block of its view is still new (its last solve), so the default
    steps; with hub_every_tick off, t_i waits for news."""
    _, spec, _ = default_run
    core = _heard_everyone(spec, {"hub_every_tick": every})[0]
    core.tick()  # uses the news of the last delivery
    before = core._t.copy()
    core.tick()  # nothing received since the last tick
    assert (not np.array_equal(core._t, before)) == every


def test_the_step_cap_bounds_the_extrapolation_under_delay(default_run):
    """Packets two ticks late (mixed-age views): with a cap, the Anderson correction of robot 0's own
    t_i (a block of the capped correction of the whole view) never exceeds hub_step_cap x the view's
    residual (P-weighted); without one it does. A cap of 0.5 binds here (uncapped ratio ~1.3, no loss);
    the default 10 binds on the far jumps of lossy runs."""
    _, spec, _ = default_run

    def largest_ratio(cap: float) -> float:
        cores = [build_free_core(spec, r, {"hub_step_cap": cap, "tol": 1e-12}, "hub") for r in spec.robot_ids]
        me, eta, worst, queue = cores[0], cores[0].params.hub_relax, 0.0, []
        for _ in range(120):
            ready = len(me._held) == len(me.neighbours) and me.ticks
            m = np.mean([me._a] + [me._held[j] for j in me.neighbours], axis=0) if ready else None
            plain = me._t + eta * (m - me._values) if ready else None
            queue.append([c.tick() for c in cores])
            if ready and me.hub_residual > 0:
                worst = max(worst, np.linalg.norm((me._t - plain) * np.sqrt(me._P)) / me.hub_residual)
            if len(queue) > 2:
                for c, packets in zip(cores, queue.pop(0)):
                    for p, j in zip(packets, c.neighbours):
                        cores[j].receive(p)
        return worst

    assert largest_ratio(0.5) <= 0.5 * (1 + 1e-9)
    assert largest_ratio(0.0) > 0.5
