"""The in-process fleet: every robot's session in one process, frames moved in memory.

It drives exactly what a robot process drives -- the same :class:`protocol.session.RobotSession`
(framing, authentication, dedup, piggyback recovery, adaptive resend, linger, neighbour death),
the same cores, the same fault-injecting links -- on a virtual clock, so it is deterministic and
fast. With no faults every frame arrives at once and the fleet advances in lock-step; with faults,
delayed and lost frames are recovered exactly as in the Zenoh shell.

Liveliness on the virtual clock: every robot's "token" is there from the start and vanishes when
its session closes (``peer_gone`` to its neighbours), so ``dead_after_s`` / ``give_up_s`` mean what
they mean in a Zenoh fleet: a neighbour that stopped for good is dropped after ``dead_after_s`` of
silence.

Crash injection (``crashes``, the CLI's ``--crash ID@ROUND``, as `launch` does with SIGKILL): a
robot that reaches the planned round is gone at once -- its token vanishes, frames to it are lost;
with ``restart`` it comes back ``restart_after`` virtual seconds later from the checkpoint it took
before its last round (what the robot process writes before every round), otherwise its
neighbours drop it after ``dead_after_s`` (fitted to the plan as `launch` fits it,
launcher/fleet.py ``fleet_timing``) and it has no result row.
"""

from __future__ import annotations

import collections
import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from agents.pdmm import FREE_ALGORITHMS, build_free_core  # noqa: F401 - the free cores live with their mathematics
from agents.problem import InfeasibleError, SolverError
from agents.spec import FleetSpec, build_core, restore_core
from protocol.links import LinkLayer
from protocol.session import BROADCAST, DEDUP_WINDOW, RobotSession

ProgressFn = Callable[[int, float], None]
FAILED = ("solver_error", "diverged")


@dataclass
class FleetOutcome:
    """What the fleet produced: one result row per robot plus run-level figures."""

    robots: list[dict[str, Any]]
    wall_s: float
    virtual_s: float
    link_stats: dict[str, int] = field(default_factory=dict)
    #: the in-process crash plan as carried out: robot, planned_round, round, at_s, restarted_at_s
    #: (None: dead for good), fired (False: the robot stopped before the planned round)
    crash_log: list[dict[str, Any]] = field(default_factory=list)


@dataclass
class _Crashes:
    """The crash plan on the virtual clock: who goes down when, and their last checkpoints."""

    plans: dict[int, list[int]]  # robot -> planned rounds, ascending
    restart: bool
    restart_after: float
    saved: dict[int, dict[str, Any]] = field(default_factory=dict)  # robot -> envelope before its last round
    down: dict[int, float] = field(default_factory=dict)  # robot -> restart time (inf: dead for good)
    log: list[dict[str, Any]] = field(default_factory=list)

    def save(self, rid: int, session: RobotSession) -> None:
        """The checkpoint a robot process writes before each round (only robots with a plan)."""
        if self.plans.get(rid) and session.ready():
            self.saved[rid] = session.checkpoint({})

    def due(self, rid: int, session: RobotSession) -> int | None:
        plans = self.plans.get(rid)
        return plans[0] if plans and session.core.round >= plans[0] else None

    def next_restart(self) -> float | None:
        finite = [t for t in self.down.values() if t != float("inf")]
        return min(finite) if finite else None

    def not_fired(self) -> None:
        for rid, plans in self.plans.items():
            self.log += [{"robot": rid, "planned_round": r, "fired": False} for r in plans]


@dataclass(frozen=True)
class MemoryFit:
    """One algorithm's memory in `simulate`, per robot (fitted from above on measured peaks)."""

    robot_mb: float  # each robot: its core, session, data, result row
    # each robot and neighbour: keyed hashers (protocol/auth.py, ~1 kB), per-peer session state, the
    # in-process link (N^2 of them on a complete graph), the frames' tags (one per receiver) ...
    link_kb: float
    # ... and per round, up to DEDUP_WINDOW rounds: the session's dedup window of that sender's frames
    # (protocol/session.py _SeenFrames: two dicts of up to 256 entries, ~30 kB per robot and neighbour)
    link_round_kb: float
    round_kb: float  # each robot and round: the trace it keeps for result.json (a fixed part ...
    round_kb_per_number: float  # ... and per number of the grid, M + 1: the values it records)


