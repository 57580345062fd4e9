"""The asyncio shell that runs one robot over Zenoh: a thin loop around its RobotSession.

The protocol -- framing and authentication, dedup, piggyback recovery, adaptive and fast resend,
linger, neighbour death on evidence, the stop reasons and the result row -- is the sans-IO
:class:`protocol.session.RobotSession` the in-process fleet drives too. This shell only moves bytes
and time, and keeps what only a process has:

    zenoh thread --(sample bytes)--> loop.call_soon_threadsafe --> receiver-side fault link (j -> me)
        --> session.receive(j, bytes, now)
    session.to_send(now) --> publisher.put (express)
    liveliness tokens --> session.peer_up / peer_gone;  router ids --> session.link_status

Main loop (one asyncio task, never sleeps in the hot path; it awaits a wake-up future that arriving
frames resolve, with a timer for the earlier of ``session.next_deadline()`` and the next delayed
frame due out of the fault link): when ``session.ready()`` it writes the checkpoint (msgpack,
crash-safe, see :func:`write_checkpoint`), calls ``session.advance(now)``, publishes, prints one
JSON status line. When the session is done it writes the result file (``row_to_file``).

A liveliness token per robot (declared after its subscriptions) lets a neighbour that (re)appears
be served at once; its disappearance is the evidence of death the session's drop rule needs. Zenoh
clients reconnect to a restarted router on the same endpoint by themselves (and re-declare their
tokens); the shell tells the session when its router is back or new (``link_status``).
SIGTERM/SIGINT (``run_robot(handle_signals=True)``) stop cleanly with ``stopped = "signal"``.
"""

from __future__ import annotations

import asyncio
import collections
import json
import logging
import os
import signal
import struct
import sys
import threading
import time
import weakref
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

import msgpack

from protocol.frames import Rejected
from protocol.keys import alive_key, alive_wildcard, state_key
from protocol.links import LinkLayer
from agents.rounds import DIVERGED_ABS, check_iterate
from protocol.session import GIVE_UP_FACTOR, RobotSession, row_to_file
from protocol.zenoh_config import robot_config, to_zenoh_config

if TYPE_CHECKING:  # annotations only: the parser is built lazily (start-up cost)
    import argparse

__all__ = [
    "run_robot",
    "RobotShell",
    "alive_key",
    "alive_wildcard",
    "read_checkpoint",
    "write_checkpoint",
    "checkpoint_exists",
    "CheckpointWriter",
    "run_robots",
    "CHECKPOINT_VERSION",
    "check_iterate",
    "DIVERGED_ABS",
    "GIVE_UP_FACTOR",
    "run_forked",
    "fleet_resume_round",
    "FLEET_CHECKPOINT_EVERY",
    "watch_parent",
]

log = logging.getLogger("shapefleet.robot")


def _process_start() -> float | None:
    """When this process started, on the monotonic clock (from /proc; None elsewhere)."""
    try:
        with open("/proc/self/stat", "rb") as fh:
            ticks = int(fh.read().rsplit(b")", 1)[1].split()[19])
        since_boot = ticks / os.sysconf("SC_CLK_TCK")
        return time.monotonic() - (time.clock_gettime(time.CLOCK_BOOTTIME) - since_boot)
    except (OSError, ValueError, IndexError, AttributeError):
        return None


_STARTED = {"process": _process_start(), "imported": time.monotonic()}

#: Zenoh calls our subscriber callbacks on its own receiving thread (``indirect=False``), not on a
#: Python thread of their own per subscriber (zenoh-python's default, ``indirect=True``): a process
#: of 16 robots on a complete graph of 32 had 530 such threads (one per neighbour key and one per
#: liveliness subscription), and each frame woke one of them -- one more thread hand-over and GIL
#: acquisition per frame (docs/robot.md, "Latency"). Our callbacks only copy the payload and queue
#: it (``_Inbox``). ``SHAPEFLEET_ZENOH_INDIRECT=1`` restores the default, for comparisons.
ZENOH_DIRECT_CALLBACKS = os.environ.get("SHAPEFLEET_ZENOH_INDIRECT", "") == ""


def zenoh_callback(fn: Callable[[Any], Any]) -> Any:
    """``fn`` as the handler of a Zenoh subscriber: run on Zenoh's thread (see
    ``ZENOH_DIRECT_CALLBACKS``); it must be short and must not block."""
    if not ZENOH_DIRECT_CALLBACKS:
        return fn
    import zenoh

    return zenoh.handlers.Callback(fn, indirect=False)


#: 2 since branch certtight: the certified guard's payload and a checkpointed certificate changed meaning
#: (|u+_l| and g_half where max|phi_i| stood), so a checkpoint of version 1 is refused, never read as today's.
#: 3 since branch illcond: an autogrid robot's frame slots -3/-2 (VOTE) and -3/-1 (hard ADMM) carry the
#: conditioning test (docs/autogrid.md); a version-2 checkpoint there would resume with zeros in them
#: 4 since branch softwarm: the hub state's `age` (the settled stop rule) and autogrid's carried soft duals
#: 5 since branches softkrylov and hardend (one release): an answer solve's end-game state, soft or hard
#: (agents/soft_endgame.py), and its payload in the frame slots after w; a version-4 robot would resume
#: that solve without it (other frames, other bits)
#: 6 since branch admmend: plain admm on a complete graph with a soft margin runs the soft end-game by default
#: (its state where the certificate's stood); a version-5 checkpoint of such a fleet would resume without it
#: 7 since branch hardon: likewise for hard margins (the hard end-game by default); a version-6 checkpoint
#: of such a fleet would resume with the certified guard's state
#: 8 since branch survivors (7: branch hardon's): a round core's checkpoint holds the robots it knows to be
#: dropped for good (`gone`, `prev_gone`) and its inbox the ones each neighbour sent; a version-7 survivor of
#: a sparse soft fleet would resume without them (another weight of |x|^2, other frames)
#: 9 since branch ringend (7 and 8: branches hardon and survivors, in parallel): a relay fleet with a hard margin
#: pauses its ADMM for end-game attempts (agents/relay_hub.py); its state and frame length changed
#: 11 since branch relaysoft (10 was kept for branch survivors2, which merged without a bump): a relay fleet with a
#: soft margin on a ring of up to 8 robots (or the 5-line) pauses for end-game attempts too; its state (the
#: attempt's) and frame length changed
#: 12 since branch relayblock: the end-game's state holds whether its attempt went back to the narrow start
#: block (`narrow`; a relay fleet's attempts start wide)
#: 13 since branch nearlsq: an autogrid lsq robot's state holds rule 2's agreed near-data marks and their chunk
#: (`_near`, `_chunk`) and its sweep's candidates, frame length and phases changed; a version-12 checkpoint would
#: resume rule 1's sweep
#: 14 since branch lsqring: an autogrid lsq robot on a sparse graph runs, beside the sweep's folds, every candidate's
#: fit of all rows (its sweep's task list changed) and starts the final fit from the chosen one's iterate and edges
CHECKPOINT_VERSION = 14
PUBLISH_EXPRESS = True  # see docs/robot.md, "Latency"
PROFILE_PHASES = ("receive", "checkpoint", "advance", "send", "status", "wait")
# wall seconds by phase, and the main thread's CPU seconds ("<phase>:cpu": immune to the
# preemption a loaded machine adds to wall times)
PROFILE_KEYS = (*PROFILE_PHASES, *(f"{p}:cpu" for p in PROFILE_PHASES if p != "wait"))
_pc = time.perf_counter
_tt = time.thread_time  # a system call (~1 us): read only when profiling (RobotShell._tt)


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
            data = fh.read()
        if data[:4] == _SLOT_MAGIC:  # a CheckpointWriter slot: length and CRC say if it is whole
            _magic, size, crc = _SLOT_HEADER.unpack_from(data)
            data = data[_SLOT_HEADER.size:_SLOT_HEADER.size + size]
            if len(data) != size or zlib.crc32(data) != crc:
                return None
        env = msgpack.unpackb(data, raw=False, strict_map_key=False)
    except FileNotFoundError:
        return None
    except Exception:  # noqa: BLE001 - truncated / corrupt: not a usable checkpoint
        return None
    if not isinstance(env, dict) or env.get("v") != CHECKPOINT_VERSION or "core" not in env:
        return None
    return env


