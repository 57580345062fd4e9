"""The sans-IO session alone, on a fake clock: resend timing, dedup, piggyback recovery, death by
silence and on evidence, linger, stop reasons, counters; and one result row for both shells."""

from __future__ import annotations

import collections

import numpy as np
import pytest

from agents.problem import SolverError
from agents.rounds import RoundCore
from protocol.frames import Decoded, FrameDecoder
from protocol.session import (
    BROADCAST,
    ROW_KEYS,
    RobotSession,
    SessionTiming,
    row_from_file,
    row_to_file,
)

TAG = b"sessiont"
SENDERS = (0, 1, 2)
TIMING = SessionTiming(retransmit_s=0.1, dead_after_s=1.0, max_wall_s=100.0, linger_s=0.5, give_up_s=10.0)


class Mean(RoundCore):
    """x <- mean of its own and its neighbours' x, for a fixed number of rounds (never converges)."""

    algorithm = "mean"

    def __init__(self, i: int, neighbours: tuple[int, ...], rounds: int = 6, fail_at: int | None = None) -> None:
        super().__init__(i, neighbours, 3, diameter=2, round_cap=rounds, keep_trace=True)
        self._values = np.array([1.0 + i, -2.0 * i, 0.5 * i])
        self.fail_at = fail_at
        self._record()

    def _step(self, mine, theirs):
        if self.round == self.fail_at:
            raise SolverError("piqp returned PIQP_MAX_ITER_REACHED")
        return np.mean([mine, *(theirs[j] for j in sorted(theirs))], axis=0), False

    def _forget_edge(self, j):
        pass

    def _save_state(self):
        return {}

    def _load_state(self, state):
        pass


def session(i: int, neighbours: tuple[int, ...], *, now: float = 0.0, timing: SessionTiming = TIMING,
            **kw) -> RobotSession:
    core_kw = {k: kw.pop(k) for k in ("rounds", "fail_at") if k in kw}
    return RobotSession(Mean(i, neighbours, **core_kw), fleet="sess", senders=SENDERS, dim=3,
                        config_tag=TAG, timing=timing, now=now, **kw)


def frames(s: RobotSession, now: float) -> list[bytes]:
    out = s.to_send(now)
    assert all(dest is BROADCAST for dest, _ in out)
    return [f for _, f in out]


def run_pair(a: RobotSession, b: RobotSession, now: float, lose=lambda src, frame: False) -> float:
    """Exchange and advance on the fake clock until both are done; the final time."""
    for _ in range(10_000):
        if a.done and b.done:
            return now
        for s, other in ((a, b), (b, a)):
            for f in frames(s, now):
                if not lose(s.me, f):
                    other.receive(s.me, f, now)
        for s in (a, b):
            while s.advance(now):
                pass
        due = [d for d in (a.next_deadline(), b.next_deadline()) if d is not None]
        now = max(now, min(due)) if due else now
    raise AssertionError("no progress")


def seq_of(frame: bytes, sender: int) -> int:
    out = FrameDecoder("sess", SENDERS, 3, TAG).decode(frame, expected_sender=sender)
    assert isinstance(out, Decoded)
    return out.seq


# ----------------------------------------------------------------------------- resend


def test_first_frame_then_resend_every_retransmit_s():
    s = session(0, (1,))
    first = frames(s, 0.0)
    assert len(first) == 1 and s.sent == 1
    assert s.next_deadline() == pytest.approx(0.1)
    assert frames(s, 0.099) == [] and s.next_deadline() == pytest.approx(0.1)
    again = frames(s, 0.1)
    assert len(again) == 1 and seq_of(again[0], 0) == seq_of(first[0], 0) + 1
    assert s.next_deadline() == pytest.approx(0.2) and s.sent == 2


def test_resend_waits_a_round_of_this_fleet_from_its_second_round_on():
    """Issue 14: before ADAPT_MIN_ROUNDS rounds, the shortest round so far (not the first, which
    holds the start-up wait) sets the resend interval; a slow fleet no longer resends every
    retransmit_s during its first rounds."""
    from protocol.session import ADAPT_FACTOR

    a, b = session(0, (1,)), session(1, (0,))
    now = 0.0
    fa, fb = frames(a, now)[-1], frames(b, now)[-1]
    for step in (2.0, 0.5, 0.4):  # round times: a slow start, then 0.5 s and 0.4 s rounds
        now += step
        a.receive(1, fb, now)
        b.receive(0, fa, now)
        assert a.advance(now) and b.advance(now)
        fa, fb = frames(a, now)[-1], frames(b, now)[-1]
    assert a.round_intervals == pytest.approx([2.0, 0.5, 0.4])
    frames(a, now)
    assert a.next_deadline() == pytest.approx(now + ADAPT_FACTOR * 0.4)  # not now + retransmit_s (0.1)


