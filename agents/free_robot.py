"""The asyncio shell of a free-running robot over Zenoh (`shapefleet launch --sync free`).

The free twin of agents/robot.py: a thin loop around the sans-IO :class:`protocol.free.FreeSession`
and a free core (agents/pdmm.py, built by ``build_free_core`` exactly as `simulate --sync free`
builds it). It only moves bytes and time:

    zenoh thread --(sample bytes)--> the loop's inbox --> receiver-side fault link (j -> me)
        --> session.receive(j, bytes, now)
    every --period on this robot's own clock (the event loop's): session.tick(now) --> publisher.put

It never waits for a neighbour and never retransmits: a frame lost on the fault link or by Zenoh
is a skipped update of the relaxed ADMM. Faults are injected on the receiving side by the
project's link layer (protocol/links.py), seeded as in lockstep launch. Status lines and the result
file have the lockstep shell's format, so the launcher (launcher/fleet.py) runs both alike; with
``SHAPEFLEET_PROFILE`` set each robot also writes ``robot-I.json.ticks.json`` (the seconds since
its start and the values of every tick, as the lockstep rows' round_times and trace: how
`sweep --over zenoh` and benchmarks/free.py measure the time to 1e-3 across processes).

Run as ``python -m agents.free_robot --fleet-file F --ids 0,1 --connect EP --workdir W --period 0.01``.
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any, TextIO

from agents.pdmm import build_free_core
from agents.robot import (PUBLISH_EXPRESS, RobotShell, _inbox_for, _open_session, _write_atomic,
                          robot_config_dict_for, robot_ids_of, robot_process_parser, watch_parent)
from protocol.free import FreeSession
from protocol.keys import state_key
from protocol.links import LinkLayer
from protocol.session import row_to_file
from protocol.zenoh_config import to_zenoh_config

log = logging.getLogger("shapefleet.free_robot")


class FreeRobotShell:
    """One free-running robot: Zenoh plumbing, its clock and its files around a FreeSession."""

    def __init__(self, spec: Any, robot_id: int, *, period: float, zenoh_config: dict[str, Any],
                 result_path: Path | None = None, status_stream: TextIO | None = None,
                 status_interval_s: float = 0.05, params: dict[str, Any] | None = None,
                 algorithm: str = "auto") -> None:
        self.spec = spec
        self.me = int(robot_id)
        self.clock = time.monotonic
        self.zenoh_config = zenoh_config
        self.result_path = None if result_path is None else Path(result_path)
        self.status_stream = status_stream
        self.status_interval_s = float(status_interval_s)
        self._status_at = float("-inf")
        core = build_free_core(spec, self.me, params, algorithm, period)
        self.session = FreeSession(core, fleet=spec.fleet, graph=spec.graph, config_tag=spec.config_tag,
                                   period=period, now=self.clock(), max_wall_s=spec.timing.max_wall_s,
                                   auth=spec.frame_auth(self.me))
        self.links = LinkLayer(spec.faults, spec.seed)
        self.received = 0
        self._closing = False
        self._waiter: asyncio.Future | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._interrupted = False
        self.ticks: list[list[float]] = []  # [seconds since start, *values] per tick (SHAPEFLEET_PROFILE)
        self._keep_ticks = bool(os.environ.get("SHAPEFLEET_PROFILE"))

    # the lockstep shell's plumbing, which needs only _closing, _inbox, _on_raw, _waiter, _loop, clock
    _on_sample_thread = RobotShell._on_sample_thread  # Zenoh thread -> the loop's inbox
    _wake = RobotShell._wake
    _wait = RobotShell._wait  # until a frame arrives or a deadline: a bare future and one timer

    def _on_raw(self, j: int, data: bytes) -> None:
        if self._closing:
            return
        self.received += 1
        now = self.clock()
        self.links.send(j, self.me, data, now)
        self._pump(now)
        self._wake()  # a delayed copy may be due before the current timer

    def _pump(self, now: float) -> None:
        for src, _dst, payload in self.links.deliver(now):
            self.session.receive(src, payload, now)

    def _transport(self) -> dict[str, int]:
        st = self.links.stats()
        return {"received": self.received, "lost": st["dropped"], "duplicated": st["duplicated"]}

    def interrupt(self) -> None:
        """Stop at the next pass of the loop (SIGTERM): the result says ``stopped = "signal"``."""
        self._interrupted = True
        self._wake()

    # -- status and result -----------------------------------------------------------------------
    def _status_line(self, stopped: str | None = None) -> None:
        """The lockstep shell's status line (round = this robot's tick), at most one per interval."""
        if self.status_stream is None:
            return
        s, core = self.session, self.session.core
        if stopped is None and self.status_interval_s > 0:
            now = time.monotonic()
            if now - self._status_at < self.status_interval_s:
                return
            self._status_at = now
        tr = self._transport()
        residual = float(core.residual)
        line = {"robot": self.me, "round": int(core.ticks), "residual": residual if residual < float("inf") else None,
                "sent": s.sent, "received": tr["received"], "lost": tr["lost"], "rejected": sum(s.rejected.values()),
                "finished": bool(core.finished)}
        if stopped is not None:
            line["stopped"] = stopped
        try:
            self.status_stream.write(json.dumps(line) + "\n")
            self.status_stream.flush()
        except (BrokenPipeError, ValueError):
            self.status_stream = None

    def result(self) -> dict[str, Any]:
        """The session's row as a result file (the lockstep shell's format, ``row_to_file``)."""
        now = self.clock()
        if self._interrupted and not self.session.done:
            self.session.interrupt()
        return row_to_file(self.session.row(now, self._transport()))

    # -- main loop -------------------------------------------------------------------------------
    async def _drive(self, pub: Any) -> str:
        s = self.session
        while not s.done and not self._interrupted:
            now = self.clock()
            self._pump(now)
            for _dest, frame in s.tick(now):
                pub.put(frame)
                if self._keep_ticks and s.stopped in (None, "finished"):
                    self.ticks.append([now - s.t0, *map(float, s.core.values)])
                self._status_line()
            deadline = s.next_deadline()
            if deadline is None:
                break
            due = self.links.next_due()
            await self._wait(deadline if due is None else min(deadline, due))
        if s.error is not None:
            log.error("%s", s.error)
        return "signal" if self._interrupted and s.stopped is None else str(s.stopped)

    async def run(self, shared: Any | None = None) -> dict[str, Any]:
        """Run to the end (finished, max_wall, a failure or a signal); the result (also written)."""
        import zenoh

        self._loop = asyncio.get_running_loop()
        self._inbox = _inbox_for(self._loop)
        session = shared if shared is not None else await _open_session(self._loop, to_zenoh_config(self.zenoh_config))
        subs: list[Any] = []
        pub = None
        try:
            for j in self.session.graph[self.me]:
                subs.append(session.declare_subscriber(state_key(self.spec.fleet, j),
                                                       lambda sample, j=j: self._on_sample_thread(j, sample)))
            pub = session.declare_publisher(state_key(self.spec.fleet, self.me), express=PUBLISH_EXPRESS,
                                            congestion_control=zenoh.CongestionControl.DROP)
            stopped = await self._drive(pub)
            self._status_line(stopped)
            result = self.result()
        finally:
            self._closing = True
            for ent in (*subs, pub):
                if ent is not None:
                    try:
                        ent.undeclare()
                    except Exception:  # noqa: BLE001 - best effort on the way out
                        pass
            if shared is None:
                await asyncio.to_thread(session.close)
        if self.result_path is not None:
            _write_atomic(self.result_path, json.dumps(result, indent=1, default=float).encode())
            if self._keep_ticks:
                _write_atomic(self.result_path.with_name(self.result_path.name + ".ticks.json"),
                              json.dumps({"robot": self.me, "ticks": self.ticks}).encode())
        return result


async def run_free_robots(spec: Any, ids: list[int], *, period: float, workdir: Path,
                          zenoh_config: dict[str, Any], status_interval_s: float = 0.05,
                          shared_session: bool = False, algorithm: str = "auto") -> dict[int, dict[str, Any] | BaseException]:
    """Robots ``ids`` as tasks of this process's loop (one Zenoh session each, or one shared);
    SIGTERM/SIGINT stop them all cleanly, each writing a result saying ``stopped = "signal"``."""
    shells: list[FreeRobotShell] = []
    failed: dict[int, BaseException] = {}
    for rid in ids:
        try:
            shells.append(FreeRobotShell(spec, rid, period=period, zenoh_config=zenoh_config,
                                         result_path=Path(workdir) / f"robot-{rid}.json", status_stream=sys.stdout,
                                         status_interval_s=status_interval_s, algorithm=algorithm))
        except Exception as exc:  # noqa: BLE001 - this robot only (e.g. its first solve failed)
            log.error("robot %d: cannot start: %s", rid, exc)
            failed[rid] = exc
    loop = asyncio.get_running_loop()
    signals = threading.current_thread() is threading.main_thread()
    if signals:
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, lambda: [sh.interrupt() for sh in shells])
    shared = None
    try:
        if shared_session and shells:
            shared = await _open_session(loop, to_zenoh_config(zenoh_config))
        out = await asyncio.gather(*(sh.run(shared) for sh in shells), return_exceptions=True)
    finally:
        if shared is not None:
            await asyncio.to_thread(shared.close)
        if signals:
            for sig in (signal.SIGTERM, signal.SIGINT):
                loop.remove_signal_handler(sig)
    return {**failed, **{sh.me: res for sh, res in zip(shells, out)}}


def main(argv: list[str] | None = None) -> int:
    """The free robot process `shapefleet launch --sync free` starts. Exit 0 when every robot here
    finished converged, 1 otherwise, 2 on bad arguments."""
    ap = robot_process_parser("python -m agents.free_robot", main.__doc__, "robot-I.json goes here")
    ap.add_argument("--period", type=float, required=True, help="seconds between two ticks")
    ap.add_argument("--free-algorithm", default="auto", choices=("auto", "hub", "radmm"),
                    help="the free algorithm (auto: the hub on a complete graph, else the relaxed ADMM)")
    ap.add_argument("--status-interval", type=float, default=0.05, help="seconds between status lines")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="robot %(message)s", stream=sys.stderr)
    watch_parent(args.parent_pid)
    from agents.spec import FleetSpec

    try:
        if not args.period > 0:
            raise ValueError(f"--period: must be positive, got {args.period}")
        spec = FleetSpec.load(args.fleet_file)
        ids = robot_ids_of(spec, args.ids, args.fleet_file)
        config = robot_config_dict_for(args.connect)
    except ValueError as exc:
        print(f"shapefleet robot: {exc}", file=sys.stderr)
        return 2
    results = asyncio.run(run_free_robots(spec, ids, period=args.period, workdir=args.workdir,
                                          zenoh_config=config, status_interval_s=args.status_interval,
                                          shared_session=args.shared_session, algorithm=args.free_algorithm))
    rows = [res for res in results.values() if not isinstance(res, BaseException)]
    for rid, res in sorted(results.items()):
        why = res if isinstance(res, BaseException) else res.get("error")
        if why:
            print(f"shapefleet: robot {rid}: {why}", file=sys.stderr)
    ok = len(rows) == len(ids) and all(r.get("stopped") == "finished" and r.get("converged") is True for r in rows)
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
