"""Free-running sync: one robot's session that never waits and never retransmits, sans-IO.

The sibling of :class:`protocol.session.RobotSession` (lockstep). A free robot ticks every
``period`` of *its own* clock: it computes with the newest neighbour values it holds, publishes,
and goes on. Lost packets are not recovered, late ones are used when they arrive (or dropped when
a newer one from the same sender was already applied -- the core's sequence numbers). That is
only sound with an algorithm built for it (agents/pdmm.py); the shells drive this one class::

    session.receive(source, payload, now)   a frame that arrived on ``source``'s key / link
    session.tick(now) -> [(BROADCAST, bytes)] at or after next_deadline(): one update, its frame
    session.next_deadline() -> float | None  the next tick on this robot's clock (None: done)
    session.done / session.stopped / row(now)

``now`` is the robot's own clock: the in-process shell gives each robot a clock with an offset
and a drift (launcher/simulate.py), a Zenoh robot its event loop's clock.

Wire: one broadcast state frame per tick (the lockstep codec, docs/protocol.md): ``round`` is the
sender's tick (its sequence number), ``flags`` its calm-hop count, and ``x`` the sender's v followed
by one edge vector y per neighbour in the sender's sorted neighbour order, zero-padded to the
fleet's largest degree (so every frame has one length and the decoder checks it). A frame is
authenticated per edge exactly as in lockstep; a forged or malformed frame is rejected and counted.
After finishing, a robot repeats its final frame for ``linger_ticks`` ticks (the same round and
values: its neighbours need its last hop count, and a repeat is not equivocation).
"""

from __future__ import annotations

import collections
from typing import Any

import numpy as np

from agents.messages import MAX_ROUND, StateUpdate
from agents.pdmm import Packet
from protocol.auth import FrameAuth
from protocol.frames import Decoded, FrameDecoder, encode_state

BROADCAST = None
LINGER_TICKS = 10  # final frames repeated: at loss 0.3 all ten are lost with probability 6e-6


def frame_dim(dim: int, graph: dict[int, tuple[int, ...]]) -> int:
    """Length of a free frame's vector: v plus one y per neighbour of the largest degree."""
    return dim * (1 + max((len(n) for n in graph.values()), default=0))


