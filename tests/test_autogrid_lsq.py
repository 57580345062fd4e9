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
from agents.autogrid_rules import AutoGridParams, coarse_lattice, min_distance
from agents.kernel import GridBasis
from agents.lsq_model import solve_central_lsq
from agents.spec import Timing, build_core
from launcher import scenario
from launcher.fleet import CrashPlan, launch_fleet
from launcher.simulate import simulate_fleet
from launcher.world import Options, build_world

from .conftest import ROOT, bounded_and_clean, cli_exit_and_stderr, run_to_end, step_all

sys.path.insert(0, str(ROOT / "benchmarks"))
import autogrid as bench  # noqa: E402  (padded_bounds: the emulation's IoU raster)
import lsq_emulation as emulation  # noqa: E402

TIMING = Timing(retransmit_s=0.02, dead_after_s=6.0, max_wall_s=40.0, linger_s=1.0)
LETTER_E = dict(robots=5, points=40, shape_file=str(ROOT / "benchmarks" / "outlines" / "letter_e.csv"))
DIGIT_3 = dict(robots=5, points=40, shape_file=str(ROOT / "benchmarks" / "outlines" / "digit_3.csv"))


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


def _cores(world, spec) -> list:
    cores = [build_core(spec, i) for i in spec.robot_ids]
    run_to_end(cores, limit=spec.autogrid_params.max_total_rounds)
    return cores


def _same_points(a, b) -> bool:
    """a and b hold the same points (as sets, to 1e-9)."""
    a, b = np.asarray(a, dtype=float).reshape(-1, 2), np.asarray(b, dtype=float).reshape(-1, 2)
    return len(a) == len(b) and max(min_distance(a, b).max(), min_distance(b, a).max()) < 1e-9


def _data(world):
    """(data box as bounds, its diagonal, every robot's points) as the emulation reads them."""
    lo, hi = world_box(world)
    return (lo[0], hi[0], lo[1], hi[1]), float(np.hypot(*(hi - lo))), np.vstack([r.points for r in world.robots])


@pytest.mark.parametrize("kwargs", [{}, LETTER_E, DIGIT_3], ids=["default", "letter_e", "digit_3"])
def test_fleet_makes_rule_2s_choice_on_its_grid_and_its_exact_fit(kwargs):
    """Rule 2 (benchmarks/lsq_emulation.py near_lattice, choice_near): every candidate's kept nodes are the
    emulation's (the fleet's min_distance marks against its cKDTree, both `<=` 1.5 sigma), its score the exact
    one (the sweep's fits stop at tol 1e-3), the choice on the fleet's scores the emulation's on its own, the
    final grid the chosen lattice and the function the exact least-squares fit on it."""
    world, spec = _spec(**kwargs)
    params = spec.autogrid_params
    cores = _cores(world, spec)
    results = [c.result() for c in cores]
    first = results[0]
    assert all(r["converged"] and r["x"] == first["x"] and r["sigma"] == first["sigma"] for r in results)
    bounds, diag, points = _data(world)
    outside, inner, fold = emulation.lidar_rows(world.robots)
    records = {int(r["divisor"]): r for r in first["sigma_validation"]}
    assert sorted(records) == list(emulation.CANDIDATES_NEAR)
    _, kept = autogrid_sweep.lsq_models(cores[0].bounds, cores[0]._diag, params, cores[0]._near)
    assert [r["grid_points"] for r in kept] == [records[k]["grid_points"] for k in emulation.CANDIDATES_NEAR]
    fleet_row, exact_row = {"near": {}}, {"near": {}}
    for k in emulation.CANDIDATES_NEAR:
        grid = emulation.near_lattice(bounds, diag / k, points)
        fits = len(grid) <= params.max_points
        record = records[k]
        assert (record["grid_points"], record["tried"], record["lattice_points"]) == (
            len(grid), fits, len(autogrid_rules.lattice(autogrid_rules.lattice_box(bounds, diag / k), diag / k, 0)))
        fleet_row["near"][k], exact_row["near"][k] = {"fits": fits}, {"fits": fits}
        if fits:
            _, score = emulation.scored(GridBasis(grid, diag / k), outside, inner, fold)
            assert record["score"] == pytest.approx(score, rel=1e-3)
            fleet_row["near"][k]["score"], exact_row["near"][k]["score"] = record["score"], score
        else:
            assert record["score"] is None and "rounds" not in record
    k = emulation.choice_near(fleet_row)
    assert k == emulation.choice_near(exact_row)
    assert first["sigma"] == pytest.approx(diag / k, rel=1e-12)
    assert _same_points(first["grid"], emulation.near_lattice(bounds, diag / k, points))
    for core in cores:  # every robot's marks: the same kept nodes of every candidate
        models, _ = autogrid_sweep.lsq_models(core.bounds, core._diag, params, core._near)
        for model in models:
            assert _same_points(model.basis.grid, emulation.near_lattice(bounds, model.sigma, points))
    basis, ref = _exact(world.robots, first)
    assert basis.function_error(np.asarray(first["c"]), first["gamma"], ref.c, ref.gamma) < 1e-3


