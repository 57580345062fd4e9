"""The asyncio shell that runs one robot's sans-IO core over Zenoh.

The shell knows nothing of the mathematics. It moves frames between the core and the network,
keeps time, and persists the core between rounds:

    zenoh thread --(sample bytes)--> loop.call_soon_threadsafe --> receiver-side fault link (j -> me)
        --> FrameDecoder (fleet, senders, dim, config tag; sender must match the key) --> core.receive

    core.outgoing() / core.advance() --> encode_state(seq++) --> publisher.put (express)

Main loop (one asyncio task, never sleeps in the hot path; it awaits a wake-up future that arriving
frames resolve, with a timer for the earliest of: next retransmission, next delayed frame due out
of the fault link, next neighbour death deadline, wall-clock cap):

* ``core.ready()``  -> checkpoint (msgpack, atomic, see :func:`write_checkpoint`), ``core.advance()``,
  publish, one JSON status line;
* waiting           -> republish the latest frame every ``retransmit_s``, or after ``fast_resend_s``
  when a neighbour's frame shows it is one round behind us (it lost our last frame); exact recovery
  comes from the previous round piggybacked in every frame plus retransmission: the shell never
  invents or substitutes values;
* a neighbour we wait for is dropped (``core.drop_neighbour(j)``) only on evidence that it is gone
  for good: its liveliness token is gone while we are connected to a router, and it has been silent
  for ``dead_after_s`` since the later of its last frame, its token's disappearance and our own
  (re)connection; or it has been silent for ``give_up_s`` (default ``GIVE_UP_FACTOR`` x
  ``dead_after_s``) whatever its token says. A paused neighbour (token still there) or a router
  that restarts (every token gone, but we are disconnected too) is waited for: the fleet resumes
  from the agreed round when it is back (lockstep: nobody is more than one round ahead);
* a robot whose every neighbour was dropped is cut off: it stops, ``stopped = "isolated"``,
  never ``converged`` on its own data;
* a local solver failure or a non-finite / exploding iterate stops the robot,
  ``stopped = "solver_error"`` / ``"diverged"`` with a one-line ``error``; never converged;
* ``core.finished`` -> linger: keep republishing the final frame until every live neighbour has been
  heard at our final round or later (it has finished too) or the bounded linger time is over;
* ``max_wall_s``    -> stop, ``converged = false``.

A liveliness token per robot (declared after its subscriptions) lets a neighbour that (re)appears
be served at once: when its token shows up we republish our latest frame instead of waiting for the
next retransmission; its disappearance is the evidence of death the drop rule needs. Zenoh clients
reconnect to a restarted router on the same endpoint by themselves (and re-declare their tokens).
"""

from __future__ import annotations

import asyncio
import collections
import json
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, TextIO

import msgpack
import numpy as np

from agents.problem import InfeasibleError, SolverError
from agents.rounds import DIVERGED_ABS, check_iterate
from protocol.frames import Decoded, FrameDecoder, StateUpdate, encode_state
from protocol.keys import alive_key, alive_wildcard, state_key
from protocol.links import LinkLayer
from protocol.zenoh_config import robot_config, to_zenoh_config

__all__ = [
    "run_robot",
    "RobotShell",
    "alive_key",
    "alive_wildcard",
    "read_checkpoint",
    "write_checkpoint",
    "checkpoint_exists",
    "CHECKPOINT_VERSION",
    "check_iterate",
    "DIVERGED_ABS",
    "GIVE_UP_FACTOR",
]

log = logging.getLogger("shapefleet.robot")

