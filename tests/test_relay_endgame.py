"""The relay hub's paused end-game (agents/relay_hub.py, RELAY_ENDGAME): the fleet pauses its ADMM for an exact
end-game attempt (one gather of every robot's payload per step) and either certifies the central QP's optimum or
resumes the ADMM where it paused; the chunked gather it rides on (agents/allreduce.py, max_slots)."""

from __future__ import annotations

import math

import networkx as nx
import numpy as np
import pytest

import agents.soft_endgame as soft_endgame
from agents import relay_hub
from agents.admm import FRAME_BUDGET
from agents.allreduce import AllReduce, ReducePlan, _layout, _graph_key
from agents.relay_hub import RelayHubADMM
from agents.soft_endgame import payload_size
from agents.spec import build_core

from .conftest import make_run, max_function_error, run_to_end, step_all
from .test_admm import restored_twin, step_with_twin


def _fleet(**kwargs):
    world, spec, central = make_run(preset="paper", **kwargs)
    return spec, central, [build_core(spec, i, keep_trace=False) for i in spec.robot_ids]


def _same_bits(cores) -> bool:
    return all(c.values.tobytes() == cores[0].values.tobytes() for c in cores)


def test_a_ring_certifies_the_exact_optimum_before_the_admm_alone_stops(monkeypatch):
    """4-ring, paper preset: the attempt certifies; every copy (each computing its own fleet steps) holds the
    same bits, within 1e-9 of the exact central QP, in fewer rounds than the ADMM alone takes to its stop; the
    rounds are the ADMM's plus the paused ones."""
    monkeypatch.setattr(relay_hub, "SHARED_KEPT", 0)  # every copy computes its own steps
    spec, central, cores = _fleet(robots=4, topology="ring")
    assert all(isinstance(c, RelayHubADMM) and c._endgame is not None for c in cores)
    run_to_end(cores, limit=3000)
    assert all(c.converged and c._mode == "certified" for c in cores)
    assert _same_bits(cores)
    assert max_function_error(spec, central, [c.result() for c in cores]) < 1e-9
    assert {c.round for c in cores} == {cores[0]._lround + cores[0]._paused} and cores[0]._paused > 0

    monkeypatch.setattr(relay_hub, "RELAY_ENDGAME", False)
    _, _, alone = _fleet(robots=4, topology="ring")
    run_to_end(alone, limit=3000)
    assert all(c.converged for c in alone)
    assert cores[0].round < alone[0].round


@pytest.mark.parametrize("C, own_steps", [(1.0, True), (100.0, False)])
def test_a_soft_ring_certifies_the_exact_soft_optimum_before_the_admm_alone_stops(monkeypatch, C, own_steps):
    """4-ring, soft margin (RELAY_SOFT_ENDGAME): the attempt certifies the exact central soft QP's optimum (its B
    rows at the box C), every copy (with own_steps: each computing its own fleet steps) holding the same bits, in
    fewer rounds than the ADMM alone -- whose answer is only within tol. The quiet streak that starts it is the
    soft piece test's."""
    if own_steps:
        monkeypatch.setattr(relay_hub, "SHARED_KEPT", 0)
    spec, central, cores = _fleet(robots=4, topology="ring", C=C)
    assert cores[0]._endgame is not None and not cores[0]._endgame.hard
    run_to_end(cores, limit=3000)
    assert all(c.converged and c._mode == "certified" for c in cores) and _same_bits(cores)
    error = max_function_error(spec, central, [c.result() for c in cores])

    monkeypatch.setattr(relay_hub, "RELAY_SOFT_ENDGAME", False)
    _, _, alone = _fleet(robots=4, topology="ring", C=C)
    assert alone[0]._endgame is None
    run_to_end(alone, limit=3000)
    assert all(c.converged for c in alone)
    assert cores[0].round < alone[0].round
    # (piqp's central soft answer is itself exact to ~1e-8 at C 100; the ADMM alone stops ~1e-6 away)
    assert error < 1e-7 < max_function_error(spec, central, [c.result() for c in alone])


