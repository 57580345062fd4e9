"""One robot's session: the retransmission and liveness protocol around an algorithm core, sans-IO.

Both shells drive this one state machine, so they behave the same by construction: the in-process
fleet (``launcher/simulate.py``) on a virtual clock, the Zenoh process (``agents/robot.py``) on the
event loop. The session never reads a clock, sleeps or touches a socket: the shell hands it bytes
and the time, and takes bytes and a deadline out (the h11 style)::

    session.receive(source, payload, now)      a frame that arrived on ``source``'s key / link
    session.peer_up(j, now) / peer_gone(j, now) what only a shell observes: j's liveliness token
    session.link_status(up, now, reconnected)   whether we have a router (only with link_checks)
    while session.ready(): session.advance(now) one round (the shell checkpoints before it)
    session.to_send(now) -> [(BROADCAST, bytes)] frames to publish now (new rounds, resends)
    session.next_deadline() -> float | None     when to call to_send again if nothing arrives
    session.done / session.stopped / row(now)   why it stopped, and the result row

What it owns: frame encode/decode with authentication, dedup (a frame no newer than the last one
heard from its sender carries nothing new), piggyback recovery (the core keeps round k-1 from
round k's frame), resend (adaptive, plus a fast resend when a neighbour's newest frame shows it lacks a value of
our last two rounds and it is still there at the fast deadline),
linger after finishing, neighbour death on evidence, the stop reasons and the result row.

Neighbour death (dropping needs evidence that it is gone for good): its liveliness token is gone
while we are connected, and it has been silent for ``dead_after_s`` since the later of its last
frame, its token's disappearance and our own (re)connection; or it has been silent for
``give_up_s`` whatever its token says. A neighbour two rounds ahead of us has dropped us (its frames
can never carry what we need): we drop it too. A robot whose every neighbour was dropped stops
``isolated``; a core that raises SolverError / InfeasibleError stops ``solver_error``; a non-finite
or exploding iterate stops ``diverged``; ``max_wall_s`` on the shell's clock stops ``max_wall``.
"""

from __future__ import annotations

import collections
from bisect import bisect_left, insort
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from agents.messages import StateUpdate
from protocol.auth import FrameAuth
from protocol.frames import Decoded, FrameDecoder, Rejected, _all_finite, encode_state

__all__ = [
    "BROADCAST",
    "RobotSession",
    "SessionTiming",
    "row_to_file",
    "row_from_file",
    "ROW_KEYS",
    "GIVE_UP_FACTOR",
    "SEQ_EPOCH",
]

BROADCAST = None  # destination of a frame meant for every current neighbour
SEQ_EPOCH = 1 << 40  # seq = restarts * SEQ_EPOCH + n: strictly increasing across restarts
# Final-frame linger when the timing has no linger_s: max(LINGER_MIN_S, LINGER_RETRANSMITS *
# retransmit_s); it ends earlier as soon as every live neighbour has been heard at our final round.
LINGER_MIN_S = 0.5
LINGER_RETRANSMITS = 5
FAST_RESEND_MIN_S = 0.002
# adaptive resend interval: ADAPT_FACTOR x the fast quartile of the last ADAPT_WINDOW round times
ADAPT_FACTOR = 1.5
ADAPT_WINDOW = 32
ADAPT_MIN_ROUNDS = 8
# A neighbour silent this many dead_after_s is given up even if its token is still there (bounded
# waiting for a paused or partitioned robot), unless the timing has its own give_up_s.
GIVE_UP_FACTOR = 10.0
DEDUP_WINDOW = 256  # frames per sender remembered for dedup
CONNECTED_POLL_S = 0.2  # how stale a link report may be before a drop needs a fresh one

#: the keys every result row has, in both shells (plus whatever the core's ``result()`` gives)
ROW_KEYS = (
    "robot", "fleet", "stopped", "error", "isolated", "converged", "rounds",
    "frames_sent", "bytes_sent", "frames_received", "frames_lost", "frames_duplicated", "frames_accepted",
    "frames_deduplicated", "frames_rejected", "frames_rejected_by_reason", "restarts",
    "neighbours_dropped", "dropped_at", "wall_s", "round_ms", "round_times", "trace",
)
_INT_KEYED = ("dropped_at", "round_times", "trace")  # int keys in a row, str keys in JSON