CHECKPOINT_VERSION = 1
SEQ_EPOCH = 1 << 40  # seq = restarts * SEQ_EPOCH + n: strictly increasing across restarts
# Final-frame linger when spec.timing has no linger_s: max(LINGER_MIN_S, LINGER_RETRANSMITS *
# retransmit_s); it ends earlier as soon as every live neighbour has been heard at our final round.
LINGER_MIN_S = 0.5
FAST_RESEND_MIN_S = 0.002
# adaptive resend interval: ADAPT_FACTOR x the fast quartile of the last ADAPT_WINDOW round times
ADAPT_FACTOR = 1.5
ADAPT_WINDOW = 32
ADAPT_MIN_ROUNDS = 8
PUBLISH_EXPRESS = True  # see docs/robot.md, "Latency"
LINGER_RETRANSMITS = 5
# A neighbour silent this many dead_after_s is given up even if its token is still there (bounded
# waiting for a paused or partitioned robot), unless spec.timing has its own give_up_s.
GIVE_UP_FACTOR = 10.0
CONNECTED_POLL_S = 0.2  # how often a stalled robot asks Zenoh whether it still has a router
def _finite(obj: Any) -> Any:
    """JSON-safe copy: non-finite floats (e.g. an initial residual of inf) become None."""
    if isinstance(obj, float):
        return obj if obj == obj and obj not in (float("inf"), float("-inf")) else None
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    return obj


# --------------------------------------------------------------------------- atomic files


