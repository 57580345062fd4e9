"""The per-robot ADMM state machine: frames in, frames out, and the invariants behind them."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest

from agents.admm import ADMMParams, ConsensusADMM
from agents.relay_hub import RelayHubADMM
from agents.rounds import RobotShare
from agents.spec import build_core, restore_core
from protocol.frames import StateUpdate

from .conftest import make_run, max_function_error, run_to_end, step_all


@pytest.fixture()
def fleet3():
    _, spec, central = make_run(tol=1e-6)
    return spec, central, [build_core(spec, i) for i in spec.robot_ids]


def test_lone_robot_solves_the_central_problem_in_round_zero():
    world, spec, central = make_run(robots=1)
    core = build_core(spec, 0)
    assert core.finished and core.round == 0
    assert max_function_error(spec, central, [core.result()]) < 1e-6


def test_missing_neighbour_blocks_the_round(fleet3):
    _, _, cores = fleet3
    a, b, c = cores
    a.receive(b.outgoing())
    assert a.missing() == (c.robot_id,)
    assert not a.ready()
    with pytest.raises(RuntimeError, match="waiting"):
        a.advance()
    a.receive(c.outgoing())
    assert a.ready()


def test_receive_ignores_strangers_and_stale_rounds(fleet3):
    _, _, cores = fleet3
    a, b, c = cores
    stranger = StateUpdate(sender=99, round=0, values=np.zeros(a.frame_dim), flags=0, prev_values=None)
    a.receive(stranger)
    assert set(a.missing()) == {b.robot_id, c.robot_id}
    step_all(cores)
    step_all(cores)
    old = StateUpdate(sender=b.robot_id, round=0, values=np.zeros(a.frame_dim), flags=0, prev_values=None)
    a.receive(old)  # round 0 is long gone: must not be taken for round 2
    assert b.robot_id in a.missing()


def test_piggybacked_previous_round_recovers_a_lost_frame(fleet3):
    _, _, cores = fleet3
    a, b, c = cores
    # b's round-0 frame to a is lost; b moves on (it heard everyone) and publishes round 1
    for x in (b, c):
        for y in cores:
            if y is not x:
                x.receive(y.outgoing())
    a.receive(c.outgoing())
    round0_of_b = b.outgoing()
    b.advance()
    c.advance()
    assert b.robot_id in a.missing()
    a.receive(b.outgoing())  # round 1 frame carries round 0 as prev
    assert a.ready()
    a.advance()
    # and the value a used is b's exact round-0 value
    np.testing.assert_array_equal(b.outgoing().prev_values, round0_of_b.values)


def test_duals_stay_exactly_antisymmetric():
    """A ring in the edge form: both ends hold the same canonical edge copy, bit for bit."""
    _, spec, _ = make_run(robots=4, topology="ring", tol=1e-6)
    spec.params["relay"] = False  # the edge form (sparse fleets run the relay hub by default)
    cores = [build_core(spec, i) for i in spec.robot_ids]
    assert all(c._hub is None for c in cores)
    for _ in range(25):
        step_all(cores)
    by_id = {c.robot_id: c for c in cores}
    for c in cores:
        assert len(c._edges) == 2
        for j, edge in c._edges.items():
            other = by_id[j]._edges[c.robot_id]
            np.testing.assert_array_equal(edge.lam, other.lam)  # same canonical copy, bit for bit
            np.testing.assert_array_equal(edge.z, other.z)
            assert edge.sign == -other.sign


def test_complete_graph_robots_hold_the_same_accelerated_state(fleet3):
    """On a complete graph every robot runs the fleet's Anderson-accelerated hub ADMM: the copies
    are bit-identical and the scaled duals sum to zero (the invariant behind exactness)."""
    _, _, cores = fleet3
    for _ in range(25):
        step_all(cores)
    hubs = [c._hub for c in cores]
    assert all(h is not None for h in hubs)
    assert len(hubs[0].hist_s) > 2  # the acceleration is running, not only the plain map
    for h in hubs[1:]:
        assert h.s.tobytes() == hubs[0].s.tobytes()
        assert [a.tobytes() for a in h.hist_f] == [a.tobytes() for a in hubs[0].hist_f]
    d = cores[0].dim
    u = hubs[0].s[d:].reshape(len(cores), d)
    assert np.abs(u.sum(axis=0)).max() <= 1e-12 * max(1.0, np.abs(u).max())


def test_all_robots_stop_in_the_same_round_with_the_central_solution(fleet3):
    spec, central, cores = fleet3
    run_to_end(cores)
    assert len({c.round for c in cores}) == 1
    assert all(c.converged for c in cores)
    # the stopping rule bounds the estimated error by tol: the measured one must honour it
    assert max_function_error(spec, central, [c.result() for c in cores]) < spec.params["tol"]


@pytest.mark.parametrize("relay", [False, True])
@pytest.mark.parametrize(
    "fleet",
    [{"robots": 4, "topology": "ring"}, {"robots": 4, "topology": "line", "shape": "bean", "seed": 2}],
)
def test_sparse_fleets_stop_within_tol_of_the_exact_solution(fleet, relay):
    """The edge form's stopping rule at the default tol 1e-3 on the paper's preset: the 4-ring of
    benchmarks/results/rounds.md and a sparse fleet where the rule has the least room in
    benchmarks/results/rounds-stop.md (bean, 4-robot line, seed 2: error 2.8e-4 at round 1742, 1e-3
    first reached at 1698). Measured offline on the recorded runs: the same rule with its estimate
    halved stops this fleet at 1.3e-3, divided by 5 it stops the 4-ring at 1.6e-3: a looser rule
    fails here, and a tighter one must still pass both. The relay hub (the default on these fleets,
    agents/relay_hub.py) must pass both too."""
    _, spec, central = make_run(preset="paper", max_rounds=5000, **fleet)
    spec.params["relay"] = relay
    cores = [build_core(spec, i, keep_trace=False) for i in spec.robot_ids]
    assert all(isinstance(c, RelayHubADMM) == relay for c in cores)
    assert relay or all(c._hub is None for c in cores)
    run_to_end(cores)
    assert all(c.converged for c in cores)
    assert max_function_error(spec, central, [c.result() for c in cores]) <= spec.params["tol"]


@pytest.mark.parametrize("anderson", [0, 20])
def test_plain_and_accelerated_reach_the_same_fixed_point(anderson):
    """Acceleration changes the path, not the answer: both stop within tol of the central QP."""
    _, spec, central = make_run(tol=1e-6)
    params = ADMMParams(**{**spec.params, "anderson": anderson})
    cores = [
        ConsensusADMM(spec.share(i), params)
        for i in spec.robot_ids
    ]
    assert all((c._hub is not None) == (anderson > 0) for c in cores)
    run_to_end(cores)
    assert all(c.converged for c in cores)
    assert max_function_error(spec, central, [c.result() for c in cores]) < spec.params["tol"]


def test_round_cap_stops_everyone_unconverged():
    _, spec, _ = make_run(max_rounds=7)
    cores = [build_core(spec, i) for i in spec.robot_ids]
    run_to_end(cores)
    assert [c.round for c in cores] == [7, 7, 7]
    assert not any(c.converged for c in cores)


def cores_with_anderson(spec, anderson):
    params = ADMMParams(**{**spec.params, "anderson": anderson})
    return [
        ConsensusADMM(spec.share(i), params)
        for i in spec.robot_ids
    ]


@pytest.mark.parametrize("anderson", [0, 30])
def test_a_stale_substitute_biases_the_answer(fleet3, anderson):
    """The trap in the architecture guide, shown: reuse an old neighbour value once and the edge
    form converges -- to the wrong point. Exact recovery is what keeps the answer right. The hub
    form (anderson > 0) builds its map from every robot's own w (shared data) and resynchronises
    copies that differ, so one stale value only costs rounds there: it must still end exact."""
    spec, central, _ = fleet3
    cores = cores_with_anderson(spec, anderson)
    assert all((c._hub is not None) == (anderson > 0) for c in cores)
    a, b, _ = cores
    for _ in range(5):
        step_all(cores)
    stale = b.outgoing()
    step_all(cores)
    # a gets b's round-5 values labelled as round 6
    forged = StateUpdate(sender=b.robot_id, round=a.round, values=stale.values, flags=0, prev_values=stale.prev_values, prev_flags=0)

    def deliver(u, c):
        return not (c is a and u.sender == b.robot_id)

    updates = [c.outgoing() for c in cores]
    for c in cores:
        for u in updates:
            if deliver(u, c):
                c.receive(u)
    a.receive(forged)
    for c in cores:
        c.advance()
    run_to_end(cores)
    error = max_function_error(spec, central, [c.result() for c in cores])
    if anderson == 0:
        assert error > 1e-2
    else:
        assert all(c.converged for c in cores) and error < spec.params["tol"]


def test_checkpoint_restore_resumes_bit_for_bit(fleet3):
    spec, _, cores = fleet3
    for _ in range(12):
        step_all(cores)
    twin = restored_twin(spec, cores[1])
    for _ in range(10):
        step_with_twin(cores, twin, cores[1])
    assert twin.outgoing() == cores[1].outgoing()


def test_a_checkpoint_without_a_field_of_this_version_is_a_clear_error(fleet3):
    """A checkpoint another version wrote (here: one state field missing) is refused with a
    ValueError naming the field, which the robot's shell reports, instead of a KeyError."""
    spec, _, cores = fleet3
    step_all(cores)
    saved = msgpack.unpackb(msgpack.packb(cores[0].checkpoint()), strict_map_key=False)
    missing = "residual"
    del saved[missing]
    with pytest.raises(ValueError, match=f"no field {missing!r}.*another version"):
        restore_core(spec, 0, saved)


