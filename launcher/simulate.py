"""The in-process fleet: every robot's core in one process, frames moved in memory.

It drives exactly what a robot process drives -- the same state machine, the same frame codec,
the same fault-injecting links -- on a virtual clock, so it is deterministic and fast. With no
faults every frame arrives at once and the fleet advances in lock-step; with faults, delayed
and lost frames are recovered the way the Zenoh shell recovers them (piggybacked previous
round plus retransmission after `retransmit_s` of virtual time).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from agents.problem import InfeasibleError, SolverError
from agents.spec import FleetSpec, build_core
from protocol.frames import Decoded, FrameDecoder, encode_state
from protocol.links import LinkLayer

ProgressFn = Callable[[int, float], None]


@dataclass
class _Robot:
    core: Any
    decoder: FrameDecoder
    seq: int = 0
    last_publish: float = 0.0
    frames_sent: int = 0
    frames_received: int = 0
    round_times: dict[int, float] = field(default_factory=lambda: {0: 0.0})


@dataclass
class FleetOutcome:
    """What the fleet produced: one result per robot plus run-level figures."""

    robots: list[dict[str, Any]]
    wall_s: float
    virtual_s: float
    link_stats: dict[str, int] = field(default_factory=dict)


class DeadlockError(RuntimeError):
    """No robot can advance and nothing is in flight: a protocol bug, never a network state."""


class FleetFailure(RuntimeError):
    """A robot's local solve failed or its iterate diverged: the run has no answer.

    The message is one line naming the robot, the round and why (the CLI prints it, exit 1).
    """


def simulate_fleet(
    spec: FleetSpec,
    *,
    progress: ProgressFn | None = None,
    max_virtual_s: float | None = None,
) -> FleetOutcome:
    """Run every robot of `spec` to completion in this process and return their results."""
    started = time.perf_counter()
    cap = spec.timing.max_wall_s if max_virtual_s is None else max_virtual_s
    auths = {rid: spec.frame_auth(rid) for rid in spec.robot_ids}
    robots = {}
    for rid in spec.robot_ids:
        try:
            core = build_core(spec, rid)
        except (SolverError, InfeasibleError) as exc:
            raise FleetFailure(f"robot {rid} round 0: local solver failed: {exc}") from None
        decoder = FrameDecoder(spec.fleet, spec.robot_ids, spec.dim, spec.config_tag, auth=auths[rid])
        robots[rid] = _Robot(core, decoder)
    links = LinkLayer(spec.faults, spec.seed)
    now = 0.0

    def publish(rid: int) -> None:
        r = robots[rid]
        payload = encode_state(
            r.core.outgoing(), fleet=spec.fleet, seq=r.seq, config_tag=spec.config_tag, auth=auths[rid]
        )
        r.seq += 1
        r.frames_sent += 1
        r.last_publish = now
        for j in r.core.neighbours:
            links.send(rid, j, payload, now)

    def still_needed(rid: int) -> bool:
        """Waiting robots retransmit; finished ones too while a neighbour may still need them."""
        core = robots[rid].core
        return not core.finished or any(not robots[j].core.finished for j in core.neighbours)

    for rid in robots:
        publish(rid)
    slowest = -1
    while not all(r.core.finished for r in robots.values()):
        for src, dst, payload in links.deliver(now):
            r = robots[dst]
            event = r.decoder.decode(payload, expected_sender=src)
            if isinstance(event, Decoded):
                r.frames_received += 1
                r.core.receive(event.update)
        advanced = False
        for rid, r in robots.items():
            if r.core.ready():
                try:
                    update = r.core.advance()
                except (SolverError, InfeasibleError, FloatingPointError) as exc:
                    raise FleetFailure(f"robot {rid} round {r.core.round}: local solver failed: {exc}") from None
                why = r.core.divergence()
                if why is not None:
                    raise FleetFailure(f"robot {rid} round {update.round}: diverged: {why}")
                r.round_times[r.core.round] = now
                publish(rid)
                advanced = True
        current = min(r.core.round for r in robots.values())
        if progress is not None and current != slowest:
            slowest = current
            progress(current, max(r.core.residual for r in robots.values()))
        if advanced:
            continue
        timers = [r.last_publish + spec.timing.retransmit_s for rid, r in robots.items() if still_needed(rid)]
        due = links.next_due()
        candidates = timers + ([due] if due is not None else [])
        if not candidates:
            raise DeadlockError("no robot can advance and no frame is in flight")
        now = max(now, min(candidates))
        if now > cap:
            break
        for rid, r in robots.items():
            if still_needed(rid) and r.last_publish + spec.timing.retransmit_s <= now:
                publish(rid)

    lost_into = {rid: 0 for rid in robots}
    for (_, dst), stats in links.link_stats().items():
        lost_into[dst] += stats["dropped"]
    results = []
    for rid, r in robots.items():
        res = r.core.result()
        res.update(
            frames_sent=r.frames_sent,
            frames_received=r.frames_received,
            frames_lost=lost_into[rid],
            frames_rejected=sum(r.decoder.counts.values()),
            restarts=0,
            trace={k: v.tolist() for k, v in r.core.trace.items()},
            round_times=r.round_times,
        )
        results.append(res)
    return FleetOutcome(results, time.perf_counter() - started, now, links.stats())
