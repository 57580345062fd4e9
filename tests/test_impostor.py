"""Impostors on the fleet's router (issue 11, "Frames that cannot be forged").

* A foreign Zenoh session republishes robot 1's frames on robot 1's key with ``x`` scaled (same
  round, flags, config tag; before frame authentication this gave exit 0, ``converged: true`` and a
  function error of 4.5e77 at 1.02, and a solver crash of every robot at 1.5). Now the fleet ends
  on the exact answer, exit 0, and the robots count the forged frames as ``auth`` rejections.
* A second fleet with the same fleet id on the same router (another launch, hence another fleet
  secret): each fleet rejects the other's frames, and both end on their own exact answers.

Processes are bounded in time and stopped by PID (the launcher's own clean-up; any leftover that
carries the test's tmp folder in its command line is killed by PID and fails the test).
"""

from __future__ import annotations

import json
import os
import queue
import subprocess
import sys
import threading
import time
from pathlib import Path

import msgpack
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from agents.spec import Timing  # noqa: E402
from launcher.fleet import launch_fleet, stop_process  # noqa: E402
from launcher.simulate import simulate_fleet  # noqa: E402
from protocol.keys import state_key  # noqa: E402
from protocol.links import LinkFaults  # noqa: E402
from protocol.zenoh_config import free_loopback_port, robot_config, router_endpoint, to_zenoh_config  # noqa: E402
from tests.conftest import bounded_and_clean, make_run, max_function_error, start_router  # noqa: E402
from tests.test_launch import _assert_gone  # noqa: E402

pytestmark = pytest.mark.integration

TIMING = Timing(retransmit_s=0.02, dead_after_s=6.0, max_wall_s=40.0, linger_s=1.0)
MAX_FORGERIES = 5000  # the impostor's traffic is bounded in count ...
IMPOSTOR_S = 40.0  # ... and in time


@pytest.fixture(autouse=True)
def bounded(tmp_path):
    with bounded_and_clean(str(tmp_path), 90, "impostor test"):
        yield


def forge(payload: bytes, scale: float) -> list[bytes]:
    """Robot 1's frame with x scaled: once keeping its (now wrong) tags, once as a bare frame."""
    sender, body, tags = msgpack.unpackb(payload, raw=False)
    frame = msgpack.unpackb(body, raw=False)
    frame["x"] = (np.frombuffer(frame["x"], "<f8") * scale).astype("<f8").tobytes()
    forged = msgpack.packb(frame, use_bin_type=True)
    return [msgpack.packb([sender, forged, tags], use_bin_type=True), forged]


class Impostor:
    """A Zenoh client on the router that republishes a robot's frames, altered, on that robot's key.

    ``session``: a dict from protocol.zenoh_config (e.g. with TLS files), default a plain loopback
    client of ``endpoint``. It never holds an edge key: only what every fleet file shares.
    """

    def __init__(self, endpoint: str, fleet: str, scale: float, *, robot: int = 1,
                 session: dict | None = None) -> None:
        self.endpoint, self.fleet, self.scale, self.robot = endpoint, fleet, scale, robot
        self.session = session
        self.forged = 0
        self.errors: list[BaseException] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self) -> Impostor:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(20)
        assert not self._thread.is_alive(), "impostor thread did not stop"

    def _run(self) -> None:
        import zenoh

        try:
            deadline = time.monotonic() + IMPOSTOR_S
            session = None
            while session is None:  # the router may not listen yet (CLI launch)
                try:
                    config = (robot_config([self.endpoint]) if self.session is None
                              else to_zenoh_config(self.session))
                    session = zenoh.open(config)
                except Exception:  # noqa: BLE001 - retried until the deadline
                    if time.monotonic() > deadline or self._stop.is_set():
                        raise
                    time.sleep(0.1)
            inbox: queue.Queue[bytes] = queue.Queue(maxsize=1000)
            mine: set[bytes] = set()  # our own puts come back to our subscriber: never re-forge them

            def on_sample(sample) -> None:
                data = sample.payload.to_bytes()
                if data not in mine:
                    try:
                        inbox.put_nowait(data)
                    except queue.Full:
                        pass

            try:
                key = state_key(self.fleet, self.robot)
                sub = session.declare_subscriber(key, on_sample)
                pub = session.declare_publisher(key)
                while not self._stop.is_set() and time.monotonic() < deadline and self.forged < MAX_FORGERIES:
                    try:
                        data = inbox.get(timeout=0.1)
                    except queue.Empty:
                        continue
                    try:
                        fakes = forge(data, self.scale)
                    except Exception:  # noqa: BLE001 - not one of robot 1's frames (ours, or noise)
                        continue
                    for fake in fakes:
                        mine.add(fake)
                        pub.put(fake)
                        self.forged += 1
                sub.undeclare()
                pub.undeclare()
            finally:
                session.close()
        except BaseException as exc:  # noqa: BLE001 - reported by the test
            self.errors.append(exc)