def test_resend_quartile_window_is_the_last_rounds_sorted_and_sets_the_interval():
    """The window kept sorted as rounds come (branch hubcost2) holds exactly the last
    ADAPT_WINDOW round intervals -- repeated values and values leaving it included -- and the
    resend interval is the 25th percentile of them (np.percentile, linear) times ADAPT_FACTOR."""
    from protocol.session import ADAPT_FACTOR, ADAPT_WINDOW

    a, b = session(0, (1,), rounds=200), session(1, (0,), rounds=200)
    now = 0.0
    fa, fb = frames(a, now)[-1], frames(b, now)[-1]
    rng = np.random.default_rng(7)
    steps = [float(x) for x in rng.choice([0.2, 0.3, 0.35, 0.5, 0.9], size=3 * ADAPT_WINDOW)]
    for k, step in enumerate(steps):
        now += step
        a.receive(1, fb, now)
        b.receive(0, fa, now)
        assert a.advance(now) and b.advance(now)
        fa, fb = frames(a, now)[-1], frames(b, now)[-1]
        last = a.round_intervals[-ADAPT_WINDOW:]
        assert a._window == sorted(last)
        if k + 1 >= 8:
            periodic, _fast = a._resend_interval()
            assert periodic == pytest.approx(max(TIMING.retransmit_s, ADAPT_FACTOR * float(np.percentile(last, 25))))


def test_neighbour_one_round_behind_triggers_a_fast_resend():
    a, b = session(0, (1,)), session(1, (0,))
    fa, fb = frames(a, 0.0), frames(b, 0.0)
    a.receive(1, fb[0], 0.0)
    assert a.advance(0.0) and a.core.round == 1
    assert len(frames(a, 0.0)) == 1  # the round-1 frame, at once
    a.receive(1, frames(b, 0.1)[0], 0.1)  # b resends round 0: it has not got our round-0 value
    fast = a.next_deadline()
    assert fast < 0.1 + 0.1 - 1e-9  # sooner than a periodic resend
    out = frames(a, fast)
    assert len(out) == 1
    b.receive(0, out[0], fast)  # round 1 carries round 0 piggybacked: b can advance
    assert b.advance(fast) and b.core.round == 1
    del fa


# ----------------------------------------------------------------------------- receive


def test_duplicate_frame_is_counted_and_ignored():
    a, b = session(0, (1,)), session(1, (0,))
    f = frames(b, 0.0)[0]
    assert isinstance(a.receive(1, f, 0.0), Decoded)
    assert a.receive(1, f, 0.0) is None
    row = a.row(0.0, {})
    assert row["frames_deduplicated"] == 1 and row["frames_accepted"] == 2 and row["frames_rejected"] == 0


def test_garbage_is_rejected_by_reason_and_never_reaches_the_core():
    a = session(0, (1,))
    a.receive(1, b"\xc1 not msgpack", 0.0)
    a.receive(1, frames(session(2, (1,)), 0.0)[0], 0.0)  # robot 2's frame on robot 1's key
    row = a.row(0.0, {})
    assert row["frames_rejected"] == 2
    assert row["frames_rejected_by_reason"] == {"not-msgpack": 1, "sender": 1}
    assert a.core.missing() == (1,)


def test_lost_frames_are_recovered_exactly_from_the_piggyback():
    clean = run_pair(session(0, (1,)), session(1, (0,)), 0.0)
    a, b = session(0, (1,)), session(1, (0,))
    seen = {0: 0, 1: 0}

    def lose(src, frame):  # every other frame of robot 0 is lost
        seen[src] += 1
        return src == 0 and seen[src] % 2 == 0

    t = run_pair(a, b, 0.0, lose)
    ref_a, ref_b = session(0, (1,)), session(1, (0,))
    run_pair(ref_a, ref_b, 0.0)
    for got, want in ((a, ref_a), (b, ref_b)):
        assert got.core.round == want.core.round == 6
        assert np.array_equal(got.core.values, want.core.values)
        assert got.stopped == "finished"
    assert t > clean  # recovery cost time, not accuracy


# ----------------------------------------------------------------------------- neighbour death