class FreeSession:
    """One robot's free-running protocol state around a free core (agents/pdmm.py)."""

    def __init__(
        self,
        core: Any,
        *,
        fleet: str,
        graph: dict[int, tuple[int, ...]],
        config_tag: bytes,
        period: float,
        now: float,
        max_wall_s: float,
        auth: FrameAuth | None = None,
        linger_ticks: int = LINGER_TICKS,
    ) -> None:
        if not period > 0 or not max_wall_s > 0:
            raise ValueError(f"period and max_wall_s must be positive, got {period}, {max_wall_s}")
        self.core = core
        self.me = int(core.robot_id)
        self.fleet = fleet
        self.graph = {int(i): tuple(sorted(int(j) for j in n)) for i, n in graph.items()}
        self.dim = int(core.dim)
        self._fdim = frame_dim(self.dim, self.graph)
        self._tag = bytes(config_tag)
        self._auth = auth
        self.decoder = FrameDecoder(fleet, tuple(self.graph), self._fdim, config_tag, auth=auth)
        self.period = float(period)
        self.t0 = now
        self.deadline = now + max_wall_s
        self._next: float | None = now  # tick at once: round 0 is the robot's own solve
        self._linger = int(linger_ticks)
        self._seq = 0
        self.sent = 0
        self.bytes_sent = 0  # encoded frame bytes (the lockstep rows' bytes_sent)
        self.rejected: collections.Counter[str] = collections.Counter()
        self.stale = 0
        self.stopped: str | None = None
        self.error: str | None = None
        self.tick_times: list[float] = []
        self._final: list[Packet] = []

    @property
    def done(self) -> bool:
        """Nothing more to do: stopped and no final frame left to repeat."""
        return self.stopped is not None and self._next is None

    def next_deadline(self) -> float | None:
        """When `tick` is due on this robot's clock (None: done)."""
        return self._next

    def receive(self, source: int, payload: bytes, now: float) -> None:
        """A frame from ``source``: decode and authenticate, hand the core its edge's update."""
        out = self.decoder.decode(payload, expected_sender=source)
        if not isinstance(out, Decoded):
            self.rejected[out.reason] += 1
            return
        u = out.update
        nbrs = self.graph.get(u.sender, ())
        if self.me not in nbrs:
            return  # not our neighbour: nothing of this frame is for us
        k = nbrs.index(self.me)
        vec = u.values
        if not self.core.receive(Packet(u.sender, u.round, vec[: self.dim], vec[(k + 1) * self.dim : (k + 2) * self.dim], u.flags)):
            self.stale += 1

    def tick(self, now: float) -> list[tuple[None, bytes]]:
        """One update if due: the frame to broadcast (none before the deadline or once done)."""
        if self._next is None or now < self._next:
            return []
        if self.stopped is None and now >= self.deadline:
            self._stop("max_wall", None)
            return []
        if self.stopped is None:
            try:
                packets = self.core.tick()
            except self.core.solve_errors as exc:
                self._stop("solver_error", f"robot {self.me} tick {self.core.ticks}: local solver failed: {exc}")
                return []
            why = self.core.divergence()
            if why is not None:
                self._stop("diverged", f"robot {self.me} tick {self.core.ticks}: {why}")
                return []
            self.tick_times.append(now)
            if self.core.finished:
                self.stopped = "finished"
                self._final = packets  # repeated as they are: a changed repeat would be equivocation
        else:
            packets = self._final
            self._linger -= 1
        self._next = None if self.stopped is not None and self._linger <= 0 else now + self.period
        return [(BROADCAST, self._encode(packets))]

    def interrupt(self) -> None:
        """The shell stops the robot from outside (a signal): its row says ``stopped = "signal"``."""
        if self.stopped is None:
            self._stop("signal", None)

    def _stop(self, why: str, error: str | None) -> None:
        self.stopped, self.error, self._next = why, error, None

    def _encode(self, packets: list[Packet]) -> bytes:
        vec = np.zeros(self._fdim)
        vec[: self.dim] = self.core.values
        for k, p in enumerate(packets):  # packets come in sorted neighbour order
            vec[(k + 1) * self.dim : (k + 2) * self.dim] = p.edge
        hops = packets[0].hops if packets else 0
        update = StateUpdate(sender=self.me, round=min(self.core.ticks, MAX_ROUND), values=vec, flags=hops, prev_values=None)
        self._seq += 1
        self.sent += 1
        frame = encode_state(update, fleet=self.fleet, seq=self._seq, config_tag=self._tag, auth=self._auth)
        self.bytes_sent += len(frame)
        return frame

    def row(self, now: float, transport: dict[str, int]) -> dict[str, Any]:
        """The result row: the core's result plus counters (lockstep rows' main keys)."""
        res = dict(self.core.result())
        if self.stopped != "finished":
            res["converged"] = False
        gaps = np.diff(self.tick_times) if len(self.tick_times) > 1 else np.zeros(0)
        res.update(
            robot=self.me, fleet=self.fleet, stopped=self.stopped or "running", error=self.error,
            isolated=False, sync="free", frames_sent=self.sent, bytes_sent=self.bytes_sent, frames_received=transport.get("received", 0),
            frames_lost=transport.get("lost", 0), frames_duplicated=transport.get("duplicated", 0),
            frames_accepted=self.decoder.accepted, frames_deduplicated=self.stale,
            frames_rejected=sum(self.rejected.values()), frames_rejected_by_reason=dict(self.rejected),
            restarts=0, neighbours_dropped=[], dropped_at={}, wall_s=float(now - self.t0),
            round_ms={"rounds": len(gaps), "median": 1e3 * float(np.median(gaps)) if len(gaps) else None,
                      "mean": 1e3 * float(np.mean(gaps)) if len(gaps) else None},
            round_times={}, trace={},
        )
        return res