def test_the_soft_piece_test_sees_a_row_change_and_ignores_the_box_rows():
    """`piece_changed(soft=True)`: W = A_E' lam_E + C A_B' 1 moves on one piece only by its E multipliers, so
    (W - W_prev) . dx = 0 there, while the hard form's W . dx picks up the box rows' C A_B' 1 . dx; a row that
    leaves E changes it by its multiplier x its margin gap."""
    rng = np.random.default_rng(0)
    a_e, a_b, a_n = rng.normal(size=(3, 4))
    dx = rng.normal(size=4)
    dx -= (dx @ a_e) / (a_e @ a_e) * a_e  # a move along the face a_e . x = 1
    x_prev = rng.normal(size=4)
    x = x_prev + dx
    C = 10.0
    W_prev, W = 0.3 * a_e + C * a_b, 0.7 * a_e + C * a_b  # one piece: E = {e}, B = {b}
    assert not relay_hub.piece_changed(x_prev[None], W_prev[None], x[None], W[None], soft=True)[0]
    assert relay_hub.piece_changed(x_prev[None], W_prev[None], x[None], W[None])[0]  # (the hard form: B's term)
    dx_off = dx + 0.5 * a_n  # row n enters E between the steps: its multiplier x its margin gap
    W_new = W + 0.4 * a_n
    assert relay_hub.piece_changed(x_prev[None], W_prev[None], (x_prev + dx_off)[None], W_new[None], soft=True)[0]


def _one_attempt_at(monkeypatch, round_: int) -> None:
    """An attempt exactly once, after ADMM round `round_` (the rule replaced), that cannot correct its guess."""
    monkeypatch.setattr(soft_endgame, "CAP", 0)  # (a violated set ends the attempt at its first verdict)
    monkeypatch.setattr(RelayHubADMM, "_start_attempt", lambda self, k, below: (
        self._endgame is not None and k + 1 == round_ and not below))


def test_a_failed_attempt_resumes_the_admm_where_it_paused_bit_for_bit(monkeypatch):
    """An attempt that ends without a certificate pauses the ADMM and nothing else: the run then stops where the
    ADMM alone stops, with its bits, its rounds plus the paused ones."""
    _one_attempt_at(monkeypatch, 20)
    spec, central, cores = _fleet(robots=4, topology="ring")
    while cores[0]._lround <= 20 or cores[0]._mode != "admm":
        step_all(cores)
    assert cores[0]._attempts == 1 and cores[0]._paused > 0  # it ran, and ended uncertified
    run_to_end(cores, limit=3000)

    monkeypatch.setattr(relay_hub, "RELAY_ENDGAME", False)
    _, _, alone = _fleet(robots=4, topology="ring")
    run_to_end(alone, limit=3000)
    assert all(c.converged for c in cores + alone)
    assert [c.values.tobytes() for c in cores] == [c.values.tobytes() for c in alone]
    assert cores[0].round == alone[0].round + cores[0]._paused
    assert max_function_error(spec, central, [c.result() for c in cores]) < spec.params["tol"]


def test_after_its_tries_the_admm_alone_finishes(monkeypatch):
    """At most RELAY_ENDGAME_TRIES attempts a run: attempts that cannot correct their guess (CAP 0), started as
    often as the rule allows (quiet 0, any estimate, gap 5), stop after 2 and the ADMM alone finishes on its own
    bits, 2 attempts' paused rounds later (16-geo seed 8 once waited out 5 failed attempts into the round cap)."""
    monkeypatch.setattr(soft_endgame, "CAP", 0)
    monkeypatch.setattr(relay_hub, "RELAY_ENDGAME_QUIET", 0)
    monkeypatch.setattr(relay_hub, "RELAY_ENDGAME_ESTIMATE", math.inf)
    monkeypatch.setattr(relay_hub, "RELAY_ENDGAME_GAP", 5)
    monkeypatch.setattr(relay_hub, "RELAY_ENDGAME_TRIES", 10**9)
    _, _, unlimited = _fleet(robots=4, topology="ring")
    run_to_end(unlimited, limit=3000)
    assert unlimited[0]._attempts > 2  # the control: without the limit the rule starts attempt after attempt
    monkeypatch.setattr(relay_hub, "RELAY_ENDGAME_TRIES", 2)
    spec, central, cores = _fleet(robots=4, topology="ring")
    run_to_end(cores, limit=3000)
    assert [c._attempts for c in cores] == [2] * 4 and all(c._mode == "admm" and c.converged for c in cores)
    monkeypatch.setattr(relay_hub, "RELAY_ENDGAME", False)
    _, _, alone = _fleet(robots=4, topology="ring")
    run_to_end(alone, limit=3000)
    assert [c.values.tobytes() for c in cores] == [c.values.tobytes() for c in alone]
    assert cores[0].round == alone[0].round + cores[0]._paused
    assert max_function_error(spec, central, [c.result() for c in cores]) < spec.params["tol"]