def test_token_gone_plus_dead_after_s_of_silence_drops_and_isolates():
    s = session(0, (1,))
    frames(s, 0.0)
    s.peer_up(1, 0.0)
    s.peer_gone(1, 2.0)
    frames(s, 2.5)
    assert s.core.neighbours == (1,)  # evidence, but not silent long enough after it
    assert s.next_deadline() <= 3.0
    frames(s, 3.0)
    assert s.neighbours_dropped == [1] and s.dropped_at == {1: 0}
    assert s.stopped == "isolated" and s.done and "isolated" in s.error
    row = s.row(3.0, {})
    assert row["isolated"] is True and row["converged"] is False and row["stopped"] == "isolated"


def test_a_token_still_there_is_waited_for_until_give_up_s():
    s = session(0, (1, 2))
    frames(s, 0.0)
    s.peer_up(1, 0.0)
    s.peer_up(2, 0.0)
    s.receive(2, frames(session(2, (0,)), 0.0)[0], 0.0)
    for t in np.arange(0.1, 9.95, 0.1):  # robot 1 silent but present (paused): waited for
        frames(s, float(t))
    assert s.neighbours_dropped == []
    frames(s, 10.0)
    assert s.neighbours_dropped == [1] and s.stopped is None
    assert s.ready()  # robot 2's value is here: the round goes on without robot 1


def test_no_drop_while_disconnected_and_the_clock_restarts_on_reconnection():
    s = session(0, (1,), link_checks=True)
    frames(s, 0.0)
    s.peer_up(1, 0.0)
    s.peer_gone(1, 0.5)
    s.disconnected(0.5)  # the router went: every token goes with it
    frames(s, 5.0)
    assert s.link_check_due  # a drop needs a fresh look at our connection
    s.link_status(False, 5.0)
    frames(s, 5.0)
    assert s.neighbours_dropped == []
    s.connected(6.0)  # back: evidence counts from now
    frames(s, 6.9)
    assert s.neighbours_dropped == []
    frames(s, 7.0)
    assert s.link_check_due
    s.link_status(True, 7.0)
    frames(s, 7.0)
    assert s.neighbours_dropped == [1]


@pytest.mark.parametrize("token_seen", [False, True])
def test_a_neighbour_two_rounds_ahead_has_dropped_us(token_seen: bool):
    """Dropped with or without the neighbour's liveliness token seen (with it: the shell's usual
    case)."""
    s = session(0, (1,))
    if token_seen:
        s.peer_up(1, 0.0)
    ahead = session(1, ())  # alone it runs ahead
    while ahead.advance(0.0):
        if ahead.core.round == 2:
            break
    s.receive(1, frames(ahead, 0.0)[-1], 1.0)  # its round-2 frame
    frames(s, 1.0)
    assert s.neighbours_dropped == [1] and s.stopped == "isolated"


def test_a_live_neighbour_one_round_ahead_is_waited_for():
    """A neighbour one round ahead with its token up is waited for until give_up_s after it was
    last heard."""
    s = session(0, (1,))
    s.peer_up(1, 0.0)
    near = session(1, ())
    near.advance(0.0)  # its round-1 frame: one round ahead, alive
    s.receive(1, frames(near, 0.0)[-1], 1.0)
    frames(s, 1.0)
    assert s.neighbours_dropped == [] and s.stopped is None
    assert s.next_deadline() <= 1.0 + TIMING.give_up_s


# ----------------------------------------------------------------------------- stops and linger


def test_linger_republishes_until_the_neighbour_has_our_final_round():
    a, b = session(0, (1,), rounds=1), session(1, (0,), rounds=1)
    a.peer_up(1, 0.0)  # b is there (a neighbour whose token is gone needs nothing from us)
    frames(a, 0.0)
    a.receive(1, frames(b, 0.0)[0], 0.0)
    assert a.advance(0.0) and a.core.finished and a.lingering and not a.done
    frames(a, 0.0)
    assert len(frames(a, 0.1)) == 1  # still republished while b has not shown round 1
    b.receive(0, frames(a, 0.2)[0], 0.2)
    assert b.advance(0.2)
    a.receive(1, frames(b, 0.2)[0], 0.2)
    frames(a, 0.2)
    assert a.done and a.stopped == "finished"