#: `simulate`'s peak memory -- the whole command: world, exact reference, sessions, rounds, report --
#: measured by benchmarks/simulate_scale.py (results/simulate_cost.md) and fitted from above:
#:     MB = SIMULATE_BASE_MB + N (robot_mb + degree (link_kb + link_round_kb min(rounds, DEDUP_WINDOW)) / 1000
#:                                 + rounds (round_kb + round_kb_per_number (M + 1)) / 1000)
#: degree the neighbours per robot, rounds the run's cap (autogrid: its planned rounds), M the grid points
#: (autogrid: its budget). On a complete graph the degree term grows as N^2: the bound's main term.
SIMULATE_BASE_MB = 130.0
SIMULATE_MEMORY = {
    "admm": MemoryFit(robot_mb=1.2, link_kb=3.6, link_round_kb=0.12, round_kb=2.0, round_kb_per_number=0.055),
    "ct-admm": MemoryFit(robot_mb=1.2, link_kb=3.6, link_round_kb=0.12, round_kb=2.0, round_kb_per_number=0.065),
    "newton": MemoryFit(robot_mb=1.2, link_kb=3.6, link_round_kb=0.12, round_kb=2.5, round_kb_per_number=0.25),
    "lsq": MemoryFit(robot_mb=1.2, link_kb=3.6, link_round_kb=0.12, round_kb=2.0, round_kb_per_number=0.055),  # (admm's core)
    "autogrid": MemoryFit(robot_mb=4.0, link_kb=3.6, link_round_kb=0.12, round_kb=2.0, round_kb_per_number=0.055),
}
#: the share of the available memory a run may take (as `launch`'s max_robots: half)
SIMULATE_MEMORY_SHARE = 0.5


def _memory_fit(algorithm: str) -> MemoryFit:
    """The algorithm's fit; a user's fleet algorithm gets the dearest of each term."""
    if algorithm in SIMULATE_MEMORY:
        return SIMULATE_MEMORY[algorithm]
    fits = SIMULATE_MEMORY.values()
    return MemoryFit(*(max(getattr(f, name) for f in fits) for name in MemoryFit.__dataclass_fields__))


def simulate_degree(topology: str, n_robots: int) -> int:
    """Neighbours per robot the memory bound counts: a geometric graph as a complete one (at a fixed
    --comm-range its degree grows with N, and the bound is checked before the graph is built)."""
    return min(2, n_robots - 1) if topology in ("ring", "line") else max(n_robots - 1, 0)


def simulate_memory_mb(n_robots: int, topology: str, algorithm: str, *, rounds: int, grid_points: int) -> float:
    """The fitted peak MB of `simulate` with this many robots (SIMULATE_MEMORY's formula)."""
    fit = _memory_fit(algorithm)
    per_link_mb = (fit.link_kb + fit.link_round_kb * min(rounds, DEDUP_WINDOW)) / 1000.0
    per_round_mb = (fit.round_kb + fit.round_kb_per_number * (grid_points + 1)) / 1000.0
    per_robot = fit.robot_mb + per_link_mb * simulate_degree(topology, n_robots) + rounds * per_round_mb
    return SIMULATE_BASE_MB + n_robots * per_robot