@pytest.mark.parametrize("C", [None, 10.0])
def test_a_checkpoint_inside_an_attempt_resumes_bit_for_bit(C):
    """A robot restarted from its checkpoint in the middle of an all-reduce sends what the original sends,
    round for round, to the certified stop (hard and soft margins)."""
    spec, _, cores = _fleet(robots=4, topology="ring", C=C)
    while cores[0]._mode != "endgame":
        step_all(cores)
    step_all(cores)  # one round into the gather (D = 2: its last round next)
    twin = restored_twin(spec, cores[1])
    while not cores[0].finished:
        step_with_twin(cores, twin, cores[1])
    assert twin.finished and twin.converged and twin.values.tobytes() == cores[1].values.tobytes()


def test_frames_stay_within_the_budget_and_soft_margins_keep_the_relay_frames():
    """Every relay frame (relayed a's, or the all-reduce's payloads) has one length within FRAME_BUDGET x (M + 1)
    floats; the 16-geo fleet's shells of 4 go over two rounds of 2 payloads. A soft margin runs the end-game
    only where a step's gather takes at most RELAY_SOFT_STEP_ROUNDS rounds (the 4-ring's 2, not the 16-ring's 8):
    the soft payload is the hard one's (payload_size), the frames the same length."""
    for kwargs in ({"robots": 16, "topology": "ring"}, {"robots": 16, "topology": "geometric", "comm_range": 3.0}):
        spec, _, cores = _fleet(**kwargs)
        dim = len(spec.grid) + 1
        plan = cores[0]._reduce.plan
        assert spec.dim == cores[0].frame_dim == 16 * dim <= FRAME_BUDGET * dim
        assert plan.slots * payload_size(dim) <= FRAME_BUDGET * dim
        widest = int(_layout(_graph_key(spec.graph)).counts.max())
        assert plan.slots < widest or kwargs["topology"] == "ring"
    spec, _, cores = _fleet(robots=16, topology="ring", C=10.0)
    assert cores[0]._endgame is None and spec.dim == cores[0].frame_dim == cores[0]._relay_dim  # (a and the guard)
    hard, _, _ = _fleet(robots=4, topology="ring")
    spec, _, cores = _fleet(robots=4, topology="ring", C=10.0)
    assert cores[0]._endgame is not None and cores[0]._reduce.plan.rounds <= relay_hub.RELAY_SOFT_STEP_ROUNDS
    assert spec.dim == cores[0].frame_dim == hard.dim == cores[0]._reduce.plan.slots * payload_size(len(spec.grid) + 1)


def _narrow_start(monkeypatch, block: int) -> None:
    """The relay end-game with `block` and the complete graphs' start block (the preconditioned 1 and t alone)."""
    monkeypatch.setattr(relay_hub, "RELAY_ENDGAME_BLOCK", block)
    narrow = lambda *a, **k: soft_endgame.SoftEndgame(*a, **{**k, "wide_start": False})  # noqa: E731
    monkeypatch.setattr(relay_hub, "SoftEndgame", narrow)


def _certified_ring():
    spec, central, cores = _fleet(robots=4, topology="ring")
    run_to_end(cores, limit=3000)
    assert all(c.converged and c._mode == "certified" for c in cores) and _same_bits(cores)
    assert max_function_error(spec, central, [c.result() for c in cores]) < 1e-9  # the exact central QP's optimum
    return cores


def test_the_wide_start_block_certifies_the_optimum_in_fewer_paused_rounds(monkeypatch):
    """The relay end-game's start block with every robot's step multipliers beside the preconditioned 1 and t
    (RELAY_ENDGAME_BLOCK, wide_start): one more Krylov vector a step, so a solve exhausts its span in fewer steps;
    the same exact optimum, fewer paused rounds (4-ring: 44 -> 32 on AVX-512, 124 -> 92 on the AVX2 8-ring: no
    figure pinned, the order only)."""
    wide = _certified_ring()
    assert wide[0]._endgame.wide_start and wide[0]._endgame.block == relay_hub.RELAY_ENDGAME_BLOCK
    _narrow_start(monkeypatch, soft_endgame.BLOCK)
    narrow = _certified_ring()
    assert 0 < wide[0]._paused < narrow[0]._paused and wide[0].round < narrow[0].round


def test_a_wide_solve_with_nothing_to_move_solves_its_set_again_from_the_narrow_start():
    """A wide start's span can fill the x space off the answer with no multiplier or margin violated (AVX2 6-ring
    seed 4): the attempt then solves the same set from the narrow start (1 and t) instead of a fresh guess; a
    narrow solve with nothing to move ends the attempt as before. The flag survives a checkpoint."""
    spec, _, cores = _fleet(robots=4, topology="ring")
    while cores[0]._mode != "endgame":
        step_all(cores)
    eg = cores[0]._endgame
    labels, attempts = eg.labels.copy(), eg.attempts
    nothing = np.zeros((len(cores), len(eg.payload)))  # verdicts: not ok, worst violation 0
    eg._correct(nothing, None)
    assert eg.narrow and eg.kind == "start" and eg.attempts == attempts and np.array_equal(eg.labels, labels)
    assert eg.U.shape[1] == 2 and not np.any(eg.payload[5])  # the start block: 1 and t alone
    twin = soft_endgame.SoftEndgame(eg.qp, eg.ids, eg.me, eg.C, block=eg.block, wide_start=True)
    twin.load(eg.state())
    assert twin.narrow
    eg._correct(nothing, None)
    assert eg.attempts == attempts + 1 and not eg.narrow  # a fresh guess: the attempt is over


