"""The hub form's stall switch (agents/admm.py, `stall_watch`): when the fleet residual has not
fallen 10x within STALL_WINDOW rounds, every copy drops Anderson for the plain Douglas-Rachford
map in the same round, stops by the plain map's rule (`plain_stop_held`) while on it, and re-arms
Anderson after STALL_WINDOW plain rounds. Complete fleets of
24-48 robots stall under Anderson (docs/algorithm.md); none of them is cheap enough for a unit
test (24 robots: ~3000 rounds), so the switch is exercised on the 3-robot paper fleet with a short
window, and the rules on constructed residual sequences."""

from __future__ import annotations

import math

import pytest

import agents.admm as admm
from agents.admm import RATE_WINDOW, STALL_DROP, STALL_HOLD, plain_stop_held, stall_watch
from agents.spec import build_core

from .conftest import make_run, max_function_error, run_to_end, step_all
from .test_admm import restored_twin, step_with_twin
from .test_hub_drop import lockstep_round, survivors_reference

SHORT_WINDOW = 15  # the paper fleet's residual does not fall 10x within 15 rounds at some point


def _fire_round(residuals: list[float]) -> int | None:
    mark, since = math.inf, 0
    for k, r in enumerate(residuals):
        mark, since, fired = stall_watch(mark, since, r)
        if fired:
            return k
    return None