def simulate_max_robots(topology: str, algorithm: str, *, rounds: int, grid_points: int,
                        available_mb: float | None = None) -> tuple[int | None, str]:
    """How many robots `simulate` holds in this machine's memory, and why (None: memory unknown).

    The largest N (at least 1) whose fitted peak (``simulate_memory_mb``) is within
    SIMULATE_MEMORY_SHARE of the available memory (/proc/meminfo's MemAvailable unless given)."""
    if available_mb is None:
        from launcher.fleet import _available_memory_mb  # (lazy: fleet imports this module)

        available_mb = _available_memory_mb()
    if available_mb is None:
        return None, "available memory unknown"
    budget = SIMULATE_MEMORY_SHARE * available_mb

    def fits(n: int) -> bool:
        return simulate_memory_mb(n, topology, algorithm, rounds=rounds, grid_points=grid_points) <= budget

    low, high = 1, 2
    while fits(high) and high < 2**40:
        low, high = high, 2 * high
    while high - low > 1:  # the fitted peak grows with N: the last N within the budget
        mid = (low + high) // 2
        low, high = (mid, high) if fits(mid) else (low, mid)
    fit = _memory_fit(algorithm)
    per_link = fit.link_kb + fit.link_round_kb * min(rounds, DEDUP_WINDOW)
    links = f" + {per_link:.3g} kB per robot and neighbour ({'2' if topology in ('ring', 'line') else 'all the others'})"
    per_round = fit.round_kb + fit.round_kb_per_number * (grid_points + 1)
    why = (f"{SIMULATE_MEMORY_SHARE:g} x {available_mb:.0f} MB available, at {SIMULATE_BASE_MB:g} MB + {fit.robot_mb:g} MB "
           f"per robot{links} + {per_round:.2g} kB per robot and round, {rounds} rounds: {algorithm}'s fit in "
           "benchmarks/results/simulate_cost.md")
    return low, why


class DeadlockError(RuntimeError):
    """No robot can advance and nothing is in flight: a protocol bug, never a network state."""


class FleetFailure(RuntimeError):
    """A robot's local solve failed or its iterate diverged: the run has no answer.

    The message is one line naming the robot, the round and why (the CLI prints it, exit 1).
    """


def _sessions(spec: FleetSpec, cap: float | None) -> dict[int, RobotSession]:
    sessions = {}
    for rid in spec.robot_ids:
        try:
            core = build_core(spec, rid)
        except (SolverError, InfeasibleError) as exc:
            raise FleetFailure(f"robot {rid} round 0: local solver failed: {exc}") from None
        sessions[rid] = RobotSession.for_spec(spec, core, now=0.0, max_wall_s=cap)
    for s in sessions.values():
        for j in s.peers:
            s.peer_up(j, 0.0)  # every robot is there from the start
    return sessions


