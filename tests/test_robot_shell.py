"""The Zenoh robot shell (agents/robot.py) driving a small fake core through a real router.

The fake core is a genuine state machine with the core interface: each round every robot replaces
its vector by the mean of its own and its neighbours' vectors (ids sorted), for K rounds. Its
iterates are computed independently below, so the networked run is checked for *exact* equality.

Everything runs on 127.0.0.1 through one router subprocess (multicast scouting off); every process
started here is stopped by its PID in a finally; every test has a hard time limit.
Run this file as a script to get one robot process (used by the crash/restart test).
"""

from __future__ import annotations

import asyncio
import functools
import io
import json
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace

import msgpack
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from agents.robot import CHECKPOINT_VERSION, alive_key, read_checkpoint, run_robot  # noqa: E402
from agents.rounds import RoundCore, check_iterate  # noqa: E402
from protocol.frames import StateUpdate, config_tag, encode_state  # noqa: E402
from protocol.keys import state_key  # noqa: E402
from protocol.links import LinkFaults  # noqa: E402
from protocol.session import SessionTiming  # noqa: E402
from protocol.zenoh_config import free_loopback_port, robot_config, router_endpoint  # noqa: E402
from tests.conftest import start_router  # noqa: E402

pytestmark = pytest.mark.integration
TEST_TIMEOUT_S = 40.0


# ----------------------------------------------------------------------------- fake core


def fast_timing(**changes: float) -> SessionTiming:
    """The fake fleet's short time-outs with ``changes``; linger and give-up derived by the
    session, as for a spec's Timing that does not give them."""
    return SessionTiming.of(SimpleNamespace(**{"retransmit_s": 0.05, "dead_after_s": 5.0, "max_wall_s": 20.0, **changes}))


@dataclass(frozen=True)
class FakeSpec:
    fleet: str
    graph: dict[int, tuple[int, ...]]
    rounds: int
    dim: int = 4
    seed: int = 7
    faults: LinkFaults = field(default_factory=LinkFaults)
    timing: SessionTiming = field(default_factory=fast_timing)
    slow_s: float = 0.0  # sleep per advance (only to give crash tests time); 0 = pure

    @property
    def robot_ids(self) -> tuple[int, ...]:
        return tuple(sorted(self.graph))

    @functools.cached_property
    def config_tag(self) -> bytes:
        return config_tag("averaging", self.rounds, self.dim, self.seed)

    def x0(self, i: int) -> np.ndarray:
        rng = np.random.default_rng([self.seed, i, sum(map(ord, self.fleet))])
        return rng.normal(size=self.dim)


class AveragingCore:
    """x_i <- mean of x_k over k in {i} + neighbours (sorted), K times. Sans-IO."""

    solve_errors = RoundCore.solve_errors  # the core interface: local-solve failures it may raise

    def __init__(self, spec: FakeSpec, robot_id: int) -> None:
        self.spec = spec
        self.robot_id = robot_id
        self.neighbours = tuple(sorted(spec.graph[robot_id]))
        self.dim = spec.dim
        self.round = 0
        self.finished = spec.rounds == 0
        self._x = spec.x0(robot_id)
        self._prev: np.ndarray | None = None
        self._inbox: dict[int, dict[int, np.ndarray]] = {}
        self.dropped: list[int] = []
        self.residual = float("inf")

    def outgoing(self) -> StateUpdate:
        return StateUpdate(self.robot_id, self.round, self._x.copy(), 0,
                           None if self._prev is None else self._prev.copy())

    def divergence(self) -> str | None:
        """The core interface: why its iterate cannot be a result (the shared rule of RoundCore)."""
        return check_iterate(self._x)

    def receive(self, u: StateUpdate) -> None:
        if u.sender not in self.neighbours:
            return
        for rnd, vals in ((u.round, u.values), (u.round - 1, u.prev_values)):
            if vals is not None and rnd in (self.round, self.round + 1):
                self._inbox.setdefault(rnd, {})[u.sender] = vals

    def missing(self) -> tuple[int, ...]:
        have = self._inbox.get(self.round, {})
        return tuple(j for j in self.neighbours if j not in have)

    def ready(self) -> bool:
        return not self.finished and not self.missing()

    def advance(self) -> StateUpdate:
        assert self.ready(), (self.robot_id, self.round, self.missing())
        if self.spec.slow_s:
            time.sleep(self.spec.slow_s)
        theirs = self._inbox.pop(self.round, {})
        vals = {self.robot_id: self._x, **{j: theirs[j] for j in self.neighbours}}
        new = np.mean(np.stack([vals[k] for k in sorted(vals)]), axis=0)
        self.residual = float(np.linalg.norm(new - self._x))
        self._prev, self._x = self._x, new
        self.round += 1
        self._inbox = {r: v for r, v in self._inbox.items() if r >= self.round}
        self.finished = self.round >= self.spec.rounds
        return self.outgoing()

    def drop_neighbour(self, j: int) -> None:
        self.neighbours = tuple(n for n in self.neighbours if n != j)
        self.dropped.append(j)
        for per in self._inbox.values():
            per.pop(j, None)

    def checkpoint(self) -> dict:
        return {
            "round": self.round, "finished": self.finished, "x": self._x.tobytes(),
            "prev": None if self._prev is None else self._prev.tobytes(),
            "neighbours": list(self.neighbours), "dropped": self.dropped, "residual": self.residual,
            "inbox": [[r, j, v.tobytes()] for r, per in self._inbox.items() for j, v in per.items()],
        }

    @classmethod
    def restore(cls, spec: FakeSpec, robot_id: int, ck: dict) -> AveragingCore:
        core = cls(spec, robot_id)
        core.round, core.finished, core.residual = ck["round"], ck["finished"], ck["residual"]
        core._x = np.frombuffer(ck["x"]).copy()
        core._prev = None if ck["prev"] is None else np.frombuffer(ck["prev"]).copy()
        core.neighbours, core.dropped = tuple(ck["neighbours"]), list(ck["dropped"])
        core._inbox = {}
        for r, j, v in ck["inbox"]:
            core._inbox.setdefault(r, {})[j] = np.frombuffer(v).copy()
        return core

    def status(self) -> dict:
        return {"robot": self.robot_id, "round": self.round, "residual": self.residual}

    def result(self) -> dict:
        return {"id": self.robot_id, "x": self._x.tolist(), "rounds": self.round,
                "converged": self.finished, "dropped": list(self.dropped)}