def test_stall_rule_fires_only_after_a_window_without_a_tenfold_fall():
    w = admm.STALL_WINDOW
    falling = [0.5 * (0.9 ** k) for k in range(5 * w)]  # 10x every ~22 rounds: progress
    assert _fire_round(falling) is None
    # progress, then a plateau: fires W rounds after the last residual that beat its mark 10x
    plateau = falling[:100] + [falling[99]] * (2 * w)
    last_mark = max(k for k in range(len(plateau)) if _is_mark(plateau, k))
    assert 0 < last_mark < 100  # set while falling; the plateau never beats it
    assert _fire_round(plateau) == last_mark + w
    assert all(plateau[k] > plateau[last_mark] / STALL_DROP for k in range(last_mark, len(plateau)))
    # a residual that keeps falling 10x within every window never fires, however slowly otherwise
    steps = [0.09 ** (k // (w - 1)) for k in range(4 * w)]
    assert _fire_round(steps) is None


def _is_mark(residuals: list[float], k: int) -> bool:
    """Whether residual k resets the watch (falls 10x below the mark in force)."""
    mark, since = math.inf, 0
    for i, r in enumerate(residuals[: k + 1]):
        new_mark, since, _ = stall_watch(mark, since, r)
        if i == k:
            return new_mark != mark
        mark = new_mark
    return False


def test_plain_stop_rule_does_not_stop_on_a_slow_sequence():
    """A residual of 1e-5 that shrinks 0.05 % a round is ~2e-2 from its fixed point: no stop, ever.
    The same level shrinking 5 % a round passes, but only after STALL_HOLD rounds in a row, and a
    single spike starts the count again."""
    tol = 1e-3
    slow = [1e-5 * 0.9995 ** k for k in range(1000)]
    held, window = 0, []
    for r in slow:
        window = (window + [r])[-2 * RATE_WINDOW:]
        held = plain_stop_held(window, held, tol)
        assert held == 0
    fast = [1e-5 * 0.95 ** k for k in range(200)]
    held, window, passed_at = 0, [], None
    for k, r in enumerate(fast):
        window = (window + [r])[-2 * RATE_WINDOW:]
        held = plain_stop_held(window, held, tol)
        if held >= STALL_HOLD and passed_at is None:
            passed_at = k
    assert passed_at is not None and passed_at >= 2 * RATE_WINDOW - 1 + STALL_HOLD - 1
    window = window[:-1] + [1e-1]  # a spike: the estimate is infinite, the count restarts
    assert plain_stop_held(window, STALL_HOLD, tol) == 0


@pytest.fixture()
def short_window(monkeypatch):
    monkeypatch.setattr(admm, "STALL_WINDOW", SHORT_WINDOW)
    admm._SHARED_STEPS.clear()  # steps taken with the real window must not be adopted
    yield
    admm._SHARED_STEPS.clear()


def test_a_switched_fleet_switches_together_and_stops_within_tol_of_the_exact_solution(short_window):
    _, spec, central = make_run(max_rounds=5000)
    cores = [build_core(spec, i) for i in spec.robot_ids]
    modes = {c.robot_id: [] for c in cores}  # each copy's map, round by round (True: plain)
    for _ in range(5000):
        if all(c.finished for c in cores):
            break
        step_all(cores)
        for c in cores:
            modes[c.robot_id].append(c._hub.plain)
            if c._hub.plain:
                assert not c._hub.hist_s  # the plain map keeps no Anderson history
    plain = modes[cores[0].robot_id]
    assert all(m == plain for m in modes.values())  # every copy switches and re-arms in the same rounds
    switches = [k for k in range(1, len(plain)) if plain[k] and not plain[k - 1]]
    rearms = [k for k in range(1, len(plain)) if plain[k - 1] and not plain[k]]
    assert switches and rearms and rearms[0] - switches[0] == SHORT_WINDOW
    assert all(c.finished and c.converged for c in cores) and len({c.round for c in cores}) == 1
    assert max_function_error(spec, central, [c.result() for c in cores]) < spec.params["tol"]
    hubs = [c._hub for c in cores]
    assert all(h.s.tobytes() == hubs[0].s.tobytes() for h in hubs[1:])


@pytest.mark.parametrize("before_switch", [True, False])
def test_the_switch_and_its_counters_survive_a_checkpoint_bit_for_bit(short_window, before_switch):
    """Restored before the switch (the watch's mark and count in flight) the twin switches in the
    same round; restored after it, it re-arms Anderson in the same round."""
    _, spec, _ = make_run(max_rounds=5000)
    cores = [build_core(spec, i) for i in spec.robot_ids]
    while not cores[1]._hub.plain:
        step_all(cores)
    switch_round = cores[1].round
    if before_switch:  # start again and stop a few rounds short of the switch
        admm._SHARED_STEPS.clear()
        cores = [build_core(spec, i) for i in spec.robot_ids]
        for _ in range(switch_round - 3):
            step_all(cores)
        assert not cores[1]._hub.plain and cores[1]._hub.since > 0
    twin = restored_twin(spec, cores[1])
    assert (twin._hub.mark, twin._hub.since, twin._hub.plain) == (cores[1]._hub.mark, cores[1]._hub.since,
                                                                  cores[1]._hub.plain)
    seen = set()
    for _ in range(2 * SHORT_WINDOW):
        step_with_twin(cores, twin, cores[1])
        assert twin._hub.plain == cores[1]._hub.plain and twin._held == cores[1]._held
        seen.add(twin._hub.plain)
    assert seen == {True, False} and twin.outgoing() == cores[1].outgoing()


def test_a_fleet_that_does_not_stall_is_unchanged_bit_for_bit(monkeypatch):
    """The paper fleet never meets the stall rule: its run equals a run with the switch disabled."""
    _, spec, _ = make_run()

    def run() -> list:
        admm._SHARED_STEPS.clear()
        cores = [build_core(spec, i) for i in spec.robot_ids]
        run_to_end(cores)
        assert not any(c._hub.plain for c in cores)
        return [(c.round, [c.trace[k].tobytes() for k in sorted(c.trace)]) for c in cores]

    with_switch = run()
    monkeypatch.setattr(admm, "STALL_WINDOW", 10 ** 9)
    assert run() == with_switch
    admm._SHARED_STEPS.clear()


@pytest.mark.parametrize("crash,offsets", [(10, (0, 2)), (25, (1, 0))])
def test_a_drop_seen_in_different_rounds_keeps_the_copies_switching_together(short_window, crash, offsets):
    """Survivors that drop a dead robot in different rounds see different residuals for a while;
    the watch restarts on every copy in the rounds they resynchronise, so they still switch in the
    same rounds and end on the survivors' exact answer."""
    world, spec, _ = make_run(robots=3, topology="complete", max_rounds=5000)
    cores = {i: build_core(spec, i) for i in spec.robot_ids}
    dead = spec.robot_ids[-1]
    drop_at = {i: crash + o for i, o in zip(spec.robot_ids[:-1], offsets)}
    survivors = [cores[i] for i in sorted(drop_at)]
    modes = []
    for k in range(5000):
        if all(c.finished for c in survivors):
            break
        lockstep_round(cores, k, dead, drop_at)
        modes.append(tuple(c._hub.plain for c in survivors))
    assert all(c.finished and c.converged for c in survivors) and len({c.round for c in survivors}) == 1
    assert all(len(set(m)) == 1 for m in modes) and any(m[0] for m in modes)
    ref = survivors_reference(world, spec, dead)
    assert max_function_error(spec, ref, [c.result() for c in survivors]) < spec.params["tol"]



def _median_by_comparisons(xs: list[float]) -> float:
    """`_median` as it was before its sum-first NaN test (main 1daaef1): the reference."""
    if not all(x == x for x in xs):
        return math.nan
    s, h = sorted(xs), len(xs) // 2
    return s[h] if len(xs) % 2 else (s[h - 1] + s[h]) / 2


def test_median_is_numpys_on_nan_inf_and_cancelling_windows():
    """`_median` (the hub's stop rule, twice a robot-round): its NaN test is a plain sum first (NaN
    only if some entry is NaN, or an inf meets a -inf), then entry by entry. Against the form that
    compared every entry (bits, the sign of a zero included) and np.median (values) -- windows with
    a NaN anywhere, infinities of both signs (a NaN sum without a NaN), huge entries whose sum
    overflows, signed zeros, odd and even lengths."""
    import numpy as np

    rng = np.random.default_rng(5)
    specials = [math.nan, math.inf, -math.inf, 1e308, -1e308, 0.0, -0.0, 5e-324]
    cases = [[math.inf, -math.inf], [1e308, 1e308, -math.inf], [math.nan], [0.0, -0.0], [-0.0, 0.0, -0.0], [-0.0]]
    for _ in range(3000):
        xs = list(rng.lognormal(-7.0, 2.0, size=rng.integers(1, 2 * RATE_WINDOW + 1)))
        for i in rng.integers(0, len(xs), size=rng.integers(0, 3)):
            xs[i] = specials[rng.integers(len(specials))]
        cases.append([float(x) for x in xs])
    for xs in cases:
        got, ref = admm._median(xs), _median_by_comparisons(xs)
        assert (math.isnan(got) and math.isnan(ref)) or (got == ref and math.copysign(1, got) == math.copysign(1, ref)), xs
        with np.errstate(invalid="ignore", over="ignore"):  # (np.median's own inf - inf)
            want = float(np.median(xs))
        assert (math.isnan(got) and math.isnan(want)) or got == want, xs