def _write_atomic(path: Path, data: bytes) -> None:
    """Write via a temporary file in the same folder then ``os.replace`` (used for the result)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as fh:
        fh.write(data)
    os.replace(tmp, path)


def _checkpoint_tmp(path: Path) -> Path:
    return path.with_name(path.name + ".tmp")


def write_checkpoint(path: Path, envelope: dict[str, Any]) -> None:
    """Crash-safe checkpoint, written before every round (so it must be cheap).

    Write ``<path>.tmp`` completely, unlink ``<path>``, rename the tmp file to ``<path>``.
    A plain ``os.replace`` over the existing file costs 1-3 ms per call on ext4 (renaming over a
    file forces write-back of the new data, ext4's ``auto_da_alloc``) -- more than a whole ADMM
    round; unlink + rename costs ~0.08 ms. A crash at any point leaves a complete checkpoint in
    ``<path>`` or in ``<path>.tmp`` (or both): :func:`read_checkpoint` takes the newest complete
    one. A crash in the middle of writing the tmp file leaves it truncated, which msgpack refuses.
    No fsync: we model process crashes, not machine crashes.
    """
    path = Path(path)
    tmp = _checkpoint_tmp(path)
    with open(tmp, "wb") as fh:
        fh.write(msgpack.packb(envelope, use_bin_type=True))
    try:
        os.unlink(path)
    except FileNotFoundError:
        pass
    os.rename(tmp, path)


def _load_envelope(path: Path) -> dict[str, Any] | None:
    try:
        with open(path, "rb") as fh:
            env = msgpack.unpackb(fh.read(), raw=False, strict_map_key=False)
    except FileNotFoundError:
        return None
    except Exception:  # noqa: BLE001 - truncated / corrupt: not a usable checkpoint
        return None
    if not isinstance(env, dict) or env.get("v") != CHECKPOINT_VERSION or "core" not in env:
        return None
    return env


def checkpoint_exists(path: Path) -> bool:
    """True if a checkpoint (complete or not) is present at ``path`` or its tmp file."""
    path = Path(path)
    return path.exists() or _checkpoint_tmp(path).exists()


def read_checkpoint(path: Path) -> dict[str, Any]:
    """The newest complete checkpoint of ``path`` / ``<path>.tmp``; ValueError if there is none."""
    path = Path(path)
    found = [env for env in (_load_envelope(path), _load_envelope(_checkpoint_tmp(path))) if env is not None]
    if not found:
        raise ValueError(f"{path}: no complete shapefleet robot checkpoint (version {CHECKPOINT_VERSION})")
    return max(found, key=lambda env: int(env.get("n", 0)))


# --------------------------------------------------------------------------- the shell


class RobotShell:
    """State of one running robot; use :func:`run_robot`."""

    def __init__(
        self,
        spec: Any,
        robot_id: int,
        *,
        connect: list[str],
        checkpoint_path: Path | None,
        result_path: Path | None,
        status_stream: TextIO | None,
        build: Callable[[Any, int], Any],
        restore: Callable[[Any, int, dict], Any],
        clock: Callable[[], float] = time.monotonic,
        zenoh_config: Any | None = None,
    ) -> None:
        self.spec = spec
        self.me = int(robot_id)
        self.connect = list(connect)
        self.zenoh_config = zenoh_config
        self.checkpoint_path = None if checkpoint_path is None else Path(checkpoint_path)
        self.result_path = None if result_path is None else Path(result_path)
        self.status_stream = status_stream
        self.clock = clock
        timing = spec.timing
        self.retransmit_s = float(timing.retransmit_s)
        self.dead_after_s = float(timing.dead_after_s)
        self.max_wall_s = float(timing.max_wall_s)
        if not (self.retransmit_s > 0 and self.dead_after_s > 0 and self.max_wall_s > 0):
            raise ValueError(f"timing values must be positive, got {timing!r}")
        # fast resend: at most one every fast_resend_s, triggered by evidence of a lost frame
        self.fast_resend_s = min(self.retransmit_s, max(FAST_RESEND_MIN_S, self.retransmit_s / 4))
        linger = getattr(timing, "linger_s", None)
        self.linger_s = float(linger) if linger is not None else max(LINGER_MIN_S, LINGER_RETRANSMITS * self.retransmit_s)
        if self.linger_s < 0:
            raise ValueError(f"linger_s must be >= 0, got {self.linger_s}")
        give_up = getattr(timing, "give_up_s", None)
        self.give_up_s = float(give_up) if give_up is not None else GIVE_UP_FACTOR * self.dead_after_s
        self.error: str | None = None  # why the robot stopped on a failure (solver, divergence)

        # counters (carried over a restart through the checkpoint)
        self.restarts = 0
        self.sent = 0
        self.received = 0  # raw samples delivered by Zenoh, before the fault link
        self.neighbours_dropped: list[int] = []
        self.dropped_at: dict[int, int] = {}  # neighbour -> the round we dropped it at
        self.rejected: collections.Counter[str] = collections.Counter()
        prior_lost = 0
        prior_duplicated = 0
        prior_accepted = 0

        core = None
        self._checkpoints = 0
        if self.checkpoint_path is not None and checkpoint_exists(self.checkpoint_path):
            env = read_checkpoint(self.checkpoint_path)
            if env.get("fleet") != spec.fleet or env.get("robot") != self.me or env.get("cfg") != spec.config_tag:
                raise ValueError(
                    f"checkpoint {self.checkpoint_path} belongs to fleet {env.get('fleet')!r} robot "
                    f"{env.get('robot')!r} (config {bytes(env.get('cfg') or b'').hex()}), not to fleet "
                    f"{spec.fleet!r} robot {self.me} (config {spec.config_tag.hex()})"
                )
            core = restore(spec, self.me, env["core"])
            self._checkpoints = int(env.get("n", 0))
            c = env.get("counters", {})
            self.restarts = int(env.get("restarts", 0)) + 1
            self.sent = int(c.get("sent", 0))
            self.received = int(c.get("received", 0))
            prior_lost = int(c.get("lost", 0))
            prior_duplicated = int(c.get("duplicated", 0))
            prior_accepted = int(c.get("accepted", 0))
            self.rejected.update({str(k): int(v) for k, v in c.get("rejected", {}).items()})
            self.neighbours_dropped = [int(j) for j in env.get("dropped", [])]
            self.dropped_at = {int(j): int(k) for j, k in (env.get("dropped_at") or {}).items()}
            log.info("robot %d: restored from %s at round %d (restart %d)",
                     self.me, self.checkpoint_path, core.round, self.restarts)
        else:
            core = build(spec, self.me)
        self.core = core
        if core.robot_id != self.me:
            raise ValueError(f"core is robot {core.robot_id}, shell is robot {self.me}")
        self._prior_lost = prior_lost
        self._prior_duplicated = prior_duplicated
        self._prior_accepted = prior_accepted
        self._seq = self.restarts * SEQ_EPOCH

        self._fleet = spec.fleet
        self._tag = bytes(spec.config_tag)
        senders = tuple(spec.robot_ids)
        # this robot's edge keys (docs/protocol.md); a spec without frame_auth (test doubles) runs unauthenticated
        self._auth = spec.frame_auth(self.me) if hasattr(spec, "frame_auth") else None
        self.decoder = FrameDecoder(spec.fleet, senders, spec.dim, spec.config_tag, auth=self._auth)
        self.links = LinkLayer(spec.faults, spec.seed)

        self.watched: tuple[int, ...] = tuple(core.neighbours)  # neighbours we subscribe to
        self.last_heard: dict[int, float] = {}
        self.heard_round: dict[int, int] = {j: -1 for j in self.watched}
        self._gone: set[int] = set(self.watched)  # neighbours without a liveliness token (yet)
        self._token_at: dict[int, float] = {}  # when a neighbour's token last appeared/vanished
        self._connected = True
        self._connected_since = 0.0  # our (re)connection to a router: drop evidence counts after it
        self._connected_polled = float("-inf")
        self._router_ids: set[str] = set()
        self._had_neighbours = bool(self.watched) or bool(self.neighbours_dropped)

        self._waiter: asyncio.Future | None = None  # set while the main loop sleeps
        self._loop: asyncio.AbstractEventLoop | None = None
        self._closing = False
        self._latest: StateUpdate | None = None
        self._last_put = float("-inf")
        self._republish_now = False
        self.round_times: list[float] = []  # wall seconds of each advance-to-advance interval

    # ---------------------------------------------------------------- counters

    @property
    def lost(self) -> int:
        return self._prior_lost + self.links.stats()["dropped"]

    @property
    def duplicated(self) -> int:
        return self._prior_duplicated + self.links.stats()["duplicated"]

    @property
    def accepted(self) -> int:
        return self._prior_accepted + self.decoder.accepted

    def _counters(self) -> dict[str, Any]:
        return {
            "sent": self.sent,
            "received": self.received,
            "lost": self.lost,
            "duplicated": self.duplicated,
            "accepted": self.accepted,
            "rejected": dict(self.rejected),
        }

    # ---------------------------------------------------------------- receive path

    def _on_sample_thread(self, j: int, sample: Any) -> None:
        """Zenoh callback thread: copy the payload out and hand it to the loop."""
        if self._closing:
            return
        data = sample.payload.to_bytes()
        try:
            self._loop.call_soon_threadsafe(self._on_raw, j, data)
        except RuntimeError:  # loop closed while shutting down
            pass

    def _on_alive_thread(self, sample: Any) -> None:
        if self._closing:
            return
        key = str(sample.key_expr)
        try:
            j = int(key.rsplit("/", 2)[-2])
        except ValueError:
            return
        appeared = sample.kind == self._zenoh.SampleKind.PUT
        try:
            self._loop.call_soon_threadsafe(self._on_alive, j, appeared)
        except RuntimeError:
            pass

    def _on_alive(self, j: int, appeared: bool) -> None:
        if j not in self.watched:
            return
        self._token_at[j] = self.clock()
        if appeared:
            self._gone.discard(j)
            self._republish_now = True
        else:
            self._gone.add(j)
            log.info("robot %d: neighbour %d left (liveliness token gone)", self.me, j)
            # Was it our router that went (every token goes with it)? Look now, so that a
            # reconnection later counts as fresh evidence time (see _drop_due).
            self._connected_polled = float("-inf")
            self._poll_connected(self.clock())
        self._wake()

    def _on_raw(self, j: int, data: bytes) -> None:
        if self._closing:
            return
        self.received += 1
        now = self.clock()
        self.links.send(j, self.me, data, now)
        self._pump(now)
        # A delayed copy may now be due before the main loop's current deadline: wake it so that
        # it re-reads links.next_due() (no-op when the frame was delivered: _pump woke it).
        self._wake()

    def _pump(self, now: float) -> None:
        """Hand every frame the fault links deliver by ``now`` to the decoder, then the core."""
        delivered = self.links.deliver(now)
        if not delivered:
            return
        core = self.core
        for src, _dst, payload in delivered:
            out = self.decoder.decode(payload, expected_sender=src)
            if not isinstance(out, Decoded):
                self.rejected[out.reason] += 1
                log.debug("robot %d: rejected frame on %d's key: %s (%s)", self.me, src, out.reason, out.detail)
                continue
            upd = out.update
            self.last_heard[src] = now
            if upd.round > self.heard_round.get(src, -1):
                self.heard_round[src] = upd.round
            if upd.round == core.round - 1:
                # src is still one round behind us after we advanced: it has not got our last
                # value (lost, or still in flight). Our latest frame carries it as prev: resend it
                # soon (rate-limited) instead of after a full retransmit_s.
                self._republish_now = True
            core.receive(upd)
        self._wake()

    # ---------------------------------------------------------------- send path

    def _publish(self, update: StateUpdate) -> None:
        self._latest = update
        self._republish_now = False
        frame = encode_state(update, fleet=self._fleet, seq=self._seq, config_tag=self._tag, auth=self._auth)
        self._seq += 1
        self._pub.put(frame)
        self.sent += 1
        self._last_put = self.clock()

    def _checkpoint(self) -> None:
        if self.checkpoint_path is None:
            return
        self._checkpoints += 1
        write_checkpoint(
            self.checkpoint_path,
            {
                "v": CHECKPOINT_VERSION,
                "n": self._checkpoints,
                "fleet": self.spec.fleet,
                "robot": self.me,
                "cfg": self.spec.config_tag,
                "restarts": self.restarts,
                "counters": self._counters(),
                "dropped": list(self.neighbours_dropped),
                "dropped_at": dict(self.dropped_at),
                "core": self.core.checkpoint(),
            },
        )

    def _status_line(self, stopped: str | None = None) -> None:
        if self.status_stream is None:
            return
        st = self.core.status()
        residual = st.get("residual")
        residual = float(residual) if residual is not None else None
        line = {
            "robot": self.me,
            "round": st.get("round", self.core.round),
            "residual": residual if residual is not None and abs(residual) < float("inf") else None,
            "sent": self.sent,
            "received": self.received,
            "lost": self.lost,
            "rejected": sum(self.rejected.values()),
            "finished": bool(self.core.finished),
        }
        if stopped is not None:  # the last line: final counters and why the robot stopped
            line["stopped"] = stopped
        try:
            self.status_stream.write(json.dumps(line) + "\n")
            self.status_stream.flush()
        except (BrokenPipeError, ValueError):  # launcher went away / stream closed
            self.status_stream = None

    # ---------------------------------------------------------------- main loop

    def _routers(self) -> set[str] | None:
        """The ids of the routers our session is connected to (None: no session to ask)."""
        session = getattr(self, "_session", None)
        if session is None:
            return None
        try:
            return {str(z) for z in session.info.routers_zid()}
        except Exception:  # noqa: BLE001 - a closing session: treat as disconnected
            return set()

    def _poll_connected(self, now: float) -> bool:
        """Whether our session has a router (asked at most every CONNECTED_POLL_S)."""
        if now - self._connected_polled >= CONNECTED_POLL_S:
            self._connected_polled = now
            ids = self._routers()
            up = ids is None or bool(ids)
            if up and (not self._connected or (ids is not None and ids != self._router_ids)):
                # back, or on another router (a restarted router has a new id) even if we
                # never saw the gap: evidence of a neighbour's death counts from now
                self._connected_since = now
                log.info("robot %d: connected to a router again", self.me)
            if ids:
                self._router_ids = ids
            elif not up and self._connected:
                log.warning("robot %d: no router; waiting for it (nobody is dropped meanwhile)", self.me)
            self._connected = up
        return self._connected

    def _drop_due(self, j: int, now: float) -> tuple[float, str | None]:
        """(when j may be dropped, why now if due): see the module doc for the rule."""
        heard = self.last_heard.get(j, self._t0)
        give_up_at = heard + self.give_up_s
        if now >= give_up_at:
            return give_up_at, f"silent for {now - heard:.2f}s (give_up_s={self.give_up_s:g}s)"
        if j not in self._gone:
            return give_up_at, None
        evidence = max(heard, self._token_at.get(j, self._t0), self._connected_since)
        gone_at = evidence + self.dead_after_s
        if now >= gone_at and self._poll_connected(now):
            gone_at = max(evidence, self._connected_since) + self.dead_after_s  # a reconnection moves it
            if now >= gone_at:
                return gone_at, (f"liveliness token gone and silent for {now - heard:.2f}s "
                                 f"(dead_after_s={self.dead_after_s:g}s)")
        return min(give_up_at, max(gone_at, now + CONNECTED_POLL_S)), None

    def _drop(self, j: int, why: str) -> None:
        log.warning("robot %d: dropping neighbour %d at round %d: %s", self.me, j, self.core.round, why)
        self.core.drop_neighbour(j)
        self.neighbours_dropped.append(j)
        self.dropped_at[j] = int(self.core.round)
        sub = self._subs.pop(j, None)
        if sub is not None:
            sub.undeclare()
        self.watched = tuple(n for n in self.watched if n != j)
        self.heard_round.pop(j, None)

    def _advance(self) -> str | None:
        """``core.advance()`` and publish; a failure or divergence stops the robot (its reason)."""
        try:
            update = self.core.advance()
        except (SolverError, InfeasibleError, FloatingPointError, np.linalg.LinAlgError) as exc:
            self.error = f"robot {self.me} round {self.core.round}: local solver failed: {exc}"
            log.error("%s", self.error)
            return "solver_error"
        why = self.core.divergence()
        if why is not None:
            self.error = f"robot {self.me} round {update.round}: diverged: {why}"
            log.error("%s", self.error)
            return "diverged"
        self._publish(update)
        return None

    def _wake(self, *_: Any) -> None:
        w = self._waiter
        if w is not None and not w.done():
            w.set_result(None)

    async def _wait(self, deadline: float) -> None:
        """Sleep until a frame arrives (``_wake``) or ``deadline`` (clock seconds).

        A bare future plus one timer handle: cheaper than ``asyncio.wait_for(event.wait())``,
        which creates a task per wait (measured: about 0.2 ms per round less on 2 cores).
        """
        timeout = deadline - self.clock()
        if timeout <= 0:
            return
        self._waiter = waiter = self._loop.create_future()
        timer = self._loop.call_later(timeout, self._wake)
        try:
            await waiter
        finally:
            timer.cancel()
            self._waiter = None

    def _resend_interval(self) -> tuple[float, float]:
        """(periodic, fast) resend intervals, adapted to how long a round takes here.

        A fixed interval shorter than a normal round (16 robots sharing 2 cores take ~50 ms a
        round) makes every waiting robot resend again and again, and the extra frames slow the
        rounds further. Like TCP's retransmission timer, wait a few typical rounds -- the fast
        quartile of recent rounds, which loss does not inflate -- and never less than
        ``retransmit_s``.
        """
        recent = self.round_times[-ADAPT_WINDOW:]
        typical = float(np.percentile(recent, 25)) if len(recent) >= ADAPT_MIN_ROUNDS else 0.0
        periodic = max(self.retransmit_s, ADAPT_FACTOR * typical)
        fast = min(periodic, max(FAST_RESEND_MIN_S, periodic / 4))
        return periodic, fast

    def _resend(self, now: float) -> float:
        """Republish the latest frame if due; return when the next resend is due.

        Due every resend interval, or sooner when a neighbour showed it is behind (or
        (re)appeared). The shell only repeats the latest frame; it never invents values.
        """
        periodic, fast = self._resend_interval()
        since = now - self._last_put
        if since >= periodic or (self._republish_now and since >= fast):
            self._publish(self._latest)
        nxt = self._last_put + periodic
        if self._republish_now:
            nxt = min(nxt, self._last_put + fast)
        return nxt

    async def _rounds(self) -> str:
        core = self.core
        wall_end = self._t0 + self.max_wall_s
        self._publish(core.outgoing())
        last_advance = self.clock()
        while True:
            now = self.clock()
            self._pump(now)
            if core.ready():  # ready() is false once finished
                self._checkpoint()
                failed = self._advance()
                if failed is not None:
                    return failed
                t = self.clock()
                self.round_times.append(t - last_advance)
                last_advance = t
                self._status_line()
                if core.ready():
                    # Still ready (no neighbours left, or their next values already here): let
                    # other tasks and callbacks run before the next round (costs one loop pass).
                    await asyncio.sleep(0)
                continue
            if core.finished:
                return "finished"
            now = self.clock()
            if now >= wall_end:
                log.warning("robot %d: max_wall_s=%.1fs reached at round %d", self.me, self.max_wall_s, core.round)
                return "max_wall"
            dropped_any = False
            drop_deadline = float("inf")
            for j in core.missing():
                when, why = self._drop_due(j, now)
                if why is not None:
                    self._drop(j, why)
                    dropped_any = True
                elif self.heard_round.get(j, -1) >= core.round + 2:
                    # A live neighbour is never more than one round ahead of us unless it dropped
                    # us (e.g. we were restarted too late): its frames carry only rounds it is past,
                    # so the value we wait for will never come. (A restored core is ready at once,
                    # so a neighbour two rounds past our checkpoint never gets here.)
                    self._drop(j, f"it is at round {self.heard_round[j]}, so it has dropped us")
                    dropped_any = True
                else:
                    drop_deadline = min(drop_deadline, when)
            if dropped_any:
                if self._had_neighbours and not core.neighbours:
                    # Cut off from every neighbour: continuing would "converge" on our own data.
                    self.error = (f"robot {self.me} round {core.round}: isolated, every neighbour dropped "
                                  f"({sorted(self.neighbours_dropped)})")
                    log.error("%s", self.error)
                    return "isolated"
                continue
            deadline = min(self._resend(now), wall_end, drop_deadline)
            due = self.links.next_due()
            if due is not None:
                deadline = min(deadline, due)
            await self._wait(deadline)

    async def _linger(self) -> None:
        """Keep the final frame available until every neighbour reached our final round or left.

        "Left" means its liveliness token vanished: it closed its session (it finished too) or
        died; in both cases waiting longer serves nobody. Bounded by ``linger_s`` anyway.
        """
        final = self.core.round
        end = min(self.clock() + self.linger_s, self._t0 + self.max_wall_s + self.linger_s)
        while True:
            now = self.clock()
            self._pump(now)
            if all(self.heard_round.get(j, -1) >= final or j in self._gone for j in self.watched) or now >= end:
                return
            deadline = min(self._resend(now), end)
            due = self.links.next_due()
            if due is not None:
                deadline = min(deadline, due)
            await self._wait(deadline)

    def result(self, stopped: str) -> dict[str, Any]:
        """core.result() plus the shell's counters; JSON-safe (non-finite floats -> None)."""
        res = dict(self.core.result())
        if stopped != "finished":
            res["converged"] = False
        if self._had_neighbours and not self.core.neighbours:
            res["converged"] = False  # alone: its answer is its own data's, not the fleet's
            res["isolated"] = True
        if self.error is not None:
            res["error"] = self.error
        rt = sorted(self.round_times)
        res.update(
            {
                "robot": self.me,
                "fleet": self.spec.fleet,
                "stopped": stopped,
                "frames_sent": self.sent,
                "frames_received": self.received,
                "frames_lost": self.lost,
                "frames_duplicated": self.duplicated,
                "frames_accepted": self.accepted,
                "frames_rejected": {"total": sum(self.rejected.values()), "by_reason": dict(self.rejected)},
                "restarts": self.restarts,
                "neighbours_dropped": list(self.neighbours_dropped),
                "dropped_at": {str(j): k for j, k in self.dropped_at.items()},
                "wall_s": self.clock() - self._t0,
                "round_ms": {
                    "rounds": len(rt),
                    "median": 1e3 * rt[len(rt) // 2] if rt else None,
                    "mean": 1e3 * sum(rt) / len(rt) if rt else None,
                },
            }
        )
        # The core's per-round iterates (ConsensusADMM keeps them by default): the launcher's
        # convergence history needs them. After a restart they start at the checkpoint's round.
        trace = getattr(self.core, "trace", None)
        if trace:
            res["trace"] = {str(k): [float(a) for a in v] for k, v in sorted(trace.items())}
        return _finite(res)

    async def run(self) -> dict[str, Any]:
        import zenoh

        self._zenoh = zenoh
        self._loop = asyncio.get_running_loop()
        self._t0 = self.clock()
        if self.zenoh_config is not None:  # e.g. TLS, remote endpoints: built by the caller
            config = to_zenoh_config(self.zenoh_config)
        else:
            config = robot_config(self.connect)
        # open/close block (TCP connect, up to the connect timeout): keep them off the event loop.
        opening = self._loop.run_in_executor(None, zenoh.open, config)
        try:
            session = await asyncio.shield(opening)
        except asyncio.CancelledError:  # do not leak a session opened after we were cancelled
            opening.add_done_callback(lambda f: f.cancelled() or f.exception() or f.result().close())
            raise
        self._session = session
        self._connected_since = self._t0
        self._router_ids = self._routers() or set()
        self._subs: dict[int, Any] = {}
        token = alive_sub = None
        try:
            fleet = self.spec.fleet
            for j in self.watched:
                self._subs[j] = session.declare_subscriber(
                    state_key(fleet, j), lambda sample, j=j: self._on_sample_thread(j, sample)
                )
            self._pub = session.declare_publisher(
                state_key(fleet, self.me), express=PUBLISH_EXPRESS, congestion_control=zenoh.CongestionControl.DROP
            )
            alive_sub = session.liveliness().declare_subscriber(
                alive_wildcard(fleet), self._on_alive_thread, history=True)
            token = session.liveliness().declare_token(alive_key(fleet, self.me))
            now = self.clock()
            for j in self.watched:
                self.last_heard.setdefault(j, now)
            stopped = await self._rounds()
            if stopped == "finished":
                await self._linger()
            self._status_line(stopped)
            result = self.result(stopped)
        finally:
            self._closing = True
            for ent in (token, alive_sub, *self._subs.values()):
                if ent is not None:
                    try:
                        ent.undeclare()
                    except Exception:  # noqa: BLE001 - best effort on the way out
                        pass
            await asyncio.to_thread(session.close)
        if self.result_path is not None:
            _write_atomic(self.result_path, json.dumps(result, indent=1, default=float).encode())
        return result


def _default_build(spec: Any, robot_id: int) -> Any:
    from agents.spec import build_core

    return build_core(spec, robot_id)


def _default_restore(spec: Any, robot_id: int, checkpoint: dict) -> Any:
    from agents.spec import restore_core

    return restore_core(spec, robot_id, checkpoint)


async def run_robot(
    spec: Any,
    robot_id: int,
    *,
    connect: list[str],
    checkpoint_path: Path | None = None,
    result_path: Path | None = None,
    status_stream: TextIO | None = sys.stdout,
    build: Callable[[Any, int], Any] | None = None,
    restore: Callable[[Any, int, dict], Any] | None = None,
    handle_signals: bool = False,
    zenoh_config: Any | None = None,
) -> dict[str, Any]:
    """Run robot ``robot_id`` of ``spec`` until its core finishes or ``spec.timing.max_wall_s``.

    ``connect``: router endpoint(s), e.g. ``["tcp/127.0.0.1:7447"]`` (validated, loopback only).
    ``zenoh_config``: the session configuration as a dict (``protocol.zenoh_config.robot_config_dict``
    with TLS files or ``loopback_only=False``); default ``robot_config(connect)``.
    ``checkpoint_path``: written (crash-safe) before every ``core.advance()``; if a checkpoint is
    there at start the robot resumes from it exactly (``restarts`` += 1); it must belong to the
    same fleet, robot and config tag (else ValueError). ``result_path``: JSON result written atomically at the end.
    ``status_stream``: one JSON line per round (None: silent).
    ``build`` / ``restore``: core factories, default ``agents.spec.build_core`` / ``restore_core``.
    ``handle_signals``: on SIGTERM/SIGINT stop cleanly (session closed, result written with
    ``stopped = "signal"``); only for a process that runs one robot in its main thread.

    Returns the result dict (also written to ``result_path``).
    """
    shell = RobotShell(
        spec,
        robot_id,
        connect=connect,
        checkpoint_path=checkpoint_path,
        result_path=result_path,
        status_stream=status_stream,
        build=build or _default_build,
        restore=restore or _default_restore,
        zenoh_config=zenoh_config,
    )
    if not handle_signals or threading.current_thread() is not threading.main_thread():
        return await shell.run()

    loop = asyncio.get_running_loop()
    task = asyncio.ensure_future(shell.run())
    stop = asyncio.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    try:
        stopper = asyncio.ensure_future(stop.wait())
        await asyncio.wait({task, stopper}, return_when=asyncio.FIRST_COMPLETED)
        stopper.cancel()
        if task.done():
            return task.result()
        task.cancel()
        try:
            await task
        except asyncio.CancelledError:
            pass
        result = shell.result("finished" if shell.core.finished else "signal")
        if shell.result_path is not None:
            _write_atomic(shell.result_path, json.dumps(result, indent=1, default=float).encode())
        return result
    finally:
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.remove_signal_handler(sig)