_SLOT_MAGIC = b"SFck"
_SLOT_HEADER = struct.Struct("<4sII")  # magic, payload length, CRC-32 of the payload


class CheckpointWriter:
    """The per-round checkpoint at the cost of one ``pwrite``: two slots written in turn in place.

    The slots are ``<path>`` and ``<path>.tmp`` (the very files :func:`read_checkpoint` looks at),
    each kept open; a checkpoint is one ``os.pwrite`` of a header (magic, length, CRC-32) and the
    msgpack envelope at offset 0 of the slot that does *not* hold the newest checkpoint. A crash in
    the middle of a write leaves that slot failing its CRC and the other slot holding the previous
    checkpoint -- exactly what the tmp-file-and-rename scheme of :func:`write_checkpoint` leaves
    (its tmp file truncated, the previous checkpoint in place): the robot resumes from the round
    before, as it does today, and recomputes the same frames. What it saves is the file-system
    metadata per round (create, unlink, rename: ~0.3 ms on a loaded 2-core machine, against
    ~0.01 ms for the ``pwrite``). No fsync: we model process crashes, not machine crashes.
    """

    def __init__(self, path: Path, *, keep_round: int | None = None) -> None:
        """``keep_round``: the round the robot resumed from when it is not the newest slot's (a
        whole-fleet process, :func:`fleet_resume_round`): that slot is kept, the other written first."""
        self.paths = (Path(path), _checkpoint_tmp(Path(path)))
        found = [_load_envelope(p) for p in self.paths]
        held = [i for i in (0, 1) if found[i] is not None
                and (keep_round is None or _core_round(found[i]) == keep_round)]
        newest = max(held, key=lambda i: int(found[i].get("n", 0)), default=1)
        self._next = 1 - newest  # never overwrite the newest complete checkpoint (or the one resumed from)
        self._fds: list[int | None] = [None, None]

    def write(self, envelope: dict[str, Any]) -> None:
        """Write ``envelope`` into the older slot (crash-safe, see the class doc)."""
        data = msgpack.packb(envelope, use_bin_type=True)
        i = self._next
        fd = self._fds[i]
        if fd is None:
            fd = self._fds[i] = os.open(self.paths[i], os.O_RDWR | os.O_CREAT, 0o644)
        # one system call for header and body, without copying the body behind the header
        os.pwritev(fd, (_SLOT_HEADER.pack(_SLOT_MAGIC, len(data), zlib.crc32(data)), data), 0)
        self._next = 1 - i

    def close(self) -> None:
        for i, fd in enumerate(self._fds):
            if fd is not None:
                os.close(fd)
                self._fds[i] = None


def checkpoint_exists(path: Path) -> bool:
    """True if a checkpoint (complete or not) is present at ``path`` or its tmp file."""
    path = Path(path)
    return path.exists() or _checkpoint_tmp(path).exists()


def read_checkpoint(path: Path, *, at_round: int | None = None) -> dict[str, Any]:
    """The newest complete checkpoint of ``path`` / ``<path>.tmp``; ValueError if there is none.

    ``at_round``: the newest complete one of the core at that round (a process hosting the whole
    fleet resumes every robot from one common round, :func:`fleet_resume_round`)."""
    path = Path(path)
    found = [env for env in (_load_envelope(path), _load_envelope(_checkpoint_tmp(path))) if env is not None]
    if at_round is not None:
        found = [env for env in found if _core_round(env) == at_round]
    if not found:
        at = "" if at_round is None else f" at round {at_round}"
        raise ValueError(f"{path}: no complete shapefleet robot checkpoint{at} (version {CHECKPOINT_VERSION})")
    return max(found, key=lambda env: int(env.get("n", 0)))


def _core_round(env: dict[str, Any]) -> int | None:
    core = env.get("core")
    rnd = core.get("round") if isinstance(core, dict) else None
    return rnd if type(rnd) is int else None


#: A process that hosts every robot of its fleet checkpoints each robot every this many rounds
#: (at rounds that are multiples of it), not before every round (branch shell3, issue 14: the
#: checkpoint was 14 % of such a process's loop). Every robot of the fleet dies with the process,
#: so they all resume from one common round (:func:`fleet_resume_round`) and recompute the rounds
#: since: the ADMM is deterministic, so the iterates are the same bit for bit. A process that
#: shares the fleet with other processes still checkpoints every round (its neighbours elsewhere
#: go on, so it must resume where its frames left off: docs/robot.md, "Checkpoints").
FLEET_CHECKPOINT_EVERY = 16


def fleet_checkpoint_every(robots: int) -> int:
    """The checkpoint period of a process hosting a whole fleet of ``robots``: at least the
    graph's diameter (< ``robots``), so that two robots' newest checkpoints are never more than
    one period apart (what :func:`fleet_resume_round` relies on)."""
    return max(FLEET_CHECKPOINT_EVERY, int(robots))


