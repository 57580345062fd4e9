"""Survivors of a sparse fleet learn who was dropped for good (agents/rounds.py `floods_gone`), widen
their stop to the survivors' graph (either margin) and, with a soft margin, solve their own problem: each weighs |x|^2 by 1 / (robots left), so the answer is
the exact central one of the survivors' data. The ids travel in the frames (protocol/frames.py "gone",
"pgone"), one hop a round; a frame that lies about them is refused and counted, never believed."""

from __future__ import annotations

import dataclasses

import msgpack
import numpy as np
import pytest

from agents.problem import solve_central
from agents.spec import build_core, restore_core
from launcher.fleet import CrashPlan, spec_for_run
from launcher.simulate import simulate_fleet
from protocol.frames import Decoded, FrameDecoder, Rejected, StateUpdate, encode_state
from protocol.session import RobotSession
from tests.conftest import make_run, max_function_error
from tests.test_crash import TIMING


def survivors_reference(world, spec, dead: int):
    """The exact central answer of the survivors' data (agents/problem.py solve_central)."""
    kept = [r for r in world.robots if r.id != dead]
    return solve_central(spec.basis, np.vstack([r.points for r in kept]), np.concatenate([r.labels for r in kept]),
                         spec.C)


# ---------------------------------------------------------------------- the frames


def _decoder(spec, receiver: int) -> FrameDecoder:
    return FrameDecoder(spec.fleet, spec.robot_ids, spec.dim, spec.config_tag, receiver=receiver)


def soft_edge_fleet(robots: int, topology: str, dead: int):
    """(world, spec) of a soft-margin fleet (C 10) given the edge form, as a run losing ``dead`` for good gives it."""
    world, spec, _ = make_run(fleet_id=f"survivors-{topology}", timing=TIMING, robots=robots, topology=topology, C=10.0)
    return world, spec_for_run(spec, [CrashPlan(dead, 40)], restart=False, restart_after=0.5)


@pytest.fixture(scope="module")
def ring():
    """A 4-ring."""
    return soft_edge_fleet(4, "ring", dead=1)


def test_the_frame_says_who_was_dropped_only_when_someone_was(ring):
    _, spec = ring
    x = np.arange(spec.dim, dtype=float)
    plain = StateUpdate(0, 7, x, 1, x + 1, 1)
    fields = msgpack.unpackb(encode_state(plain, fleet=spec.fleet, seq=3, config_tag=spec.config_tag))
    assert "gone" not in fields and "pgone" not in fields  # a fleet that never loses a robot: its old frames

    told = dataclasses.replace(plain, gone=(1, 2), prev_gone=(1,))
    frame = encode_state(told, fleet=spec.fleet, seq=4, config_tag=spec.config_tag)
    fields = msgpack.unpackb(frame)
    assert (fields["gone"], fields["pgone"]) == ([1, 2], [1])
    got = _decoder(spec, receiver=3).decode(frame, expected_sender=0)
    assert isinstance(got, Decoded) and got.update == told
    # robot 2 is here to read it: the sender's problem is not the fleet's -- refused by robot 2 alone
    mine = _decoder(spec, receiver=2)
    refused = mine.decode(frame, expected_sender=0)
    assert isinstance(refused, Rejected) and refused.reason == "gone" and mine.counts == {"gone": 1}


def test_a_round_sent_twice_with_other_lists_is_equivocation(ring):
    """The list is the sender's word as much as its values: a second frame of the same round that says
    otherwise is refused, and so is one whose `pgone` contradicts the round before."""
    _, spec = ring
    auth = spec.frame_auth(0)
    decoder = FrameDecoder(spec.fleet, spec.robot_ids, spec.dim, spec.config_tag, auth=spec.frame_auth(3))
    x = np.arange(spec.dim, dtype=float)
    send = lambda upd, seq: decoder.decode(  # noqa: E731
        encode_state(upd, fleet=spec.fleet, seq=seq, config_tag=spec.config_tag, auth=auth), expected_sender=0)
    assert isinstance(send(StateUpdate(0, 5, x, 0, x, 0), 1), Decoded)
    assert send(StateUpdate(0, 5, x, 0, x, 0, gone=(1,)), 2).reason == "equivocation"
    assert isinstance(send(StateUpdate(0, 6, x, 0, x, 0, gone=(1,)), 3), Decoded)  # round 5 said nobody: pgone ()
    assert send(StateUpdate(0, 6, x, 0, x, 0, gone=(1, 2)), 4).reason == "equivocation"
    assert isinstance(send(StateUpdate(0, 7, x, 0, x, 0, gone=(1,), prev_gone=(1,)), 5), Decoded)
    assert send(StateUpdate(0, 8, x, 0, x, 0, gone=(1,)), 6).reason == "equivocation"  # round 7 said (1,), not ()
    assert decoder.counts == {"equivocation": 3}


