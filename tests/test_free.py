"""Free-running sync (issue 13): the relaxed ADMM core, the free session and the in-process run.

The claim under test: robots that never wait and never retransmit, acting on whatever packets
arrived, still reach the exact centralized answer (within 1e-3) with the relaxed ADMM, because
a lost packet is a skipped update and old or duplicated packets are dropped by sequence number.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from agents.pdmm import Packet, RelaxedADMM, RelaxedADMMParams
from launcher.report import agreement_verdict
from launcher.simulate import ClockModel, simulate_free
from protocol.free import FreeSession
from protocol.links import LinkFaults

from .conftest import make_run, max_function_error

BOUND = 1e-3  # every robot's function error against the certified central solve


def _core(spec, rid, **params):
    return RelaxedADMM(spec.share(rid), RelaxedADMMParams(**params))


def _agree(spec, robots):
    b = spec.basis

    def pair(r, s):
        return b.function_error(b.c_from_x(np.asarray(r["x"])), r["gamma"], b.c_from_x(np.asarray(s["x"])), s["gamma"])

    return agreement_verdict(robots, pair, tol=BOUND)


def test_free_run_under_loss_and_delay_reaches_the_exact_answer(default_run):
    world, spec, central = default_run
    assert central.solved and central.certified
    faulty = dataclasses.replace(spec, faults=LinkFaults(loss=0.3, delay=0.02))
    out = simulate_free(faulty, max_virtual_s=30.0)
    assert all(r["stopped"] == "finished" and r["converged"] for r in out.robots), [r["stopped"] for r in out.robots]
    assert max_function_error(spec, central, out.robots) < BOUND
    assert _agree(spec, out.robots)["converged"]
    assert out.link_stats["dropped"] > 0.2 * out.link_stats["sent"]  # the loss really happened


def test_free_run_is_reproducible_and_the_seed_moves_the_clocks(default_run):
    _, spec, _ = default_run
    faulty = dataclasses.replace(spec, faults=LinkFaults(loss=0.1, delay=0.005, jitter=0.004, reorder=0.1, duplicate=0.1))
    a = simulate_free(faulty, max_virtual_s=30.0)
    b = simulate_free(faulty, max_virtual_s=30.0)
    assert [r["x"] for r in a.robots] == [r["x"] for r in b.robots] and a.virtual_s == b.virtual_s
    c = simulate_free(dataclasses.replace(faulty, seed=faulty.seed + 1), max_virtual_s=30.0)
    assert c.virtual_s != a.virtual_s
    # reordered and duplicated packets happened and were dropped as old, not applied
    assert sum(r["packets_stale"] for r in a.robots) > 0


def test_old_and_duplicated_packets_are_dropped_by_sequence_number(default_run):
    _, spec, _ = default_run
    core = _core(spec, 0)
    core.tick()
    j = core.neighbours[0]
    v = np.ones(core.dim)
    assert core.receive(Packet(j, 5, v, 2.0 * v, 0))
    z = core._z[j].copy()
    assert not core.receive(Packet(j, 5, v, 7.0 * v, 0))  # duplicate
    assert not core.receive(Packet(j, 3, v, 9.0 * v, 0))  # overtaken by a newer one
    assert np.array_equal(core._z[j], z) and core.stale == 2
    assert core.receive(Packet(j, 6, v, 4.0 * v, 0))
    a = core.params.alpha
    assert np.allclose(core._z[j], (1 - a) * z + a * 4.0 * v)  # the relaxed update


def test_a_lost_packet_is_a_skipped_update_not_a_wrong_one(default_run):
    """Deliver each packet only with probability 1/2, synchronously: still the exact answer."""
    _, spec, central = default_run
    cores = {rid: _core(spec, rid) for rid in spec.robot_ids}
    rng = np.random.default_rng(0)
    for _ in range(3000):
        out = {rid: c.tick() for rid, c in cores.items()}
        for rid, c in cores.items():
            for j, p in zip(c.neighbours, out[rid]):
                if rng.random() < 0.5:
                    cores[j].receive(p)
        if all(c.finished for c in cores.values()):
            break
    rows = [c.result() for c in cores.values()]
    assert all(r["converged"] for r in rows)
    assert max_function_error(spec, central, rows) < BOUND


def _session(spec, rid, period=0.01, now=0.0):
    return FreeSession(_core(spec, rid), fleet=spec.fleet, graph=spec.graph, config_tag=spec.config_tag,
                       period=period, now=now, max_wall_s=5.0, auth=spec.frame_auth(rid))


def test_the_session_ticks_on_its_own_clock_and_never_waits(default_run):
    _, spec, _ = default_run
    s = _session(spec, 0, period=0.01, now=3.0)
    assert s.next_deadline() == 3.0
    assert len(s.tick(3.0)) == 1  # nothing received: it publishes anyway
    assert s.tick(3.005) == []  # not due
    assert s.next_deadline() == pytest.approx(3.01)
    assert len(s.tick(3.01)) == 1 and s.core.ticks == 2
    for k in range(600):  # alone (no neighbour frames) it never finishes; max_wall_s stops it
        s.tick(3.02 + 0.01 * k)
    assert s.done and s.stopped == "max_wall"


def test_forged_and_garbage_frames_are_rejected_and_counted(default_run):
    _, spec, _ = default_run
    s0, s1 = _session(spec, 0), _session(spec, 1)
    frame = s1.tick(0.0)[0][1]
    s0.receive(1, frame, 0.0)
    assert s0.core.applied == 1
    s0.receive(1, b"\x00garbage", 0.0)
    forged = bytearray(frame)
    forged[len(forged) // 2] ^= 0x01  # one bit of the signed frame: the tag to robot 0 fails
    s0.receive(1, bytes(forged), 0.0)
    s0.receive(2, frame, 0.0)  # robot 1's frame on robot 2's key
    assert sum(s0.rejected.values()) == 3 and s0.core.applied == 1
    s0.receive(1, frame, 0.0)  # a replay of an applied frame: stale
    assert s0.stale == 1 and s0.core.applied == 1


def test_clock_model_refuses_bad_values():
    with pytest.raises(ValueError, match="drift"):
        ClockModel(drift=0.7)
    with pytest.raises(ValueError, match="offset_s"):
        ClockModel(offset_s=-1.0)


def test_cli_free_run_converges_and_bad_input_exits_2(tmp_path, capsys):
    import json

    from launcher.cli import main

    out = tmp_path / "run"
    code = main(["simulate", "--sync", "free", "--preset", "paper", "--loss", "0.3", "--delay", "20ms",
                 "--loss-burst", "3", "--out", str(out)])
    result = json.loads((out / "result.json").read_text())
    assert code == 0 and result["converged"] and result["sync"] == "free"
    assert result["free_algorithm"] == "hub"  # the paper preset's fleet is a complete graph
    assert result["metrics"]["function_error"] < BOUND
    assert all(r["frames_rejected"] == 0 for r in result["robots"])  # lingering repeats are not equivocation
    assert result["faults"]["loss_burst"] == 3.0
    for argv, flag in ((["--sync", "free"], "--sync free"), (["--sync", "free", "--preset", "paper", "--crash", "1@5"], "--crash"),
                       (["--loss", "0.9", "--loss-burst", "2"], "--loss-burst"), (["--partition", "0,1/1@2s-5s"], "--partition"),
                       (["--sync", "free", "--preset", "paper", "--free-algorithm", "pdmm"], "--free-algorithm"),
                       (["--sync", "free", "--preset", "paper", "--robots", "4", "--topology", "ring", "--free-algorithm", "hub"],
                        "--free-algorithm hub")):
        with pytest.raises(SystemExit) as exc:
            main(["simulate", *argv, "--out", str(tmp_path / "bad")])
        assert exc.value.code == 2
        err = capsys.readouterr().err
        assert flag in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
        assert not (tmp_path / "bad").exists()



def test_the_fast_gap_is_relative_gap():
    from agents.pdmm import _gap
    from agents.rounds import relative_gap

    rng = np.random.default_rng(0)
    for _ in range(50):
        v, w = rng.normal(size=16), [rng.normal(size=16) for _ in range(3)]
        assert _gap(v, w) == pytest.approx(relative_gap(v, np.array(w)), rel=1e-12)


def test_a_free_run_cut_short_is_not_converged(default_run):
    """Success means agreement: robots stopped by the time cap report no convergence, and the
    launcher's verdict says which robots did not meet their stopping rule."""
    _, spec, _ = default_run
    out = simulate_free(dataclasses.replace(spec, faults=LinkFaults(loss=0.3)), max_virtual_s=0.5)
    assert all(r["stopped"] == "max_wall" and not r["converged"] for r in out.robots)
    verdict = _agree(spec, out.robots)
    assert not verdict["converged"] and "did not meet their stopping rule" in verdict["verdict"]