def fleet_resume_round(paths: list[Path]) -> int | None:
    """The round a process hosting the whole fleet resumes every robot from (None: start fresh).

    Each robot's two checkpoint slots hold its last two checkpoints (rounds a period apart) or one
    of them and a torn write. A robot's newest complete checkpoint is at most one period ahead of
    any other's (lockstep, period >= diameter), so the oldest of the robots' newest rounds is held
    complete by every robot: a consistent cut of the fleet, each robot with its neighbours' values
    of that round. A robot without a complete checkpoint died before its first (round 0, written
    before any robot can pass round 1): it starts fresh, which is its round 0, and the others
    resume from round 0. None when no robot has a checkpoint.
    """
    newest: list[int] = []
    for path in paths:
        rounds = [r for r in (_core_round(e) for e in (_load_envelope(path), _load_envelope(_checkpoint_tmp(path)))
                              if e is not None) if r is not None]
        newest.append(max(rounds, default=-1))
    return None if not newest or max(newest) < 0 else max(0, min(newest))


# --------------------------------------------------------------------------- Zenoh -> loop


class _Inbox:
    """Calls from Zenoh's threads to the event loop, one wake-up per burst.

    ``loop.call_soon_threadsafe`` per frame costs a self-pipe write and a loop wake-up each; a
    process with several robots gets a burst of frames per round (8 robots on a complete graph of
    16: 120). Here the first call of a burst schedules one drain, the others only queue (FIFO:
    the order the frames came in is kept).

    The robots a burst makes ready are woken at the end of the drain in the order of their ids
    (``wake_later``), not in the order their last missing frame happened to come: the loop then
    computes a process's robots in the same order every round. Woken as their frames came, the
    robot that computed last in a round (its frame completes the others' inputs) computed first
    in the next, so each robot's place in the round rotated and its own round times alternated
    between a fraction of the fleet's round and more than a whole one (3 robots in a process:
    0.55 / 2.5 ms, the median 2.0 ms for a mean round of 1.6; results/round_cost.md, branch
    shell3). The work and its order within a robot are unchanged; only which robot goes first.
    """

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self._items: collections.deque = collections.deque()
        self._lock = threading.Lock()
        self._armed = False
        self._draining = False
        self._to_wake: list[RobotShell] = []
        self._loop_thread = threading.get_ident()  # made on the loop's thread (_inbox_for)

    def wake_later(self, shell: RobotShell) -> bool:
        """During a drain (loop thread): queue ``shell``'s wake-up for its end (in id order)
        and say True; outside one: False (the caller wakes it now)."""
        if not self._draining:
            return False
        self._to_wake.append(shell)
        return True

    def put(self, fn: Callable[..., None], *args: Any) -> None:
        """Queue ``fn(*args)`` for the loop (any thread); RuntimeError once the loop is closed.

        From the loop's own thread (Zenoh runs the callbacks of a ``put`` to a subscriber of the
        same session inside the ``put``: every frame between robots of one process) the drain is
        scheduled with ``call_soon``: no self-pipe write to wake a loop that is awake, and no
        read of it on the next pass."""
        with self._lock:
            self._items.append((fn, args))
            if self._armed:
                return
            self._armed = True
        if threading.get_ident() == self._loop_thread:
            self._loop.call_soon(self._drain)
        else:
            self._loop.call_soon_threadsafe(self._drain)

    def _drain(self) -> None:
        with self._lock:
            items, self._items = self._items, collections.deque()
            self._armed = False
        self._draining = True
        try:
            for fn, args in items:
                try:
                    fn(*args)
                except Exception:  # noqa: BLE001 - one bad call must not lose the others (as call_soon)
                    log.exception("callback %r failed", fn)
        finally:
            self._draining = False
            woken, self._to_wake = self._to_wake, []
            if len(woken) > 1:
                woken.sort(key=_shell_id)
            for shell in woken:
                shell._wake()


def _shell_id(shell: RobotShell) -> int:
    return shell.me


_INBOXES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _inbox_for(loop: asyncio.AbstractEventLoop) -> _Inbox:
    """The one inbox of ``loop`` (every robot of the process shares it)."""
    box = _INBOXES.get(loop)
    if box is None:
        box = _INBOXES[loop] = _Inbox(loop)
    return box


class _Fanout:
    """One Zenoh subscriber per neighbour key for all the robots of a shared session.

    With one subscriber per robot, a frame of robot j reaches a process hosting K of j's
    neighbours as K Zenoh callbacks (each a GIL hand-over from Zenoh's thread and a payload
    copy). Here it is one callback, one copy and one inbox entry; the loop hands the same bytes
    to each of the K robots (whose decoders then share the parse, protocol.frames). The frames
    still cross Zenoh; what is shared is the delivery inside the process.
    """

    def __init__(self, session: Any) -> None:
        self._session = session
        self._subs: dict[str, Any] = {}
        self._shells: dict[str, tuple[RobotShell, ...]] = {}

    def subscribe(self, key: str, j: int, shell: RobotShell) -> _FanoutHandle:
        """Deliver ``j``'s frames on ``key`` to ``shell`` (loop thread); undeclare the handle."""
        self._shells[key] = (*self._shells.get(key, ()), shell)
        if key not in self._subs:
            self._subs[key] = self._session.declare_subscriber(
                key, zenoh_callback(lambda sample, key=key, j=j: self._on_sample_thread(key, j, sample)))
        return _FanoutHandle(self, key, shell)

    def _on_sample_thread(self, key: str, j: int, sample: Any) -> None:
        shells = self._shells.get(key, ())
        if not shells:
            return
        try:
            shells[0]._inbox.put(self._deliver, key, j, sample.payload.to_bytes())
        except RuntimeError:  # loop closed while shutting down
            pass

    def _deliver(self, key: str, j: int, data: bytes) -> None:
        shells = self._shells.get(key, ())
        if not shells:
            return
        if not isinstance(shells[0], RobotShell):  # free robots (agents/free_robot.py)
            for shell in shells:
                shell._on_raw(j, data)
            return
        # one clock read and one pair of profile timers per frame and process, not per robot
        # (at 32 robots in 2 processes: ~650 deliveries a round and process)
        tt = shells[0]._tt
        t, c = _pc(), tt()
        clock = shells[0].clock
        now = clock()
        for shell in shells:
            shell._receive_frame(j, data, now if shell.clock is clock else shell.clock())
        dt, dc = (_pc() - t) / len(shells), (tt() - c) / len(shells)
        for shell in shells:
            prof = shell.profile
            prof["receive"] += dt
            prof["receive:cpu"] += dc

    def unsubscribe(self, key: str, shell: RobotShell) -> None:
        """Stop delivering ``key`` to ``shell``; the last one out undeclares the subscriber."""
        left = tuple(s for s in self._shells.get(key, ()) if s is not shell)
        self._shells[key] = left
        if not left:
            sub = self._subs.pop(key, None)
            if sub is not None:
                sub.undeclare()