def test_linger_is_bounded_by_linger_s():
    a = session(0, (1,), rounds=1)
    a.peer_up(1, 0.0)
    a.receive(1, frames(session(1, (0,)), 0.0)[0], 0.0)
    a.advance(0.0)
    frames(a, 0.49)
    assert not a.done
    frames(a, 0.5)
    assert a.done and a.row(0.5, {})["stopped"] == "finished"


def test_solver_failure_and_divergence_are_stop_reasons():
    s = session(0, (), fail_at=2)
    while s.advance(0.0):
        pass
    assert s.stopped == "solver_error" and s.done
    assert s.error == "robot 0 round 2: local solver failed: piqp returned PIQP_MAX_ITER_REACHED"
    s = session(1, ())
    s.core._values = s.core._values * 1e80
    assert not s.advance(0.0)
    assert s.stopped == "diverged" and s.error.startswith("robot 1 round 1: diverged: exploding iterate")
    assert s.row(0.0, {})["converged"] is False


def test_max_wall_s():
    s = session(0, (1,), timing=SessionTiming(0.1, 60.0, 0.5, 0.5, 600.0))
    frames(s, 0.0)
    assert s.next_deadline() == pytest.approx(0.1)
    frames(s, 0.5)
    assert s.done and s.stopped == "max_wall" and s.next_deadline() is None


# ----------------------------------------------------------------------------- counters and rows


def test_counters_survive_a_restart():
    a, b = session(0, (1,)), session(1, (0,))
    a.receive(1, b"junk", 0.0)
    a.receive(1, frames(b, 0.0)[0], 0.0)
    a.advance(0.0)
    frames(a, 0.0)
    env = a.checkpoint({"received": 5, "lost": 2, "duplicated": 1})
    core = Mean(0, (1,))
    core.restore(env["core"])
    again = RobotSession(core, fleet="sess", senders=SENDERS, dim=3, config_tag=TAG, timing=TIMING,
                         now=10.0, resume=env)
    row = again.row(10.0, {"received": 1, "lost": 0, "duplicated": 0})
    assert row["restarts"] == 1 and row["frames_sent"] == 3  # 2 before + the restart's first frame
    assert (row["frames_received"], row["frames_lost"], row["frames_duplicated"]) == (6, 2, 1)
    assert row["frames_rejected_by_reason"] == {"not-msgpack": 1} and row["frames_accepted"] == 1
    # a restarted sender's seqs are all newer than any of its former life
    assert seq_of(frames(again, 10.0)[0], 0) > seq_of(frames(session(0, (1,)), 0.0)[0], 0) + 1000


def test_row_has_every_key_and_survives_the_result_file():
    a, b = session(0, (1,)), session(1, (0,))
    run_pair(a, b, 0.0)
    row = a.row(1.0, {"received": 9, "lost": 1, "duplicated": 0})
    assert set(ROW_KEYS) <= row.keys()
    assert isinstance(row["frames_rejected"], int) and isinstance(row["frames_rejected_by_reason"], dict)
    assert all(isinstance(k, int) for key in ("trace", "round_times") for k in row[key])
    assert sorted(row["round_times"]) == list(range(7)) and row["round_ms"]["rounds"] == 6
    back = row_from_file(row_to_file(row))
    assert back.keys() == row.keys()
    assert {k: v for k, v in back.items() if k != "residual"} == {k: v for k, v in row.items() if k != "residual"}


def test_simulate_rows_have_the_session_schema():
    """simulate_fleet's rows are RobotSession.row()s, and a result file read back gives the same
    keys and types (the Zenoh side of this check runs in tests/test_robot_shell.py)."""
    from launcher.simulate import simulate_fleet

    from .conftest import make_run

    _world, spec, _central = make_run(robots=3, max_rounds=15)
    rows = simulate_fleet(spec).robots
    for r in rows:
        assert set(ROW_KEYS) <= r.keys()
        back = row_from_file(row_to_file(r))
        assert back.keys() == r.keys()
        assert {k: type(v) for k, v in back.items()} == {k: type(v) for k, v in r.items()}
        assert r["frames_received"] >= r["frames_accepted"] > 0 and r["stopped"] == "finished"


# ----------------------------------------------------------------------------- issue 14: resends