def test_a_candidate_over_the_budget_is_not_tried_and_nothing_fitting_falls_back_to_rule_1s_widest(monkeypatch):
    """max_points 150: the default run's diag/24 and diag/32 keep 197 and 267 nodes, not tried (no task, no
    score); the choice among the others is the emulation's. max_points 20: no kept lattice fits, the widest
    candidate on its lattice coarsened to the budget is the one tried (the emulation's fallback)."""
    world, spec = _spec(max_grid_points=150)
    bounds, diag, points = _data(world)
    running, swept = autogrid_sweep.SigmaSweep._running, set()

    def seen(sweep):
        tasks = running(sweep)
        swept.update(t.divisor for t in tasks)
        return tasks

    monkeypatch.setattr(autogrid_sweep.SigmaSweep, "_running", seen)
    cores = _cores(world, spec)
    first = cores[0].result()
    sizes = {k: len(emulation.near_lattice(bounds, diag / k, points)) for k in emulation.CANDIDATES_NEAR}
    assert any(m > 150 for m in sizes.values()) and any(m <= 150 for m in sizes.values())
    records = {int(r["divisor"]): r for r in first["sigma_validation"]}
    assert {k for k, r in records.items() if r["tried"]} == {k for k, m in sizes.items() if m <= 150}
    assert swept == {k for k, m in sizes.items() if m <= 150}  # the sweep ran no task of the others
    assert all(r["score"] is None for r in records.values() if not r["tried"])
    best = min((k for k, r in records.items() if r["tried"]), key=lambda k: (records[k]["score"], k))
    assert first["converged"] and first["sigma"] == pytest.approx(diag / best, rel=1e-12)
    assert _same_points(first["grid"], emulation.near_lattice(bounds, diag / best, points))

    world, spec = _spec(max_grid_points=20)
    assert min(sizes.values()) > 20
    first = _fleet(world, spec)[0]
    tried = [r for r in first["sigma_validation"] if r["tried"]]
    assert [int(r["divisor"]) for r in tried] == [min(emulation.CANDIDATES_NEAR)] and first["converged"]
    # the marks of the seven lattices (1543 nodes) over frames of 336 floats: in chunks, the same kept nodes
    chunks = [p for p, _ in first["phases"]].count("marks")
    lattices = sum(r["lattice_points"] for r in first["sigma_validation"])
    assert chunks == -(-lattices // spec.autogrid_params.dim) > 1
    assert all(r["grid_points"] == sizes[int(r["divisor"])] for r in first["sigma_validation"] if not r["tried"])
    sigma = diag / min(emulation.CANDIDATES_NEAR)
    _, _, coarse = coarse_lattice(bounds, sigma, emulation.SPACING, 20)
    assert first["sigma"] == pytest.approx(sigma, rel=1e-12) and _same_points(first["grid"], coarse)
    assert tried[0]["grid_points"] == len(coarse) <= 20 and "coarsened" in tried[0]["grid"]
    basis, ref = _exact(world.robots, first)
    assert basis.function_error(np.asarray(first["c"]), first["gamma"], ref.c, ref.gamma) < 1e-3


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


def test_crash_and_restart_in_the_marks_the_sweep_and_the_fit_end_on_the_clean_answer():
    """Robots killed in the near-data marks, in the sweep (round 20) and in the final fit resume from their
    checkpoints."""
    _, spec = _spec(fleet_id="autolsq-crash", timing=TIMING, topology="ring", robots=4)
    clean = {r["id"]: r for r in simulate_fleet(spec).robots}
    phases = dict(clean[0]["phases"])
    fit_round = phases["admm"] + 5
    assert phases["validate"] - phases["marks"] >= 2  # (D = 2: the crash is inside the phase)
    crashes = [CrashPlan(3, phases["marks"] + 1), CrashPlan(1, 20), CrashPlan(2, fit_round)]
    out = simulate_fleet(spec, crashes=crashes, restart=True, restart_after=0.5)
    assert [c["fired"] for c in out.crash_log] == [True, True, True]
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


def test_crash_and_restart_inside_chunked_marks_ends_on_the_clean_answer():
    """max_points 20: the marks take several frames (chunks of D rounds); a robot killed in the third chunk resumes
    from its checkpoint (the marks agreed so far and the chunk) and the fleet ends on the clean run's bits."""
    _, spec = _spec(fleet_id="autolsq-chunks", timing=TIMING, topology="ring", robots=4, max_grid_points=20)
    clean = {r["id"]: r for r in simulate_fleet(spec).robots}
    marks = [r for p, r in clean[0]["phases"] if p == "marks"]
    assert len(marks) >= 3
    out = simulate_fleet(spec, crashes=[CrashPlan(2, marks[2] + 1)], restart=True, restart_after=0.5)
    assert [c["fired"] for c in out.crash_log] == [True]
    for r in out.robots:
        want = clean[r["id"]]
        assert (r["x"], r["gamma"], r["rounds"], r["grid"]) == (want["x"], want["gamma"], want["rounds"], want["grid"])
        assert r["sigma_validation"] == want["sigma_validation"]  # (every candidate's kept nodes: the marks)


@pytest.mark.parametrize("topology", ["complete", "ring"])
def test_survivors_of_a_loss_in_the_marks_fit_their_own_data(topology):
    """Robot 1 dies for good in the near-data marks: the survivors agree on the marks without it (a max-consensus
    as BOUNDS'), sweep and fit their own rows exactly on the grid they chose."""
    world, spec = _spec(fleet_id=f"autolsq-markloss-{topology}", timing=TIMING, topology=topology, robots=4)
    marks = dict(simulate_fleet(spec).robots[0]["phases"])["marks"]
    out = simulate_fleet(spec, crashes=[CrashPlan(1, marks)], restart=False)
    assert [r["id"] for r in out.robots] == [0, 2, 3] and all(r["converged"] for r in out.robots)
    assert len({(r["sigma"], tuple(r["x"])) for r in out.robots}) == 1
    basis, ref = _exact([r for r in world.robots if r.id != 1], out.robots[0])
    assert max(basis.function_error(np.asarray(r["c"]), r["gamma"], ref.c, ref.gamma) for r in out.robots) < 1e-3



# -- sparse graphs: the plain edge form (agents/lsq_admm.py; benchmarks/results/lsq.md) --------------
@pytest.mark.parametrize("topology", ["ring", "line"])
def test_sparse_fleets_end_on_the_exact_fit_of_their_rows(topology):
    """A ring and a line of 4 run the sweep and the final fit in the edge form: every robot ends converged on the
    same bits, within the run's tolerance of the exact central least-squares fit on the grid they chose."""
    world, spec = _spec(fleet_id=f"autolsq-{topology}", topology=topology, robots=4)
    results = _fleet(world, spec)
    assert all(r["converged"] and r["x"] == results[0]["x"] and r["gamma"] == results[0]["gamma"] for r in results)
    basis, ref = _exact(world.robots, results[0])
    error = basis.function_error(np.asarray(results[0]["c"]), results[0]["gamma"], ref.c, ref.gamma)
    assert error < spec.autogrid_params.tol


def test_a_sparse_final_fit_starts_where_the_sweeps_fit_of_all_rows_ended():
    """On a ring the sweep also runs every candidate's fit of all rows (`SigmaSweep.full_fit`, not scored) and the
    final fit starts from the chosen one's iterate and edge states: at its first round every robot's v is that
    iterate, and both ends of every edge hold the same carried (z, lambda) -- not zero -- so lambda_lj = -lambda_jl
    and the fixed point stays the exact fit, which the fleet ends on."""
    world, spec = _spec(fleet_id="autolsq-warmfit", topology="ring", robots=4)
    cores = [build_core(spec, i) for i in spec.robot_ids]
    for _ in range(spec.autogrid_params.max_total_rounds):
        sweeps = {c.robot_id: c._sweep for c in cores}
        step_all(cores)
        if all(c._sub is not None for c in cores):
            break
    by_id = {c.robot_id: c for c in cores}
    for c in cores:
        sweep = sweeps[c.robot_id]
        cand = next(i for i, m in enumerate(sweep.models) if m.sigma == c.sigma)
        full = sweep.task(cand, spec.autogrid_params.sweep_folds)
        assert full.held_pairs is not None and len(full.held_pairs) == 0  # (not scored)
        assert np.array_equal(c._sub.values, full.sub.values)
        for j, edge in c._sub._edges.items():
            other = by_id[j]._sub._edges[c.robot_id]
            assert np.array_equal(edge.z, other.z) and np.array_equal(edge.lam, other.lam)
            assert np.any(edge.lam != 0)
    run_to_end(cores, limit=spec.autogrid_params.max_total_rounds)
    results = [c.result() for c in cores]
    basis, ref = _exact(world.robots, results[0])
    assert all(r["converged"] for r in results)
    assert all(r["folds"] == spec.autogrid_params.sweep_folds for r in results[0]["sigma_validation"] if r["tried"])
    assert max(basis.function_error(np.asarray(r["c"]), r["gamma"], ref.c, ref.gamma) for r in results) < 1e-3


def test_a_ring_robot_killed_in_the_tally_or_the_fits_first_round_resumes_on_the_clean_answer():
    """The warm start is built from the sweep's tasks at the tally's end: a robot killed inside the tally (its
    sweep restored from the checkpoint) and one killed at the fit's first round resume on the clean run's bits."""
    _, spec = _spec(fleet_id="autolsq-crash-warm", timing=TIMING, topology="ring", robots=4)
    clean = {r["id"]: r for r in simulate_fleet(spec).robots}
    phases = dict(clean[0]["phases"])
    assert phases["admm"] - phases["tally"] >= 2  # (the crash is inside the tally)
    out = simulate_fleet(spec, crashes=[CrashPlan(2, phases["tally"] + 1), CrashPlan(3, phases["admm"] + 1)],
                         restart=True, restart_after=0.5)
    assert [c["fired"] for c in out.crash_log] == [True, True]
    for r in out.robots:
        want = clean[r["id"]]
        assert (r["x"], r["gamma"], r["rounds"], r["sigma"]) == (want["x"], want["gamma"], want["rounds"], want["sigma"])


def test_survivors_of_a_loss_in_the_sweep_of_a_ring_fit_their_own_data():
    """Robot 1 of a 5-ring dies for good in the sweep: the survivors (a line of 4) learn it by the flooded list,
    weigh lam by the robots left and end on the exact fit of their own rows."""
    world, spec = _spec(fleet_id="autolsq-ringloss", timing=TIMING, topology="ring", robots=5)
    out = simulate_fleet(spec, crashes=[CrashPlan(1, 20)], restart=False)
    assert [r["id"] for r in out.robots] == [0, 2, 3, 4] and all(r["converged"] for r in out.robots)
    assert dict(out.robots[0]["phases"])["tally"] > 20  # (the loss was in the sweep)
    assert len({(r["sigma"], tuple(r["x"])) for r in out.robots}) == 1
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
    records = result["sigma_validation"]  # every candidate: its grid size, whether it was tried, its score
    assert [r["divisor"] for r in records] == list(emulation.CANDIDATES_NEAR)
    assert all(np.isfinite(r["score"]) and r["held_out_pairs"] > 0 for r in records if r["tried"])
    assert all(f"diag/{r['divisor']:g}: {r['grid_points']} nodes" in result["sigma_reason"] for r in records)
    world, _ = _spec(lsq_lambda=0.2)
    _, ref = _exact(world.robots, result)
    assert result["central"]["c"] == ref.c.tolist()  # measured against the least-squares fit, not the margin QP
    assert result["metrics"]["function_error"] < 1e-3


@pytest.mark.integration
@pytest.mark.parametrize("graph", [{}, {"topology": "ring", "robots": 4}], ids=["complete", "ring"])
def test_launch_equals_simulate_bit_for_bit(tmp_path, graph):
    """Real robot processes over Zenoh run the sweep and the fit as `simulate` does, bit for bit: the hub form
    (the default complete graph) and the edge form (a ring: per-edge duals, the fits of all rows in the sweep)."""
    _, spec = _spec(fleet_id=f"autolsq-launch-{len(graph)}", timing=TIMING, **graph)
    want = {r["id"]: r for r in simulate_fleet(spec).robots}
    with bounded_and_clean(str(tmp_path), 60.0, "autolsq-launch"):
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
    """The default lsq sweep (35 tasks of up to 300 nodes: 21 000 floats with the hub's w in one pass) shares a
    frame of 16 (max_points + 1) floats, which also holds a final fit's and every candidate's marks of a run."""
    params = AutoGridParams(model="lsq", hub_frames=hub_frames)
    assert params.dim == params.lsq_sweep_frame == 16 * (params.max_points + 1)
    assert params.sweep_folds * sum(params._fold_blocks()) > params.dim  # (shared: not every task at once)
    assert params.tally_slots >= 300  # robot ids: one tally slot each per candidate


def test_scheduled_sweep_is_the_one_pass_sweep_bit_for_bit(monkeypatch):
    """The tasks sharing the frame round by round (complete graph) give the one-pass sweep's scores and fit,
    bit for bit; every round's blocks are disjoint and within the frame rule."""
    world, spec = _spec()
    params = spec.autogrid_params
    assert params.dim <= 16 * (params.max_points + 1)
    running, layouts = autogrid_sweep.SigmaSweep._running, []

    def checked(sweep):
        tasks = running(sweep)
        spans = sorted((t.offset, t.offset + sweep._block(t)) for t in tasks)
        assert all(end <= start for (_, end), (start, _) in zip(spans, spans[1:])) and spans[-1][1] <= sweep.dim
        layouts.append(len(tasks))
        return tasks

    monkeypatch.setattr(autogrid_sweep.SigmaSweep, "_running", checked)
    grouped = _fleet(world, spec)
    assert 0 < min(layouts) and max(layouts) < params.sweep_folds * len(params.lsq_divisors)  # (shared)
    monkeypatch.undo()
    monkeypatch.setattr(autogrid_rules, "FRAME_BUDGET", 10**6)  # room for every task at once
    assert spec.autogrid_params.dim == spec.autogrid_params.sweep_folds * sum(spec.autogrid_params._fold_blocks())
    one_pass = _fleet(world, spec)
    for a, b in zip(grouped, one_pass):
        without_rounds = lambda records: [{k: v for k, v in r.items() if k != "rounds"} for r in records]
        assert without_rounds(a["sigma_validation"]) == without_rounds(b["sigma_validation"])
        assert (a["x"], a["gamma"], a["sigma"]) == (b["x"], b["gamma"], b["sigma"])
        assert a["rounds"] > b["rounds"]  # (a task waits while the frame is full)