class _FanoutHandle:
    """A robot's share of a :class:`_Fanout` subscriber, undeclared like a Zenoh subscriber."""

    def __init__(self, fanout: _Fanout, key: str, shell: RobotShell) -> None:
        self._fanout, self._key, self._shell = fanout, key, shell

    def undeclare(self) -> None:
        self._fanout.unsubscribe(self._key, self._shell)


# --------------------------------------------------------------------------- the shell


class RobotShell:
    """One running robot: Zenoh plumbing, time and files around its :class:`RobotSession`;
    use :func:`run_robot`."""

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
        status_interval_s: float = 0.0,
        crash_at: int | None = None,
        checkpoint_every: int = 1,
        resume_round: int | None = None,
    ) -> None:
        """``checkpoint_every`` > 1 (a process hosting the whole fleet, :func:`run_robots`): the
        checkpoint is written before the rounds that are multiples of it only; ``resume_round``:
        resume from the checkpoint at that round (:func:`fleet_resume_round`), not the newest."""
        self.spec = spec
        self.checkpoint_every = max(1, int(checkpoint_every))
        self._resume_round = resume_round
        self.crash_at = crash_at  # fault injection: SIGKILL this process on reaching that round
        self.me = int(robot_id)
        self.connect = list(connect)
        self.zenoh_config = zenoh_config
        self.checkpoint_path = None if checkpoint_path is None else Path(checkpoint_path)
        self.result_path = None if result_path is None else Path(result_path)
        self.status_stream = status_stream
        self.status_interval_s = float(status_interval_s)
        self._status_at = float("-inf")
        self.clock = clock
        env = self._read_own_checkpoint()
        self._writer = None if self.checkpoint_path is None else CheckpointWriter(
            self.checkpoint_path, keep_round=None if env is None else resume_round)
        self._checkpoints = 0 if env is None else int(env.get("n", 0))
        core = build(spec, self.me) if env is None else restore(spec, self.me, env["core"])
        if core.robot_id != self.me:
            raise ValueError(f"core is robot {core.robot_id}, shell is robot {self.me}")
        self.core = core
        self._t0 = clock()
        self.session = RobotSession.for_spec(spec, core, now=self._t0, link_checks=True, resume=env)
        if env is not None:
            log.info("robot %d: restored from %s at round %d (restart %d)",
                     self.me, self.checkpoint_path, core.round, self.session.restarts)
        self.links = LinkLayer(spec.faults, spec.seed)
        self._clean_links = spec.faults.is_clean
        self.received = 0  # raw samples delivered by Zenoh, before the fault link
        self._subs: dict[int, Any] = {}
        self._n_dropped = len(self.session.neighbours_dropped)
        self._router_ids: set[str] = set()
        self._waiter: asyncio.Future | None = None  # set while the main loop sleeps
        self._timer: asyncio.TimerHandle | None = None  # the pending wake-up at a deadline (`_wait_kept`)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._inbox: _Inbox | None = None  # the loop's (run)
        self._closing = False
        self._pub: Any = None
        # Where the time goes (perf_counter seconds by phase) and when things happened (monotonic
        # clock, comparable across processes): benchmarks/round_cost.py reads it (profile_path).
        self.profile: dict[str, float] = dict.fromkeys(PROFILE_KEYS, 0.0)
        self._prof_first = self._prof_last = self.profile
        self._rounds_done = 0
        # The main thread's CPU per phase and the per-round marks cost ~10 us of system calls a
        # robot-round (thread_time, os.times): only with SHAPEFLEET_PROFILE, which writes them.
        self._profiling = bool(os.environ.get("SHAPEFLEET_PROFILE"))
        self._tt: Callable[[], float] = _tt if self._profiling else _pc
        self._passes = 0  # times the main loop slept and woke (benchmarks/round_cost.py: per round)
        self.marks: dict[str, float] = {**{k: v for k, v in _STARTED.items() if v is not None},
                                        "shell": time.monotonic()}

    def _read_own_checkpoint(self) -> dict[str, Any] | None:
        """This robot's checkpoint envelope if there is one (ValueError if it is another's)."""
        path, spec = self.checkpoint_path, self.spec
        if path is None or not checkpoint_exists(path):
            return None
        env = read_checkpoint(path, at_round=self._resume_round)
        if env.get("fleet") != spec.fleet or env.get("robot") != self.me or env.get("cfg") != spec.config_tag:
            raise ValueError(
                f"checkpoint {path} belongs to fleet {env.get('fleet')!r} robot "
                f"{env.get('robot')!r} (config {bytes(env.get('cfg') or b'').hex()}), not to fleet "
                f"{spec.fleet!r} robot {self.me} (config {spec.config_tag.hex()})"
            )
        return env

    @property
    def round_times(self) -> list[float]:
        """Clock seconds of each advance-to-advance interval (the session's)."""
        return self.session.round_intervals

    def _transport(self) -> dict[str, int]:
        """What Zenoh and the fault link did to frames into this robot (since this process started)."""
        st = self.links.stats()
        return {"received": self.received, "lost": st["dropped"], "duplicated": st["duplicated"]}

    # ---------------------------------------------------------------- receive path

    def _on_sample_thread(self, j: int, sample: Any) -> None:
        """Zenoh callback thread: copy the payload out and hand it to the loop."""
        if self._closing:
            return
        try:
            self._inbox.put(self._on_raw, j, sample.payload.to_bytes())
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
            self._inbox.put(self._on_alive, j, appeared)
        except RuntimeError:
            pass

    def _on_alive(self, j: int, appeared: bool) -> None:
        now = self.clock()
        if appeared:
            self.session.peer_up(j, now)
        elif j in self.session.peers:
            self.session.peer_gone(j, now)
            log.info("robot %d: neighbour %d left (liveliness token gone)", self.me, j)
            # Was it our router that went (every token goes with it)? Look now, so that a
            # reconnection later counts as fresh evidence time.
            self._report_link(now)
        self._wake()

    def _on_raw(self, j: int, data: bytes) -> None:
        if self._closing:
            return
        t, c = _pc(), self._tt()
        self._receive_frame(j, data, self.clock())
        self.profile["receive"] += _pc() - t
        self.profile["receive:cpu"] += self._tt() - c

    def _receive_frame(self, j: int, data: bytes, now: float) -> None:
        """A frame on ``j``'s key at ``now``: through the fault link (if any) to the session."""
        if self._closing:
            return
        self.received += 1
        if self._clean_links:  # nothing to delay, drop or copy: straight to the session
            s = self.session
            asked = s.asking_resend()
            self._feed(j, data, now)
            # Wake the main loop only if this frame can change what it does next: the core can
            # advance, a neighbour asks for a resend (its deadline may come sooner), or the
            # linger may end. Anything else only moves deadlines later (a neighbour heard from):
            # the loop wakes at its old deadline and looks again. At 32 robots this avoids ~5 of
            # ~6 wake-ups per robot-round (results/round_cost.md, branch shellcost).
            if s.ready() or s.lingering or s.asking_resend() != asked:
                box = self._inbox
                if box is None or not box.wake_later(self):  # in a drain: woken at its end, in id order
                    self._wake()
            return
        self.links.send(j, self.me, data, now)
        self._pump(now)
        # A delayed copy may now be due before the main loop's current deadline: wake it so that
        # it re-reads links.next_due().
        self._wake()

    def _pump(self, now: float) -> None:
        """Hand every frame the fault links deliver by ``now`` to the session."""
        for src, _dst, payload in self.links.deliver(now):
            self._feed(src, payload, now)

    def _feed(self, src: int, payload: bytes, now: float) -> None:
        out = self.session.receive(src, payload, now)
        if isinstance(out, Rejected):
            log.debug("robot %d: rejected frame on %d's key: %s (%s)", self.me, src, out.reason, out.detail)

    # ---------------------------------------------------------------- send path, files, status

    def _send(self, now: float) -> None:
        for _dest, frame in self.session.to_send(now):  # always BROADCAST: one key per robot
            self._pub.put(frame)

    def _checkpoint(self) -> None:
        if self.checkpoint_path is None:
            return
        self._checkpoints += 1
        self._writer.write(
            {"v": CHECKPOINT_VERSION, "n": self._checkpoints, "fleet": self.spec.fleet, "robot": self.me,
             "cfg": self.spec.config_tag, **self.session.checkpoint(self._transport())},
        )

    def _status_line(self, stopped: str | None = None) -> None:
        """One JSON line for the launcher: every round, or at most one per ``status_interval_s``
        (the first round's and the last line always) -- a line costs a pipe write and wakes the
        launcher, about as much as the round itself on a loaded machine."""
        if self.status_stream is None:
            return
        if stopped is None and self.status_interval_s > 0 and not self.core.finished:
            now = time.monotonic()
            if now - self._status_at < self.status_interval_s:
                return
            self._status_at = now
        st = self.core.status()
        residual = st.get("residual")
        residual = float(residual) if residual is not None else None
        c = self.session.counters(self._transport())
        line = {
            "robot": self.me,
            "round": st.get("round", self.core.round),
            "residual": residual if residual is not None and abs(residual) < float("inf") else None,
            "sent": c["sent"],
            "received": c["received"],
            "lost": c["lost"],
            "rejected": sum(self.session.rejected.values()),
            "finished": bool(self.core.finished),
        }
        if stopped is not None:  # the last line: final counters and why the robot stopped
            line["stopped"] = stopped
        try:
            self.status_stream.write(json.dumps(line) + "\n")
            self.status_stream.flush()
        except (BrokenPipeError, ValueError):  # launcher went away / stream closed
            self.status_stream = None

    # ---------------------------------------------------------------- what only Zenoh knows

    def _routers(self) -> set[str] | None:
        """The ids of the routers our session is connected to (None: no session to ask)."""
        session = getattr(self, "_session", None)
        if session is None:
            return None
        try:
            return {str(z) for z in session.info.routers_zid()}
        except Exception:  # noqa: BLE001 - a closing session: treat as disconnected
            return set()

    def _report_link(self, now: float) -> None:
        """Tell the session whether we have a router, and whether it is a new one (a restart)."""
        ids = self._routers()
        up = ids is None or bool(ids)
        reconnected = bool(ids) and ids != self._router_ids
        was = self.session.link_up
        if up and (not was or reconnected):
            log.info("robot %d: connected to a router again", self.me)
        elif not up and was:
            log.warning("robot %d: no router; waiting for it (nobody is dropped meanwhile)", self.me)
        if ids:
            self._router_ids = ids
        self.session.link_status(up, now, reconnected=reconnected)

    def _sync_drops(self) -> None:
        """Unsubscribe from neighbours the session dropped (and say why)."""
        s = self.session
        for j in s.neighbours_dropped[self._n_dropped:]:
            log.warning("robot %d: dropping neighbour %d at round %d: %s", self.me, j, s.dropped_at.get(j, -1),
                        s.drop_reasons.get(j, "restored"))
            sub = self._subs.pop(j, None)
            if sub is not None:
                sub.undeclare()
        self._n_dropped = len(s.neighbours_dropped)

    # ---------------------------------------------------------------- main loop

    def _mark_round(self) -> None:
        """Profile snapshots at the first and the latest round (steady state = their difference)."""
        now = time.monotonic()
        cpu = os.times()
        if "first_round" not in self.marks:
            self.marks["first_round"] = now
            self.marks["process_cpu_first"] = cpu.user + cpu.system
            self._prof_first = dict(self.profile)
        self.marks["last_round"] = now
        self.marks["process_cpu_last"] = cpu.user + cpu.system
        self._prof_last = dict(self.profile)
        self._rounds_done += 1

    def _wake(self, *_: Any) -> None:
        w = self._waiter
        if w is not None and not w.done():
            w.set_result(None)

    async def _wait(self, deadline: float) -> None:
        """Sleep until a frame arrives (``_wake``) or ``deadline`` (clock seconds).

        A bare future plus one timer handle: cheaper than ``asyncio.wait_for(event.wait())``,
        which creates a task per wait (measured: about 0.2 ms per round less on 2 cores).
        (The free-running shell borrows this one; the lockstep loop uses `_wait_kept`.)
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

    async def _wait_kept(self, deadline: float) -> None:
        """`_wait`, with a timer that outlives the wait: a round usually ends by a frame long
        before its deadline (a resend, tens of rounds away), and the next wait keeps a pending
        timer that fires no later than it needs -- no timer made and cancelled per round. One that
        fires early (the deadline moved later meanwhile) only costs a pass of the loop, which then
        waits again (branch hubcost)."""
        loop = self._loop
        timeout = deadline - self.clock()
        if timeout <= 0:
            return
        when = loop.time() + timeout
        timer = self._timer
        if timer is None or timer.when() > when:
            if timer is not None:
                timer.cancel()
            self._timer = loop.call_at(when, self._on_timer)
        self._waiter = waiter = loop.create_future()
        try:
            await waiter
        finally:
            self._waiter = None

    def _on_timer(self) -> None:
        self._timer = None
        self._wake()

    def _cancel_timer(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def _crash_now(self) -> None:
        """The planned crash, at the planned round exactly (a SIGKILL from the launcher lands a
        few rounds late on a fast fleet): checkpoint this round, as the in-process fleet does,
        then die the way a killed process dies -- no result, no goodbye."""
        self._checkpoint()
        self._status_line()  # the launcher learns the round it died at
        os.kill(os.getpid(), signal.SIGKILL)

    async def _drive(self) -> str:
        """Move frames and time between Zenoh and the session until it is done; why it stopped."""
        s = self.session
        clean = self._clean_links  # (clean links: frames go straight to the session, none is ever in them)
        while True:
            now = self.clock()
            if not clean:
                self._pump(now)
            if s.ready():  # false once finished or stopped
                prof, tt = self.profile, self._tt
                t0, c0 = _pc(), tt()
                if self.checkpoint_every == 1 or self.core.round % self.checkpoint_every == 0:
                    self._checkpoint()
                t1, c1 = _pc(), tt()
                advanced = s.advance(now)
                t2, c2 = _pc(), tt()
                prof["checkpoint"] += t1 - t0
                prof["advance"] += t2 - t1
                prof["checkpoint:cpu"] += c1 - c0
                prof["advance:cpu"] += c2 - c1
                if advanced:
                    for _dest, frame in s.queued():  # the loop's next pass runs the timers (to_send)
                        self._pub.put(frame)
                    if self.crash_at is not None and self.core.round >= self.crash_at and not s.done:
                        self._crash_now()
                    t3, c3 = _pc(), tt()
                    self._status_line()
                    prof["send"] += t3 - t2
                    prof["status"] += _pc() - t3
                    prof["send:cpu"] += c3 - c2
                    prof["status:cpu"] += tt() - c3
                    if self._profiling:
                        self._mark_round()
                if s.ready():
                    # Still ready (no neighbours left, or their next values already here): let
                    # other tasks and callbacks run before the next round (costs one loop pass).
                    await asyncio.sleep(0)
                continue
            self._send(now)
            if len(s.neighbours_dropped) != self._n_dropped:
                self._sync_drops()
            if s.link_check_due:
                self._report_link(now)
                continue
            if s.done:
                if s.error is not None:
                    log.error("%s", s.error)
                elif s.stopped == "max_wall":
                    log.warning("robot %d: max_wall_s=%.1fs reached at round %d", self.me,
                                s.timing.max_wall_s, self.core.round)
                self._cancel_timer()
                return str(s.stopped)
            deadline = s.next_deadline()
            due = None if clean else self.links.next_due()
            if due is not None:
                deadline = min(deadline, due)
            t = _pc()
            await self._wait_kept(deadline)
            self.profile["wait"] += _pc() - t
            self._passes += 1

    def result(self, stopped: str | None = None) -> dict[str, Any]:
        """The session's result row as this robot's result file (``row_to_file``, JSON-safe).

        ``stopped``: the shell interrupted the run (a signal) before the session was done.
        """
        now = self.clock()
        if stopped is not None and not self.session.done:
            self.session.interrupt(now)
        return row_to_file(self.session.row(now, self._transport()))

    def config(self) -> Any:
        """This robot's ``zenoh.Config``."""
        if self.zenoh_config is not None:  # e.g. TLS, remote endpoints: built by the caller
            return to_zenoh_config(self.zenoh_config)
        return robot_config(self.connect)

    async def run(self, shared: Any | None = None, fanout: _Fanout | None = None) -> dict[str, Any]:
        """Run to the end. ``shared``: an open Zenoh session several robots of this process use
        (each still with its own publisher, key, subscriptions and liveliness token); it is left
        open. Without it the robot opens (and closes) its own session. ``fanout``: the shared
        session's neighbour subscribers (one per key for every robot of the process)."""
        import zenoh

        self._zenoh = zenoh
        self._loop = asyncio.get_running_loop()
        self._inbox = _inbox_for(self._loop)
        session = shared if shared is not None else await _open_session(self._loop, self.config())
        self._session = session
        self.marks["session_open"] = time.monotonic()
        self._router_ids = self._routers() or set()
        token = None
        alive_subs: list[Any] = []
        try:
            fleet = self.spec.fleet
            for j in self.session.peers:
                if fanout is not None:
                    self._subs[j] = fanout.subscribe(state_key(fleet, j), j, self)
                    continue
                self._subs[j] = session.declare_subscriber(
                    state_key(fleet, j), zenoh_callback(lambda sample, j=j: self._on_sample_thread(j, sample))
                )
            self._pub = session.declare_publisher(
                state_key(fleet, self.me), express=PUBLISH_EXPRESS, congestion_control=zenoh.CongestionControl.DROP
            )
            # the neighbours' tokens only (not the fleet's wildcard): N x degree deliveries at start
            # instead of N x N (1000 robots: 6000 instead of a million, docs/scaling.md)
            on_alive = zenoh_callback(self._on_alive_thread)
            alive_subs = [session.liveliness().declare_subscriber(alive_key(fleet, j), on_alive, history=True)
                          for j in self.session.peers]
            token = session.liveliness().declare_token(alive_key(fleet, self.me))
            self.marks["declared"] = time.monotonic()
            stopped = await self._drive()
            self.marks["done"] = time.monotonic()
            self._status_line(stopped)
            result = self.result()
        finally:
            self._closing = True
            self._cancel_timer()
            for ent in (token, *alive_subs, *self._subs.values(), self._pub):
                if ent is not None:
                    try:
                        ent.undeclare()
                    except Exception:  # noqa: BLE001 - best effort on the way out
                        pass
            if self._writer is not None:
                self._writer.close()
            if shared is None:
                await asyncio.to_thread(session.close)
            self.marks["closed"] = time.monotonic()
        if self.result_path is not None:
            _write_atomic(self.result_path, json.dumps(result, indent=1, default=float).encode())
        self._write_profile()
        return result

    def _write_profile(self) -> None:
        """With ``SHAPEFLEET_PROFILE`` set (any value) and a result file: ``<result>.profile.json``
        with the phase times and marks (not part of the result row, which both shells share)."""
        if self.result_path is None or not os.environ.get("SHAPEFLEET_PROFILE"):
            return
        steady = {k: self._prof_last[k] - self._prof_first[k] for k in PROFILE_KEYS}
        body = {"robot": self.me, "rounds": self._rounds_done, "phases_s": steady, "marks": self.marks,
                "wakeups": self._passes,
                "resends": dict(self.session.resends)}
        _write_atomic(self.result_path.with_name(self.result_path.name + ".profile.json"),
                      json.dumps(body).encode())