def test_a_silent_neighbour_is_no_evidence_of_calm(default_run):
    """Robot 2 never speaks (its frames are all lost): robots 0 and 1 may agree with each other but
    never stop as converged, since 2 was not heard within the window."""
    _, spec, _ = default_run
    out = simulate_free(dataclasses.replace(spec, faults=LinkFaults(robot_loss=((2, 1.0),))), max_virtual_s=3.0)
    assert not any(r["converged"] for r in out.robots)
    assert {r["stopped"] for r in out.robots} == {"max_wall"}


def test_free_rows_have_the_session_schema(default_run):
    from protocol.session import ROW_KEYS, row_from_file, row_to_file

    _, spec, _ = default_run
    out = simulate_free(spec, max_virtual_s=30.0)
    for row in out.robots:
        assert set(ROW_KEYS) <= set(row)
        assert row_from_file(row_to_file(row))["x"] == row["x"]


def test_free_algorithm_option_picks_the_relaxed_admm_on_a_complete_graph(tmp_path):
    """--free-algorithm radmm overrides auto's hub (simulate; launch passes it to agents/free_robot.py)."""
    import json

    from launcher.cli import main

    out = tmp_path / "radmm"
    assert main(["simulate", "--sync", "free", "--preset", "paper", "--free-algorithm", "radmm", "--out", str(out)]) == 0
    result = json.loads((out / "result.json").read_text())
    assert result["free_algorithm"] == "radmm" and {r["algorithm"] for r in result["robots"]} == {"radmm"}
    assert result["converged"] and result["metrics"]["function_error"] < BOUND


def test_launch_hands_the_free_algorithm_to_the_robot_processes(capsys):
    """launch's robot command line carries --free-algorithm; the robot process refuses a bad one (exit 2)."""
    import argparse

    from agents import free_robot
    from launcher.cli import _launch_free

    argv = _launch_free(argparse.Namespace(period=0.005, free_algorithm="radmm"))["robot_argv"]
    assert argv[argv.index("--free-algorithm") + 1] == "radmm"
    with pytest.raises(SystemExit) as exc:
        free_robot.main(["--fleet-file", "f.json", "--ids", "0", "--connect", "tcp/127.0.0.1:1", "--workdir", ".",
                         "--period", "0.01", "--free-algorithm", "pdmm"])
    assert exc.value.code == 2 and "--free-algorithm" in capsys.readouterr().err