@pytest.mark.parametrize("gone, prev_gone, why", [
    ((0,), (), "own sender"), ((2, 1), (), "not strictly ascending"), ((1,), (2,), "not a subset"),
    ((1, 1), (), "not strictly ascending")])
def test_a_message_cannot_be_built_with_a_bad_list(gone, prev_gone, why):
    with pytest.raises(ValueError, match=why):
        StateUpdate(0, 7, np.ones(3), 0, np.ones(3), 0, gone=gone, prev_gone=prev_gone)


def _signed(spec, sender: int, body: dict) -> bytes:
    """A frame body signed with the sender's real keys: what a robot that lies (or a bug) could send."""
    raw = msgpack.packb(body, use_bin_type=True)
    return msgpack.packb([sender, raw, spec.frame_auth(sender).tag_entries(raw)], use_bin_type=True)


def test_a_forged_list_is_refused_and_counted_and_the_robot_goes_on(ring):
    """Robot 3's session gets robot 0's round-0 frame five times: four signed by robot 0's own keys but
    naming robot 3 (the receiver), robot 0 (the sender), robot 9 (no fleet member), or unsorted ids;
    then the true one. The four are refused with "gone" and counted; the true one is taken as it is."""
    _, spec = ring
    receiver = build_core(spec, 3)
    session = RobotSession.for_spec(spec, receiver, now=0.0)
    sender = build_core(spec, 0)
    honest = msgpack.unpackb(msgpack.unpackb(encode_state(
        sender.outgoing(), fleet=spec.fleet, seq=0, config_tag=spec.config_tag, auth=spec.frame_auth(0)))[1])
    assert "gone" not in honest
    for n, lie in enumerate(([3], [0], [1, 9], [2, 1])):
        out = session.receive(0, _signed(spec, 0, {**honest, "seq": 10 + n, "gone": lie}), now=0.1)
        assert isinstance(out, Rejected) and out.reason == "gone", (lie, out)
    assert session.rejected == {"gone": 4} and receiver.missing() == (0, 2)
    out = session.receive(0, _signed(spec, 0, honest), now=0.2)
    assert isinstance(out, Decoded) and receiver.missing() == (2,)
    assert session.row(0.3, {})["frames_rejected_by_reason"] == {"gone": 4}


# ---------------------------------------------------------------------- the cores, in lockstep


def _lockstep(spec, dead: int, at: int, *, restart: tuple[int, int] | None = None, rounds: int = 2000,
              frames: list | None = None, floods: bool = True, keep_trace: bool = False):
    """Every robot's core in one loop, all in the same round: `dead` sends nothing from round `at` on
    and its neighbours drop it in that round; ``restart`` = (robot, round): that robot is rebuilt from
    its checkpoint there (msgpack, as on disk), its frame before and after put in ``frames``.
    ``floods=False`` turns the lists off (what the edge form did before, for comparison); ``rounds``
    bounds the loop (a robot stopped alone leaves its neighbours waiting).
    Returns (cores, round -> robot -> its `gone`)."""
    cores = {i: build_core(spec, i, keep_trace=keep_trace) for i in spec.robot_ids}
    for c in cores.values():
        c.floods_gone = c.floods_gone and floods
    heard: dict[int, dict[int, tuple[int, ...]]] = {}
    for _ in range(rounds):
        live = {i: c for i, c in cores.items() if i != dead or c.round < at}
        if all(c.finished for i, c in live.items() if i != dead):
            break
        outs = {i: c.outgoing() for i, c in live.items()}
        for i, c in live.items():
            for j in c.neighbours:
                if j in outs:
                    c.receive(outs[j])
            if dead in c.neighbours and c.round >= at:  # its value of this round never comes
                c.drop_neighbour(dead)
        for i, c in live.items():
            if c.ready():
                c.advance()
                heard.setdefault(c.round, {})[i] = c.gone
        if restart is not None and cores[restart[0]].round == restart[1]:
            state = msgpack.unpackb(msgpack.packb(cores[restart[0]].checkpoint(), use_bin_type=True),
                                    strict_map_key=False)
            before = cores[restart[0]].outgoing()
            cores[restart[0]] = restore_core(spec, restart[0], state)
            if frames is not None:
                frames += [before, cores[restart[0]].outgoing()]
            restart = None
    cores.pop(dead, None)
    return cores, heard