def test_a_larger_block_alone_sends_the_same_numbers(monkeypatch):
    """Without the wide start a block of 5 changes the frames' length only: a step's new vectors are the images
    of the last step's, never more than the start block's 2 (hard margins), so every copy ends on the same bits
    after the same paused rounds as with the block of 3."""
    _narrow_start(monkeypatch, 3)
    three = _certified_ring()
    _narrow_start(monkeypatch, 5)
    five = _certified_ring()
    assert five[0].frame_dim > three[0].frame_dim and five[0]._endgame.block == 5
    assert [c.values.tobytes() for c in five] == [c.values.tobytes() for c in three]
    assert five[0]._paused == three[0]._paused and five[0].round == three[0].round


@pytest.mark.parametrize("seed", range(4))
def test_a_chunked_gather_delivers_every_contribution_in_id_order(seed):
    """With max_slots, a shell wider than it goes over several rounds: every robot ends with every robot's
    contribution, the same rows in id order, frames of at most max_slots contributions, and as many rounds as
    the shells' chunks."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(5, 20))
    g = nx.connected_watts_strogatz_graph(n, 4, 0.3, seed=seed)
    graph = {int(a): tuple(int(b) for b in g[a]) for a in g}
    counts = _layout(_graph_key(graph)).counts
    for cap in (1, 2, 3):
        reducers = {i: AllReduce(ReducePlan.build(graph, i, "gather", cap), 5) for i in graph}
        values = {i: rng.normal(size=5) for i in graph}
        frames = {i: reducers[i].begin(values[i]) for i in graph}
        rounds = 0
        while not all(r.done for r in reducers.values()):
            assert all(len(f) == reducers[i].frame_size <= cap * 5 for i, f in frames.items())
            frames = {i: reducers[i].step({j: frames[j] for j in graph[i]}) for i in graph}
            rounds += 1
        want = np.array([values[i] for i in sorted(graph)])
        assert all(np.array_equal(r.contributions(), want) for r in reducers.values())
        diameter = counts.shape[1] - 1
        assert rounds == sum(math.ceil(counts[:, r].max() / cap) for r in range(diameter))


@pytest.mark.integration
@pytest.mark.parametrize("robots, C", [(8, None), (6, 10.0)])
def test_launch_equals_simulate_with_a_crash_inside_an_attempt(tmp_path, robots, C):
    """Over Zenoh with lossy links, a ring of the paper preset (the 8-ring hard, the 6-ring soft with C 10) pauses
    for an attempt and certifies; robot 3 killed in the middle of the attempt and restarted from its checkpoint:
    every robot's iterates are simulate's, bit for bit."""
    from launcher.fleet import CrashPlan
    from protocol.links import LinkFaults

    from .conftest import bounded_and_clean
    from .test_launch import _assert_same_iterates, _launch, _run, _simulate

    with bounded_and_clean(str(tmp_path), 120, "relay-endgame-launch"):
        _world, spec, central = _run(preset="paper", robots=robots, topology="ring", C=C,
                                     fleet_id=f"launch-relay-endgame-{robots}",
                                     faults=LinkFaults(loss=0.1, delay=0.002, jitter=0.001))
        want = _simulate(spec)
        assert all(w["converged"] for w in want.values())
        # the attempt's rounds in simulate: the cores' paused rounds before the stop
        cores = [build_core(spec, i, keep_trace=False) for i in spec.robot_ids]
        run_to_end(cores, limit=3000)
        assert cores[0]._mode == "certified" and cores[0].round == want[0]["rounds"]
        crash = cores[0].round - cores[0]._paused // 2  # inside the attempt (it ends the run)
        out = _launch(spec, tmp_path, crashes=[CrashPlan(3, crash)], restart=True, restart_after=0.5)
        assert [(c.robot, c.planned_round) for c in out.crashes] == [(3, crash)]
        _assert_same_iterates(out.robots, want, restarted=(3,))
        assert max_function_error(spec, central, out.robots) < 1e-7  # (the soft reference: piqp's, ~1e-8)