class CrashingCore(AveragingCore):
    """Raises in advance() at round ``crash_at`` (a crash the checkpoint must survive)."""

    crash_at = 5

    def advance(self) -> StateUpdate:
        if self.round == self.crash_at:
            raise RuntimeError("simulated crash")
        return super().advance()


def expected(spec: FakeSpec, graph: dict[int, tuple[int, ...]] | None = None) -> dict[int, np.ndarray]:
    graph = spec.graph if graph is None else graph
    x = {i: spec.x0(i) for i in graph}
    for _ in range(spec.rounds):
        x = {i: np.mean(np.stack([x[k] for k in sorted((i, *graph[i]))]), axis=0) for i in graph}
    return x


LINE3 = {0: (1,), 1: (0, 2), 2: (1,)}


# ----------------------------------------------------------------------------- checkpoint files


def test_checkpoint_survives_a_crash_at_any_step(tmp_path):
    from agents.robot import checkpoint_exists, read_checkpoint, write_checkpoint

    path = tmp_path / "ck"
    assert not checkpoint_exists(path)
    with pytest.raises(ValueError, match="no complete"):
        read_checkpoint(path)
    env = lambda n: {"v": CHECKPOINT_VERSION, "n": n, "core": {"round": n}}  # noqa: E731
    write_checkpoint(path, env(1))
    assert read_checkpoint(path)["n"] == 1 and not (tmp_path / "ck.tmp").exists()
    # crash while writing the tmp file: truncated tmp, old checkpoint intact
    (tmp_path / "ck.tmp").write_bytes(msgpack.packb(env(2))[:-3])
    assert read_checkpoint(path)["n"] == 1
    # crash after the tmp file was complete, before or after the unlink: the newest wins
    (tmp_path / "ck.tmp").write_bytes(msgpack.packb(env(2)))
    assert read_checkpoint(path)["n"] == 2
    path.unlink()
    assert checkpoint_exists(path) and read_checkpoint(path)["n"] == 2
    write_checkpoint(path, env(3))  # the next write cleans up
    assert read_checkpoint(path)["n"] == 3 and not (tmp_path / "ck.tmp").exists()


def test_checkpoint_writer_slots_survive_a_crash_at_any_step(tmp_path):
    """The shell's per-round writer (two slots overwritten in turn): a write cut anywhere leaves
    the previous checkpoint readable; a whole write is the newest; a restart never overwrites it."""
    from agents.robot import CheckpointWriter, _load_envelope, read_checkpoint

    path = tmp_path / "ck"
    env = lambda n: {"v": CHECKPOINT_VERSION, "n": n, "core": {"round": n, "pad": bytes([n]) * (40 - n)}}  # noqa: E731
    w = CheckpointWriter(path)
    for n in (1, 2, 3):
        w.write(env(n))
        assert read_checkpoint(path)["n"] == n
    w.close()
    slots = [path, tmp_path / "ck.tmp"]
    newest = max(slots, key=lambda p: _load_envelope(p)["n"])
    older = next(p for p in slots if p != newest)
    whole = older.read_bytes()
    for frac in (0.05, 0.15, 0.3, 0.99):  # crash in the middle of writing round 4 over round 2
        blob = bytearray(whole)
        older.write_bytes(whole)
        w4 = CheckpointWriter(path)
        w4.write(env(4))
        w4.close()
        four = older.read_bytes()[:12 + len(msgpack.packb(env(4)))]
        assert read_checkpoint(path)["n"] == 4
        cut = int(frac * len(four))
        blob[:cut] = four[:cut]  # the first bytes of round 4 landed over round 2, then SIGKILL
        older.write_bytes(bytes(blob))
        assert read_checkpoint(path)["n"] == 3, cut
    # a restarted robot writes into the slot that does not hold the newest checkpoint
    w5 = CheckpointWriter(path)
    w5.write(env(5))
    w5.close()
    assert read_checkpoint(path)["n"] == 5
    assert _load_envelope(newest)["n"] == 3  # round 3 kept until 5 is whole


def test_checkpoint_of_another_robot_is_refused(tmp_path):
    from agents.robot import RobotShell, write_checkpoint

    spec = FakeSpec("shell-ck", LINE3, rounds=3)
    path = tmp_path / "ck"
    write_checkpoint(path, {"v": CHECKPOINT_VERSION, "n": 1, "fleet": spec.fleet, "robot": 2, "cfg": spec.config_tag,
                            "core": AveragingCore(spec, 2).checkpoint()})
    with pytest.raises(ValueError, match="belongs to fleet 'shell-ck' robot 2"):
        RobotShell(spec, 1, connect=["tcp/127.0.0.1:7447"], checkpoint_path=path, result_path=None,
                   status_stream=None, build=AveragingCore, restore=AveragingCore.restore)


# ----------------------------------------------------------------------------- router fixture


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


@pytest.fixture(scope="module")
def router(tmp_path_factory):
    port = free_loopback_port()
    proc = start_router(tmp_path_factory.mktemp("router"), port, max_wall_s=300)
    try:
        yield router_endpoint(port)
    finally:
        _stop(proc)
    assert proc.returncode == 0, proc.stderr.read().decode()


def _run(spec, i, endpoint, **kw):
    kw.setdefault("status_stream", None)
    kw.setdefault("checkpoint_path", None)
    kw.setdefault("result_path", None)
    kw.setdefault("build", AveragingCore)
    kw.setdefault("restore", AveragingCore.restore)
    return run_robot(spec, i, connect=[endpoint], **kw)