async def _open_session(loop: asyncio.AbstractEventLoop, config: Any) -> Any:
    """``zenoh.open`` off the event loop (it blocks: TCP connect, up to the connect timeout)."""
    import zenoh

    opening = loop.run_in_executor(None, zenoh.open, config)
    try:
        return await asyncio.shield(opening)
    except asyncio.CancelledError:  # do not leak a session opened after we were cancelled
        opening.add_done_callback(lambda f: f.cancelled() or f.exception() or f.result().close())
        raise


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
    status_interval_s: float = 0.0,
) -> dict[str, Any]:
    """Run robot ``robot_id`` of ``spec`` until its core finishes or ``spec.timing.max_wall_s``.

    ``connect``: router endpoint(s), e.g. ``["tcp/127.0.0.1:7447"]`` (validated, loopback only).
    ``zenoh_config``: the session configuration as a dict (``protocol.zenoh_config.robot_config_dict``
    with TLS files or ``loopback_only=False``); default ``robot_config(connect)``.
    ``checkpoint_path``: written (crash-safe, :class:`CheckpointWriter`) before every
    ``core.advance()``; if a checkpoint is there at start the robot resumes from it exactly
    (``restarts`` += 1); it must belong to the same fleet, robot and config tag (else ValueError).
    ``result_path``: JSON result written atomically at the end.
    ``status_stream``: one JSON line per round (None: silent; ``status_interval_s`` > 0: at most
    one per that many seconds, plus the first and the last).
    ``build`` / ``restore``: core factories, default ``agents.spec.build_core`` / ``restore_core``.
    ``handle_signals``: on SIGTERM/SIGINT stop cleanly (session closed, result written with
    ``stopped = "signal"``); only for a process that runs its robots in its main thread.

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
        status_interval_s=status_interval_s,
    )
    if not handle_signals or threading.current_thread() is not threading.main_thread():
        return await shell.run()
    out = await _run_shells([shell], handle_signals)
    if isinstance(out[0], BaseException):
        raise out[0]
    return out[0]


async def run_robots(
    spec: Any,
    robot_ids: list[int],
    *,
    connect: list[str],
    workdir: Path | None = None,
    status_stream: TextIO | None = sys.stdout,
    handle_signals: bool = False,
    zenoh_config: Any | None = None,
    status_interval_s: float = 0.0,
    shared_session: bool = False,
    crash_at: int | None = None,
) -> dict[int, dict[str, Any] | BaseException]:
    """Several robots as tasks of this process's event loop, each with its own Zenoh session, key,
    liveliness token, checkpoint and result -- frames between them still cross Zenoh (and the
    router), exactly as between processes. ``workdir``: ``robot-I.ckpt`` / ``robot-I.json`` there.

    ``shared_session``: one Zenoh session for every robot here (each keeps its own publisher,
    key, subscriptions and token): a frame between two robots of this process is delivered by
    Zenoh inside the process, and the router sends each frame once per process instead of once
    per subscribing robot (docs/scaling.md).

    A robot whose core cannot be built (first local solve failed) or whose task fails is reported
    as that exception in the returned dict; the others run on. Everything else as
    :func:`run_robot`, whose signal handling covers every robot here.
    """
    shells: list[RobotShell] = []
    failed: dict[int, BaseException] = {}
    wd = None if workdir is None else Path(workdir)
    # the whole fleet here: checkpoints every few rounds, resumed from one common round
    # (FLEET_CHECKPOINT_EVERY); a planned crash (one robot's process) keeps every round's
    whole = wd is not None and crash_at is None and set(spec.robot_ids) <= set(robot_ids)
    every = fleet_checkpoint_every(len(robot_ids)) if whole else 1
    resume = fleet_resume_round([wd / f"robot-{rid}.ckpt" for rid in robot_ids]) if whole else None
    for rid in robot_ids:
        try:
            shells.append(RobotShell(
                spec, rid, connect=connect,
                checkpoint_path=None if wd is None else wd / f"robot-{rid}.ckpt",
                result_path=None if wd is None else wd / f"robot-{rid}.json",
                status_stream=status_stream, build=_default_build, restore=_default_restore,
                zenoh_config=zenoh_config, status_interval_s=status_interval_s,
                crash_at=crash_at if len(robot_ids) == 1 else None,
                checkpoint_every=every, resume_round=resume))
        except Exception as exc:  # noqa: BLE001 - this robot only; its neighbours will drop it
            log.error("robot %d: cannot start: %s", rid, exc)
            failed[rid] = exc
    session = None
    if shared_session and shells:
        session = await _open_session(asyncio.get_running_loop(), shells[0].config())
    try:
        out = await _run_shells(shells, handle_signals, session) if shells else []
    finally:
        if session is not None:
            await asyncio.to_thread(session.close)
    return {**failed, **{sh.me: res for sh, res in zip(shells, out)}}


async def _run_shells(shells: list[RobotShell], handle_signals: bool, session: Any | None = None) -> list[Any]:
    """Run every shell to its end (results or exceptions, in order); with ``handle_signals``
    SIGTERM/SIGINT stop them all cleanly, each writing a result saying ``stopped = "signal"``."""
    fanout = None if session is None or os.environ.get("SHAPEFLEET_SUBSCRIBER_PER_ROBOT") else _Fanout(session)
    if len(shells) > 1 and not os.environ.get("SHAPEFLEET_NO_PRIME"):
        for sh in shells:  # the robots here need not parse each other's frames (encode_state's prime)
            sh.session.prime_memo = True
    tasks = [asyncio.ensure_future(sh.run(session, fanout)) for sh in shells]
    signals = handle_signals and threading.current_thread() is threading.main_thread()
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    if signals:
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, stop.set)
    stopper = asyncio.ensure_future(stop.wait())
    try:
        pending = set(tasks)
        while pending and not stop.is_set():
            _done, pending = await asyncio.wait(pending | {stopper}, return_when=asyncio.FIRST_COMPLETED)
            pending.discard(stopper)
        return [await _outcome(sh, task) for sh, task in zip(shells, tasks)]
    except asyncio.CancelledError:  # we were cancelled: so are the robots (sessions closed)
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        raise
    finally:
        stopper.cancel()
        if signals:
            for sig in (signal.SIGTERM, signal.SIGINT):
                loop.remove_signal_handler(sig)


async def _outcome(sh: RobotShell, task: asyncio.Future) -> Any:
    """A finished robot's result or exception; a running one is stopped ("signal" result)."""
    if task.done():
        if task.cancelled():
            return asyncio.CancelledError()
        return task.exception() or task.result()
    task.cancel()
    try:
        await task
    except asyncio.CancelledError:
        pass
    res = sh.result("signal")
    if sh.result_path is not None:
        _write_atomic(sh.result_path, json.dumps(res, indent=1, default=float).encode())
    return res