def test_a_neighbour_repeating_our_own_round_gets_a_fast_resend_and_an_overtaken_frame_none():
    """A neighbour's repeat of the round we are at shows it lacks a value of that round (maybe
    ours, lost): answered after the fast interval, not the periodic one. A frame of its overtaken
    by a newer one of its sender's (reordered, late) is no evidence: no resend for it."""
    b = session(1, (0,))
    fb0 = frames(b, 0.0)[0]
    b.receive(0, frames(session(0, (1,)), 0.0)[0], 0.0)
    assert b.advance(0.0)
    fb1 = frames(b, 0.0)[0]
    fb1_again = frames(b, 0.1)[0]  # b waits for our round 1 (lost) and repeats its round 1
    fc0 = frames(session(2, (0,)), 0.0)[0]
    for late, fast in ((fb1_again, True), (fb0, False)):
        a = session(0, (1, 2))  # robot 2 keeps a from advancing past round 1
        frames(a, 0.0)
        a.receive(1, fb0, 0.0)
        a.receive(2, fc0, 0.0)
        assert a.advance(0.0) and a.core.round == 1
        assert len(frames(a, 0.0)) == 1
        a.receive(1, fb1, 0.01)  # b is at our round: it holds our round 0
        assert frames(a, 0.01) == []
        periodic = a.next_deadline()
        a.receive(1, late, 0.02)
        assert frames(a, 0.02) == []
        assert (a.next_deadline() < periodic) is fast


def test_a_fleet_sends_one_frame_per_robot_and_round_without_loss_and_the_same_answer_under_loss():
    """Without faults every robot sends exactly one frame a round (no resend at all); with 30 %
    loss the fleet still finishes at the same bits as without loss."""
    import dataclasses

    from launcher.simulate import simulate_fleet
    from protocol.links import LinkFaults

    from .conftest import make_run

    _world, spec, _central = make_run(robots=8, max_rounds=25, topology="geometric")
    clean = simulate_fleet(spec).robots
    assert all(r["frames_sent"] == r["rounds"] + 1 for r in clean)
    lossy = simulate_fleet(dataclasses.replace(spec, faults=LinkFaults(loss=0.3))).robots
    assert sum(r["frames_lost"] for r in lossy) > 0
    by_id = {r["id"]: r for r in lossy}
    for r in clean:
        assert by_id[r["id"]]["x"] == r["x"] and by_id[r["id"]]["gamma"] == r["gamma"]


def test_repeats_of_our_round_are_answered_once_per_half_interval_a_robot_behind_every_time():
    """Issue 14: a neighbour repeating the round we are at gets a fast resend of ours, but its next
    repeat within half a periodic interval waits (each answer is itself a repeat to every robot at
    our round: answered every time, 16 robots stormed). One round behind is still answered."""
    b = session(1, (0,))
    fb0 = frames(b, 0.0)[0]
    b.receive(0, frames(session(0, (1,)), 0.0)[0], 0.0)
    assert b.advance(0.0)
    fb1, fb1_again, fb1_third = frames(b, 0.0)[0], frames(b, 0.1)[0], frames(b, 0.2)[0]
    c = session(2, (0,))
    fc0, fc0_again = frames(c, 0.0)[0], frames(c, 0.1)[0]
    a = session(0, (1, 2))  # at round 1 it waits for robot 2's round 1
    frames(a, 0.0)
    a.receive(1, fb0, 0.0)
    a.receive(2, fc0, 0.0)
    assert a.advance(0.0) and a.core.round == 1 and len(frames(a, 0.0)) == 1
    a.receive(1, fb1, 0.01)
    a.receive(1, fb1_again, 0.02)  # b repeats our round: the fast resend
    assert frames(a, 0.02) == []
    fast = a.next_deadline()
    assert fast < 0.1 and len(frames(a, fast)) == 1
    a.receive(1, fb1_third, 0.03)  # again, 5 ms after our answer: no second fast resend
    assert frames(a, 0.03) == [] and a.next_deadline() == pytest.approx(fast + 0.1)
    a.receive(2, fc0_again, 0.04)  # robot 2 repeats round 0, one behind us: fast resend
    assert frames(a, 0.04) == [] and a.next_deadline() == pytest.approx(fast + 0.025)


