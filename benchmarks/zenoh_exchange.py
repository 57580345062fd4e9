"""Zenoh round exchange: N processes through one loopback router, ms per round.

Each worker process is one "robot" on a complete graph. A round is: publish my round-r frame
(a small binary payload of ``dim`` float64), then wait until every other worker's round-r frame has
arrived. The bare variants have no mathematics and no codec: they are the floor under the robot
shell's per-round latency; the shell variants run ``agents/robot.py`` itself.

Variants measured (each with a fresh router and fresh workers):

* ``asyncio``  -- subscriber callback -> ``loop.call_soon_threadsafe`` -> ``asyncio.Event``,
                  publisher ``express=True``;
* ``asyncio-batched`` -- same, publisher without ``express`` (Zenoh's default batching);
* ``shell``    -- ``agents.robot.RobotShell`` with a trivial averaging core (codec, fault link with no
                  faults, decoder, checkpoint before every round, status accounting): the shell's
                  own cost on top of the bare exchange; ``shell-no-checkpoint`` without checkpoints;
* ``blocking`` -- no event loop: subscriber callback -> ``queue.SimpleQueue`` -> blocking ``get``,
                  ``express=True``.

Everything is bounded: ``--rounds`` rounds, ``--timeout`` seconds per worker, every process is
stopped by its PID. Multicast scouting is off, only 127.0.0.1 is used.

    .venv/bin/python benchmarks/zenoh_exchange.py --robots 3 --rounds 500
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import statistics
import struct
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from protocol.zenoh_config import free_loopback_port, robot_config, router_endpoint  # noqa: E402

HEADER = struct.Struct("<IQ")  # sender, round
RETRANSMIT_S = 0.2  # only if Zenoh lost something (it should not on loopback TCP)


def _key(run: str, i: int) -> str:
    return f"bench/{run}/robot/{i}"


def _alive_key(run: str, i: int) -> str:
    return f"bench/{run}/alive/{i}"


def _payload(i: int, r: int, dim: int) -> bytes:
    return HEADER.pack(i, r) + bytes(8 * dim)


def _wait_peers(session, run: str, me: int, peers: list[int], timeout: float) -> None:
    """Liveliness barrier: declared after my subscribers, seen once the peers' are in place."""
    seen: set[int] = set()
    cond = threading.Condition()

    def on_token(sample):
        j = int(str(sample.key_expr).rsplit("/", 1)[1])
        with cond:
            seen.add(j)
            cond.notify_all()

    sub = session.liveliness().declare_subscriber(f"bench/{run}/alive/*", on_token, history=True)
    try:
        with cond:
            if not cond.wait_for(lambda: set(peers) <= seen, timeout):
                raise TimeoutError(f"worker {me}: peers {sorted(set(peers) - seen)} not seen in {timeout}s")
    finally:
        sub.undeclare()


# ----------------------------------------------------------------------------------- workers


def _declare(session: Any, run: str, me: int, peers: list[int], on_sample: Any, express: bool) -> tuple[list, Any, Any]:
    """A worker's subscriber per peer (``on_sample`` each), its publisher and liveliness token."""
    subs = [session.declare_subscriber(_key(run, j), on_sample) for j in peers]
    pub = session.declare_publisher(_key(run, me), express=express)
    return subs, pub, session.liveliness().declare_token(_alive_key(run, me))


def _publish_rounds(pub: Any, me: int, rounds: int, dim: int) -> Iterator[tuple[int, bytes]]:
    """Publish worker ``me``'s frame of each round in turn; yields (round, frame) for the caller
    to wait on its peers' frames of that round (and resend the frame while it waits)."""
    for r in range(rounds):
        frame = _payload(me, r, dim)
        pub.put(frame)
        yield r, frame


def _time_left(deadline: float, me: int, r: int) -> float:
    """Seconds left before ``deadline``; TimeoutError naming the worker's round when none are."""
    left = deadline - time.monotonic()
    if left <= 0:
        raise TimeoutError(f"worker {me} stuck in round {r}")
    return left


def _undeclare(subs: list, pub: Any, token: Any) -> None:
    """Withdraw what `_declare` declared, before the session closes."""
    token.undeclare()
    for s in subs:
        s.undeclare()
    pub.undeclare()