def robot_process_parser(prog: str, doc: str | None, workdir_help: str) -> argparse.ArgumentParser:
    """The arguments every robot process takes, lockstep (this module) or free (agents/free_robot.py):
    which fleet file, which of its robots, which router, where results go."""
    import argparse

    ap = argparse.ArgumentParser(prog=prog, description=(doc or "").strip().splitlines()[0])
    ap.add_argument("--fleet-file", type=Path, required=True)
    who = ap.add_mutually_exclusive_group(required=True)
    who.add_argument("--id", dest="ids", help="one robot id")
    who.add_argument("--ids", help="comma-separated robot ids, e.g. 0,1,2")
    ap.add_argument("--connect", action="append", required=True)
    ap.add_argument("--workdir", type=Path, required=True, help=workdir_help)
    ap.add_argument("--shared-session", action="store_true", help="one Zenoh session for the robots here")
    ap.add_argument("--parent-pid", type=int, default=None,
                    help="stop (as on SIGTERM) when this process is no longer our parent (the launcher is gone)")
    return ap


def watch_parent(parent_pid: int | None, period_s: float = 0.5) -> None:
    """When ``parent_pid`` stops being this process's parent (a launcher killed by SIGKILL cannot
    stop its robots), SIGTERM ourselves: the robots stop as on any SIGTERM, results written with
    ``stopped = "signal"``, instead of waiting up to ``max_wall_s`` for a router that died with
    the launcher. A daemon thread; it sends nothing and ends with the process."""
    if parent_pid is None:
        return

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(period_s)
        log.warning("launcher (pid %d) gone: stopping", parent_pid)
        os.kill(os.getpid(), signal.SIGTERM)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def robot_ids_of(spec: Any, ids_text: str, fleet_file: Path) -> list[int]:
    """The robot ids of ``--id``/``--ids``, each one of the fleet file's (ValueError otherwise)."""
    ids = [int(x) for x in ids_text.split(",") if x.strip()]
    bad = [i for i in ids if i not in spec.robots]
    if bad or not ids:
        raise ValueError(f"--ids: robot {bad[0] if bad else ids_text!r} is not in {fleet_file}")
    return ids