@dataclass(frozen=True)
class SessionTiming:
    """The session's time-outs in seconds of the shell's clock (never part of the mathematics)."""

    retransmit_s: float
    dead_after_s: float
    max_wall_s: float
    linger_s: float
    give_up_s: float

    @classmethod
    def of(cls, timing: Any, *, max_wall_s: float | None = None) -> SessionTiming:
        """From a spec's ``Timing`` (``linger_s`` / ``give_up_s`` optional: derived defaults)."""
        retransmit = float(timing.retransmit_s)
        dead = float(timing.dead_after_s)
        wall = float(timing.max_wall_s if max_wall_s is None else max_wall_s)
        if not (retransmit > 0 and dead > 0 and wall > 0):
            raise ValueError(f"timing values must be positive, got {timing!r}")
        linger = getattr(timing, "linger_s", None)
        linger = float(linger) if linger is not None else max(LINGER_MIN_S, LINGER_RETRANSMITS * retransmit)
        if linger < 0:
            raise ValueError(f"linger_s must be >= 0, got {linger}")
        give_up = getattr(timing, "give_up_s", None)
        give_up = float(give_up) if give_up is not None else GIVE_UP_FACTOR * dead
        return cls(retransmit, dead, wall, linger, give_up)


DUPLICATE, NEWEST, GAP, REPEAT = -1, 1, 2, 4  # _SeenFrames.note's answers