def worker_asyncio(endpoint: str, run: str, me: int, n: int, rounds: int, dim: int, express: bool, timeout: float):
    import zenoh

    async def main() -> list[float]:
        loop = asyncio.get_running_loop()
        peers = [j for j in range(n) if j != me]
        latest = {j: -1 for j in peers}
        event = asyncio.Event()

        def deliver(data: bytes) -> None:
            j, r = HEADER.unpack_from(data)
            if r > latest.get(j, r):
                latest[j] = r
            event.set()

        def on_sample(sample) -> None:  # zenoh thread
            data = sample.payload.to_bytes()
            try:
                loop.call_soon_threadsafe(deliver, data)
            except RuntimeError:  # loop closed during shutdown
                pass

        session = zenoh.open(robot_config([endpoint]))
        try:
            subs, pub, token = _declare(session, run, me, peers, on_sample, express)
            await asyncio.to_thread(_wait_peers, session, run, me, peers, timeout)
            stamps = []
            deadline = time.monotonic() + timeout
            for r, frame in _publish_rounds(pub, me, rounds, dim):
                while min(latest.values()) < r:
                    event.clear()
                    try:
                        await asyncio.wait_for(event.wait(), min(RETRANSMIT_S, _time_left(deadline, me, r)))
                    except TimeoutError:
                        pub.put(frame)
                stamps.append(time.perf_counter())
            # linger so that slower peers get my last frame even if they lost it
            end = time.monotonic() + 0.3
            while time.monotonic() < end:
                pub.put(_payload(me, rounds - 1, dim))
                await asyncio.sleep(0.05)
            _undeclare(subs, pub, token)
            return stamps
        finally:
            session.close()

    return asyncio.run(main())


def worker_blocking(endpoint: str, run: str, me: int, n: int, rounds: int, dim: int, express: bool, timeout: float):
    import queue

    import zenoh

    peers = [j for j in range(n) if j != me]
    latest = {j: -1 for j in peers}
    inbox: queue.SimpleQueue[bytes] = queue.SimpleQueue()
    session = zenoh.open(robot_config([endpoint]))
    try:
        subs, pub, token = _declare(session, run, me, peers, lambda s: inbox.put(s.payload.to_bytes()), express)
        _wait_peers(session, run, me, peers, timeout)
        stamps = []
        deadline = time.monotonic() + timeout
        for r, frame in _publish_rounds(pub, me, rounds, dim):
            while min(latest.values()) < r:
                try:
                    data = inbox.get(timeout=min(RETRANSMIT_S, _time_left(deadline, me, r)))
                except queue.Empty:
                    pub.put(frame)
                    continue
                j, rr = HEADER.unpack_from(data)
                if rr > latest[j]:
                    latest[j] = rr
            stamps.append(time.perf_counter())
        end = time.monotonic() + 0.3
        while time.monotonic() < end:
            pub.put(_payload(me, rounds - 1, dim))
            time.sleep(0.05)
        _undeclare(subs, pub, token)
        return stamps
    finally:
        session.close()


class _MeanCore:
    """Minimal core for the shell variants: x <- mean of own and neighbours' x, ``rounds`` times."""

    def __init__(self, me: int, n: int, rounds: int, dim: int) -> None:
        import numpy as np

        self.robot_id, self.neighbours, self.dim = me, tuple(j for j in range(n) if j != me), dim
        self.round, self.finished, self._rounds = 0, False, rounds
        self._x, self._prev, self._inbox = np.full(dim, float(me)), None, {}

    def outgoing(self):
        from protocol.frames import StateUpdate

        return StateUpdate(self.robot_id, self.round, self._x, 0, self._prev)

    def receive(self, u) -> None:
        for rnd, v in ((u.round, u.values), (u.round - 1, u.prev_values)):
            if v is not None and rnd in (self.round, self.round + 1) and u.sender in self.neighbours:
                self._inbox.setdefault(rnd, {})[u.sender] = v

    def missing(self):
        have = self._inbox.get(self.round, {})
        return tuple(j for j in self.neighbours if j not in have)

    def ready(self) -> bool:
        return not self.finished and not self.missing()

    def advance(self):
        theirs = self._inbox.pop(self.round, {})
        self._prev, self._x = self._x, (self._x + sum(theirs.values())) / (1 + len(theirs))
        self.round += 1
        self.finished = self.round >= self._rounds
        return self.outgoing()

    def drop_neighbour(self, j: int) -> None:
        self.neighbours = tuple(k for k in self.neighbours if k != j)

    def divergence(self) -> str | None:
        """The shell asks every core whether its function went bad (agents/rounds.py): a mean never does."""
        return None

    def checkpoint(self) -> dict:
        return {"round": self.round, "x": self._x.tobytes(),
                "inbox": [[r, j, v.tobytes()] for r, d in self._inbox.items() for j, v in d.items()]}

    def status(self) -> dict:
        return {"round": self.round, "residual": 0.0}

    def result(self) -> dict:
        return {"rounds": self.round, "converged": self.finished}


def worker_shell(endpoint: str, run: str, me: int, n: int, rounds: int, dim: int, checkpoint: bool, timeout: float):
    """agents/robot.py's shell with a trivial core: the shell's own cost on top of Zenoh."""
    import itertools
    from types import SimpleNamespace

    from agents.robot import RobotShell
    from protocol.links import LinkFaults

    spec = SimpleNamespace(
        fleet=run, config_tag=b"benchmrk", robot_ids=tuple(range(n)), dim=dim, faults=LinkFaults(), seed=0,
        timing=SimpleNamespace(retransmit_s=RETRANSMIT_S, dead_after_s=timeout, max_wall_s=timeout, linger_s=0.5),
    )
    with tempfile.TemporaryDirectory(prefix="zx-ck-") as tmp:
        shell = RobotShell(
            spec, me, connect=[endpoint], checkpoint_path=Path(tmp) / f"ck-{me}" if checkpoint else None,
            result_path=None, status_stream=None, build=lambda _spec, i: _MeanCore(i, n, rounds, dim),
            restore=None,
        )
        res = asyncio.run(shell.run())
    if res["stopped"] != "finished":
        raise RuntimeError(f"shell worker {me} stopped: {res['stopped']}")
    return list(itertools.accumulate(shell.round_times))