def main(argv: list[str] | None = None) -> int:
    """``python -m agents.robot --fleet-file F --ids 0,1 --connect EP --workdir W``: the robot
    process ``shapefleet launch`` starts (one or several robots). Only what a robot needs is
    imported (not the launcher's scenario, topology and plotting modules). Exit 0 when every robot
    here finished converged, 1 otherwise, 2 on bad arguments."""
    ap = robot_process_parser("python -m agents.robot", main.__doc__, "robot-I.ckpt / robot-I.json go here")
    ap.add_argument("--status-interval", type=float, default=0.0, help="seconds between status lines (0: every round)")
    ap.add_argument("--allow-remote", action="store_true", help="a router beyond loopback (multi-host)")
    ap.add_argument("--crash-at", type=int, help="fault injection: SIGKILL this (one-robot) process on reaching this round")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="robot %(message)s", stream=sys.stderr)
    watch_parent(args.parent_pid)
    from agents.spec import FleetSpec

    _STARTED["algorithms_imported"] = time.monotonic()

    try:
        spec = FleetSpec.load(args.fleet_file)
        ids = robot_ids_of(spec, args.ids, args.fleet_file)
        config = robot_config_dict_for(args.connect, loopback_only=not args.allow_remote)
        if args.crash_at is not None and len(ids) != 1:
            raise ValueError("--crash-at: a planned crash takes one robot's process (give --id)")
    except ValueError as exc:
        print(f"shapefleet robot: {exc}", file=sys.stderr)
        return 2
    run = run_robots(spec, ids, connect=args.connect, workdir=args.workdir, handle_signals=True,
                     zenoh_config=config, status_interval_s=args.status_interval,
                     shared_session=args.shared_session, crash_at=args.crash_at,
                     status_stream=sys.stdout)  # today's (a forked robot's is new: launcher/fleet.py)
    results = _profiled(asyncio.run, run, args.workdir / f"robots-{ids[0]}-{ids[-1]}.cprofile")
    ok = True
    for rid in ids:
        res = results[rid]
        if isinstance(res, BaseException):
            print(f"shapefleet: robot {rid}: {res}", file=sys.stderr)
            ok = False
            continue
        if res.get("error"):
            print(f"shapefleet: {res['error']}", file=sys.stderr)
        ok = ok and res.get("stopped") == "finished" and res.get("converged", True) is not False
    return 0 if ok else 1