def _assert_exact(results: dict[int, dict], want: dict[int, np.ndarray], rounds: int) -> None:
    for i, res in results.items():
        assert res["rounds"] == rounds, res
        assert res["stopped"] == "finished", res
        np.testing.assert_array_equal(np.array(res["x"]), want[i])


# ----------------------------------------------------------------------------- tests


async def test_three_robots_exact_iterates(router, tmp_path):
    async with asyncio.timeout(TEST_TIMEOUT_S):
        spec = FakeSpec("shell-exact", LINE3, rounds=60)
        streams = {i: io.StringIO() for i in spec.robot_ids}
        paths = {i: tmp_path / f"result-{i}.json" for i in spec.robot_ids}
        out = await asyncio.gather(*(
            _run(spec, i, router, status_stream=streams[i], result_path=paths[i],
                 checkpoint_path=tmp_path / f"ck-{i}.msgpack")
            for i in spec.robot_ids
        ))
        results = dict(zip(spec.robot_ids, out))
        _assert_exact(results, expected(spec), 60)
        for i, res in results.items():
            assert json.loads(paths[i].read_text()) == json.loads(json.dumps(res))
            assert res["frames_rejected"]["total"] == 0 and res["frames_lost"] == 0
            assert res["restarts"] == 0 and res["neighbours_dropped"] == []
            assert res["frames_sent"] >= 61
            lines = [json.loads(x) for x in streams[i].getvalue().splitlines()]
            assert [x["round"] for x in lines[:60]] == list(range(1, 61))
            assert set(lines[0]) >= {"robot", "round", "residual", "sent", "received", "lost", "rejected"}
            ck = read_checkpoint(tmp_path / f"ck-{i}.msgpack")  # the newest of the writer's two slots
            assert ck["core"]["round"] == 59  # written before the last advance


async def test_lossy_delayed_links_still_exact(router):
    """Loss, duplication, delay, jitter and reordering on every receiving link: same iterates."""
    async with asyncio.timeout(TEST_TIMEOUT_S):
        faults = LinkFaults(delay=0.002, jitter=0.001, loss=0.3, duplicate=0.2, reorder=0.2)
        spec = FakeSpec("shell-lossy", LINE3, rounds=30, faults=faults, timing=fast_timing(retransmit_s=0.02))
        out = await asyncio.gather(*(_run(spec, i, router) for i in spec.robot_ids))
        results = dict(zip(spec.robot_ids, out))
        _assert_exact(results, expected(spec), 30)
        assert sum(r["frames_lost"] for r in out) > 0
        assert sum(r["frames_duplicated"] for r in out) > 0


async def test_garbage_is_rejected_and_counted(router):
    import zenoh

    async with asyncio.timeout(TEST_TIMEOUT_S):
        spec = FakeSpec("shell-garbage", LINE3, rounds=20)
        other = FakeSpec("shell-other", LINE3, rounds=20)
        good = StateUpdate(2, 0, np.zeros(spec.dim), 0, None)
        nan_frame = msgpack.unpackb(encode_state(good, fleet=spec.fleet, seq=1, config_tag=spec.config_tag))
        nan_frame["x"] = np.full(spec.dim, np.nan).tobytes()
        garbage = {
            "not-msgpack": b"\xc1garbage",
            "fleet": encode_state(good, fleet=other.fleet, seq=1, config_tag=spec.config_tag),
            "config": encode_state(good, fleet=spec.fleet, seq=1, config_tag=b"12345678"),
            "sender": encode_state(StateUpdate(0, 0, np.zeros(spec.dim), 0, None),
                                   fleet=spec.fleet, seq=1, config_tag=spec.config_tag),
            "vector-length": encode_state(StateUpdate(2, 0, np.zeros(spec.dim + 1), 0, None),
                                          fleet=spec.fleet, seq=1, config_tag=spec.config_tag),
            "non-finite": msgpack.packb(nan_frame),
        }
        session = await asyncio.to_thread(zenoh.open, robot_config([router]))
        try:
            seen = asyncio.Event()
            loop = asyncio.get_running_loop()
            alive = session.liveliness().declare_subscriber(
                alive_key(spec.fleet, 1), lambda s: loop.call_soon_threadsafe(seen.set), history=True)
            pub = session.declare_publisher(state_key(spec.fleet, 2))
            early = [asyncio.ensure_future(_run(spec, i, router)) for i in (0, 1)]
            await seen.wait()  # robot 1 subscribed to robot 2's key; it cannot finish without robot 2
            for payload in garbage.values():
                pub.put(payload)
            await asyncio.sleep(0.2)
            late = await _run(spec, 2, router)
            r0, r1 = await asyncio.gather(*early)
            alive.undeclare()
            pub.undeclare()
        finally:
            await asyncio.to_thread(session.close)
        _assert_exact({0: r0, 1: r1, 2: late}, expected(spec), 20)
        assert r1["frames_rejected"]["by_reason"] == {reason: 1 for reason in garbage}
        assert r1["frames_rejected"]["total"] == len(garbage)
        assert r0["frames_rejected"]["total"] == 0  # robot 0 does not listen to robot 2


async def test_other_fleet_on_same_router_is_not_heard(router):
    async with asyncio.timeout(TEST_TIMEOUT_S):
        a = FakeSpec("shell-fleet-a", LINE3, rounds=40)
        b = FakeSpec("shell-fleet-b", LINE3, rounds=40, seed=8)
        out = await asyncio.gather(*(_run(s, i, router) for s in (a, b) for i in s.robot_ids))
        ra, rb = dict(zip(a.robot_ids, out[:3])), dict(zip(b.robot_ids, out[3:]))
        _assert_exact(ra, expected(a), 40)
        _assert_exact(rb, expected(b), 40)
        for res in out:
            assert res["frames_rejected"]["total"] == 0  # never even delivered
            assert res["frames_received"] == res["frames_accepted"]