class _SeenFrames:
    """One sender's recent frames, seq -> round, with what `receive` asks of them each frame --
    the newest seq and whether a round is among them -- kept up to date instead of scanned
    (up to DEDUP_WINDOW entries per frame and sender: ~500 frames per round and process in a
    32-robot fleet)."""

    __slots__ = ("rounds", "per_round", "top")

    def __init__(self) -> None:
        self.rounds: dict[int, int] = {}
        self.per_round: dict[int, int] = {}  # round -> how many seqs of `rounds` carry it
        self.top = -1  # max(rounds) when rounds is not empty

    def note(self, seq: int, rnd: int) -> int:
        """What `receive` asks of a frame, then remember it (one call per frame): DUPLICATE if
        (seq, rnd) is remembered already (nothing changes), else the bits NEWEST (no newer seq
        remembered), GAP (seqs skipped since the newest) and REPEAT (its round was seen)."""
        rounds = self.rounds
        old = rounds.get(seq)
        if old == rnd:
            return DUPLICATE
        if rounds:
            top = self.top
            if len(rounds) >= DEDUP_WINDOW:
                self.keep_after(top - DEDUP_WINDOW // 2)
                old = rounds.get(seq)  # (it may have forgotten seq)
            kind = (NEWEST if seq > top else 0) | (GAP if seq > top + 1 else 0)
        else:
            kind = NEWEST
        per_round = self.per_round
        if rnd in per_round:  # (a round's count there is never 0)
            kind |= REPEAT
        if old is not None:
            self._uncount(old)
        rounds[seq] = rnd
        per_round[rnd] = per_round.get(rnd, 0) + 1
        if len(rounds) == 1 or seq > self.top:
            self.top = seq
        return kind

    def keep_after(self, seq: int) -> None:
        """Forget every frame with a seq up to ``seq`` (the newest stays)."""
        for q in [q for q in self.rounds if q <= seq]:
            self._uncount(self.rounds.pop(q))

    def _uncount(self, rnd: int) -> None:
        left = self.per_round[rnd] - 1
        if left:
            self.per_round[rnd] = left
        else:
            del self.per_round[rnd]


class RobotSession:
    """One robot's protocol state around its core; see the module doc for the rules."""

    def __init__(
        self,
        core: Any,
        *,
        fleet: str, senders: tuple[int, ...], dim: int, config_tag: bytes,  # the frames it accepts
        timing: SessionTiming, now: float,  # its clock
        auth: FrameAuth | None = None, link_checks: bool = False, resume: Mapping[str, Any] | None = None,
    ) -> None:
        """``resume``: a checkpoint envelope (``checkpoint()`` output) whose core ``core`` was
        restored from; its counters carry over and ``restarts`` grows by one. ``link_checks``:
        the shell reports router connectivity (``link_status``), asked for by ``link_check_due``;
        without it the session is always connected (the in-process fleet)."""
        self.core = core
        self.me = int(core.robot_id)
        self.timing = timing
        self.fleet = fleet
        self._tag = bytes(config_tag)
        self._auth = auth
        self.decoder = FrameDecoder(fleet, senders, dim, config_tag, auth=auth, receiver=self.me)
        self.t0 = now
        self._restore_counters(resume or {})
        # why frames were sent again (not part of the row: benchmarks read it from the profile)
        self.resends: collections.Counter[str] = collections.Counter()
        self._seq = self.restarts * SEQ_EPOCH
        self.peers: tuple[int, ...] = tuple(core.neighbours)  # neighbours we listen to
        self.last_heard: dict[int, float] = {j: now for j in self.peers}
        self.heard_round: dict[int, int] = {j: -1 for j in self.peers}
        self._seen: dict[int, _SeenFrames] = {}  # sender -> its recent frames (seq -> round)
        self._behind: set[int] = set()  # neighbours whose frame shows they lack a value (receive)
        self._answered: dict[int, tuple[int, float]] = {}  # neighbour -> (our round, when) we answered its repeat
        self.drop_reasons: dict[int, str] = {}
        self._gone: set[int] = set(self.peers)  # neighbours without a liveliness token (yet)
        self._token_at: dict[int, float] = {}
        self._had_neighbours = bool(self.peers) or bool(self.neighbours_dropped)
        self._link_checks = link_checks
        self._connected = True
        self._connected_since = now
        self._link_at = now
        self.link_check_due = False  # the shell should report link_status now
        self.stopped: str | None = None
        self.error: str | None = None
        self.lingering = False
        self._linger_end = float("inf")
        self._out: list[tuple[int | None, bytes]] = []
        self._latest: StateUpdate | None = None
        self._last_put = float("-inf")
        self._republish_now = False
        self._deadline: float | None = None
        self._last_advance = now
        # the shell of a process of several robots: our frames' parse goes into the process's memo
        # as we encode them, so that the robots here that receive them do not parse them
        # (protocol.frames.encode_state's ``prime``)
        self.prime_memo = False
        self.round_intervals: list[float] = []  # shell-clock seconds of each advance-to-advance
        self._intervals_for: tuple[int, tuple[float, float]] = (-1, (0.0, 0.0))  # resend cache
        # the last ADAPT_WINDOW round_intervals, kept sorted as they come (the resend quartile's window:
        # the same values sorted() of the slice gave, without a slice and a sort every round)
        self._window: list[float] = []
        self.round_times: dict[int, float] = {int(core.round): 0.0}  # round -> when it was reached
        self._publish(core.outgoing(), now)
        self._enter_linger_if_finished(now)

    @classmethod
    def for_spec(cls, spec: Any, core: Any, *, now: float, max_wall_s: float | None = None,
                 link_checks: bool = False, resume: Mapping[str, Any] | None = None) -> RobotSession:
        """The session of ``core`` in fleet ``spec`` (a spec without ``frame_auth``: unauthenticated)."""
        me = int(core.robot_id)
        auth = spec.frame_auth(me) if hasattr(spec, "frame_auth") else None
        return cls(core, fleet=spec.fleet, senders=tuple(spec.robot_ids), dim=spec.dim,
                   config_tag=spec.config_tag, timing=SessionTiming.of(spec.timing, max_wall_s=max_wall_s),
                   now=now, auth=auth, link_checks=link_checks, resume=resume)

    def _restore_counters(self, env: Mapping[str, Any]) -> None:
        c = env.get("counters", {})
        self.restarts = int(env["restarts"]) + 1 if "restarts" in env else 0
        self.sent = int(c.get("sent", 0))
        self.bytes_sent = int(c.get("bytes_sent", 0))  # encoded frame bytes, resends included
        self.prior_transport = {k: int(c.get(k, 0)) for k in ("received", "lost", "duplicated")}
        self._prior_accepted = int(c.get("accepted", 0))
        self.deduplicated = int(c.get("deduplicated", 0))
        self.rejected: collections.Counter[str] = collections.Counter(
            {str(k): int(v) for k, v in c.get("rejected", {}).items()})
        self.neighbours_dropped: list[int] = [int(j) for j in env.get("dropped", [])]
        self.dropped_at: dict[int, int] = {int(j): int(k) for j, k in (env.get("dropped_at") or {}).items()}

    # ---------------------------------------------------------------- events from the shell

    def receive(self, source: int, payload: bytes, now: float) -> Decoded | Rejected | None:
        """A frame that arrived on ``source``'s key: decode, authenticate, dedup, feed the core.

        Returns the decoder's verdict (None for a duplicate or a frame of a dropped neighbour).
        """
        out = self.decoder.decode(payload, expected_sender=source)
        if type(out) is not Decoded:
            self.rejected[out.reason] += 1
            return out
        heard = self.heard_round.get(source)
        if heard is None:  # not (or no longer) a neighbour we listen to
            return None
        upd = out.update
        seq, rnd = out.seq, upd.round
        seen = self._seen.get(source)
        if seen is None:
            seen = self._seen[source] = _SeenFrames()
        kind = seen.note(seq, rnd)
        if kind == DUPLICATE:
            self.deduplicated += 1  # a copy of a frame we had (a restarted sender reuses no seq
            return None             # with another round, see SEQ_EPOCH; a fresh one may: kept)
        if kind & GAP:
            self.resends["seq_gap"] += 1  # a frame of source's that never came (lost, or overtaken)
        newest, repeat = kind & NEWEST, kind & REPEAT
        self.last_heard[source] = now
        if rnd > heard:
            self.heard_round[source] = heard = rnd
        if not newest:
            pass
        elif out.need is not None and self.me not in out.need:
            self._behind.discard(source)  # its newest frame says it holds our value
        elif heard == rnd and (rnd == self.core.round - 1
                               or (repeat and rnd == self.core.round and self._may_answer(source, now))):
            # source's newest frame shows it lacks a value of its round r: it is one round behind
            # us (r = ours - 1), or it repeats our own round (a resend: it waits for round-r
            # values). It may lack ours (lost), or only a third robot's. Our latest frame carries
            # our rounds r and r - 1: resend it after the fast interval if source is still at r
            # then (_behind_now). A frame overtaken by a newer one of source's is no evidence: a
            # robot at round r + 1 holds our round r. Before issue 14's follow-up only "one round
            # behind" counted, overtaken frames included, and a lost frame of our own round waited
            # for the periodic resend (whose interval the slow lossy rounds stretch).
            # A neighbour's repeats of our own round are answered at most once per half periodic
            # interval (_may_answer): every robot at our round is waiting too, so a repeat is
            # usually a wait for a slow robot, and our answer is itself a repeat that the others
            # at our round answer in turn -- answered every time, 16 robots on 2 cores resent in
            # a storm, 2-4 frames per robot-round with no loss at all (issue 14).
            # A frame that says what its sender lacks ("need", every frame a session sends)
            # settles it: only the robots it names answer -- the one a waiting robot waits for,
            # not all 31 of its neighbours at 32 robots (issue 14, third pass).
            self._behind.add(source)
        self.core.receive(upd)
        return out

    def peer_up(self, j: int, now: float) -> None:
        """j's liveliness token appeared: it is there; serve it our latest frame at once."""
        if j in self.heard_round:
            self._token_at[j] = now
            self._gone.discard(j)
            self._republish_now = True

    def peer_gone(self, j: int, now: float) -> None:
        """j's liveliness token vanished: evidence of death (it counts while we are connected)."""
        if j in self.heard_round:
            self._token_at[j] = now
            self._gone.add(j)

    def link_status(self, up: bool, now: float, *, reconnected: bool = False) -> None:
        """Whether we have a router; ``reconnected``: a new one (a restart) even without a gap.

        A (re)connection restarts the death clock: tokens vanish with a router and come back.
        """
        self._link_at = now
        self.link_check_due = False
        if up and (not self._connected or reconnected):
            self._connected_since = now
        self._connected = up

    @property
    def link_up(self) -> bool:
        """The last connectivity the shell reported (True until it reports otherwise)."""
        return self._connected

    def connected(self, now: float) -> None:
        """We (re)connected to a router."""
        self.link_status(True, now, reconnected=True)

    def disconnected(self, now: float) -> None:
        """We have no router: nobody is dropped meanwhile."""
        self.link_status(False, now)

    def interrupt(self, now: float) -> None:
        """The shell stops us (a signal): "finished" if the core had finished, else "signal"."""
        if self.stopped is None or self.lingering:
            self.stopped = "finished" if self.core.finished else "signal"
            self.lingering = False

    # ---------------------------------------------------------------- rounds

    def ready(self) -> bool:
        """True when the core can compute its next round now (the shell checkpoints first)."""
        return self.stopped is None and self.core.ready()

    def asking_resend(self) -> int:
        """How many neighbours' newest frames show they lack our value (a fast resend is due for
        them). A received frame changes it by at most one (its sender), so a shell that compares
        it before and after a frame knows whether that frame can bring a resend sooner."""
        return len(self._behind)

    def advance(self, now: float) -> bool:
        """One round of the core, its frame queued; a failure becomes a stop reason (False)."""
        if not self.ready():
            return False
        core = self.core
        try:
            update = core.advance()
        except core.solve_errors as exc:  # the core names its own local-solve failures
            return self._stop("solver_error", now, f"robot {self.me} round {core.round}: local solver failed: {exc}")
        # the core judges its own iterate (only it knows which part of a frame is a function:
        # Newton's frames carry reduction terms, autogrid's sweep carries flags as floats); a
        # frame must still be finite to be sent at all
        why = core.divergence()
        if why is None and not _all_finite(update.values):
            why = "non-finite values in its frame"
        if why is not None:
            return self._stop("diverged", now, f"robot {self.me} round {update.round}: diverged: {why}")
        self._publish(update, now)
        iv = now - self._last_advance
        self.round_intervals.append(iv)
        w = self._window
        if len(w) == ADAPT_WINDOW:  # the interval leaving the window (an equal value: the same multiset)
            del w[bisect_left(w, self.round_intervals[-ADAPT_WINDOW - 1])]
        insort(w, iv)
        self._last_advance = now
        self.round_times[int(core.round)] = now - self.t0
        self._enter_linger_if_finished(now)
        return True

    def _stop(self, reason: str, now: float, error: str | None = None) -> bool:
        self.stopped = reason
        self.lingering = False
        if error is not None:
            self.error = error
        return False

    def _enter_linger_if_finished(self, now: float) -> None:
        if self.core.finished and self.stopped is None:
            self.stopped = "finished"
            self.lingering = True
            t = self.timing
            self._linger_end = min(now + t.linger_s, self.t0 + t.max_wall_s + t.linger_s)

    @property
    def done(self) -> bool:
        """True once the shell may close: stopped, and no longer lingering."""
        return self.stopped is not None and not self.lingering

    # ---------------------------------------------------------------- time

    def to_send(self, now: float) -> list[tuple[int | None, bytes]]:
        """Frames to publish now (after running the timers): ``(BROADCAST, frame)`` pairs."""
        self.tick(now)
        return self.queued()

    def queued(self) -> list[tuple[int | None, bytes]]:
        """The frames queued so far (``advance``'s), without running the timers: for a shell that
        calls ``to_send`` again before it sleeps, so that the timers run once a round, not twice."""
        out, self._out = self._out, []
        return out

    def next_deadline(self) -> float | None:
        """When ``to_send`` has work again if nothing arrives (None: done)."""
        return None if self.done else self._deadline

    def tick(self, now: float) -> None:
        """Run the timers: linger end, max_wall_s, neighbour death, resend; set the deadline."""
        if self.done:
            self._deadline = None
            return
        if self.lingering:
            final = self.core.round
            if now >= self._linger_end or all(
                    self.heard_round[j] >= final or j in self._gone for j in self.peers):
                self.lingering = False
                self._deadline = None
                return
            self._deadline = min(self._resend(now), self._linger_end)
            return
        if self.core.ready():
            self._deadline = now  # the shell advances first
            return
        wall_end = self.t0 + self.timing.max_wall_s
        if now >= wall_end:
            self._stop("max_wall", now)
            self._deadline = None
            return
        n_dropped = len(self.neighbours_dropped)
        drop_deadline = self._check_neighbours(now)
        # (only a drop can make the core ready here: it was not just above)
        if self.stopped is not None or (len(self.neighbours_dropped) != n_dropped and self.core.ready()):
            self._deadline = None if self.done else now
            return
        self._deadline = min(self._resend(now), wall_end, drop_deadline)

    def _check_neighbours(self, now: float) -> float:
        """Drop every neighbour we wait for that is gone for good; when to look again."""
        deadline = float("inf")
        dropped = False
        for j in self.core.missing():
            when, why = self._drop_due(j, now)
            if why is None and self.heard_round.get(j, -1) >= self.core.round + 2:
                # A live neighbour is never more than one round ahead of us unless it dropped us
                # (we were restarted too late): the value we wait for will never come.
                why = f"it is at round {self.heard_round[j]}, so it has dropped us"
            if why is not None:
                self._drop(j, why)
                dropped = True
            else:
                deadline = min(deadline, when)
        if dropped and self._had_neighbours and not self.core.neighbours:
            # Cut off from every neighbour: continuing would "converge" on our own data.
            self._stop("isolated", now, f"robot {self.me} round {self.core.round}: isolated, every "
                                        f"neighbour dropped ({sorted(self.neighbours_dropped)})")
        return deadline

    def _drop_due(self, j: int, now: float) -> tuple[float, str | None]:
        """(when j may be dropped, why now if due): see the module doc for the rule."""
        t = self.timing
        heard = self.last_heard.get(j, self.t0)
        give_up_at = heard + t.give_up_s
        if now >= give_up_at:
            return give_up_at, f"silent for {now - heard:.2f}s (give_up_s={t.give_up_s:g}s)"
        if j not in self._gone:
            return give_up_at, None
        gone_at = max(heard, self._token_at.get(j, self.t0), self._connected_since) + t.dead_after_s
        if now >= gone_at:
            if self._link_checks and now - self._link_at >= CONNECTED_POLL_S:
                self.link_check_due = True  # a drop needs a fresh look at our own connection
                return now, None
            if self._connected:
                return gone_at, (f"liveliness token gone and silent for {now - heard:.2f}s "
                                 f"(dead_after_s={t.dead_after_s:g}s)")
        return min(give_up_at, max(gone_at, now + CONNECTED_POLL_S)), None

    def _drop(self, j: int, why: str) -> None:
        self.core.drop_neighbour(j)
        self.neighbours_dropped.append(j)
        self.dropped_at[j] = int(self.core.round)
        self.peers = tuple(n for n in self.peers if n != j)
        self.heard_round.pop(j, None)
        self.drop_reasons[j] = why

    def _resend_interval(self) -> tuple[float, float]:
        """(periodic, fast) resend intervals, adapted to how long a round takes here.

        A fixed interval shorter than a normal round (16 robots sharing 2 cores take ~50 ms a
        round) makes every waiting robot resend again and again, and the extra frames slow the
        rounds further. Like TCP's retransmission timer, wait a few typical rounds -- the fast
        quartile of recent rounds, which loss does not inflate -- and never less than
        ``retransmit_s``.
        """
        n = len(self.round_intervals)
        if self._intervals_for[0] == n:  # unchanged since the last round: no new percentile
            return self._intervals_for[1]
        typical = 0.0
        if n >= ADAPT_MIN_ROUNDS:  # np.percentile(recent, 25), linear, without numpy's overhead
            xs = self._window  # == sorted(self.round_intervals[-ADAPT_WINDOW:])
            pos = 0.25 * (len(xs) - 1)
            lo = int(pos)
            typical = xs[lo] + (xs[min(lo + 1, len(xs) - 1)] - xs[lo]) * (pos - lo)
        elif n >= 2:
            # Too few rounds for a quartile: the shortest so far (not the first, which holds the
            # wait for the neighbours to start) is a lower bound of a round here.
            # Without it, a big fleet (32 robots on 2 cores: ~150 ms a round) resent every
            # retransmit_s during its first rounds, each resend answered by its neighbours' fast
            # resends: 3.5 frames per robot-round over a 40-round run instead of ~1.
            typical = min(self.round_intervals[1:])
        periodic = max(self.timing.retransmit_s, ADAPT_FACTOR * typical)
        fast = min(periodic, max(FAST_RESEND_MIN_S, periodic / 4))
        self._intervals_for = (n, (periodic, fast))
        return periodic, fast

    def _resend(self, now: float) -> float:
        """Queue the latest frame again if due; return when the next resend is due."""
        periodic, fast = self._resend_interval()
        last = self._last_put  # compare with the very sums returned as deadlines (virtual clock)
        if now >= last + periodic or ((self._republish_now or self._behind_now()) and now >= last + fast):
            if now >= last + periodic:
                self.resends["periodic"] += 1
            elif self._republish_now:
                self.resends["peer_up"] += 1
            else:
                self.resends["fast"] += 1
                for j in self._behind:
                    self._answered[j] = (self.core.round, now)
            self._publish(self._latest, now)
        nxt = self._last_put + periodic
        if self._republish_now or self._behind_now():
            nxt = min(nxt, self._last_put + fast)
        return nxt

    def _may_answer(self, source: int, now: float) -> bool:
        """Whether source's repeat of our round may schedule a fast resend: not if we answered
        one of its repeats of this round less than half a periodic interval ago (its next
        periodic repeat, should our answer be lost, comes about a whole interval later)."""
        rnd, at = self._answered.get(source, (-1, 0.0))
        return rnd != self.core.round or now >= at + 0.5 * self._resend_interval()[0]

    def _behind_now(self) -> bool:
        """Whether a neighbour whose frame showed it lacks a value is, as far as we heard, still at
        that round: one that has moved on since holds our value of it (it could not have advanced
        without it), so a resend for it would be wasted."""
        if self._behind:
            rnd = self.core.round
            self._behind = {j for j in self._behind if self.heard_round.get(j, -2) in (rnd - 1, rnd)}
        return bool(self._behind)

    def _publish(self, update: StateUpdate, now: float) -> None:
        self._latest = update
        self._republish_now = False
        self._behind.clear()
        # what we still lack of this frame's round: a neighbour answers a repeat only if named
        need = () if self.core.finished or update.round != self.core.round else self.core.missing()
        frame = encode_state(update, fleet=self.fleet, seq=self._seq, config_tag=self._tag, auth=self._auth,
                             need=need, prime=self.decoder if self.prime_memo else None)
        self._seq += 1
        self._out.append((BROADCAST, frame))
        self.sent += 1
        self.bytes_sent += len(frame)
        self._last_put = now

    # ---------------------------------------------------------------- persistence and result

    def checkpoint(self, transport: Mapping[str, int]) -> dict[str, Any]:
        """What a restart needs besides the shell's envelope: counters, drops, the core.

        ``transport``: the shell's own counts since it started (received, lost, duplicated).
        """
        return {
            "restarts": self.restarts,
            "counters": {**self.counters(transport), "rejected": dict(self.rejected)},
            "dropped": list(self.neighbours_dropped),
            "dropped_at": dict(self.dropped_at),
            "core": self.core.checkpoint(),
        }

    def counters(self, transport: Mapping[str, int]) -> dict[str, int]:
        """sent, bytes_sent, received, lost, duplicated, accepted, deduplicated (restored ones included)."""
        return {
            "sent": self.sent,
            "bytes_sent": self.bytes_sent,
            **{k: v + int(transport.get(k, 0)) for k, v in self.prior_transport.items()},
            "accepted": self._prior_accepted + self.decoder.accepted,
            "deduplicated": self.deduplicated,
        }

    def row(self, now: float, transport: Mapping[str, int]) -> dict[str, Any]:
        """The result row (same keys and types in both shells): ``core.result()`` plus counters."""
        res = dict(self.core.result())
        stopped = self.stopped if self.stopped is not None and not self.lingering else "running"
        isolated = self._had_neighbours and not self.core.neighbours
        if stopped != "finished" or isolated:
            res["converged"] = False  # alone: its answer is its own data's, not the fleet's
        c = self.counters(transport)
        rt = sorted(self.round_intervals)
        trace = getattr(self.core, "trace", None) or {}
        res.update(
            robot=self.me, fleet=self.fleet, stopped=stopped, error=self.error, isolated=isolated,
            frames_sent=c["sent"], bytes_sent=c["bytes_sent"], frames_received=c["received"], frames_lost=c["lost"],
            frames_duplicated=c["duplicated"], frames_accepted=c["accepted"],
            frames_deduplicated=c["deduplicated"], frames_rejected=sum(self.rejected.values()),
            frames_rejected_by_reason=dict(self.rejected), restarts=self.restarts,
            neighbours_dropped=list(self.neighbours_dropped), dropped_at=dict(self.dropped_at),
            wall_s=float(now - self.t0),
            round_ms={"rounds": len(rt), "median": 1e3 * rt[len(rt) // 2] if rt else None,
                      "mean": 1e3 * sum(rt) / len(rt) if rt else None},
            round_times=dict(self.round_times),
            trace={int(k): [float(a) for a in v] for k, v in sorted(trace.items())},
        )
        return res


# -------------------------------------------------------------------- the result file


def _finite(obj: Any) -> Any:
    """JSON-safe copy: non-finite floats (e.g. an initial residual of inf) become None."""
    if isinstance(obj, float):
        return obj if obj == obj and obj not in (float("inf"), float("-inf")) else None
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    return obj


def row_to_file(row: Mapping[str, Any]) -> dict[str, Any]:
    """A row as a robot's result file (docs/result.md): JSON-safe, str keys, and
    ``frames_rejected`` as ``{"total", "by_reason"}`` (the file format deploy/collect read)."""
    out = dict(row)
    out["frames_rejected"] = {"total": int(row["frames_rejected"]),
                              "by_reason": dict(row.get("frames_rejected_by_reason", {}))}
    out.pop("frames_rejected_by_reason", None)
    for key in _INT_KEYED:
        if key in out:
            out[key] = {str(k): v for k, v in out[key].items()}
    return _finite(out)


def row_from_file(res: Mapping[str, Any]) -> dict[str, Any]:
    """A robot's result file -> the row :meth:`RobotSession.row` gives (inverse of row_to_file)."""
    out = dict(res)
    rej = out.get("frames_rejected", 0)
    if isinstance(rej, dict):
        out["frames_rejected"] = int(rej.get("total", 0))
        out["frames_rejected_by_reason"] = {str(k): int(v) for k, v in rej.get("by_reason", {}).items()}
    else:
        out["frames_rejected"] = int(rej or 0)
        out.setdefault("frames_rejected_by_reason", {})
    for key in _INT_KEYED:
        if key in out:
            out[key] = {int(k): v for k, v in (out[key] or {}).items()}
    out["id"] = int(out["id"])
    for k in ("frames_sent", "bytes_sent", "frames_received", "frames_lost", "restarts"):
        out[k] = int(out.get(k, 0) or 0)
    return out
