"""The certified stop guard on the relay hub (agents/relay_hub.py): the bound every copy computes is
>= the true function error every round (4-ring, 6-line), the guard refuses a rule that always says
stop, certify 0 keeps main's frames and iterates, a checkpoint resumes bit for bit with the guard on."""

from __future__ import annotations

import math

import numpy as np
import pytest

import agents.admm as admm
import agents.relay_hub as relay_hub
from agents.certificate import PAYLOAD
from agents.relay_hub import RelayHubADMM
from agents.spec import build_core
from protocol.frames import StateUpdate

from .conftest import assert_bound_holds_every_round, make_run, max_function_error, run_to_end, step_all
from .test_admm import restored_twin, step_with_twin


@pytest.fixture(autouse=True)
def _admm_alone(monkeypatch):
    """These tests pin the guard on the relay's ADMM path; the paused end-game (relay_hub.RELAY_ENDGAME,
    tests/test_relay_endgame.py) would end their runs first, exactly, before the guard decides."""
    monkeypatch.setattr(relay_hub, "RELAY_ENDGAME", False)


def _errors(spec, central, cores) -> list[float]:
    b = spec.basis
    return [b.function_error(b.c_from_x(c.values[:-1]), c.values[-1], central.c, central.gamma) for c in cores]


@pytest.mark.parametrize("kwargs", [{"topology": "ring", "robots": 4}, {"topology": "line", "robots": 6}],
                         ids=["4-ring", "6-line"])
def test_the_relay_bound_holds_every_round_against_the_central_solve(kwargs, monkeypatch):
    monkeypatch.setattr(admm, "CERTIFY_EVERY_ROUND", True)  # (else only rounds whose rule passed)
    monkeypatch.setattr(admm, "CERTIFY_ARM", math.inf)  # (else the payloads only near the rule's stop)
    _, spec, central = make_run(tol=1e-14, max_rounds=500, **kwargs)
    cores = [build_core(spec, i, keep_trace=False) for i in spec.robot_ids]
    assert all(isinstance(c, RelayHubADMM) and c._cert_on for c in cores)

    def same_bound_on_every_copy(cores) -> None:  # every copy decides on the same bound (the same bits)
        assert len({c._fleet_bound for c in cores}) == 1

    bounded = assert_bound_holds_every_round(spec, central, cores, 500, _errors, same_bound_on_every_copy)
    assert bounded > 400 * len(cores)  # the certificate exists on most rounds (not a vacuous loop)
    assert max(c.error_bound() for c in cores) < 1e-2, [c.error_bound() for c in cores]  # certified by round 500


def test_the_relay_guard_refuses_a_rule_that_always_says_stop(monkeypatch):
    monkeypatch.setattr(relay_hub, "error_estimate", lambda *a, **k: 0.0)
    _, spec, central = make_run(topology="ring", robots=4)
    tol = spec.params["tol"]
    stops = {}
    for certify in (0.0, 10.0):
        spec.params["certify"] = certify
        cores = [build_core(spec, i, keep_trace=False) for i in spec.robot_ids]
        run_to_end(cores)
        assert all(c.converged for c in cores)
        bounds = [c.error_bound() for c in cores]
        errors = _errors(spec, central, cores)
        assert all(b is None or e <= b for e, b in zip(errors, bounds))
        stops[certify] = (cores[0].round, max(errors), bounds, cores[0]._fleet_bound)
    rounds, error, bounds, _ = stops[0.0]
    assert error > 1e-2 and bounds == [None] * 4
    guarded, error, bounds, _ = stops[10.0]
    # the stop decided on the bound of round k + 1 - D's x (<= the threshold); the robots report the
    # bound at their newest x, D flood rounds later (measured 0.0109 against 0.01)
    assert guarded > rounds and error < 10 * max(tol, 1e-3) and max(bounds) < 2 * 10 * max(tol, 1e-3)


def test_certify_zero_keeps_the_relay_frames_and_the_guard_never_moves_an_iterate():
    _, spec, _ = make_run(topology="ring", robots=4)
    runs = {}
    for certify in (0.0, 10.0):
        spec.params["certify"] = certify
        cores = [build_core(spec, i, keep_trace=False) for i in spec.robot_ids]
        values = []
        while not all(c.finished for c in cores) and len(values) < 100:
            step_all(cores)
            values.append(np.concatenate([c.values for c in cores]))
        runs[certify] = (cores, values)
    (off, v_off), (on, v_on) = runs[0.0], runs[10.0]
    n, d = 4, off[0].dim
    assert len(off[0].outgoing().values) == n * d and len(on[0].outgoing().values) == n * (d + PAYLOAD)
    assert all(np.array_equal(a, b) for a, b in zip(v_off, v_on))  # the same iterates, bit for bit
    assert all(c.result()["error_bound"] is None for c in off)


def test_a_relay_checkpoint_resumes_bit_for_bit_with_the_guard_on():
    _, spec, _ = make_run(topology="ring", robots=4)
    cores = [build_core(spec, i, keep_trace=False) for i in spec.robot_ids]
    for _ in range(40):
        step_all(cores)
    twin = restored_twin(spec, cores[1])
    while not all(c.finished for c in cores):
        step_with_twin(cores, twin, cores[1])
    assert twin.finished and twin.round == cores[1].round
    assert twin.result() == cores[1].result() and twin.error_bound() is not None