@pytest.fixture(scope="module")
def line():
    """A 5-line; robot 0 dies at round 40: robot 4 is 3 hops from the news."""
    return soft_edge_fleet(5, "line", dead=0)


def test_the_news_crosses_one_hop_a_round_and_the_survivors_solve_their_problem(line):
    world, spec = line
    cores, heard = _lockstep(spec, dead=0, at=40)
    # robot 1 dropped robot 0 in round 40 and weighs by 1/4 from its step into 41; robot k, k - 1 hops on,
    # a round later per hop (frames and stop flags move alike)
    learned = {i: min(k for k, g in heard.items() if g.get(i) == (0,)) for i in cores}
    assert learned == {1: 41, 2: 42, 3: 43, 4: 44}
    assert all(g.get(i, (0,)) == () for k, g in heard.items() for i in cores if k < learned[i])
    assert all(c.converged and c.round == cores[1].round for c in cores.values())
    ref = survivors_reference(world, spec, dead=0)
    rows = [c.result() for c in cores.values()]
    assert max_function_error(spec, ref, rows) < 1e-3


def test_a_survivor_restarted_from_its_checkpoint_after_the_news_goes_on_bit_for_bit(line):
    """Robot 4 learned of the loss at round 44; rebuilt from its round-45 checkpoint it knows it still
    (the checkpoint holds `gone` and what its inbox heard), and every robot ends on the same bits."""
    _, spec = line
    clean, _ = _lockstep(spec, dead=0, at=40)
    frames: list[StateUpdate] = []
    again, _ = _lockstep(spec, dead=0, at=40, restart=(4, 45), frames=frames)
    before, after = frames  # the frame it sends again is the one it sent (its lists included)
    assert before == after and (after.round, after.gone, after.prev_gone) == (45, (0,), (0,))
    for i, c in clean.items():
        assert again[i].round == c.round and again[i].gone == c.gone == (0,)
        np.testing.assert_array_equal(again[i].values, c.values)


# ---------------------------------------------------------------------- whole runs


@pytest.mark.parametrize("robots, topology, dead, algorithm", [
    pytest.param(6, "ring", 1, "admm", id="6-ring"),  # the survivors' path is wider (4) than the ring (3)
    pytest.param(5, "line", 0, "admm", id="5-line"),
    pytest.param(4, "ring", 1, "ct-admm", id="ct-admm-4-ring"),  # its duals' bound C N beta: the same defect
])
def test_a_sparse_soft_fleet_losing_a_robot_for_good_ends_on_its_survivors_exact_answer(robots, topology, dead,
                                                                                         algorithm):
    """Before: every survivor kept 1 / N and they settled 0.17-0.21 from it, NOT converged (the 6-ring's
    path ends also stopped rounds apart: the stop flags reached 3 hops, the path is 4 wide)."""
    world, spec, _ = make_run(fleet_id=f"survivors-{topology}", timing=TIMING, robots=robots, topology=topology,
                              C=10.0, algorithm=algorithm)
    out = simulate_fleet(spec, crashes=[CrashPlan(dead, 40)], restart=False)
    assert sorted(r["id"] for r in out.robots) == [i for i in range(robots) if i != dead]
    assert all(r["converged"] and r["stopped"] == "finished" and r["frames_rejected"] == 0 for r in out.robots)
    assert len({r["rounds"] for r in out.robots}) == 1  # one stop, every robot in the same round
    assert max_function_error(spec, survivors_reference(world, spec, dead), out.robots) < 1e-3


def test_the_hub_form_sends_no_list_the_edge_form_does_with_either_margin(ring):
    """A complete graph's hub sees every drop itself: its frames and bits stay as they were (nothing
    flooded). The edge form floods with a hard margin too: its stop needs the news (below)."""
    _, spec = ring
    assert build_core(spec, 0).floods_gone
    assert build_core(dataclasses.replace(spec, C=None), 0).floods_gone
    _, complete, _ = make_run(fleet_id="survivors-complete", timing=TIMING, C=10.0)
    assert not build_core(spec_for_run(complete, [], restart=False, restart_after=0.5), 0).floods_gone


# ---------------------------------------------------------------------- hard margins: only the stop


def hard_edge_fleet(robots: int, topology: str, dead: int):
    """(world, spec) of a hard-margin fleet given the edge form, as a run losing ``dead`` for good gives it."""
    world, spec, _ = make_run(fleet_id=f"survivors-hard-{topology}", timing=TIMING, robots=robots, topology=topology)
    return world, spec_for_run(spec, [CrashPlan(dead, 40)], restart=False, restart_after=0.5)