async def test_restart_resumes_from_checkpoint(router, tmp_path):
    async with asyncio.timeout(TEST_TIMEOUT_S):
        spec = FakeSpec("shell-restart", LINE3, rounds=25)
        ck = tmp_path / "ck-1.msgpack"
        others = [asyncio.ensure_future(_run(spec, i, router)) for i in (0, 2)]
        with pytest.raises(RuntimeError, match="simulated crash"):
            await _run(spec, 1, router, checkpoint_path=ck, build=CrashingCore)
        assert ck.exists()
        r1 = await _run(spec, 1, router, checkpoint_path=ck)
        r0, r2 = await asyncio.gather(*others)
        _assert_exact({0: r0, 1: r1, 2: r2}, expected(spec), 25)
        assert r1["restarts"] == 1


async def test_silent_neighbour_is_dropped(router):
    async with asyncio.timeout(TEST_TIMEOUT_S):
        spec = FakeSpec("shell-dead", LINE3, rounds=10, timing=fast_timing(dead_after_s=0.5))
        r0, r1 = await asyncio.gather(*(_run(spec, i, router) for i in (0, 1)))  # robot 2 never starts
        _assert_exact({0: r0, 1: r1}, expected(spec, {0: (1,), 1: (0,)}), 10)
        assert r1["neighbours_dropped"] == [2] and r0["neighbours_dropped"] == []


async def test_neighbour_that_dropped_us_is_dropped_too(router):
    """Robot 2 comes too late: robot 1 has dropped it and moved on. Robot 2 keeps hearing robot 1
    (so it is not silent) but at rounds that can never give it what it needs: it drops robot 1
    instead of hanging until max_wall_s. Cut off from every neighbour, it stops "isolated": it
    never declares convergence on its own data."""
    async with asyncio.timeout(TEST_TIMEOUT_S):
        spec = FakeSpec("shell-ahead", LINE3, rounds=150, slow_s=0.005, timing=fast_timing(dead_after_s=0.3))
        early = [asyncio.ensure_future(_run(spec, i, router)) for i in (0, 1)]
        await asyncio.sleep(0.6)
        t = time.monotonic()
        r2 = await _run(spec, 2, router)
        assert time.monotonic() - t < 5
        r0, r1 = await asyncio.gather(*early)
        assert r1["neighbours_dropped"] == [2] and r2["neighbours_dropped"] == [1]
        want = expected(spec, {0: (1,), 1: (0,)})
        _assert_exact({0: r0, 1: r1}, want, 150)
        assert r2["stopped"] == "isolated" and r2["converged"] is False and r2["isolated"] is True
        assert r2["rounds"] == 0 and r2["x"] == spec.x0(2).tolist() and "isolated" in r2["error"]


class FailingCore(AveragingCore):
    """Robot 1's local solve fails at round 3 (SolverError), or its iterate explodes."""

    mode = "solver"

    def advance(self) -> StateUpdate:
        if self.robot_id == 1 and self.round == 3:
            if self.mode == "solver":
                from agents.problem import SolverError

                raise SolverError("piqp returned PIQP_MAX_ITER_REACHED")
            self._x = self._x * 1e80
        return super().advance()


class ExplodingCore(FailingCore):
    mode = "explode"


@pytest.mark.parametrize("core, stopped, words", [(FailingCore, "solver_error", "local solver failed: piqp"),
                                                   (ExplodingCore, "diverged", "diverged: exploding iterate")])
async def test_solver_failure_or_divergence_stops_the_robot_never_converged(router, core, stopped, words):
    """Issue 11: robot 1 stops with a one-line error; its neighbours, cut off from their only
    neighbour once its token is gone, stop isolated: nobody converges on a broken fleet."""
    async with asyncio.timeout(TEST_TIMEOUT_S):
        spec = FakeSpec(f"shell-fail-{stopped}", LINE3, rounds=20, timing=fast_timing(dead_after_s=0.3))
        r0, r1, r2 = await asyncio.gather(*(_run(spec, i, router, build=core) for i in (0, 1, 2)))
        assert r1["stopped"] == stopped and r1["converged"] is False and words in r1["error"]
        assert r1["error"].startswith("robot 1 round ")
        for r in (r0, r2):
            assert r["stopped"] == "isolated" and r["converged"] is False and r["neighbours_dropped"] == [1]


async def test_wall_clock_cap(router):
    async with asyncio.timeout(TEST_TIMEOUT_S):
        spec = FakeSpec("shell-wall", LINE3, rounds=10, timing=fast_timing(dead_after_s=60, max_wall_s=0.5))
        t = time.monotonic()
        stream = io.StringIO()
        res = await _run(spec, 0, router, status_stream=stream)  # robot 1 never comes
        assert time.monotonic() - t < 5
        last = json.loads(stream.getvalue().splitlines()[-1])
        assert last["stopped"] == "max_wall" and last["round"] == 0 and last["residual"] is None
        assert res["stopped"] == "max_wall" and res["converged"] is False and res["rounds"] == 0


# ----------------------------------------------------------------------------- the real core


def _real_spec(fleet: str, faults: LinkFaults | None = None, rounds: int = 120):
    from agents.spec import FleetSpec, RobotSpec
    from agents.spec import Timing as SpecTiming

    rng = np.random.default_rng(3)

    def robot(i: int, neighbours: tuple[int, ...]) -> RobotSpec:
        ang, r = rng.uniform(0, 2 * np.pi, 25), rng.uniform(0.2, 2.0, 25)
        return RobotSpec(i, neighbours, np.c_[r * np.cos(ang), r * np.sin(ang)], np.where(r > 1.0, 1, -1))

    gx, gy = np.meshgrid(np.linspace(-2, 2, 4), np.linspace(-2, 2, 4))
    return FleetSpec(
        fleet=fleet, algorithm="admm", sigma=0.8, C=10.0, grid=np.c_[gx.ravel(), gy.ravel()],
        robots={i: robot(i, nb) for i, nb in LINE3.items()},
        params={"max_rounds": rounds, "tol": 1e-3, "diameter": 2},
        faults=faults or LinkFaults(), seed=11,
        timing=SpecTiming(retransmit_s=0.02, dead_after_s=10.0, max_wall_s=30.0, linger_s=1.0),
    )


