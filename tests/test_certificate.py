"""The certified stop guard (agents/certificate.py, ADMMParams.certify): the bound is proven >= the true
function error, the guard refuses stops the rule alone makes far from the optimum, certify = 0 keeps
today's frames and iterates, checkpoints resume bit for bit with the guard on, and bad payloads neither
crash a robot nor let it stop by the certificate."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

import agents.admm as admm
from agents.admm import ADMMParams
from agents.certificate import PAYLOAD, fleet_certificate, margin_extremes, payload, sides
from agents.spec import build_core
from protocol.frames import StateUpdate

from .conftest import assert_bound_holds_every_round, make_run, max_function_error, run_to_end, step_all
from .test_admm import restored_twin, step_with_twin

L_SHAPE = "x,y\n-2,-1.5\n2,-1.5\n2,0\n0,0\n0,1.5\n-2,1.5\n"

# two points on a line: phi = (1, 0) labelled +1, phi = (-1, 0) labelled -1; rows y [phi, 1].
# Optimum x* = (1, 0), gamma* = 0, P* = 1/2, multipliers 1/2 each.
ROWS = np.array([[1.0, 0.0, 1.0], [1.0, 0.0, -1.0]])
POS = sides(ROWS)


def _two_point(lam: np.ndarray, x_bar: np.ndarray):
    margins = margin_extremes(ROWS[:, :-1] @ x_bar, POS)
    w_x = ROWS[:, :-1].T @ lam  # the sum of the robots' gradients, residual 0
    spread = float(np.linalg.norm(lam[POS[0]] @ ROWS[POS[0], :-1]))  # |u+|: the positive rows' lam_i phi_i
    return fleet_certificate(payload(margins, POS, lam, 0.0, spread)[None], x_bar, w_x)


def _error(v: np.ndarray) -> float:  # function_error against (x*, gamma*) = ((1, 0), 0) on this toy
    return float(np.linalg.norm(v[:-1] - [1.0, 0.0])) / 1.0 + abs(v[-1]) / 1.0


def test_the_bound_is_tight_at_the_optimum_and_an_upper_bound_elsewhere():
    cert = _two_point(np.array([0.5, 0.5]), np.array([1.0, 0.0]))
    # at the optimum the radius is the rounding allowance alone (c = ROUNDING x the sum of |terms|: 2e-13;
    # gamma's half-width 3 e0: slope max(|u+| / S+, (|u+| + |W|) / S-) = 3)
    assert cert.e0 < 1e-6 and cert.bound(np.array([1.0, 0.0, 0.0])) < 3e-6
    v = np.array([1.1, 0.0, 0.1])
    assert _error(v) <= cert.bound(v) <= _error(v) + 3e-6  # tight: 0.2
    # an unbalanced dual and a mean off the optimum: still a bound, looser
    cert = _two_point(np.array([0.7, 0.5]), np.array([0.8, 0.2]))  # (2x off: none, the slope grows)
    for v in (np.array([1.0, 0.0, 0.0]), np.array([0.7, 0.2, 0.05]), np.array([2.0, -1.0, 1.0])):
        assert cert.bound(v) >= _error(v)
    # one side's multipliers empty: no gamma interval, no certificate
    assert _two_point(np.array([1.0, 0.0]), np.array([1.0, 0.0])) is None


@pytest.mark.parametrize("bad", [math.nan, math.inf, -1.0])
def test_a_bad_payload_gives_no_certificate(bad):
    good = payload((1.0, -1.0), POS, np.array([0.5, 0.5]), 0.0, 1.0)
    assert fleet_certificate(good[None], np.array([1.0, 0.0]), np.array([1.0, 0.0])) is not None
    for k in range(2, PAYLOAD):  # a sum, the residual or |u+_l| not finite or negative
        forged = good.copy()
        forged[k] = bad
        assert fleet_certificate(forged[None], np.array([1.0, 0.0]), np.array([1.0, 0.0])) is None
    assert payload((math.nan, -1.0), POS, np.array([0.5, 0.5]), 0.0, 1.0).tolist() == [0.0] * PAYLOAD  # sent as none


@pytest.mark.parametrize("k", range(PAYLOAD))
def test_a_huge_finite_payload_overflows_to_no_certificate_never_an_error(k):
    """A forged or garbled frame with finite but huge numbers: float ** and fsum would raise
    OverflowError inside the copy's certificate (a robot's crash); it gives no certificate instead."""
    good = payload((1.0, -1.0), POS, np.array([0.5, 0.5]), 0.0, 1.0)
    for huge in (1e300, -1e300, 1e-300):
        forged = good.copy()
        forged[k] = huge
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # not even a RuntimeWarning on the robot's stderr
            cert = fleet_certificate(np.vstack([forged, good]), np.array([1.0, 0.0]), np.array([1.0, 0.0]))
            assert cert is None or math.isfinite(cert.bound(np.array([1.0, 0.0, 0.0])))
            if cert is not None:
                assert cert.bound(np.array([1e300, -1e300, 1e300])) == math.inf


#: as `--certify 10`: the guard asked for (a complete hard fleet silent on it runs the exact end-game since
#: branch hardon, agents/spec.py `endgame_default`)
GUARDED = {"certify": 10.0}


def _errors(spec, central, cores) -> list[float]:
    b = spec.basis
    return [b.function_error(b.c_from_x(c.values[:-1]), c.values[-1], central.c, central.gamma) for c in cores]


@pytest.mark.parametrize("kwargs", [{}, {"shape": "crescent"}], ids=["paper", "crescent"])
def test_the_bound_holds_every_round_against_the_central_solve(kwargs, monkeypatch):
    monkeypatch.setattr(admm, "CERTIFY_EVERY_ROUND", True)  # (else only rounds whose rule passed)
    monkeypatch.setattr(admm, "CERTIFY_ARM", math.inf)  # (else the payloads only near the rule's stop)
    _, spec, central = make_run(tol=1e-14, max_rounds=160, **GUARDED, **kwargs)
    cores = [build_core(spec, i, keep_trace=False) for i in spec.robot_ids]
    bounded = assert_bound_holds_every_round(spec, central, cores, 160, _errors)
    assert bounded > 100 * len(cores)  # the certificate exists on most rounds (not a vacuous loop)
    assert max(c.error_bound() for c in cores) < 1e-3  # and certifies these fleets by round 160


def _stop(spec, central, certify: float) -> tuple[int, float, float | None]:
    spec.params["certify"] = certify
    cores = [build_core(spec, i, keep_trace=False) for i in spec.robot_ids]
    run_to_end(cores)
    assert all(c.converged for c in cores)
    bounds = [c.error_bound() for c in cores]
    return cores[0].round, max(_errors(spec, central, cores)), None if None in bounds else max(bounds)


def test_the_guard_refuses_the_l_shapes_plateau_stop_with_the_warm_qp(tmp_path, monkeypatch):
    """With WARM_QP the rule alone stops the L shape of test_simulate on an Anderson plateau (measured:
    round 112, error 6.7e-2); the guard holds the fleet until its certified bound is <= 10 tol."""
    # the warm QP also without the guard (by default it runs only where the guard decides)
    monkeypatch.setattr(admm.ConsensusADMM, "_warm_guess", lambda self: self._values if self._C is None else None)
    shape = tmp_path / "l.csv"
    shape.write_text(L_SHAPE)
    _, spec, central = make_run(shape_file=str(shape))
    tol = spec.params["tol"]
    rounds, error, bound = _stop(spec, central, 0.0)
    assert error > 10 * tol and bound is None
    guarded, error, bound = _stop(spec, central, 10.0)
    assert guarded > rounds and error <= bound < 10 * tol and error < tol


def test_the_guard_refuses_a_rule_that_always_says_stop(monkeypatch):
    monkeypatch.setattr(admm, "error_estimate", lambda *a, **k: 0.0)
    _, spec, central = make_run()
    tol = spec.params["tol"]
    rounds, error, _ = _stop(spec, central, 0.0)
    assert rounds <= 3 and error > 1e-1
    rounds, error, bound = _stop(spec, central, 10.0)
    assert error <= bound < 10 * tol and error < tol


def test_certify_zero_keeps_the_frames_and_the_iterates(monkeypatch):
    """certify = 0: frames are [v; w] (main's layout), no bound; the guard only adds a payload and never
    moves an iterate: certify 10 runs the paper preset through the very same values to the same stop
    (with piqp's steps on both sides: the guard's default warm QP, admm.WARM_QP, moves the last bits)."""
    monkeypatch.setattr(admm, "WARM_QP", False)
    _, spec, central = make_run()
    runs = {}
    for certify in (0.0, 10.0):
        spec.params["certify"] = certify
        cores = [build_core(spec, i, keep_trace=False) for i in spec.robot_ids]
        values = []
        while not all(c.finished for c in cores):
            step_all(cores)
            values.append(np.concatenate([c.values for c in cores]))
        runs[certify] = (cores, values)
    (off, v_off), (on, v_on) = runs[0.0], runs[10.0]
    assert len(off[0].outgoing().values) == 2 * off[0].dim and len(on[0].outgoing().values) == 2 * on[0].dim + PAYLOAD
    assert off[0].outgoing().values.tolist() == np.concatenate([off[0].values, off[0]._w]).tolist()
    assert len(v_off) == len(v_on) == 120 and all(np.array_equal(a, b) for a, b in zip(v_off, v_on))
    assert all(c.result()["error_bound"] is None for c in off)
    bounds = [c.result()["error_bound"] for c in on]
    assert max(_errors(spec, central, on)) <= max(bounds) <= 10 * spec.params["tol"]


@pytest.mark.parametrize("at", [60, 118])  # (after round 118 the checkpoint holds an armed payload; stop at 120)
def test_a_checkpoint_resumes_bit_for_bit_with_the_guard_on(at):
    _, spec, central = make_run(**GUARDED)
    assert spec.algorithm_params.certify == 10.0 and not spec.algorithm_params.soft_polish  # as asked
    cores = [build_core(spec, i, keep_trace=False) for i in spec.robot_ids]
    for _ in range(at):
        step_all(cores)
    twin = restored_twin(spec, cores[1])
    while not all(c.finished for c in cores):
        step_with_twin(cores, twin, cores[1])
    assert twin.finished and twin.round == cores[1].round == 120
    assert twin.result() == cores[1].result() and twin.error_bound() is not None


def test_a_forged_payload_neither_crashes_a_robot_nor_lets_it_stop(monkeypatch):
    """A frame whose certificate payload is non-finite (a decoder would reject it: protocol/frames.py)
    or negative reaches a core in process, in the round where the honest payloads let it stop (the
    rule patched to pass every round): the round runs, the certificate is absent, no stop by it."""
    monkeypatch.setattr(admm, "error_estimate", lambda *a, **k: 0.0)
    _, spec, _ = make_run(**GUARDED)
    cores = [build_core(spec, i, keep_trace=False) for i in spec.robot_ids]
    k = 0
    while not cores[0]._flags & 1:  # the first round whose guard passes
        step_all(cores)
        k += 1
    assert 40 < k < 200 and cores[0]._fleet_bound <= 10 * spec.params["tol"]
    for bad in (math.nan, math.inf, -5.0):
        cores = [build_core(spec, i, keep_trace=False) for i in spec.robot_ids]
        for _ in range(k - 1):
            step_all(cores)
        updates = [c.outgoing() for c in cores]
        forged = updates[2].values.copy()
        forged[-PAYLOAD:] = bad
        u = updates[2]
        updates[2] = StateUpdate(sender=u.sender, round=u.round, values=forged, flags=u.flags,
                                 prev_values=u.prev_values, prev_flags=u.prev_flags)
        for u in updates:
            cores[0].receive(u)
        cores[0].advance()
        assert cores[0]._fleet_bound == math.inf and not cores[0]._flags & 1


def _guarded_rounds(spec, rounds: int) -> tuple[list, int | None, list[int]]:
    """Lock-step rounds of the fleet: (cores, the first round whose rule passed, the rounds in which
    some robot voted stop), asserting that every vote came in a round whose frames all carried a
    payload (an armed round) and whose fleet bound was <= the guard's threshold."""
    cores = [build_core(spec, i, keep_trace=False) for i in spec.robot_ids]
    tol, first_rule, votes = spec.params["tol"], None, []
    for _ in range(rounds):
        if all(c.finished for c in cores):
            break
        updates = [c.outgoing() for c in cores]
        armed = all(np.any(u.values[-PAYLOAD:] != 0) for u in updates)
        for c in cores:
            for u in updates:
                c.receive(u)
        for c in cores:
            c.advance()
        if first_rule is None and cores[0].status()["error_estimate"] < tol:
            first_rule = cores[0].round
        if any(c._flags & 1 for c in cores):
            votes.append(cores[0].round)
            assert armed and all(c._fleet_bound <= 10 * tol for c in cores), (cores[0].round, armed)
    return cores, first_rule, votes


def test_no_stop_without_a_certificate_when_the_rule_passes_before_arming(monkeypatch):
    """The payload is computed only in armed rounds (`admm.cert_armed`: the next round's rule may
    pass, or it is the cap's last). Default: armed in time, the paper preset votes in round 119 as
    unarmed. Armed a round late (once the rule has passed), the rule's first passing round has
    frames without a payload: no certificate, no stop there -- the vote comes a round later, from
    payloads of every robot. Never armed but in the cap's last round: no stop before it (the rule
    passes from round 119 on)."""
    _, spec, central = make_run(**GUARDED)
    _, first_default, votes_default = _guarded_rounds(spec, 400)
    assert first_default == 119 and votes_default[0] == 119  # the paper preset's stop (round 120), as branch guard
    # armed only once the rule has passed (a round late): its first passing round finds no payload
    monkeypatch.setattr(admm, "cert_armed", lambda res, tol, **_: admm.error_estimate(res, typical_older=True) < tol)
    _, first_rule, votes = _guarded_rounds(spec, 400)
    assert first_rule == 119 and votes and votes[0] == 120
    monkeypatch.undo()
    monkeypatch.setattr(admm, "CERTIFY_ARM", 0.0)
    spec.params["max_rounds"] = 200
    cores, first_rule, votes = _guarded_rounds(spec, 400)
    assert first_rule is not None and first_rule < 190 and set(votes) <= {200}  # none before the cap's last round
    assert all(c.finished for c in cores) and cores[0].round == 200
    bounds = [c.error_bound() for c in cores]  # the cap's last round was armed: a bound is reported
    assert None not in bounds and max(_errors(spec, central, cores)) <= max(bounds)


@pytest.mark.parametrize("certify", [-1.0, math.nan, math.inf])
def test_a_bad_certify_is_refused(certify):
    with pytest.raises(ValueError, match="certify"):
        ADMMParams(certify=certify)


def test_the_certify_flag_reaches_the_fleet_file_only_when_given():
    from launcher.options import Options
    from launcher.world import build_world

    _w, spec = build_world(Options(fleet_id="c", preset="paper", certify=1.0))
    assert spec.params["certify"] == 1.0 and spec.algorithm_params.certify == 1.0
    _w, spec = build_world(Options(fleet_id="c", preset="paper"))
    assert "certify" not in spec.params  # files stay as they were (complete and hard: the end-game instead)
    assert spec.algorithm_params.soft_polish and spec.algorithm_params.hard_endgame
    _w, spec = build_world(Options(fleet_id="c", preset="paper", certify=0.0, topology="ring", robots=6))
    assert spec.params["certify"] == 0.0  # 0 is accepted anywhere admm runs: the rule alone


@pytest.mark.parametrize("kwargs, says", [
    ({}, "--algorithm admm only (this run: autogrid)"),
    ({"preset": "paper", "algorithm": "newton"}, "--algorithm admm only (this run: newton)"),
    ({"preset": "paper", "C": 10.0}, "needs a hard margin"),
    ({"preset": "paper", "polish": True}, "the end-game certifies the stop itself"),
    ({"preset": "paper", "topology": "ring", "robots": 20}, "runs the edge form"),
    ({"preset": "paper", "topology": "ring", "robots": 12}, "only while N (M + 1 + 6) floats fit"),
])
def test_the_certify_flag_refuses_what_would_change_nothing(kwargs, says):
    from launcher.options import Options
    from launcher.scenario import ScenarioError
    from launcher.world import build_world

    with pytest.raises(ScenarioError, match="--certify: ") as err:
        build_world(Options(fleet_id="c", certify=1.0, **kwargs))
    assert says in str(err.value)


def test_the_certify_flag_is_taken_by_the_relay_hub_where_its_payload_fits():
    from launcher.options import Options
    from launcher.world import build_world

    _, spec = build_world(Options(fleet_id="c", certify=1.0, preset="paper", topology="ring", robots=11))
    assert spec.algorithm_params.certify == 1.0 and spec.dim == 11 * (16 + PAYLOAD)


def test_the_certify_flag_on_the_command_line(tmp_path):
    """--certify 0 is main's rule alone (no bound reported); a bad value is exit 2 with one line."""
    from launcher.cli import main

    assert main(["simulate", "--preset", "paper", "--certify", "0", "--out", str(tmp_path / "r")]) == 0
    import json

    result = json.loads((tmp_path / "r" / "result.json").read_text())
    assert result["converged"] and result["rounds"] == 120 and result["metrics"]["error_bound"] is None
    with pytest.raises(SystemExit) as exit_:
        main(["simulate", "--preset", "paper", "--certify", "-1", "--out", str(tmp_path / "bad")])
    assert exit_.value.code == 2