def test_the_relay_guard_is_off_where_the_payload_does_not_fit():
    _, spec, _ = make_run(topology="ring", robots=16)
    core = build_core(spec, 0, keep_trace=False)
    assert isinstance(core, RelayHubADMM) and not core._cert_on and core.frame_dim == 16 * core.dim
    assert core.result()["error_bound"] is None and math.isfinite(spec.params["tol"])


def test_certify_zero_sends_mains_relay_frames():
    """certify 0: main's relay layout (N vectors of M + 1, no payload) and the rule alone's stop (the 4-ring
    of rounds.md: 354 rounds where numpy, OpenBLAS and piqp run AVX2 kernels, 356 on AVX-512; the
    certified default stops at 327 on AVX-512), within tol of the exact answer. (Bit equality of the
    iterates with the guard on: the test above; a pinned round or hash of piqp's bits would tie the suite
    to one CPU.)"""
    _, spec, central = make_run(topology="ring", robots=4, certify=0.0)
    cores = [build_core(spec, i, keep_trace=False) for i in spec.robot_ids]
    while not all(c.finished for c in cores) and cores[0].round < 3000:
        assert all(len(c.outgoing().values) == 4 * c.dim for c in cores)
        step_all(cores)
    robots = [c.result() for c in cores]
    assert all(c.finished and c.converged and r["error_bound"] is None for c, r in zip(cores, robots))
    assert max_function_error(spec, central, robots) <= spec.params["tol"]


def test_arming_moves_no_relay_stop(monkeypatch):
    """Payloads only in armed rounds (`_armed`: _held within D of the hold) stop where payloads in
    every round stop, with the same bound: a stop needs the hold of passing rounds, held grows by one."""
    _, spec, _ = make_run(topology="line", robots=5)
    ends = []
    for arm in (admm.CERTIFY_ARM, math.inf):
        monkeypatch.setattr(admm, "CERTIFY_ARM", arm)
        cores = [build_core(spec, i, keep_trace=False) for i in spec.robot_ids]
        run_to_end(cores)
        ends.append((cores[0].round, [c.error_bound() for c in cores], [c.values.tobytes() for c in cores]))
    assert ends[0] == ends[1] and None not in ends[0][1]


@pytest.mark.parametrize("bad", [math.nan, math.inf, -5.0])
def test_a_forged_relayed_payload_neither_crashes_a_robot_nor_lets_it_stop(bad, monkeypatch):
    """Robot 0 of a 4-ring gets every relayed payload forged (non-finite -- a decoder would refuse
    it -- or negative) for the D + 1 rounds up to the one where the honest payloads let it stop (the
    rule patched to pass every round): the rounds run, the certificate is absent, no stop by it."""
    monkeypatch.setattr(relay_hub, "error_estimate", lambda *a, **k: 0.0)
    _, spec, _ = make_run(topology="ring", robots=4)
    cores = [build_core(spec, i, keep_trace=False) for i in spec.robot_ids]
    k = 0
    while not cores[0]._flags & 1:  # the first round whose guard passes
        step_all(cores)
        k += 1
    assert cores[0]._fleet_bound <= 10 * max(spec.params["tol"], 1e-3)
    cores = [build_core(spec, i, keep_trace=False) for i in spec.robot_ids]
    me, d, D = cores[0], cores[0].dim, cores[0].delay
    for _ in range(k - D - 1):
        step_all(cores)
    for _ in range(D + 1):
        updates = [c.outgoing() for c in cores]
        for c in cores:
            for u in updates:
                if c is me and u.sender != 0:
                    forged = u.values.copy().reshape(4, d + PAYLOAD)
                    forged[:, d:] = bad
                    u = StateUpdate(sender=u.sender, round=u.round, values=forged.ravel(), flags=u.flags,
                                    prev_values=u.prev_values, prev_flags=u.prev_flags)
                c.receive(u)
        for c in cores:
            c.advance()
    assert me.round == k and me._fleet_bound == math.inf and not me._flags & 1
    assert cores[2]._flags & 1  # (robot 2, which reads no value through robot 0, passes there)


def test_the_relay_warm_qp_runs_only_where_the_guard_decides(monkeypatch):
    """RELAY_WARM_QP (off by default: measured worse on the relay fleets, docs/algorithm.md) gives the
    local step a guess only where the certified guard decides (as the hub's admm.WARM_QP + cert_active):
    its exact KKT steps took plateau stops the rule alone could not refuse. certify 0: piqp, no guess."""
    from agents.problem import MarginQP

    assert relay_hub.RELAY_WARM_QP is False
    monkeypatch.setattr(relay_hub, "RELAY_WARM_QP", True)
    guesses: list[bool] = []
    solve = MarginQP.solve

    def spy(self, q, guess=None):
        guesses.append(guess is not None)
        return solve(self, q, guess)

    monkeypatch.setattr(MarginQP, "solve", spy)
    for certify, guarded in ((10.0, True), (0.0, False)):
        _, spec, _ = make_run(topology="ring", robots=4, certify=certify)
        cores = [build_core(spec, i, keep_trace=False) for i in spec.robot_ids]
        assert all(c._cert_on == guarded for c in cores)
        guesses.clear()
        for _ in range(5):
            step_all(cores)
        assert len(guesses) == 5 * 4 and all(g == guarded for g in guesses)