def test_a_repeat_is_answered_only_by_the_neighbours_it_names_in_need():
    """Issue 14, third pass: every frame says which neighbours' values of its round its sender
    still lacks ("need"). A neighbour repeating the round we are at while waiting for a third
    robot does not name us: no fast resend (at 32 robots every one of 31 neighbours answered);
    the same repeat from a neighbour that lacks our frame names us and is answered fast."""
    for b_has_ours in (True, False):
        a, b, c = session(0, (1, 2)), session(1, (0, 2)), session(2, (0, 1))
        fa0, fb0, fc0 = frames(a, 0.0)[0], frames(b, 0.0)[0], frames(c, 0.0)[0]
        for s, got in ((a, ((1, fb0), (2, fc0))), (b, ((0, fa0), (2, fc0)))):
            for src, f in got:
                s.receive(src, f, 0.0)
            assert s.advance(0.0) and s.core.round == 1
        fa1, fb1 = frames(a, 0.0)[0], frames(b, 0.0)[0]
        if b_has_ours:
            b.receive(0, fa1, 0.01)
        fb1_again = frames(b, 0.1)[0]  # b still waits for robot 2 (and for us unless b_has_ours)
        need = FrameDecoder("sess", SENDERS, 3, TAG).decode(fb1_again, expected_sender=1).need
        assert need == ((2,) if b_has_ours else (0, 2))
        a.receive(1, fb1, 0.01)
        assert frames(a, 0.01) == []
        periodic = a.next_deadline()
        a.receive(1, fb1_again, 0.02)  # (b's clock is not ours: delivered before our resend is due)
        assert frames(a, 0.02) == []
        assert (a.next_deadline() < periodic) is (not b_has_ours)


def _plain_note(rounds: dict[int, int], seq: int, rnd: int) -> tuple[bool, bool, bool] | None:
    """The dedup rule written plainly: None for a frame remembered already, else (newest, gap,
    repeat); a full window forgets every seq up to the newest - DEDUP_WINDOW // 2 first."""
    from protocol.session import DEDUP_WINDOW

    if rounds.get(seq) == rnd:
        return None
    newest, gap = True, False
    if rounds:
        top = max(rounds)
        if len(rounds) >= DEDUP_WINDOW:
            for q in [q for q in rounds if q <= top - DEDUP_WINDOW // 2]:
                del rounds[q]
        newest, gap = seq > top, seq > top + 1
    repeat = rnd in rounds.values()
    rounds[seq] = rnd
    return newest, gap, repeat


def test_seen_frames_note_matches_the_plain_dedup_rule():
    """_SeenFrames keeps receive's answers up to date instead of scanning: same answers and same
    memory as the plain rule, frame after frame, over seqs in order, copies, late and reused seqs
    (a fresh sender reuses a seq with another round) and several window overflows."""
    from protocol.session import DUPLICATE, GAP, NEWEST, REPEAT, _SeenFrames

    from protocol.session import DEDUP_WINDOW

    rng = np.random.default_rng(5)
    # first a full window, then a seq it is about to forget, reused with another round
    frames = [(s, s // 3) for s in range(DEDUP_WINDOW)] + [(5, 999)]
    seq = DEDUP_WINDOW
    for _ in range(800):
        if rng.random() < 0.7:
            seq += int(rng.integers(1, 3))
            s = seq
        else:  # a copy, a late frame, or a seq far back (possibly forgotten, possibly reused)
            s = max(0, seq - int(rng.integers(0, 300)))
        frames.append((s, s // 3 if rng.random() < 0.9 else int(rng.integers(0, 600))))
    seen, model = _SeenFrames(), {}
    for s, rnd in frames:
        kind, want = seen.note(s, rnd), _plain_note(model, s, rnd)
        if want is None:
            assert kind == DUPLICATE
        else:
            assert kind >= 0 and (bool(kind & NEWEST), bool(kind & GAP), bool(kind & REPEAT)) == want
        assert seen.rounds == model and seen.top == max(model)
        assert seen.per_round == collections.Counter(model.values())


def test_queued_hands_over_the_frames_of_advance_without_running_the_timers():
    """``RobotSession.queued`` (issue 14, branch shell3): the Zenoh shell publishes the frame of an
    advance at once and runs the timers (``to_send``) once, on the loop's next pass -- the same
    frames, the timers not run twice a round."""
    a, b = session(0, (1,)), session(1, (0,))
    for f in frames(a, 0.0):
        b.receive(0, f, 0.0)
    for f in frames(b, 0.0):
        a.receive(1, f, 0.0)
    assert a.queued() == [] and a.advance(0.01) and a.core.round == 1
    out = a.queued()
    assert len(out) == 1 and out[0][0] is BROADCAST and a.queued() == []
    assert b.receive(0, out[0][1], 0.01).update.round == 1  # the round-1 frame itself
    # max_wall_s passed: the timers (to_send's tick) stop the session; queued does not
    late = TIMING.max_wall_s + 1.0
    assert a.queued() == [] and a.stopped is None
    assert frames(a, late) == [] and a.stopped == "max_wall"