def _in_memory(spec) -> dict[int, dict]:
    """Reference: the same cores driven by a perfect in-memory exchange."""
    from agents.spec import build_core
    from tests.conftest import exchange_until_finished

    cores = {i: build_core(spec, i) for i in spec.robot_ids}
    exchange_until_finished(cores, 10 * spec.params["max_rounds"])
    return {i: c.result() for i, c in cores.items()}


def _assert_same_as_reference(results: dict[int, dict], ref: dict[int, dict]) -> None:
    for i, want in ref.items():
        got = results[i]
        assert got["stopped"] == "finished"
        assert (got["rounds"], got["converged"]) == (want["rounds"], want["converged"])
        assert got["x"] == want["x"] and got["gamma"] == want["gamma"]  # bit for bit


@pytest.mark.parametrize(
    "faults",
    [None, LinkFaults(delay=0.001, jitter=0.001, loss=0.2, duplicate=0.1, reorder=0.1)],
    ids=["clean", "lossy"],
)
async def test_real_admm_core_same_iterates_as_in_memory(router, tmp_path, faults):
    async with asyncio.timeout(TEST_TIMEOUT_S):
        spec = _real_spec(f"shell-real-{'lossy' if faults else 'clean'}", faults)
        ref = _in_memory(spec)
        assert all(r["rounds"] >= 20 for r in ref.values())  # a real run, not a trivial one
        out = await asyncio.gather(*(
            run_robot(spec, i, connect=[router], checkpoint_path=tmp_path / f"ck-{i}", result_path=None,
                      status_stream=None)
            for i in spec.robot_ids
        ))
        _assert_same_as_reference(dict(zip(spec.robot_ids, out)), ref)


async def test_real_admm_core_crash_and_restore(router, tmp_path):
    from agents.spec import build_core

    def crashing_build(spec, i):
        core = build_core(spec, i)
        advance = core.advance

        def crash_at_7():
            if core.round == 7:
                raise RuntimeError("simulated crash")
            return advance()

        core.advance = crash_at_7
        return core

    async with asyncio.timeout(TEST_TIMEOUT_S):
        spec = _real_spec("shell-real-crash")
        ref = _in_memory(spec)
        others = [asyncio.ensure_future(run_robot(spec, i, connect=[router], status_stream=None)) for i in (0, 2)]
        with pytest.raises(RuntimeError, match="simulated crash"):
            await run_robot(spec, 1, connect=[router], checkpoint_path=tmp_path / "ck-1",
                            status_stream=None, build=crashing_build)
        r1 = await run_robot(spec, 1, connect=[router], checkpoint_path=tmp_path / "ck-1", status_stream=None)
        r0, r2 = await asyncio.gather(*others)
        _assert_same_as_reference({0: r0, 1: r1, 2: r2}, ref)
        assert r1["restarts"] == 1


@pytest.mark.parametrize(
    "faults",
    [LinkFaults(), LinkFaults(delay=0.001, jitter=0.0005, loss=0.1, duplicate=0.1, reorder=0.1)],
    ids=["clean", "lossy"],
)
async def test_same_results_as_the_in_process_simulator(router, faults):
    """The architecture's contract: both shells drive the same cores to the same iterates."""
    from agents.spec import Timing as SpecTiming
    from launcher.simulate import simulate_fleet
    from launcher.world import Options, build_world

    async with asyncio.timeout(TEST_TIMEOUT_S):
        _world, spec = build_world(Options(
            robots=4, points=15, grid="4x3", sigma=1.0, algorithm="admm", topology="ring", max_rounds=60, faults=faults,
            timing=SpecTiming(retransmit_s=0.02, dead_after_s=10.0, max_wall_s=30.0, linger_s=1.0),
            fleet_id=f"shell-sim-{'clean' if faults.is_clean else 'lossy'}",
        ))
        sim = {r["id"]: r for r in simulate_fleet(spec).robots}
        out = await asyncio.gather(*(run_robot(spec, i, connect=[router], status_stream=None)
                                     for i in spec.robot_ids))
        _assert_same_as_reference(dict(zip(spec.robot_ids, out)), sim)
        # one result row for both shells: same keys, same types (the file read back as a row)
        from protocol.session import ROW_KEYS, row_from_file

        for i, res in zip(spec.robot_ids, out):
            row = row_from_file(res)
            assert set(ROW_KEYS) <= row.keys() and row.keys() == sim[i].keys()
            assert {k: type(v) for k, v in row.items()} == {k: type(v) for k, v in sim[i].items()}
            assert row["trace"] == sim[i]["trace"]


def _robot_cmd(spec_args: list[str], endpoint: str, i: int, tmp: Path) -> list[str]:
    return [sys.executable, __file__, "--robot", str(i), "--connect", endpoint, "--dir", str(tmp), *spec_args]