def restored_twin(spec, core):
    """`core` restarted from a msgpack round trip of its checkpoint (what a robot process writes)."""
    saved = msgpack.unpackb(msgpack.packb(core.checkpoint()), strict_map_key=False)
    return restore_core(spec, core.robot_id, saved)


def step_with_twin(cores, twin, original) -> None:
    """One lock-step round of `cores`, the restored `twin` of `original` fed the same frames; the
    twin must send what the original sends."""
    assert twin.outgoing() == original.outgoing()
    updates = [c.outgoing() for c in cores]
    for u in updates:
        twin.receive(u)
    step_all(cores)
    twin.advance()


def test_hub_sums_match_math_fsum_bit_for_bit():
    """The hub's vectorised sums (TwoSum pairwise) give math.fsum's exactly rounded bits -- on
    plain, wide-ranging and cancelling sums of every length up to 1100 -- whatever the layout."""
    import math

    from agents.admm import _dots, _pairwise_sum, _solve_spd

    rng = np.random.default_rng(7)
    for n in [*range(0, 66), 127, 128, 129, 600, 1100]:
        q = rng.normal(size=(n, 6)) * np.exp(rng.normal(scale=10, size=(n, 6)))
        q[n // 2 :, 3:] = -q[: n - n // 2, 3:] * (1 + 1e-9 * rng.normal(size=(n - n // 2, 3)))  # near-cancelling
        got = _pairwise_sum(q.copy())
        assert [float(x).hex() for x in got] == [math.fsum(q[:, j].tolist()).hex() for j in range(6)], n
    rows, v = rng.normal(size=(5, 300)), rng.normal(size=300)
    expect = [math.fsum((r * v).tolist()) for r in rows]
    assert _dots(rows, v).tolist() == expect and _dots(rows[None], np.stack([v, v])[:, None, :]).tolist() == [expect] * 2
    a = rng.normal(size=(12, 40))
    h, g = a @ a.T + np.eye(12), rng.normal(size=12)
    assert np.allclose(h @ _solve_spd(h, g), g, rtol=0, atol=1e-12)


def test_hub_gram_built_step_by_step_is_the_rebuilt_one():
    """The Anderson Gram matrix grows one row per round (and loses the oldest); a restored copy
    rebuilds it from the history: both must be the same bits, or restarts would change the run."""
    _, spec, _ = make_run(tol=1e-9)
    cores = [build_core(spec, i) for i in spec.robot_ids]
    hub = cores[0]._hub
    sizes = []
    for _ in range(60):
        step_all(cores)
        if len(hub._dg) > 1:
            twin = type(hub)(hub.ids, hub.dim, hub.penalty, cores[0].params)
            twin.load(hub.state())
            assert twin._gram.tobytes() == hub._gram.tobytes()
            sizes.append(len(hub._dg))
    assert len(sizes) > 30 and max(sizes) == cores[0].params.anderson  # full memory: rows dropped too


@pytest.mark.parametrize("topology", ["complete", "line"])
def test_dropping_a_dead_neighbour_converges_on_the_survivors_data(topology):
    """Complete graph: the hub drops the dead robot's dual; line (edge form: the relay hub cannot
    drop a robot, tests/test_relay_hub.py): the edge to the dead end robot goes. Either way the
    survivors end on the exact answer for their own data."""
    world, spec, _ = make_run(robots=5, topology=topology, tol=1e-6, max_rounds=5000)
    spec.params["relay"] = False
    cores = [build_core(spec, i) for i in spec.robot_ids]
    for _ in range(20):
        step_all(cores)
    dead = cores.pop()
    for c in cores:
        c.drop_neighbour(dead.robot_id)
    run_to_end(cores)
    from agents.problem import solve_central

    survivors = [r for r in world.robots if r.id != dead.robot_id]
    ref = solve_central(spec.basis, np.vstack([r.points for r in survivors]), np.concatenate([r.labels for r in survivors]))
    assert ref.solved
    assert max_function_error(spec, ref, [c.result() for c in cores]) < spec.params["tol"]
    had_it = [c for c in cores if dead.robot_id in spec.robots[c.robot_id].neighbours]
    assert had_it and all(dead.robot_id in c.result()["dropped"] for c in had_it)
    assert all(c.converged for c in cores)


@pytest.mark.parametrize(
    "kwargs,match",
    [({"rho": 0}, "rho"), ({"relax": 2.0}, "relaxation"), ({"tol": -1}, "tol"), ({"max_rounds": 0}, "max_rounds"),
     ({"diameter": 63}, "diameter"), ({"anderson": -1}, "anderson"), ({"safeguard": 1.0}, "safeguard")],
)
def test_bad_parameters_are_refused(kwargs, match):
    with pytest.raises(ValueError, match=match):
        ADMMParams(**kwargs)


def test_robot_cannot_be_its_own_neighbour():
    with pytest.raises(ValueError, match="itself"):
        ConsensusADMM(RobotShare(0, (0, 1), np.ones((2, 3)), np.array([1, -1]), n_robots=2), ADMMParams())


def test_hub_form_only_when_every_robot_sees_the_whole_fleet():
    """A hub robot of a star has N - 1 neighbours, but its leaves do not: all must agree on the
    form, so the verdict needs every neighbour's degree too (missing degrees: edge form)."""
    from agents.admm import complete_graph

    assert complete_graph(4, (1, 2, 3), {1: 3, 2: 3, 3: 3})
    assert not complete_graph(4, (1, 2, 3), {1: 1, 2: 1, 3: 1})  # the centre of a star
    assert not complete_graph(4, (0,), {0: 3})  # a leaf of that star
    assert not complete_graph(4, (1, 2, 3), {})
    assert not complete_graph(1, (), {})


def test_sessions_count_the_bytes_they_send_and_keep_them_over_a_restart():
    """bytes_sent (result rows, result.json) is the sum of the encoded frames a robot published,
    resends included, and a restarted robot continues its count from the checkpoint."""
    from protocol.session import RobotSession

    _world, spec, _central = make_run(robots=2, max_rounds=12)
    sessions = {i: RobotSession.for_spec(spec, build_core(spec, i), now=0.0) for i in spec.robot_ids}
    published = {i: 0 for i in sessions}
    now = 0.0
    for _ in range(200):  # bounded: 12 rounds need far fewer exchanges
        for i, s in sessions.items():
            for _dest, frame in s.to_send(now):
                published[i] += len(frame)
                for j, other in sessions.items():
                    if j != i:
                        other.receive(i, frame, now)
        for s in sessions.values():
            while s.ready():
                s.advance(now)
        now += 0.3  # past the resend interval: resends are counted too
        if all(s.done for s in sessions.values()):
            break
    rows = {i: s.row(now, {}) for i, s in sessions.items()}
    for i, r in rows.items():
        assert r["bytes_sent"] == published[i] and r["frames_sent"] > r["rounds"] > 0
        assert r["bytes_sent"] > 8 * spec.dim * r["frames_sent"]  # each frame carries its vector
    env = sessions[0].checkpoint({})
    again = RobotSession.for_spec(spec, restore_core(spec, 0, env["core"]), now=now, resume=env)
    first = sum(len(f) for _d, f in again.to_send(now))
    assert again.row(now, {})["bytes_sent"] == published[0] + first



def test_warm_qp_runs_only_where_the_guard_decides(monkeypatch):
    """admm.WARM_QP: the exact warm-started KKT solve answers the hub's steps only where the certified
    guard decides (certify > 0, hard margin); with certify = 0 the cores give their MarginQP no guess,
    so piqp answers every step (main's bits). Guarded, the paper preset stops within tol of the central
    QP and a checkpointed robot resumes bit for bit (its guess is its v)."""
    import agents.admm as admm
    import agents.problem as problem

    calls = []
    solve = problem._WarmKKT.solve
    monkeypatch.setattr(problem._WarmKKT, "solve", lambda self, q, g: calls.append(1) or solve(self, q, g))
    _, spec, central = make_run()
    assert admm.WARM_QP is True and spec.params.get("certify", 10.0) > 0
    spec.params["certify"] = 0.0
    cores = [build_core(spec, i, keep_trace=False) for i in spec.robot_ids]
    for _ in range(5):
        step_all(cores)
    assert not calls
    spec.params["certify"] = 10.0
    cores = [build_core(spec, i, keep_trace=False) for i in spec.robot_ids]
    for _ in range(12):
        step_all(cores)
    twin = restored_twin(spec, cores[1])
    for _ in range(10):
        step_with_twin(cores, twin, cores[1])
    assert twin.outgoing() == cores[1].outgoing() and calls
    run_to_end(cores)
    assert all(c.converged for c in cores)
    assert max_function_error(spec, central, [c.result() for c in cores]) < spec.params["tol"]