def simulate_fleet(
    spec: FleetSpec,
    *,
    progress: ProgressFn | None = None,
    max_virtual_s: float | None = None,
    crashes: Sequence[Any] = (),
    restart: bool = True,
    restart_after: float = 1.0,
) -> FleetOutcome:
    """Run every robot of `spec` to completion in this process and return their result rows.

    ``max_virtual_s`` replaces ``spec.timing.max_wall_s`` as the cap on the virtual clock.
    ``crashes``: plans with ``robot`` and ``round`` (launcher/fleet.py CrashPlan), carried out as
    the module doc says; ``restart`` / ``restart_after`` as `launch`'s --no-restart / --restart-after.
    """
    started = time.perf_counter()
    plan = _Crashes({}, restart, restart_after)
    from launcher.fleet import spec_for_run  # the same dead_after_s and form as launch (lazy: fleet imports us)

    spec = spec_for_run(spec, list(crashes or []), restart=restart, restart_after=restart_after)
    if crashes:
        for c in sorted(crashes, key=lambda c: (c.robot, c.round)):
            plan.plans.setdefault(int(c.robot), []).append(int(c.round))
    sessions = _sessions(spec, max_virtual_s)
    links = LinkLayer(spec.faults, spec.seed)
    received: collections.Counter[int] = collections.Counter()  # frames put on links into a robot
    running = dict(sessions)
    now = 0.0
    slowest = -1
    while running or plan.next_restart() is not None:
        _restart_due(spec, plan, sessions, running, now, max_virtual_s)
        for src, dst, payload in links.deliver(now):
            if dst in running:  # a crashed robot's frames are lost
                sessions[dst].receive(src, payload, now)
        advanced = False
        for rid, s in running.items():
            plan.save(rid, s)
            while s.advance(now):
                advanced = True
                plan.save(rid, s)
            if s.stopped in FAILED:
                raise FleetFailure(s.error)
        for rid, s in running.items():
            for dest, payload in s.to_send(now):
                for j in s.peers if dest is BROADCAST else (dest,):
                    links.send(rid, j, payload, now)
                    received[j] += 1
        for rid in [rid for rid, s in running.items() if s.done or plan.due(rid, s) is not None]:
            if not running[rid].done:
                _crash(plan, rid, running[rid], now)
            del running[rid]
            for s in running.values():
                s.peer_gone(rid, now)  # its session closed: its token is gone
        alive = [s for rid, s in sessions.items() if rid not in plan.down or rid in running]
        current = min((s.core.round for s in alive), default=slowest)
        if progress is not None and current != slowest:
            slowest = current
            progress(current, max(s.core.residual for s in alive))
        if advanced:
            continue
        due = [d for d in (s.next_deadline() for s in running.values()) if d is not None]
        for extra in (links.next_due(), plan.next_restart()):
            if extra is not None:
                due.append(extra)
        if running and not due:
            raise DeadlockError("no robot can advance and no frame is in flight")
        if due:
            now = max(now, min(due))
    plan.not_fired()
    kept = {rid: s for rid, s in sessions.items() if plan.down.get(rid) != float("inf")}
    stats = {**links.stats(), "bytes_sent": links.bytes_sent()}  # bytes: the sweep's (issue 13)
    return FleetOutcome(_rows(kept, links, received, now), time.perf_counter() - started, now, stats, plan.log)


def _crash(plan: _Crashes, rid: int, session: RobotSession, now: float) -> None:
    """Robot ``rid`` is killed now (its planned round reached): down until its restart, or for good."""
    planned = plan.plans[rid].pop(0)
    plan.down[rid] = now + plan.restart_after if plan.restart else float("inf")
    plan.log.append({"robot": rid, "planned_round": planned, "round": int(session.core.round), "at_s": now,
                     "restarted_at_s": plan.down[rid] if plan.restart else None, "fired": True})


def _restart_due(spec: FleetSpec, plan: _Crashes, sessions: dict[int, RobotSession],
                 running: dict[int, RobotSession], now: float, cap: float | None) -> None:
    """Robots whose restart time has come resume from their last checkpoint, as a process would."""
    for rid in [rid for rid, t in plan.down.items() if t <= now]:
        del plan.down[rid]
        env = plan.saved[rid]
        s = RobotSession.for_spec(spec, restore_core(spec, rid, env["core"]), now=now, max_wall_s=cap, resume=env)
        sessions[rid] = running[rid] = s
        for j in s.peers:
            if j in running and j != rid:
                s.peer_up(j, now)
                running[j].peer_up(rid, now)


def _rows(sessions: dict[int, RobotSession], links: LinkLayer, received: collections.Counter[int],
          now: float) -> list[dict[str, Any]]:
    """One row per robot (RobotSession.row), with what its incoming links did."""
    transport = {rid: {"received": received[rid], "lost": 0, "duplicated": 0} for rid in sessions}
    for (_, dst), stats in links.link_stats().items():
        if dst not in transport:  # a robot dead for good has no row
            continue
        transport[dst]["lost"] += stats["dropped"]
        transport[dst]["duplicated"] += stats["duplicated"]
    return [s.row(now, transport[rid]) for rid, s in sessions.items()]


# -- free-running sync (issue 13): robots on their own clocks, no waiting, no retransmission ------