async def test_processes_crash_and_restart(router, tmp_path):
    """Three robot processes; robot 1 is SIGKILLed mid-run and restarted from its checkpoint."""
    async with asyncio.timeout(TEST_TIMEOUT_S):
        spec = FakeSpec("shell-procs", LINE3, rounds=150, slow_s=0.004)
        args = ["--fleet", spec.fleet, "--rounds", "150", "--slow", "0.004"]
        procs: list[subprocess.Popen] = []
        try:
            for i in spec.robot_ids:
                procs.append(subprocess.Popen(_robot_cmd(args, router, i, tmp_path), cwd=ROOT,
                                              stdout=subprocess.PIPE, stderr=subprocess.PIPE))
            victim = procs[1]
            # wait until robot 1 has done >= 20 rounds (its status lines), then kill it hard
            while True:
                line = await asyncio.to_thread(victim.stdout.readline)
                assert line, victim.stderr.read().decode()
                if json.loads(line)["round"] >= 20:
                    break
            victim.kill()
            victim.wait(5)
            await asyncio.sleep(0.2)
            procs.append(subprocess.Popen(_robot_cmd(args, router, 1, tmp_path), cwd=ROOT,
                                          stdout=subprocess.DEVNULL, stderr=subprocess.PIPE))
            for p in (procs[0], procs[2], procs[3]):
                rc = await asyncio.to_thread(p.wait, 30)
                assert rc == 0, p.stderr.read().decode()
        finally:
            for p in procs:
                _stop(p)
            for p in procs:
                for s in (p.stdout, p.stderr):
                    if s is not None:
                        s.close()
        results = {i: json.loads((tmp_path / f"result-{i}.json").read_text()) for i in spec.robot_ids}
        _assert_exact(results, expected(spec), 150)
        assert results[1]["restarts"] == 1 and results[0]["restarts"] == 0