def _cli() -> list[str]:
    script = Path(sys.executable).with_name("shapefleet")
    return [str(script)] if script.exists() else [sys.executable, "-m", "launcher.cli"]


@pytest.mark.parametrize("scale", [1.02, 1.5])
def test_impostor_republishing_robot_1_changes_nothing(tmp_path, scale):
    out = tmp_path / "run"
    port = free_loopback_port()
    fleet = f"impostor-{int(scale * 100)}"
    # 5 ms of link delay: the 121 rounds take ~1 s, so the impostor (which can only connect once the
    # launcher's router listens) forges through the run: without it the rounds took ~0.4 s and it
    # forged 96-246 frames in six runs, sometimes under the bound below
    cmd = [*_cli(), "launch", "--preset", "paper", "--tol", "1e-4", "--delay", "5ms", "--out", str(out),
           "--fleet-id", fleet, "--zenoh-port", str(port)]
    with Impostor(router_endpoint(port), fleet, scale) as impostor:
        proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=80,
                              env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert not impostor.errors, impostor.errors
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr
    result = json.loads((out / "result.json").read_text())
    assert result["converged"] is True
    assert result["metrics"]["function_error"] <= 1e-3, result["metrics"]
    assert impostor.forged > 100  # the impostor really was at work during the run
    rows = {r["id"]: r for r in result["robots"]}
    for i in (0, 2):  # both listen to robot 1's key
        reasons = rows[i]["frames_rejected_by_reason"]
        assert reasons.get("auth", 0) > 0, reasons
        assert set(reasons) == {"auth"}, reasons  # forged frames, nothing else refused
        assert rows[i]["frames_rejected"] == reasons["auth"]
    assert rows[1]["frames_rejected"] == 0  # robot 1 does not listen to its own key


def test_a_second_fleet_with_the_same_id_is_refused_and_changes_nothing(tmp_path):
    """Same fleet id, same robot ids, same router, same time: only the launch (the secret) differs.
    Both fleets' links delay every frame 30 ms, so each run lasts seconds and the twins overlap
    however their processes' start-ups are ordered (undelayed, a ended in ~0.2 s and the twins could
    miss each other; with only a delayed, b -- started second -- still finished before a's robots
    came up once, under a loaded full suite)."""
    specs = {
        "a": make_run(tol=1e-3, fleet_id="twin", timing=TIMING, faults=LinkFaults(delay=0.030)),
        "b": make_run(tol=1e-3, seed=3, points=15, fleet_id="twin", timing=TIMING, faults=LinkFaults(delay=0.030)),
    }
    assert specs["a"][1].secret != specs["b"][1].secret
    want = {k: {r["id"]: r for r in simulate_fleet(s).robots} for k, (_w, s, _c) in specs.items()}
    port = free_loopback_port()
    (tmp_path / "router").mkdir()
    router = start_router(tmp_path / "router", port, max_wall_s=80)
    outs: dict[str, object] = {}
    errors: list[BaseException] = []
    try:
        def run(k: str) -> None:
            try:
                outs[k] = launch_fleet(specs[k][1], workdir=tmp_path / k, crashes=[], restart_after=0.5,
                                       restart=True, zenoh_port=None, progress=False,
                                       router=router_endpoint(port))
            except BaseException as exc:  # noqa: BLE001
                errors.append(exc)

        other = threading.Thread(target=run, args=("a",), daemon=True)
        other.start()
        run("b")
        other.join(60)
        assert not errors and not other.is_alive(), errors
    finally:
        stop_process(router)
        router.stderr.close()
    _assert_gone([router.pid])
    for k, (_world, spec, central) in specs.items():
        robots = outs[k].robots
        _assert_gone(outs[k].pids)
        assert sorted(r["id"] for r in robots) == [0, 1, 2]
        for r in robots:
            w = want[k][r["id"]]
            assert r["stopped"] == "finished" and r["converged"] and r["rounds"] == w["rounds"]
            assert r["x"] == w["x"] and r["gamma"] == w["gamma"]  # bit for bit the fleet's own answer
            reasons = r["frames_rejected_by_reason"]
            assert set(reasons) <= {"auth"}, reasons
        assert max_function_error(spec, central, robots) <= 1e-3
    # the twins overlap in time, so each robot heard (and refused) the other fleet's robots
    assert sum(r["frames_rejected_by_reason"].get("auth", 0) for k in outs for r in outs[k].robots) > 0