@pytest.fixture(scope="module")
def hard_six_ring():
    """A hard 6-ring: without robot 1 its survivors form a path of diameter 4, the flags reach 3 hops."""
    return hard_edge_fleet(6, "ring", dead=1)


def test_a_hard_six_ring_losing_a_robot_stops_together_on_its_survivors_exact_answer(hard_six_ring):
    """Before, the flags (sized for the ring's diameter 3) stopped the path's ends rounds apart (600 and
    1208 here; NOT converged): the lists let every survivor widen its stop to the survivors' graph.
    The hard steps do not use the lists: round for round, the iterates are those of the run without
    them, up to the round where that run's first robot stopped alone."""
    world, spec = hard_six_ring
    cores, heard = _lockstep(spec, dead=1, at=40, keep_trace=True)
    assert sorted(cores) == [0, 2, 3, 4, 5]
    stop = {c.round for c in cores.values()}
    assert len(stop) == 1 and all(c.converged for c in cores.values())  # one stop, every robot in it
    assert all(c.gone == (1,) for c in cores.values())
    assert all(g == () for k, g in heard.items() if k <= 40 for g in g.values())  # no list before the loss
    ref = survivors_reference(world, spec, dead=1)
    assert max_function_error(spec, ref, [c.result() for c in cores.values()]) < 1e-3

    # the same run without the lists: the ends stop apart (bounded loop: the others wait on robot 2)
    before, _ = _lockstep(spec, dead=1, at=40, floods=False, keep_trace=True, rounds=stop.pop() + 20)
    alone = [i for i, c in before.items() if c.finished]
    assert alone and len(alone) < len(before)  # some robot stopped, not all: the gap this closes
    first = min(c.round for c in before.values())
    for i, c in cores.items():
        for k in range(first + 1):
            np.testing.assert_array_equal(c.trace[k], before[i].trace[k])


def test_a_hard_fleet_without_a_loss_sends_no_list_and_keeps_its_bits():
    """No loss, no list: every frame is the one sent before (no `gone`), and the run with the lists on
    is the run with them off, bit for bit, stop round included."""
    _, spec = hard_edge_fleet(5, "ring", dead=1)
    on, heard = _lockstep(spec, dead=-1, at=0)
    off, _ = _lockstep(spec, dead=-1, at=0, floods=False)
    assert all(g == () for per in heard.values() for g in per.values())
    assert all(c.converged for c in on.values()) and len({c.round for c in on.values()}) == 1
    for i, c in on.items():
        assert c.round == off[i].round and c.outgoing() == off[i].outgoing()
        np.testing.assert_array_equal(c.values, off[i].values)


def test_a_hard_survivor_restarted_from_its_checkpoint_keeps_the_wider_stop(hard_six_ring):
    """The widened stop is not in the checkpoint: it follows from `gone`, which is. Robot 3 (two hops
    from the loss) rebuilt from its round-50 checkpoint stops with the others, on the same bits."""
    _, spec = hard_six_ring
    clean, _ = _lockstep(spec, dead=1, at=40)
    again, _ = _lockstep(spec, dead=1, at=40, restart=(3, 50))
    for i, c in clean.items():
        assert again[i].round == c.round and again[i].converged and again[i].gone == (1,)
        np.testing.assert_array_equal(again[i].values, c.values)


def test_a_hard_ct_admm_ring_losing_a_robot_stops_together_on_its_survivors_exact_answer():
    """ct-admm with a hard margin floods the lists too (its stop alone needs them). Before, an 8-ring
    losing robot 3 at round 40 stopped its path's ends at rounds 5147 and 11918, 0.19 from the survivors'
    answer, each robot reporting converged; the wider stop makes it one stop, 4.8e-4 from it."""
    world, spec, _ = make_run(fleet_id="survivors-ct-hard", timing=TIMING, robots=8, topology="ring",
                              algorithm="ct-admm", ct_stop_time=60.0)
    assert spec.C is None
    out = simulate_fleet(spec, crashes=[CrashPlan(3, 40)], restart=False)
    assert sorted(r["id"] for r in out.robots) == [0, 1, 2, 4, 5, 6, 7]
    assert all(r["converged"] and r["stopped"] == "finished" for r in out.robots)
    assert len({r["rounds"] for r in out.robots}) == 1  # one stop, every robot in the same round
    assert max_function_error(spec, survivors_reference(world, spec, dead=3), out.robots) < 1e-3