async def test_process_stops_cleanly_on_sigterm(router, tmp_path):
    import zenoh

    async with asyncio.timeout(TEST_TIMEOUT_S):
        fleet = "shell-sigterm"
        session = await asyncio.to_thread(zenoh.open, robot_config([router]))
        proc = None
        try:
            seen = asyncio.Event()
            loop = asyncio.get_running_loop()
            alive = session.liveliness().declare_subscriber(
                alive_key(fleet, 0), lambda s: loop.call_soon_threadsafe(seen.set), history=True)
            proc = subprocess.Popen(_robot_cmd(["--fleet", fleet, "--rounds", "10"], router, 0, tmp_path),
                                    cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
            await seen.wait()  # robot 0 is up (and waits forever for robot 1)
            proc.send_signal(signal.SIGTERM)
            rc = await asyncio.to_thread(proc.wait, 10)
            assert rc == 0, proc.stderr.read().decode()
            alive.undeclare()
        finally:
            if proc is not None:
                _stop(proc)
                proc.stderr.close()
            await asyncio.to_thread(session.close)
        res = json.loads((tmp_path / "result-0.json").read_text())
        assert res["stopped"] == "signal" and res["converged"] is False and res["rounds"] == 0


def _main() -> None:
    import argparse

    ap = argparse.ArgumentParser()
    ap.add_argument("--robot", type=int, required=True)
    ap.add_argument("--connect", required=True)
    ap.add_argument("--dir", type=Path, required=True)
    ap.add_argument("--fleet", required=True)
    ap.add_argument("--rounds", type=int, required=True)
    ap.add_argument("--slow", type=float, default=0.0)
    a = ap.parse_args()
    spec = FakeSpec(a.fleet, LINE3, rounds=a.rounds, slow_s=a.slow)
    asyncio.run(run_robot(
        spec, a.robot, connect=[a.connect], checkpoint_path=a.dir / f"ck-{a.robot}.msgpack",
        result_path=a.dir / f"result-{a.robot}.json", status_stream=sys.stdout,
        build=AveragingCore, restore=AveragingCore.restore, handle_signals=True,
    ))


if __name__ == "__main__":
    _main()


def test_fanout_one_subscriber_per_key_for_the_robots_of_a_process():
    """Robots sharing a session share one Zenoh subscriber per neighbour key (issue 14): a frame is
    one callback and one inbox entry, handed to every robot that listens to that key, in order;
    a robot that drops the neighbour stops getting it; the last one out undeclares."""
    from agents.robot import _Fanout, _Inbox

    class Sub:
        def __init__(self, key, cb):
            self.key, self.cb, self.undeclared = key, cb, False

        def undeclare(self):
            self.undeclared = True

    class Session:
        def __init__(self):
            self.subs = []

        def declare_subscriber(self, key, cb):
            self.subs.append(Sub(key, cb))
            return self.subs[-1]

    class Payload:
        def __init__(self, data):
            self.data = data

        def to_bytes(self):
            return self.data

    class Sample:
        def __init__(self, data):
            self.payload = Payload(data)

    got = []

    class Shell:
        def __init__(self, me):
            self.me = me

        def _on_raw(self, j, data):
            got.append((self.me, j, data))

    loop = asyncio.new_event_loop()
    try:
        session = Session()
        fan = _Fanout(session)
        a, b = Shell(0), Shell(2)
        a._inbox = b._inbox = _Inbox(loop)
        ha = fan.subscribe("k/1", 1, a)
        hb = fan.subscribe("k/1", 1, b)
        fan.subscribe("k/3", 3, b)
        assert [s.key for s in session.subs] == ["k/1", "k/3"]  # one per key, not per robot
        session.subs[0].cb(Sample(b"f1"))
        session.subs[1].cb(Sample(b"f3"))
        loop.run_until_complete(asyncio.sleep(0))
        assert got == [(0, 1, b"f1"), (2, 1, b"f1"), (2, 3, b"f3")]
        hb.undeclare()  # robot 2 dropped neighbour 1: robot 0 still hears it
        session.subs[0].cb(Sample(b"f1'"))
        loop.run_until_complete(asyncio.sleep(0))
        assert got[3:] == [(0, 1, b"f1'")] and not session.subs[0].undeclared
        ha.undeclare()
        assert session.subs[0].undeclared and not session.subs[1].undeclared
        session.subs[0].cb(Sample(b"late"))  # a sample in flight after the last one left
        loop.run_until_complete(asyncio.sleep(0))
        assert len(got) == 4
    finally:
        loop.close()


def test_a_frame_wakes_the_main_loop_only_when_it_can_change_the_next_step():
    """agents/robot.py `_receive_frame` (issue 14, branch shellcost): with clean links a frame
    resolves the sleeping main loop's waiter only if the core can now advance, the frame asks us
    for a resend (a fast resend may come due sooner), or we linger -- not for every frame (at 32
    robots ~6 wake-ups a round, each a full pass of the loop). Everything else only moves the
    loop's deadlines later; the frame reaches the session either way."""
    from agents.robot import RobotShell

    spec = FakeSpec("shell-wake", LINE3, rounds=3)
    shell = RobotShell(spec, 1, connect=["tcp/127.0.0.1:7447"], checkpoint_path=None, result_path=None,
                       status_stream=None, build=AveragingCore, restore=AveragingCore.restore)
    s = shell.session
    seqs = {0: 0, 2: 0}

    def frame(j: int, rnd: int, need=None) -> bytes:
        x = spec.x0(j)
        seqs[j] += 1
        return encode_state(StateUpdate(j, rnd, x, 0, None if rnd == 0 else x), fleet=spec.fleet, seq=seqs[j],
                            config_tag=spec.config_tag, need=need)

    loop = asyncio.new_event_loop()
    try:
        def deliver(j: int, data: bytes) -> bool:
            """Hand a frame to the shell as its main loop sleeps: did it wake the loop?"""
            shell._waiter = loop.create_future()
            accepted = shell.session.decoder.accepted
            shell._receive_frame(j, data, 1.0)
            assert shell.session.decoder.accepted == accepted + 1  # the session got it either way
            return shell._waiter.done()

        assert not deliver(0, frame(0, 0))  # robot 0's round 0: robot 2's still missing
        assert not s.ready()
        assert deliver(2, frame(2, 0))  # now the core can advance
        assert s.ready() and s.advance(1.0) and shell.core.round == 1
        assert not deliver(0, frame(0, 1, need=()))  # round 1 of robot 0, which lacks nothing
        # robot 2 repeats its round 0, lacking our value of it (ours was lost): answer soon
        assert deliver(2, frame(2, 0, need=(1,)))
        assert deliver(2, frame(2, 1))  # and its round 1: the core can advance again
        assert s.advance(1.0) and shell.core.round == 2
        shell._clean_links = False  # fault links: a delayed copy may be due sooner, always wake
        assert deliver(0, frame(0, 1, need=()))  # (an old round: it changes nothing, still wakes)
    finally:
        loop.close()


@pytest.mark.parametrize("direct", [True, False])
def test_subscriber_callbacks_run_on_zenohs_thread_not_a_thread_each(router, monkeypatch, direct):
    """agents/robot.py `zenoh_callback` (issue 14, branch zenoh32): Zenoh runs the shell's
    subscriber callbacks on its own receiving thread. zenoh-python's default starts a Python
    thread per subscriber and hands every sample to it (a 16-robot process of a 32-robot complete
    graph had 530 threads, one wake-up per frame); ``SHAPEFLEET_ZENOH_INDIRECT=1`` restores it
    (``direct=False`` here: the same check sees the extra threads, so it can fail)."""
    import os
    import threading

    import zenoh

    import agents.robot as robot

    monkeypatch.setattr(robot, "ZENOH_DIRECT_CALLBACKS", direct)
    keys = [f"shapefleet/cb-{direct}/robot/{i}/state" for i in range(24)]
    got: dict[str, str] = {}
    all_in = threading.Event()

    def on_sample(sample) -> None:
        got[str(sample.key_expr)] = type(threading.current_thread()).__name__
        if len(got) == len(keys):
            all_in.set()

    def threads() -> int:
        return len(os.listdir("/proc/self/task"))

    rx = zenoh.open(robot_config([router]))
    tx = zenoh.open(robot_config([router]))
    subs, pubs = [], []
    try:
        before = threads()
        subs = [rx.declare_subscriber(k, robot.zenoh_callback(on_sample)) for k in keys]
        pubs = [tx.declare_publisher(k, express=True) for k in keys]
        for _ in range(50):  # bounded: a put per key per 0.1 s until all arrived (subscriptions propagate)
            for k, p in zip(keys, pubs):
                if k not in got:
                    p.put(b"x")
            if all_in.wait(0.1):
                break
        assert all_in.is_set(), sorted(set(keys) - set(got))
        grown = threads() - before
        if direct:  # Zenoh's own thread (not one Python started), and no thread per subscriber
            assert set(got.values()) == {"_DummyThread"} and grown <= 2, (got, grown)
        else:
            assert grown >= len(keys), grown
    finally:
        for ent in (*subs, *pubs):
            ent.undeclare()
        tx.close()
        rx.close()


def test_a_drain_wakes_the_robots_it_made_ready_in_id_order():
    """agents/robot.py `_Inbox.wake_later` (issue 14, branch shell3): the robots of a process that
    one burst of frames makes ready are woken at the end of the drain in the order of their ids,
    whatever order their last missing frames came in. Woken as the frames came, the robot that
    computed last in a round (its frame completes the others' inputs) computed first in the next:
    each robot's place in the round rotated and its own round times alternated between a fraction
    of the fleet's round and more than a whole one (median 2.0 ms for a mean of 1.6, 3 robots)."""
    from agents.robot import RobotShell, _Inbox

    spec = FakeSpec("shell-order", {0: (1, 2), 1: (0, 2), 2: (0, 1)}, rounds=3)
    loop = asyncio.new_event_loop()
    try:
        inbox = _Inbox(loop)
        shells = {i: RobotShell(spec, i, connect=["tcp/127.0.0.1:7447"], checkpoint_path=None, result_path=None,
                                status_stream=None, build=AveragingCore, restore=AveragingCore.restore)
                  for i in spec.robot_ids}
        woken: list[int] = []
        for i, sh in shells.items():
            sh._inbox = inbox
            sh._waiter = loop.create_future()
            sh._waiter.add_done_callback(lambda _f, i=i: woken.append(i))
        frames = {j: encode_state(StateUpdate(j, 0, spec.x0(j), 0, None), fleet=spec.fleet, seq=1,
                                  config_tag=spec.config_tag) for j in spec.robot_ids}
        # the order in which the fleet's round-0 frames reach each robot: robot 2 is made ready
        # first (by robot 1's frame), then robot 0 and robot 1 (both by robot 2's frame, 0 first)
        for j, i in [(0, 2), (0, 1), (1, 2), (1, 0), (2, 0), (2, 1)]:
            inbox.put(shells[i]._receive_frame, j, frames[j], 1.0)
        assert not inbox.wake_later(shells[0])  # outside a drain the caller wakes at once
        loop.run_until_complete(asyncio.sleep(0.01))
        assert all(sh.session.ready() for sh in shells.values())
        assert woken == [0, 1, 2], woken  # as frames came it would be [2, 0, 1]
    finally:
        loop.close()


def test_a_whole_fleet_process_resumes_every_robot_from_one_common_round(tmp_path):
    """agents/robot.py `fleet_resume_round` (issue 14, branch shell3): a process hosting the whole
    fleet checkpoints every FLEET_CHECKPOINT_EVERY rounds; after a crash every robot resumes from
    the oldest of the robots' newest complete checkpoints, which each of them holds (a torn write
    included), and the writer keeps that slot while it writes the other one first."""
    from agents.robot import CheckpointWriter, _core_round, _load_envelope, fleet_resume_round, read_checkpoint

    env = lambda n, rnd: {"v": CHECKPOINT_VERSION, "n": n, "core": {"round": rnd, "pad": bytes(64)}}  # noqa: E731
    paths = [tmp_path / f"robot-{i}.ckpt" for i in range(3)]
    assert fleet_resume_round(paths) is None  # nothing written: start fresh
    writers = [CheckpointWriter(p) for p in paths]
    for i, w in enumerate(writers):  # every robot wrote rounds 0 and 16; robot 0 also 32
        w.write(env(1, 0))
        w.write(env(2, 16))
    writers[0].write(env(3, 32))
    assert fleet_resume_round(paths) == 16
    assert [int(read_checkpoint(p, at_round=16)["n"]) for p in paths] == [2, 2, 2]
    with pytest.raises(ValueError, match="at round 32"):
        read_checkpoint(paths[1], at_round=32)
    # robot 1's write of round 32 torn by the crash: its newest complete is 16 (its slot of 0 is
    # gone); everyone resumes from 16
    writers[1].write(env(3, 32))
    for w in writers:
        w.close()
    slot = next(p for p in (paths[1], paths[1].with_name(paths[1].name + ".tmp"))
                if _core_round(_load_envelope(p)) == 32)
    slot.write_bytes(slot.read_bytes()[:-10])
    assert fleet_resume_round(paths) == 16
    # robot 0 resumes from 16 although its newest is 32: the writer keeps 16, overwrites 32 first
    w0 = CheckpointWriter(paths[0], keep_round=16)
    w0.write(env(4, 16))
    w0.close()
    rounds = sorted(_core_round(_load_envelope(p)) for p in (paths[0], paths[0].with_name(paths[0].name + ".tmp")))
    assert rounds == [16, 16] and fleet_resume_round(paths) == 16
    # a robot without any checkpoint (it died before its first, round 0): everyone from round 0
    for p in (paths[2], paths[2].with_name(paths[2].name + ".tmp")):
        p.unlink()
    assert fleet_resume_round(paths) == 0


async def test_a_whole_fleet_process_killed_mid_run_resumes_on_the_same_iterates(router, tmp_path):
    """The three robots of a line in one process (shared session, run_robots: what `launch` runs
    for 3 robots) checkpoint every FLEET_CHECKPOINT_EVERY rounds; the process stops dead mid-run
    (every robot at once, no result written) and a new one resumes all three from one common
    round: the same iterates bit for bit as an uninterrupted in-memory run."""
    from agents.robot import FLEET_CHECKPOINT_EVERY, read_checkpoint, run_robots

    async with asyncio.timeout(TEST_TIMEOUT_S):
        spec = _real_spec("shell-real-fleet-crash")
        ref = _in_memory(spec)
        stop_at = FLEET_CHECKPOINT_EVERY + 5
        assert all(r["rounds"] > stop_at + 5 for r in ref.values())

        class Status(io.StringIO):  # stops the process's robots once robot 0 reaches stop_at
            def write(self, line: str) -> int:
                st = json.loads(line)
                if st["robot"] == 0 and st["round"] >= stop_at and not task.done():
                    task.cancel()  # like SIGKILL: no result file, the checkpoints as they are
                return len(line)

        task = asyncio.ensure_future(run_robots(spec, list(spec.robot_ids), connect=[router], workdir=tmp_path,
                                                status_stream=Status(), shared_session=True))
        with pytest.raises(asyncio.CancelledError):
            await task
        assert not list(tmp_path.glob("robot-*.json"))
        rounds = {i: int(read_checkpoint(tmp_path / f"robot-{i}.ckpt")["core"]["round"]) for i in spec.robot_ids}
        assert set(rounds.values()) == {FLEET_CHECKPOINT_EVERY}, rounds  # not every round's
        out = await run_robots(spec, list(spec.robot_ids), connect=[router], workdir=tmp_path,
                               status_stream=None, shared_session=True)
        _assert_same_as_reference(out, ref)
        assert all(r["restarts"] == 1 for r in out.values())


def test_a_checkpoint_of_an_older_format_is_refused_not_read_as_todays(tmp_path):
    """Version 1 checkpoints carry the guard's payload and certificate of before branch certtight (max|phi_i|
    where |u+_l| and g_half stand now): read as today's they would unseat a proven bound, so they are refused."""
    from agents.robot import checkpoint_exists, write_checkpoint

    path = tmp_path / "ck"
    write_checkpoint(path, {"v": CHECKPOINT_VERSION - 1, "n": 1, "core": {"round": 1}})
    assert checkpoint_exists(path)  # (present, but not a usable checkpoint)
    with pytest.raises(ValueError, match=f"no complete shapefleet robot checkpoint.*version {CHECKPOINT_VERSION}"):
        read_checkpoint(path)