@dataclass(frozen=True)
class ClockModel:
    """How far apart the robots' clocks and computers are in a free in-process run (all seeded).

    Robot i's clock reads ``offset_i + (1 + drift_i) t`` at true time t, with offset_i uniform in
    [0, offset_s) and drift_i uniform in [-drift, drift]; it starts ticking at a uniform time in
    [0, period); each tick's frame leaves after a compute time uniform in [0, compute_jitter_s)."""

    offset_s: float = 1.0
    drift: float = 1e-3
    compute_jitter_s: float = 0.002

    def __post_init__(self) -> None:
        for name in ("offset_s", "drift", "compute_jitter_s"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {v!r}")
        if self.drift >= 0.5:
            raise ValueError(f"drift must be below 0.5, got {self.drift}")


TickFn = Callable[[float, int, "np.ndarray"], None]


def simulate_free(
    spec: FleetSpec,
    *,
    period: float = 0.01,
    clock: ClockModel | None = None,
    params: dict[str, Any] | None = None,
    algorithm: str = "auto",
    max_virtual_s: float | None = None,
    on_tick: TickFn | None = None,
) -> FleetOutcome:
    """Every robot of ``spec`` free-running on a virtual clock (protocol/free.py), through the
    same seeded links as lockstep. ``on_tick(t, robot, values)`` sees every update (true time t).
    Deterministic for a given spec (its seed draws the clocks too)."""
    import numpy as np

    from protocol.free import FreeSession

    started = time.perf_counter()
    clock = clock or ClockModel()
    rng = np.random.default_rng([spec.seed, 13])
    ids = spec.robot_ids
    off = dict(zip(ids, rng.uniform(0.0, clock.offset_s, len(ids)).tolist()))
    rate = dict(zip(ids, (1.0 + rng.uniform(-clock.drift, clock.drift, len(ids))).tolist()))
    start = dict(zip(ids, rng.uniform(0.0, period, len(ids)).tolist()))
    cap = float(spec.timing.max_wall_s if max_virtual_s is None else max_virtual_s)

    def local(i: int, t: float) -> float:
        return off[i] + rate[i] * t

    sessions: dict[int, FreeSession] = {}
    for rid in ids:
        try:
            core = build_free_core(spec, rid, params, algorithm, period)
        except (SolverError, InfeasibleError) as exc:
            raise FleetFailure(f"robot {rid}: local solver failed: {exc}") from None
        sessions[rid] = FreeSession(core, fleet=spec.fleet, graph=spec.graph, config_tag=spec.config_tag, period=period,
                                    now=local(rid, start[rid]), max_wall_s=cap, auth=spec.frame_auth(rid))
    links = LinkLayer(spec.faults, spec.seed)
    received: collections.Counter[int] = collections.Counter()
    now = 0.0
    while True:
        for src, dst, payload in links.deliver(now):
            sessions[dst].receive(src, payload, local(dst, now))
        for rid, s in sessions.items():
            due = s.next_deadline()
            if due is None or (due - off[rid]) / rate[rid] > now:
                continue
            frames = s.tick(max(local(rid, now), due))
            if s.stopped in FAILED:
                raise FleetFailure(s.error)
            if frames and on_tick is not None and s.stopped in (None, "finished"):
                on_tick(now, rid, s.core.values)
            sent_at = now + float(rng.uniform(0.0, clock.compute_jitter_s)) if clock.compute_jitter_s else now
            for _, payload in frames:
                for j in s.core.neighbours:
                    links.send(rid, j, payload, sent_at)
                    received[j] += 1
        dues = [(d - off[r]) / rate[r] for r, d in ((r, s.next_deadline()) for r, s in sessions.items()) if d is not None]
        if links.next_due() is not None and dues:
            dues.append(links.next_due())
        if not dues:
            break
        now = max(now, min(dues))
    transport = {rid: {"received": received[rid], "lost": 0, "duplicated": 0} for rid in sessions}
    for (_, dst), st in links.link_stats().items():
        transport[dst]["lost"] += st["dropped"]
        transport[dst]["duplicated"] += st["duplicated"]
    rows = [s.row(local(rid, now), transport[rid]) for rid, s in sessions.items()]
    stats = {**links.stats(), "bytes_sent": links.bytes_sent()}
    return FleetOutcome(rows, time.perf_counter() - started, now, stats)