VARIANTS = {
    "asyncio": (worker_asyncio, True),
    "asyncio-batched": (worker_asyncio, False),
    "blocking": (worker_blocking, True),
    "shell": (worker_shell, True),
    "shell-no-checkpoint": (worker_shell, False),
}


# ----------------------------------------------------------------------------------- driver


def _stop(proc: subprocess.Popen, grace: float = 3.0) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(grace)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(grace)


def run_variant(variant: str, n: int, rounds: int, dim: int, timeout: float) -> dict:
    port = free_loopback_port()
    endpoint = router_endpoint(port)
    procs: list[subprocess.Popen] = []
    with tempfile.TemporaryDirectory(prefix="zx-") as tmp:
        ready = Path(tmp) / "router.ready"
        env = dict(os.environ, PYTHONPATH=str(ROOT))
        try:
            router = subprocess.Popen(
                [sys.executable, "-m", "launcher.router", "--port", str(port), "--ready-file", str(ready),
                 "--max-wall-s", str(timeout + 30)],
                cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
            )
            procs.append(router)
            t_end = time.monotonic() + 15
            while not ready.exists():
                if router.poll() is not None or time.monotonic() > t_end:
                    raise RuntimeError(f"router did not start: {router.stderr.read().decode()[-2000:]}")
                time.sleep(0.02)
            run = f"r{os.getpid()}x{port}"
            workers = []
            for i in range(n):
                p = subprocess.Popen(
                    [sys.executable, __file__, "--worker", variant, "--endpoint", endpoint, "--run", run,
                     "--me", str(i), "--robots", str(n), "--rounds", str(rounds), "--dim", str(dim),
                     "--timeout", str(timeout)],
                    cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                )
                procs.append(p)
                workers.append(p)
            results = []
            for p in workers:
                out, err = p.communicate(timeout=timeout + 20)
                if p.returncode != 0:
                    raise RuntimeError(f"worker failed ({p.returncode}): {err.decode()[-2000:]}")
                results.append(json.loads(out.decode().strip().splitlines()[-1]))
        finally:
            for p in reversed(procs):
                _stop(p)
    # per-round time at each worker: differences between consecutive round completions,
    # skipping the first 10 rounds (warm-up); total wall time over all rounds as well.
    per_round = []
    totals = []
    for stamps in results:
        d = [b - a for a, b in zip(stamps, stamps[1:])][10:]
        per_round.extend(d)
        totals.append((stamps[-1] - stamps[0]) / max(1, len(stamps) - 1))
    per_round.sort()
    ms = [x * 1e3 for x in per_round]
    return {
        "variant": variant,
        "robots": n,
        "rounds": rounds,
        "mean_ms": statistics.fmean(ms),
        "p50_ms": ms[len(ms) // 2],
        "p95_ms": ms[int(len(ms) * 0.95)],
        "max_ms": ms[-1],
        "rounds_per_s": 1.0 / max(totals),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", type=int, default=3)
    ap.add_argument("--rounds", type=int, default=500)
    ap.add_argument("--dim", type=int, default=65, help="float64 values per frame (grid size + 1)")
    ap.add_argument("--timeout", type=float, default=60.0, help="seconds per worker, hard cap")
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--json", action="store_true", help="print JSON lines instead of a table")
    # worker mode (internal)
    ap.add_argument("--worker", choices=list(VARIANTS))
    ap.add_argument("--endpoint")
    ap.add_argument("--run")
    ap.add_argument("--me", type=int)
    args = ap.parse_args(argv)
    if not 2 <= args.robots <= 16 or not 11 < args.rounds <= 100_000:
        ap.error("need 2..16 robots and 12..100000 rounds")

    if args.worker:
        fn, express = VARIANTS[args.worker]
        stamps = fn(args.endpoint, args.run, args.me, args.robots, args.rounds, args.dim, express, args.timeout)
        print(json.dumps(stamps))
        return 0

    rows = [run_variant(v, args.robots, args.rounds, args.dim, args.timeout) for v in args.variants.split(",")]
    if args.json:
        for r in rows:
            print(json.dumps(r))
        return 0
    print(f"Zenoh round exchange, {args.robots} processes, complete graph, {args.dim} float64/frame, "
          f"one loopback router, {args.rounds} rounds (first 10 skipped)")
    print(f"{'variant':<21}{'mean ms':>9}{'p50 ms':>9}{'p95 ms':>9}{'max ms':>9}{'rounds/s':>10}")
    for r in rows:
        print(f"{r['variant']:<21}{r['mean_ms']:>9.3f}{r['p50_ms']:>9.3f}{r['p95_ms']:>9.3f}"
              f"{r['max_ms']:>9.3f}{r['rounds_per_s']:>10.0f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
