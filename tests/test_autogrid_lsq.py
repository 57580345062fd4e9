"""autogrid --model lsq: the fleet runs the least-squares rule of benchmarks/lsq_emulation.py (its
specification) from its own data -- the same choice of sigma, the exact fit on the chosen lattice --
and the shells' checks. It is autogrid's default model; the SVM model (--model svm) is pinned by
tests/test_autogrid*.py."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest
import shapely

from agents import autogrid_rules, autogrid_sweep
from agents.autogrid_rules import AutoGridParams, coarse_lattice
from agents.kernel import GridBasis
from agents.lsq_model import solve_central_lsq
from agents.spec import Timing, build_core
from launcher import scenario
from launcher.fleet import CrashPlan, launch_fleet
from launcher.simulate import simulate_fleet
from launcher.world import Options, build_world

from .conftest import ROOT, bounded_and_clean, cli_exit_and_stderr, run_to_end

sys.path.insert(0, str(ROOT / "benchmarks"))
import autogrid as bench  # noqa: E402  (padded_bounds: the emulation's IoU raster)
import lsq_emulation as emulation  # noqa: E402

TIMING = Timing(retransmit_s=0.02, dead_after_s=6.0, max_wall_s=40.0, linger_s=1.0)
LETTER_E = dict(robots=5, points=40, shape_file=str(ROOT / "benchmarks" / "outlines" / "letter_e.csv"))


def _spec(**kwargs):
    kwargs.setdefault("fleet_id", "autolsq")
    return build_world(Options(algorithm="autogrid", model="lsq", **kwargs))


def _fleet(world, spec) -> list[dict]:
    cores = [build_core(spec, i) for i in spec.robot_ids]
    run_to_end(cores, limit=spec.autogrid_params.max_total_rounds)
    return [c.result() for c in cores]


def _exact(robots, result: dict):
    """The exact least-squares fit of the robots' rows on the result's grid and sigma."""
    basis = GridBasis(np.asarray(result["grid"]), result["sigma"])
    points = np.vstack([r.points for r in robots])
    labels = np.concatenate([r.labels for r in robots])
    robot_of = np.concatenate([np.full(len(r.labels), r.id) for r in robots])
    return basis, solve_central_lsq(basis, points, labels, result["lsq_lambda"], robot_of=robot_of)


@pytest.mark.parametrize("kwargs", [{}, LETTER_E], ids=["default", "letter_e"])
def test_fleet_makes_the_emulations_choice_and_its_exact_fit(kwargs, monkeypatch):
    world, spec = _spec(**kwargs)
    results = _fleet(world, spec)
    monkeypatch.setattr(emulation, "SVC_KS", ())  # the emulation's least-squares part alone (SVC: 2-4 s)
    row = emulation.one(("world", kwargs, {}))
    first = results[0]
    assert all(r["converged"] and r["x"] == first["x"] and r["sigma"] == first["sigma"] for r in results)
    # every candidate's score is the emulation's exact one (the sweep's fits stop at tol 1e-3), the choice its
    scores = {int(r["divisor"]): r["score"] for r in first["sigma_validation"]}
    assert sorted(scores) == sorted(emulation.CANDIDATES)
    for k, score in scores.items():
        assert score == pytest.approx(row["lsq"][k]["score"], rel=1e-3)
    k = emulation.choice(row)
    lo, hi = world_box(world)
    assert first["sigma"] == pytest.approx(np.hypot(*(hi - lo)) / k, rel=1e-12)
    _, _, lattice = coarse_lattice((lo[0], hi[0], lo[1], hi[1]), first["sigma"], emulation.SPACING,
                                   spec.autogrid_params.max_points)
    np.testing.assert_allclose(first["grid"], lattice, rtol=0, atol=1e-12)
    # the final function: the exact least-squares fit on that grid, within 1e-3; its IoU the emulation's
    basis, ref = _exact(world.robots, first)
    c, gamma = np.asarray(first["c"]), first["gamma"]
    assert basis.function_error(c, gamma, ref.c, ref.gamma) < 1e-3
    q = scenario.make_grid(emulation.RES, emulation.RES, bench.padded_bounds(world.shape))
    truth = shapely.contains_xy(world.shape, q[:, 0], q[:, 1])  # (the emulation's raster and truth)
    inside = basis.decision(q, c, gamma) < 0
    iou = np.count_nonzero(truth & inside) / np.count_nonzero(truth | inside)
    assert iou == pytest.approx(row["lsq"][k]["iou"], abs=1e-3)


def world_box(world) -> tuple[np.ndarray, np.ndarray]:
    points = np.vstack([r.points for r in world.robots])
    return points.min(axis=0), points.max(axis=0)


def test_model_lsq_is_the_default_autogrid():
    """--model lsq writes the parameters the default writes (the same fleet file); --model svm another model."""
    _, default = build_world(Options(fleet_id="m"))
    _, lsq = build_world(Options(fleet_id="m", model="lsq"))
    _, svm = build_world(Options(fleet_id="m", model="svm"))
    assert default.algorithm == "autogrid" and default.autogrid_params == lsq.autogrid_params
    assert default.autogrid_params.lsq and not svm.autogrid_params.lsq


def test_crash_and_restart_in_the_sweep_and_the_fit_end_on_the_clean_answer():
    """A robot killed in the sweep (round 20) and one in the final fit resume from their checkpoints."""
    _, spec = _spec(fleet_id="autolsq-crash", timing=TIMING, topology="ring", robots=4)
    clean = {r["id"]: r for r in simulate_fleet(spec).robots}
    phases = dict(clean[0]["phases"])
    fit_round = phases["admm"] + 5
    out = simulate_fleet(spec, crashes=[CrashPlan(1, 20), CrashPlan(2, fit_round)], restart=True, restart_after=0.5)
    assert [c["fired"] for c in out.crash_log] == [True, True]
    for r in out.robots:
        want = clean[r["id"]]
        assert (r["x"], r["gamma"], r["rounds"], r["sigma"]) == (want["x"], want["gamma"], want["rounds"], want["sigma"])


def test_survivors_of_a_loss_in_the_sweep_fit_their_own_data():
    """Robot 1 dies for good in the sweep of a complete graph: the final fit, built after the loss, weighs lam
    by the robots left and ends on the exact fit of the survivors' rows."""
    world, spec = _spec(fleet_id="autolsq-loss", timing=TIMING, topology="complete", robots=4)
    out = simulate_fleet(spec, crashes=[CrashPlan(1, 20)], restart=False)
    assert [r["id"] for r in out.robots] == [0, 2, 3] and all(r["converged"] for r in out.robots)
    assert dict(out.robots[0]["phases"])["tally"] > 20  # (the loss was in the sweep)
    basis, ref = _exact([r for r in world.robots if r.id != 1], out.robots[0])
    assert max(basis.function_error(np.asarray(r["c"]), r["gamma"], ref.c, ref.gamma) for r in out.robots) < 1e-3