def _profiled(fn: Callable[..., Any], arg: Any, path: Path) -> Any:
    """``fn(arg)``, under cProfile when ``SHAPEFLEET_CPROFILE`` is set (stats dumped to ``path``,
    for ``python -m pstats``): where the event loop thread of a robot process spends its time
    (the hand-over from Zenoh's threads is seen, their own work is not)."""
    if not os.environ.get("SHAPEFLEET_CPROFILE"):
        return fn(arg)
    import cProfile

    prof = cProfile.Profile()
    try:
        return prof.runcall(fn, arg)
    finally:
        prof.dump_stats(path)


def robot_config_dict_for(connect: list[str], *, loopback_only: bool = True) -> dict[str, Any]:
    """The client configuration of ``connect`` (ValueError naming a bad endpoint)."""
    from protocol.zenoh_config import robot_config_dict

    return robot_config_dict(connect, loopback_only=loopback_only)


def run_forked(argv: list[str]) -> int:
    """:func:`main` in a robot process forked from its launcher (launcher/fleet.py ``fork_robot``):
    its marks start at the fork."""
    _STARTED["process"] = _process_start()
    _STARTED["adopted"] = time.monotonic()
    return main(argv)


if __name__ == "__main__":
    code = main()
    # the process ends next: objects in the permanent generation are not walked by the
    # interpreter's last collections (0.06-0.09 s -> 0.02 s of exit, see launcher.cli.freeze_before_exit)
    __import__("gc").freeze()
    raise SystemExit(code)