# -- the shells -------------------------------------------------------------------------------------
def test_bad_model_exits_2_naming_the_flag(tmp_path, capsys):
    code, err = cli_exit_and_stderr(["simulate", "--model", "bogus", "--out", str(tmp_path / "x")], capsys)
    assert code == 2 and "--model" in err[-1]


def test_lsq_model_refuses_two_widths_and_a_fixed_grid(tmp_path, capsys):
    """(--C and data without pairs: tests/test_lsq.py, for both lsq fleets)"""
    for flags, named in ((["--narrow-ratio", "3"], "--narrow-ratio"), (["--preset", "paper"], "--model"),
                         (["--rho", "2"], "--rho")):
        code, err = cli_exit_and_stderr(["simulate", "--model", "lsq", *flags, "--out", str(tmp_path / "n")], capsys)
        assert code == 2 and named in err[-1]
    for flags, named in ((["--narrow-ratio", "3"], "--narrow-ratio"), (["--rho", "2"], "--rho")):  # the default model
        code, err = cli_exit_and_stderr(["simulate", *flags, "--out", str(tmp_path / "d")], capsys)
        assert code == 2 and named in err[-1] and "--model svm" in err[-1]


def test_simulate_reports_the_model_its_choice_and_its_exact_reference(tmp_path, capsys):
    code, _ = cli_exit_and_stderr(["simulate", "--lsq-lambda", "0.2", "--out", str(tmp_path / "r")], capsys)  # (the default model)
    result = json.loads((tmp_path / "r" / "result.json").read_text())
    assert code == 0 and result["converged"] and "least squares" in result["model"] and result["lsq_lambda"] == 0.2
    assert len(result["sigma_validation"]) == len(emulation.CANDIDATES)
    assert all(np.isfinite(r["score"]) and r["held_out_pairs"] > 0 for r in result["sigma_validation"])
    world, _ = _spec(lsq_lambda=0.2)
    _, ref = _exact(world.robots, result)
    assert result["central"]["c"] == ref.c.tolist()  # measured against the least-squares fit, not the margin QP
    assert result["metrics"]["function_error"] < 1e-3


@pytest.mark.integration
def test_launch_equals_simulate_bit_for_bit(tmp_path):
    """Real robot processes over Zenoh run the sweep and the fit as `simulate` does, bit for bit."""
    _, spec = _spec(fleet_id="autolsq-launch", timing=TIMING)
    want = {r["id"]: r for r in simulate_fleet(spec).robots}
    with bounded_and_clean(str(tmp_path), 45.0, "autolsq-launch"):
        out = launch_fleet(spec, workdir=tmp_path / "fleet", crashes=[], restart_after=0.5, restart=True,
                           zenoh_port=None, progress=False)
    assert not out.timed_out and sorted(r["id"] for r in out.robots) == sorted(want)
    for r in out.robots:
        w = want[r["id"]]
        assert r["stopped"] == "finished" and (r["rounds"], r["converged"]) == (w["rounds"], True)
        assert (r["x"], r["gamma"], r["sigma"], r["sigma_validation"]) == (w["x"], w["gamma"], w["sigma"],
                                                                            w["sigma_validation"])


# -- issue 10's frame rule --------------------------------------------------------------------------
@pytest.mark.parametrize("hub_frames", [False, True], ids=["sparse", "complete"])
def test_sweep_frames_stay_within_16_function_space_vectors(hub_frames):
    """The default lsq sweep (25 tasks; with the hub's w 6820 floats in one pass) fits 16 (max_points + 1)."""
    params = AutoGridParams(model="lsq", hub_frames=hub_frames)
    assert params.dim <= 16 * (params.max_points + 1)
    assert sum(params.sweep_blocks()) <= params.dim
    groups = {params.sweep_group(fold) for fold in range(params.sweep_folds)}
    assert groups == set(range(params.sweep_groups)) and (params.sweep_groups > 1) == hub_frames


def test_scheduled_sweep_is_the_one_pass_sweep_bit_for_bit(monkeypatch):
    """The tasks sharing a frame sized for three folds round by round (complete graph) give the one-pass
    sweep's scores and fit, bit for bit; every round's blocks are disjoint and within the frame rule."""
    world, spec = _spec()
    params = spec.autogrid_params
    assert params.sweep_groups == 2 and params.dim <= 16 * (params.max_points + 1)
    running, layouts = autogrid_sweep.SigmaSweep._running, []

    def checked(sweep):
        tasks = running(sweep)
        spans = sorted((t.offset, t.offset + sweep._block(t)) for t in tasks)
        assert all(end <= start for (_, end), (start, _) in zip(spans, spans[1:])) and spans[-1][1] <= sweep.dim
        layouts.append(len(tasks))
        return tasks

    monkeypatch.setattr(autogrid_sweep.SigmaSweep, "_running", checked)
    grouped = _fleet(world, spec)
    assert 0 < min(layouts) and max(layouts) < params.sweep_folds * len(params.validate_divisors)  # (shared)
    monkeypatch.undo()
    monkeypatch.setattr(autogrid_rules, "FRAME_BUDGET", 10**6)  # room for every task at once
    assert spec.autogrid_params.sweep_groups == 1
    one_pass = _fleet(world, spec)
    for a, b in zip(grouped, one_pass):
        without_rounds = lambda records: [{k: v for k, v in r.items() if k != "rounds"} for r in records]
        assert without_rounds(a["sigma_validation"]) == without_rounds(b["sigma_validation"])
        assert (a["x"], a["gamma"], a["sigma"]) == (b["x"], b["gamma"], b["sigma"])
        assert a["rounds"] > b["rounds"]  # (a task waits while the frame is full)
