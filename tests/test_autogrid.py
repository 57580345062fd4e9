"""The fleet chooses its grid and kernel width itself (agents/autogrid.py).

A small lock-step driver moves every frame through the real codec (encode_state /
FrameDecoder, fixed vector length max_points + 2), like launcher.simulate with no faults.
"""

from __future__ import annotations

import dataclasses

import msgpack
from pathlib import Path

import numpy as np
import pytest
from sklearn.svm import SVC

from agents.autogrid import AdaptiveGridCore, AutoGridParams, choose_sigma, holdout_units, is_solid, lattice
from agents.kernel import GridBasis
from agents.problem import solve_central
from agents.rounds import RobotShare
from launcher import scenario
from launcher.gridstudy import _shifted_bounds
from launcher.world import Options, build_world
from protocol.frames import Decoded, FrameDecoder, config_tag, encode_state

from .conftest import step_all

FLEET = "autogrid-test"
TAG = config_tag("autogrid")


def make_cores(robots, params, *, start_grid=None, scale=1.0):
    """robots: {id: (neighbours, points, labels)} -> one core per robot."""
    return [
        AdaptiveGridCore(
            RobotShare(rid, nb, np.asarray(pts) * scale, lab, n_robots=len(robots), degrees={j: len(robots[j][0]) for j in nb}),
            params,
            start_grid=None if start_grid is None else np.asarray(start_grid) * scale,
        )
        for rid, (nb, pts, lab) in sorted(robots.items())
    ]


def run_fleet(cores, limit=40_000):
    """Lock-step rounds through the frame codec until every robot has finished."""
    ids = [c.robot_id for c in cores]
    decoders = {c.robot_id: FrameDecoder(FLEET, ids, cores[0].dim, TAG) for c in cores}
    seq = 0
    for _ in range(limit):
        if all(c.finished for c in cores):
            return cores
        frames = []
        for c in cores:
            frames.append((c.robot_id, encode_state(c.outgoing(), fleet=FLEET, seq=seq, config_tag=TAG)))
        seq += 1
        for c in cores:
            for src, payload in frames:
                if src in c.neighbours:
                    event = decoders[c.robot_id].decode(payload, expected_sender=src)
                    assert isinstance(event, Decoded), event
                    c.receive(event.update)
        for c in cores:
            if not c.finished:
                c.advance()
    raise AssertionError("fleet did not finish")


def _checkpoint_blobs(cores):
    """Every robot's checkpoint as msgpack bytes (what a robot process writes to disk)."""
    return [msgpack.packb(c.checkpoint(), use_bin_type=True) for c in cores]


def _resume_from_checkpoints(cores, robots, params, blobs=None):
    """Restart every robot from a msgpack round trip of its checkpoint (of `cores`, or the
    `blobs` taken earlier) and run to the end."""
    blobs = _checkpoint_blobs(cores) if blobs is None else blobs
    resumed = make_cores(robots, params)
    for c, b in zip(resumed, blobs):
        c.restore(msgpack.unpackb(b, raw=False, strict_map_key=False))
    run_fleet(resumed)
    return resumed


def robots_of(spec):
    return {i: (r.neighbours, r.points, r.labels) for i, r in spec.robots.items()}


def fast_params(spec, **kw):
    kw.setdefault("tol", 1e-4)
    kw.setdefault("max_points", 120)
    kw.setdefault("validate_divisors", ())  # the fixed rule diag / 8 unless a test sweeps sigma
    return AutoGridParams(model="svm", diameter=spec.params["diameter"], **kw)


@pytest.fixture(scope="module")
def blob():
    world, spec = build_world(Options(model="svm", fleet_id="t"))
    params = fast_params(spec)
    cores = run_fleet(make_cores(robots_of(spec), params))
    return world, spec, params, cores


def test_every_robot_ends_with_the_same_grid_and_function(blob):
    world, spec, params, cores = blob
    first = cores[0]
    grid, c, gamma = first.function()
    assert all(core.converged and core.phase == "done" for core in cores)
    assert len({core.round for core in cores}) == 1  # all stop in the same round
    for core in cores[1:]:
        g2, c2, gamma2 = core.function()
        assert np.array_equal(g2, grid) and np.array_equal(c2, c) and gamma2 == gamma  # bit for bit
        assert core.sigma == first.sigma and core.grid_history == first.grid_history
    assert len(grid) <= params.max_points
    # within 1e-3 of the centralized solve on the final grid
    basis = GridBasis(grid, first.sigma)
    central = solve_central(basis, world.points, world.labels)
    assert central.solved and first.margin == "hard"
    assert basis.function_error(c, gamma, central.c, central.gamma) < 1e-3
    # the grids used and the chosen sigma, with the reason, are reported
    res = first.result()
    assert res["grid"] == grid.tolist() and res["sigma"] == first.sigma and "diag" in res["sigma_reason"]
    sizes = [h["size"] for h in res["grid_history"]]
    assert sizes == sorted(sizes) and len(sizes) >= 2  # refined at least once
    # each grid is a superset of the one before (the warm start c_new = [c_old; 0] is exact)
    for before, after in zip(res["grid_history"], res["grid_history"][1:]):
        assert np.array_equal(np.asarray(after["grid"])[: before["size"]], np.asarray(before["grid"]))


def test_bounds_agreed_by_max_consensus_match_the_data(blob):
    world, _, _, cores = blob
    lo, hi = world.points.min(axis=0), world.points.max(axis=0)
    for core in cores:
        assert core.bounds == (lo[0], hi[0], lo[1], hi[1])  # exact: a max of floats rounds nothing
    diag = np.hypot(*(hi - lo))
    assert cores[0].sigma == pytest.approx(diag / 8.0)


def test_scale_free_millimetres_give_the_same_shape_scaled(blob):
    world, spec, params, cores = blob
    scaled = run_fleet(make_cores(robots_of(spec), params, scale=1000.0))
    a, b = cores[0], scaled[0]
    assert b.sigma == pytest.approx(1000.0 * a.sigma, rel=1e-12)
    assert len(b.grid) == len(a.grid)
    np.testing.assert_allclose(b.grid, 1000.0 * a.grid, rtol=1e-9, atol=1e-9 * 1000.0 * a.sigma)
    probe = scenario.make_grid(120, 120, (-3.5, 3.5, -3.0, 3.0))
    fa, fb = a.decision(probe), b.decision(1000.0 * probe)
    assert np.mean(np.sign(fa) == np.sign(fb)) > 0.999
    np.testing.assert_allclose(fb, fa, atol=1e-5)


def test_fig5_coarse_shifted_start_grid_ends_separating_all_data():
    world, spec = build_world(Options(model="svm", fleet_id="t"))
    bounds = scenario.parse_bounds(_shifted_bounds(world.bounds, "4x2", (0.5, 0.0)))
    start = scenario.make_grid(4, 2, bounds)
    assert solve_central(GridBasis(start, 1.0), world.points, world.labels).status == "infeasible"
    params = fast_params(spec, sigma=1.0, hard_rounds=600)  # the paper's sigma, its bad grid
    cores = run_fleet(make_cores(robots_of(spec), params, start_grid=start))
    core = cores[0]
    history = core.result()["grid_history"]
    # (infeasible centrally; the fleet can only see that its hard ADMM did not converge in hard_rounds)
    assert history[0]["size"] == 8 and history[0]["status"] == "hard-not-converged"
    assert core.margin == "hard" and core.message == ""
    assert np.array_equal(core.grid[:8], start)  # the start grid is kept, points are added
    margins = world.labels * core.decision(world.points)
    assert margins.min() > 1 - 1e-3  # every point on its side, with the hard margin
    central = solve_central(GridBasis(core.grid, 1.0), world.points, world.labels)
    _, c, gamma = core.function()
    assert GridBasis(core.grid, 1.0).function_error(c, gamma, central.c, central.gamma) < 1e-3


def test_inseparable_data_falls_back_to_a_soft_margin_and_says_so():
    # two robots see the same point with opposite labels: no grid can separate that
    pts = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [2.0, 2.0]])
    robots = {
        0: ((1,), pts[:3], np.array([-1, 1, 1])),
        1: ((0,), np.vstack([pts[:1], pts[3:]]), np.array([1, 1])),
    }
    # (the round-cap detector alone: ill_multiplier 0; with the conditioning test the diverging iterate
    # switches earlier, tests/test_autogrid_illcond.py)
    params = AutoGridParams(model="svm", diameter=1, max_points=40, max_refinements=2, hard_rounds=300, soft_rounds=3000,
                            ill_multiplier=0.0)
    cores = run_fleet(make_cores(robots, params))
    for core in cores:
        assert core.finished and core.margin == "soft"
        assert "soft margin" in core.message and "not converged within 300 rounds" in core.message
        assert "hard margin stayed infeasible" not in core.message  # (it may be feasible and slow: not claimed)
        assert any(h["status"] == "hard-not-converged" for h in core.grid_history)
    assert np.array_equal(cores[0].function()[1], cores[1].function()[1])


def test_local_infeasibility_is_voted_without_running_admm():
    pts = np.array([[0.0, 0.0], [0.0, 0.0], [3.0, 1.0]])
    robots = {0: ((1,), pts[:2], np.array([1, -1])), 1: ((0,), pts[2:], np.array([1]))}
    params = AutoGridParams(model="svm", diameter=1, max_points=20, max_refinements=0)
    cores = run_fleet(make_cores(robots, params))
    first = cores[0].grid_history[0]
    assert first["status"] == "hard-infeasible" and first["detected_by"].startswith("vote")
    assert cores[0].margin == "soft" and cores[1].margin == "soft"


def test_lone_robot_runs_every_phase_at_once():
    world, _ = build_world(Options(model="svm", fleet_id="t", robots=1))
    r = world.robots[0]
    core = AdaptiveGridCore(RobotShare(0, (), r.points, r.labels), AutoGridParams(model="svm", diameter=0, max_points=80))
    assert core.finished and core.converged and core.round == 0
    grid, c, gamma = core.function()
    central = solve_central(GridBasis(grid, core.sigma), r.points, r.labels)
    assert GridBasis(grid, core.sigma).function_error(c, gamma, central.c, central.gamma) < 1e-6


def _lockstep(cores, rounds):
    for _ in range(rounds):
        step_all(cores)


@pytest.fixture(scope="module")
def small_run():
    world, spec = build_world(Options(model="svm", fleet_id="t"))
    params = fast_params(spec, max_points=60, max_refinements=1, tol=1e-3)
    robots = robots_of(spec)
    return robots, params, run_fleet(make_cores(robots, params))


def _phase_rounds(core, name, nth=0):
    """(first round, first round of the next phase) of the nth `name` phase of a finished run."""
    starts = [(p, r) for p, r in core.phases]
    i = [k for k, (p, _) in enumerate(starts) if p == name][nth]
    return starts[i][1], starts[i + 1][1]


WHEN = ("vote", "admm-start", "admm", "flood")


def _checkpoints_at(robots, params, stops):
    """{key: (the phase the robots were in, their checkpoints)} after stops[key] lock-step rounds.

    One run takes them all in turn (a checkpoint only reads the state): the resumes share its
    prefix instead of running it once each."""
    cores, done, taken = make_cores(robots, params), 0, {}
    for key in sorted(stops, key=stops.get):
        _lockstep(cores, stops[key] - done)
        done = stops[key]
        taken[key] = (cores[0].phase, _checkpoint_blobs(cores))
    return taken


@pytest.fixture(scope="module")
def phase_checkpoints(small_run):
    robots, params, ref = small_run
    stops = {}
    for when in WHEN:
        start, end = _phase_rounds(ref[0], when.split("-")[0])
        stops[when] = {"vote": start, "admm-start": start, "admm": (start + end) // 2, "flood": end - 1}[when]
    return _checkpoints_at(robots, params, stops)


@pytest.mark.parametrize("when", WHEN)
def test_checkpoint_in_every_phase_resumes_bit_for_bit(small_run, phase_checkpoints, when):
    robots, params, ref = small_run
    in_phase, blobs = phase_checkpoints[when]
    assert in_phase == when.split("-")[0]
    resumed = _resume_from_checkpoints(None, robots, params, blobs)
    for a, b in zip(ref, resumed):
        assert a.round == b.round and a.grid_history == b.grid_history and a.phases == b.phases
        assert np.array_equal(a.function()[1], b.function()[1])


def test_lattice_levels_are_nested():
    box = (-2.3, 2.9, -1.1, 1.7)
    coarse, fine = lattice(box, 0.9, 1), lattice(box, 0.9, 2)
    d = np.sqrt(((coarse[:, None, :] - fine[None, :, :]) ** 2).sum(-1)).min(axis=1)
    assert d.max() < 1e-12


def _svc_iou(shape, points, labels, bounds, sigma):
    clf = SVC(kernel="rbf", C=1e6, gamma=1.0 / (2 * sigma * sigma)).fit(points, labels)
    return scenario.iou_on_raster(shape, lambda q: clf.decision_function(q) < 0, bounds, resolution=120)


MM = {"standoff": 1500.0, "lidar_range": 4000.0, "offset": 300.0, "noise": 10.0}
IOU_SHAPES = {
    "star": {"shape": "star"},
    "bean": {"shape": "bean"},
    "crescent": {"shape": "crescent"},
    "cross": {"shape": "cross"},
    "bracket_mm.csv": {"shape_file": str(Path(__file__).resolve().parents[1] / "benchmarks/data/bracket_mm.csv"), **MM},
}


@pytest.fixture(scope="module")
def iou_table():
    """Fleet defaults (sigma by the sweep, grid by refinement) vs SVC on five non-convex shapes."""
    from sklearn.model_selection import StratifiedKFold, cross_val_score

    rows = {}
    for name, kw in IOU_SHAPES.items():
        world, spec = build_world(Options(model="svm", fleet_id="t", robots=3, points=20, **kw))
        params = AutoGridParams(model="svm", diameter=spec.params["diameter"], tol=1e-3, max_points=100)
        cores = run_fleet(make_cores(robots_of(spec), params))
        core = cores[0]
        x0, x1, y0, y1 = scenario.shape_bounds(world.shape)
        pad = 0.2 * max(x1 - x0, y1 - y0)
        bounds = (x0 - pad, x1 + pad, y0 - pad, y1 + pad)
        diag = float(np.hypot(*np.ptp(world.points, axis=0)))
        sweep = {k: _svc_iou(world.shape, world.points, world.labels, bounds, diag / k) for k in (2, 4, 6, 8, 12, 16)}
        cv = StratifiedKFold(5, shuffle=True, random_state=0)
        scores = {
            k: cross_val_score(SVC(kernel="rbf", C=1e6, gamma=k * k / (2 * diag * diag)), world.points, world.labels, cv=cv).mean()
            for k in sweep
        }
        rows[name] = {
            "fleet": scenario.iou_on_raster(world.shape, lambda q: core.decision(q) < 0, bounds, resolution=120),
            "same": _svc_iou(world.shape, world.points, world.labels, bounds, core.sigma),
            "best": max(sweep.values()),
            "cv": sweep[max(scores, key=lambda k: (scores[k], -k))],  # ties -> the larger sigma
            "divisor": diag / core.sigma,
            "identical": all(np.array_equal(k.function()[1], core.function()[1]) for k in cores),
        }
    return rows


def test_iou_against_sklearn_svc_on_five_non_convex_shapes(iou_table, capsys):
    with capsys.disabled():
        print("\nshape            fleet (diag/k)  SVC same sigma  SVC 5-fold CV  SVC best of sweep (oracle)")
        for name, r in iou_table.items():
            print(f"{name:16s} {r['fleet']:.3f} (/{r['divisor']:.0f})     {r['same']:.3f}           {r['cv']:.3f}          {r['best']:.3f}")
        mean = {k: np.mean([r[k] for r in iou_table.values()]) for k in ("fleet", "same", "cv", "best")}
        print(f"{'mean':16s} {mean['fleet']:.3f}           {mean['same']:.3f}           {mean['cv']:.3f}          {mean['best']:.3f}")
    for name, r in iou_table.items():
        assert r["identical"], name
        # the grid and its refinement lose nothing against the full kernel machine at the same sigma
        assert r["fleet"] >= r["same"] - 0.02, name
    # the fleet's own choice of sigma is at least as good, on average, as a central user's
    # 5-fold cross-validation over a larger sweep; the oracle (best by IoU with the truth) is
    # NOT reached on every shape: see docs/autogrid.md
    assert mean["fleet"] >= mean["cv"] - 0.005


def run_lossy(cores, faults, *, seed=3, retransmit_s=0.02, cap_s=500.0):
    """launcher.simulate's loop (virtual clock, fault-injecting links, retransmission)."""
    from protocol.links import LinkLayer

    ids = [c.robot_id for c in cores]
    by_id = {c.robot_id: c for c in cores}
    decoders = {i: FrameDecoder(FLEET, ids, cores[0].dim, TAG) for i in ids}
    links = LinkLayer(faults, seed)
    last = {i: 0.0 for i in ids}
    seq = {i: 0 for i in ids}
    now = 0.0

    def publish(i):
        payload = encode_state(by_id[i].outgoing(), fleet=FLEET, seq=seq[i], config_tag=TAG)
        seq[i] += 1
        last[i] = now
        for j in by_id[i].neighbours:
            links.send(i, j, payload, now)

    def needed(i):
        c = by_id[i]
        return not c.finished or any(not by_id[j].finished for j in c.neighbours)

    for i in ids:
        publish(i)
    while not all(c.finished for c in cores):
        for src, dst, payload in links.deliver(now):
            event = decoders[dst].decode(payload, expected_sender=src)
            if isinstance(event, Decoded):
                by_id[dst].receive(event.update)
        advanced = False
        for i in ids:
            if by_id[i].ready():
                by_id[i].advance()
                publish(i)
                advanced = True
        if advanced:
            continue
        due = links.next_due()
        candidates = [last[i] + retransmit_s for i in ids if needed(i)] + ([due] if due is not None else [])
        now = max(now, min(candidates))
        assert now < cap_s, "virtual time cap"
        for i in ids:
            if needed(i) and last[i] + retransmit_s <= now:
                publish(i)
    return cores


def test_loss_delay_and_reordering_change_nothing():
    # a line of 3 robots (diameter 2): rounds stay exact under faults, so the outcome is the
    # same bit for bit as without faults
    from protocol.links import LinkFaults

    world, spec = build_world(Options(model="svm", fleet_id="t", robots=3, topology="line"))
    params = fast_params(spec, tol=1e-3, max_points=60, max_refinements=1, hard_rounds=800)
    assert params.diameter == 2
    clean = run_fleet(make_cores(robots_of(spec), params))
    faulty = run_lossy(
        make_cores(robots_of(spec), params), LinkFaults(delay=0.002, jitter=0.004, loss=0.2, duplicate=0.1, reorder=0.2)
    )
    for a, b in zip(clean, faulty):
        assert a.round == b.round and np.array_equal(a.grid, b.grid)
        assert np.array_equal(a.function()[1], b.function()[1])
    assert all(np.array_equal(c.function()[1], clean[0].function()[1]) for c in clean)


# -- sigma by held-out validation (issue 6) ------------------------------------------------------


@pytest.fixture(scope="module")
def sweep_runs():
    world, spec = build_world(Options(model="svm", fleet_id="t", shape="star", points=25))
    params = _sweep_params(spec)
    assert params.validates and params.validate_divisors == (4.0, 6.0, 8.0, 12.0, 16.0)
    robots = robots_of(spec)
    plain = run_fleet(make_cores(robots, params))
    scaled = run_fleet(make_cores(robots, params, scale=1000.0))
    return world, robots, params, plain, scaled


def test_sigma_sweep_is_identical_on_every_robot(sweep_runs):
    world, _, params, cores, _ = sweep_runs
    first = cores[0]
    val = first.sigma_validation
    assert [r["divisor"] for r in val] == list(params.validate_divisors)
    # the exact fleet-wide sum over the folds: every point of units u % 5 in {4, 3}
    held = sum(
        int(np.sum(np.isin(holdout_units(r.points, r.labels) % 5, [4, 3]) & (holdout_units(r.points, r.labels) >= 0)))
        for r in world.robots
    )
    assert params.validate_folds == 2
    assert all(r["held_out"] == held and r["folds"] == 2 for r in val)
    for core in cores:
        assert core.converged and core.sigma == first.sigma  # bit for bit
        assert core.sigma_validation == val and core.sigma_reason == first.sigma_reason
        assert np.array_equal(core.function()[1], first.function()[1])
    # the rule: among the solid candidates, fewest held-out errors, ties -> the smaller sigma
    pool = [r for r in val if r["solid"]] or val
    fewest = min(r["errors"] for r in pool)
    assert first.sigma == min(r["sigma"] for r in pool if r["errors"] == fewest)
    diag = float(np.hypot(*np.ptp(world.points, axis=0)))
    assert any(first.sigma == pytest.approx(diag / d, rel=1e-12) for d in params.validate_divisors)
    res = first.result()
    assert "fewest held-out errors" in res["sigma_reason"] and f"({fewest}/{held})" in res["sigma_reason"]
    assert res["sigma_validation"] == val and res["sigma"] == first.sigma
    # the final run is on all data at the chosen sigma, within tol of the central solve
    grid, c, gamma = first.function()
    basis = GridBasis(grid, first.sigma)
    central = solve_central(basis, world.points, world.labels, None if first.margin == "hard" else params.soft_C)
    assert basis.rank == len(grid)  # the reference is the exact optimum
    assert basis.function_error(c, gamma, central.c, central.gamma) < params.tol


def test_sigma_sweep_is_scale_free(sweep_runs):
    _, _, _, plain, scaled = sweep_runs
    a, b = plain[0], scaled[0]
    assert b.sigma == pytest.approx(1000.0 * a.sigma, rel=1e-12)  # the same choice, x1000
    assert [(r["divisor"], r["errors"], r["held_out"]) for r in a.sigma_validation] == [
        (r["divisor"], r["errors"], r["held_out"]) for r in b.sigma_validation
    ]
    for ra, rb in zip(a.sigma_validation, b.sigma_validation):
        assert rb["sigma"] == pytest.approx(1000.0 * ra["sigma"], rel=1e-12)
        assert rb["hinge"] == pytest.approx(ra["hinge"], rel=1e-6, abs=1e-6)
    assert all(k.sigma == b.sigma for k in scaled)
    np.testing.assert_allclose(b.grid, 1000.0 * a.grid, rtol=1e-9, atol=1e-9 * 1000.0 * a.sigma)


SWEEP_PHASES = ("validate", "tally", "seed")


@pytest.fixture(scope="module")
def sweep_checkpoints(sweep_runs):
    """{phase: (the phase the robots were in, their checkpoints)}, each taken in the middle of
    that phase of the sweep, all three by one lock-step run (_checkpoints_at)."""
    _, robots, params, ref, _ = sweep_runs
    # inside the phase (the middle of the one-pass sweep)
    return _checkpoints_at(robots, params, {p: sum(_phase_rounds(ref[0], p)) // 2 for p in SWEEP_PHASES})


@pytest.mark.parametrize("phase", SWEEP_PHASES)
def test_checkpoint_during_the_sigma_sweep_resumes_bit_for_bit(sweep_runs, sweep_checkpoints, phase):
    _, robots, params, ref, _ = sweep_runs
    in_phase, blobs = sweep_checkpoints[phase]
    assert in_phase == phase
    resumed = _resume_from_checkpoints(None, robots, params, blobs)
    for a, b in zip(ref, resumed):
        assert a.round == b.round and a.sigma == b.sigma and a.sigma_validation == b.sigma_validation
        assert np.array_equal(a.function()[1], b.function()[1])


def test_sweep_solves_every_candidate_and_fold_in_one_pass(sweep_runs):
    _, _, params, cores, _ = sweep_runs
    first = cores[0]
    start, end = _phase_rounds(first, "validate")
    tasks = [r["rounds"] for r in first.sigma_validation]  # the slowest fold of each candidate
    assert end - start == max(tasks) <= params.validate_rounds  # the slowest task, not the sum
    assert sum(tasks) > end - start
    assert params.dim <= 16 * (params.max_points + 1)  # function-space vectors only, bounded
    assert sum(params.sweep_blocks()) <= params.dim


def _sweep_params(spec, **kw):
    # no refinement: the seed's refinement orders lattice nodes by |f| of a sweep iterate, whose
    # last bits (and stop round) are not scale-invariant, so x1000 could swap a near tie at the
    # budget's cut; the level-0 lattice is (test_sigma_sweep_is_scale_free)
    return AutoGridParams(
        model="svm", diameter=spec.params["diameter"], tol=1e-3, max_points=60, max_refinements=0, **kw
    )


def test_holdout_units_pair_each_inside_point_with_its_nearest_outside_point():
    points = np.array([[0.0, 0.0], [0.0, 1.0], [5.0, 0.0], [5.0, 1.2], [9.0, 9.0]])
    labels = np.array([1, -1, 1, -1, 1])
    units = holdout_units(points, labels)
    assert units.tolist() == [0, 0, 1, 1, -1]  # the stray outside point is never held out
    assert holdout_units(points[:1], labels[:1]).tolist() == [0]  # one class only: points alone


def test_solid_region_check():
    ring = np.zeros((9, 9), dtype=bool)
    ring[2:7, 2:7] = True
    assert is_solid(ring)
    ring[4, 4] = False  # a hole
    assert not is_solid(ring)
    islands = np.zeros((9, 9), dtype=bool)
    islands[1:3, 1:3] = islands[6:8, 6:8] = True
    assert not is_solid(islands)
    assert not is_solid(np.zeros((9, 9), dtype=bool))
    edge = np.zeros((9, 9), dtype=bool)
    edge[:, :4] = True  # touching the border is fine: no enclosed outside cell
    assert is_solid(edge)


def test_solid_check_can_allow_holes_but_never_islands():
    """holes_allowed (issue 15): a ring (one piece around an enclosed outside cell) passes, two
    pieces still fail, a plain disc passes either way."""
    ring = np.zeros((9, 9), dtype=bool)
    ring[2:7, 2:7] = True
    ring[4, 4] = False
    two = np.zeros((9, 9), dtype=bool)
    two[1:3, 1:3] = two[6:8, 6:8] = True
    disc = np.zeros((9, 9), dtype=bool)
    disc[2:7, 2:7] = True
    assert not is_solid(ring) and is_solid(ring, holes_allowed=True)
    assert not is_solid(two) and not is_solid(two, holes_allowed=True)
    assert is_solid(disc) and is_solid(disc, holes_allowed=True)


def test_choose_sigma_skips_candidates_that_are_not_solid():
    params = AutoGridParams(model="svm")
    rec = lambda d, e, solid: {"divisor": d, "sigma": 10.0 / d, "errors": e, "held_out": 20, "solid": solid}
    records = [rec(4, 1, True), rec(8, 0, True), rec(12, 0, True), rec(16, 0, False)]
    sigma, why = choose_sigma(records, 10.0, params)
    assert sigma == 10.0 / 12  # the smallest solid sigma among the fewest errors, not diag/16
    assert "diag/16: 0 (not solid)" in why and "the smaller sigma wins" in why
    sigma, why = choose_sigma([rec(4, 2, False), rec(8, 1, False)], 10.0, params)
    assert sigma == 10.0 / 8 and "no candidate gave a solid inside region" in why


def test_choose_sigma_ties_can_go_to_the_larger_sigma():
    """Issue 15: with sigma_ties="larger" the same tallies pick the widest of the tied solid
    candidates (diag/8, not diag/12); a candidate with fewer errors still wins outright."""
    params = AutoGridParams(model="svm", sigma_ties="larger")
    rec = lambda d, e, solid: {"divisor": d, "sigma": 10.0 / d, "errors": e, "held_out": 20, "solid": solid}
    sigma, why = choose_sigma([rec(4, 1, True), rec(8, 0, True), rec(12, 0, True), rec(16, 0, False)], 10.0, params)
    assert sigma == 10.0 / 8 and "the larger sigma wins" in why
    sigma, _ = choose_sigma([rec(4, 1, True), rec(8, 2, True), rec(12, 0, True)], 10.0, params)
    assert sigma == 10.0 / 12
    with pytest.raises(ValueError, match="sigma_ties"):
        AutoGridParams(model="svm", sigma_ties="middle")


# -- agreement measured, not manufactured (issue 18); exact references, grids near data (issue 10) --


def test_disagreement_is_measured_before_the_flood_and_reported(blob):
    from launcher import report

    world, _, params, cores = blob
    gaps = {core.disagreement for core in cores}
    assert len(gaps) == 1  # the fleet-wide max, identical on every robot
    gap = gaps.pop()
    assert 0.0 < gap <= params.tol  # measured (robots are never exactly equal before the flood), within tol
    results = [core.result() for core in cores]
    assert all(r["disagreement_before_flood"] == gap and r["converged"] for r in results)
    assert all(h["disagreement_before_flood"] <= params.tol for h in cores[0].grid_history if "norm2" in h)
    refs = report.autogrid_references(results, world.points, world.labels, C=None, soft_C=params.soft_C)
    out = report.build_autogrid_result(world, results, refs, wall_s=0.0)
    assert out["robots_agree"] and out["disagreement_before_flood"] == gap
    assert out["metrics"]["consensus_error"] == gap  # not a manufactured 0
    assert out["reference_exact"] and out["reference_note"] is None


def test_round_cap_is_neither_converged_nor_flooded():
    # a soft margin stopped at its round cap long before the robots agree: each robot keeps its
    # own function, and nobody claims convergence
    world, spec = build_world(Options(model="svm", fleet_id="t"))
    params = fast_params(spec, C=10.0, soft_rounds=20, max_refinements=1)
    cores = run_fleet(make_cores(robots_of(spec), params))
    for core in cores:
        res = core.result()
        assert core.phase == "done" and not core.converged and not res["converged"]
        assert res["disagreement_before_flood"] > params.tol and not res["agreed"]
        assert "disagree" in core.message and "not flooded" in core.message
    assert not np.array_equal(cores[0].function()[1], cores[1].function()[1])  # their own functions
    assert len(cores[0].grid_history) == 1  # no refinement from a function the fleet does not share


def test_soft_margin_cap_within_tolerance_is_not_converged():
    # the soft margin stopped by its cap, robots close enough to flood: the answer is shared, but
    # a capped solve is not a converged one
    world, spec = build_world(Options(model="svm", fleet_id="t"))
    ref = run_fleet(make_cores(robots_of(spec), fast_params(spec, C=10.0, tol=1e-2)))
    needed = ref[0].grid_history[0]["rounds"]
    cap = needed - 10  # a few rounds short of the stopping rule: close, but capped
    assert ref[0].converged and cap >= 40
    params = fast_params(spec, C=10.0, soft_rounds=cap, tol=1e-2)
    cores = run_fleet(make_cores(robots_of(spec), params))
    assert cores[0].disagreement <= params.tol and all(core.result()["agreed"] for core in cores)
    assert cores[0].grid_history[0]["status"] == "soft-margin round cap"
    assert f"round cap ({cap} rounds)" in cores[0].message
    assert not any(core.converged or core.result()["converged"] for core in cores)


def test_total_round_cap_is_not_converged():
    world, spec = build_world(Options(model="svm", fleet_id="t"))
    params = fast_params(spec, max_total_rounds=60)
    cores = run_fleet(make_cores(robots_of(spec), params))
    assert all(core.finished and not core.converged and core.round == 60 for core in cores)
    assert "round cap 60" in cores[0].message


def test_refined_grid_stays_near_data_and_full_rank(blob):
    world, _, params, cores = blob
    core = cores[0]
    res = core.result()
    assert res["grid_rank"] == len(core.grid)  # K_G keeps full numerical rank: the reference is exact
    assert all(h["rank"] == h["size"] for h in core.grid_history)
    coarse = lattice(core._box, core._h0, 0)
    added = core.grid[np.sqrt(((core.grid[:, None] - coarse[None]) ** 2).sum(-1)).min(axis=1) > 1e-9]
    assert len(added) > 0
    # a refined node's level-0 cell was marked by a robot with data within near_data * sigma + h0/sqrt2
    reach = params.near_data * core.sigma + np.sqrt(2.0) * core._h0
    d = np.sqrt(((added[:, None] - world.points[None]) ** 2).sum(-1)).min(axis=1)
    assert d.max() <= reach + 1e-9
    # no two grid points closer than the finest spacing the kernel can use
    gap = np.sqrt(((core.grid[:, None] - core.grid[None]) ** 2).sum(-1)) + np.eye(len(core.grid)) * 1e9
    assert gap.min() >= params.min_spacing * core.sigma * (1 - 1e-9)


def test_warm_start_maps_are_exact_on_the_superset_grid():
    from agents.autogrid_warm import carry_edges, superset_maps

    rng = np.random.default_rng(3)
    old = GridBasis(lattice((-1.0, 1.0, -1.0, 1.0), 0.9, 0), 0.6)
    new = GridBasis(np.vstack([old.grid, rng.uniform(-1, 1, (6, 2))]), 0.6)
    P, Q = superset_maps(old, new)
    x, lam = rng.normal(size=old.size), rng.normal(size=old.size)
    probe = rng.uniform(-2, 2, (50, 2))
    f_old = old.decision(probe, old.c_from_x(x), 0.3)
    f_new = new.decision(probe, new.c_from_x(P @ x), 0.3)
    np.testing.assert_allclose(f_new, f_old, atol=1e-9)  # the same function: c_new = [c_old; 0]
    assert (Q @ lam) @ (P @ x) == pytest.approx(lam @ x, rel=1e-9)  # the pairing lambda'x is kept

    class Edge:  # both ends of an edge hold the same (z, lambda): their carried copies stay equal
        def __init__(self):
            self.z, self.lam = np.append(x, 0.3), np.append(lam, -1.0)

    a, b = carry_edges({1: Edge()}, old, new), carry_edges({0: Edge()}, old, new)
    assert np.array_equal(a[1][1], b[0][1]) and np.array_equal(a[1][0], b[0][0])
    assert a[1][1][-1] == -1.0 and a[1][0][-1] == 0.3  # gamma carried unchanged


def test_sigma_sweep_tallies_match_independent_central_solves(sweep_runs):
    """The fleet's held-out error counts, checked against a count made without the fleet: for
    every candidate and fold, one central soft-margin solve (C = soft_C) on the training points of
    all robots on the candidate's coarse lattice, its sign on the held-out points. The fleet stops
    its sweep at validate_tol, so a held-out point within 0.05 of the decision boundary may land
    on either side; every other point must be counted the same."""
    from agents.autogrid_rules import coarse_lattice
    from agents.autogrid_sweep import held_mask

    world, robots, params, cores, _ = sweep_runs
    first = cores[0]
    for record in first.sigma_validation:
        sigma = first._diag / record["divisor"]  # the candidate, from the agreed data box
        _, _, grid = coarse_lattice(first.bounds, sigma, params.spacing_ratio, params.sweep_slot(record["divisor"]))
        basis = GridBasis(grid, sigma)
        errors, ambiguous = 0, 0
        for fold in range(params.validate_folds):
            held = {i: held_mask(holdout_units(p, y), fold, params) for i, (_, p, y) in robots.items()}
            train_p = np.vstack([p[~held[i]] for i, (_, p, _y) in robots.items()])
            train_y = np.concatenate([y[~held[i]] for i, (_, _p, y) in robots.items()])
            central = solve_central(basis, train_p, train_y, C=params.soft_C)
            for i, (_, p, y) in robots.items():
                yf = y[held[i]] * basis.decision(p[held[i]], central.c, central.gamma)
                errors += int(np.sum(yf <= 0))
                ambiguous += int(np.sum(np.abs(yf) < 0.05))
        assert abs(record["errors"] - errors) <= ambiguous, (record, errors, ambiguous)


# -- the sweep ends once its outcome is decided (issue 10) ----------------------------------------


def test_sweep_drops_wider_candidates_once_a_narrower_one_is_perfect():
    """On the notch (3 robots x 20 points) diag/16 stops with no held-out error and a solid
    region on every robot: no wider candidate can win any more (ties go to the smaller sigma), so
    the wider ones still running are dropped. The choice, the seed and the final function are
    those of the full sweep, bit for bit; only the sweep's rounds change."""
    notch = Path(__file__).resolve().parent / "data/notch.csv"
    world, spec = build_world(Options(model="svm", fleet_id="t", shape_file=str(notch), robots=3, points=20))
    robots = robots_of(spec)
    runs = {}
    for drop in (False, True):
        params = _sweep_params(spec, early_drop=drop)
        runs[drop] = run_fleet(make_cores(robots, params))
    full, early = runs[False][0], runs[True][0]
    assert early.sigma == full.sigma and early.sigma_reason == full.sigma_reason
    assert np.array_equal(early.grid, full.grid) and np.array_equal(early.function()[1], full.function()[1])
    assert all(np.array_equal(c.function()[1], early.function()[1]) and c.converged for c in runs[True])
    perfect = [r for r in full.sigma_validation if r["errors"] == 0 and r["solid"]]
    narrowest = max(perfect, key=lambda r: r["divisor"])
    assert all(r["converged"] for r in full.sigma_validation if r["divisor"] >= narrowest["divisor"])
    dropped = [r for r in early.sigma_validation if r["dropped"]]
    assert dropped and all(r["divisor"] < narrowest["divisor"] and not r["converged"] for r in dropped)
    for a, b in zip(full.sigma_validation, early.sigma_validation):
        if not b["dropped"]:
            assert a == {**b, "dropped": False}  # the tasks that ran to their stop: the same record
    # the sweep ends D rounds after the narrowest perfect candidate stopped (and every narrower
    # one), before the slowest task
    start, end = _phase_rounds(early, "validate")
    narrower = [r["rounds"] for r in early.sigma_validation if r["divisor"] > narrowest["divisor"]]
    assert end - start == max([narrowest["rounds"] + early.params.diameter, *narrower])
    assert end - start < _phase_rounds(full, "validate")[1] - start
    assert early.round < full.round


@pytest.mark.parametrize("ties", ["smaller", "larger"])
def test_early_drop_drops_only_candidates_that_lose_every_tie(ties):
    """Early drop's decision on its own (no fleet): diag/8 stopped perfect (D rounds ago, verdict
    0). Ties to the smaller sigma: the wider diag/4 is dropped once the narrower diag/16 has
    stopped, not before. Ties to the larger (issue 15): the mirror image, diag/16 is dropped once
    the wider diag/4 has stopped."""
    from types import SimpleNamespace

    from agents.autogrid_sweep import SigmaSweep

    sweep = object.__new__(SigmaSweep)
    sweep.params = AutoGridParams(model="svm", diameter=2, sigma_ties=ties)
    task = lambda cand, d, since, verdict: SimpleNamespace(cand=cand, fold=0, sigma=10.0 / d, since=since,
                                                           verdict=verdict, dropped=False)
    loser, winner = (0, 2) if ties == "smaller" else (2, 0)  # indices into diag/4, diag/8, diag/16
    tasks = [task(0, 4, -1, 0.0), task(1, 8, 2, 0.0), task(2, 16, -1, 0.0)]
    sweep.tasks = tasks
    sweep._drop_decided()
    assert not any(t.dropped for t in tasks)  # the candidate that would win a tie is still running
    tasks[winner].since, tasks[winner].verdict = 0, 1.0  # it stopped with a held-out error
    sweep._drop_decided()
    assert tasks[loser].dropped and not tasks[1].dropped and not tasks[winner].dropped


def test_near_data_cell_is_decided_on_lattice_indices_with_ties_allowed_both_ways():
    """Issue 19: a fine node is allowed when any of its nearest level-0 nodes is marked, decided
    on indices (exact), the same set as exact distances give, in any unit."""
    from agents.autogrid_rules import allowed_by_index

    rng = np.random.default_rng(5)
    for scale in (1.0, 1000.0, 1e-3):
        box = (-1.3 * scale, 2.9 * scale, -0.7 * scale, 1.6 * scale)
        h0 = 0.61 * scale
        coarse, shape0 = lattice(box, h0, 0, with_shape=True)
        marks = rng.random(len(coarse)) < 0.4
        for level in (1, 2):
            fine, shape = lattice(box, h0, level, with_shape=True)
            got = allowed_by_index(marks.reshape(shape0), level).ravel()
            d = np.sqrt(((fine[:, None] - coarse[None]) ** 2).sum(-1))
            nearest = d <= d.min(axis=1, keepdims=True) * (1 + 1e-9) + 1e-12 * scale
            want = (nearest & marks[None]).any(axis=1)
            assert got.shape == (len(fine),) and np.array_equal(got, want), (scale, level)
            assert (nearest.sum(axis=1) > 1).any()  # ties exist: halfway nodes and cell centres


def test_sweep_raster_kernel_kept_gives_the_basis_bits():
    """The sweep keeps k(raster, G) per candidate for the solid check: the decision values must
    be the basis's own bits, for the kept points and after the points change."""
    from agents.autogrid_sweep import _RasterBasis
    from agents.kernel import lattice as kernel_lattice

    rng = np.random.default_rng(3)
    basis = GridBasis(kernel_lattice(6, 5, (-2.0, 2.0, -1.5, 1.5)), 0.7)
    kept = _RasterBasis(basis)
    for points in (rng.normal(size=(50, 2)), rng.normal(size=(50, 2)), rng.normal(size=(7, 2))):
        for _ in range(2):
            c, gamma = rng.normal(size=basis.size), float(rng.normal())
            assert kept.decision(points, c, gamma).tobytes() == basis.decision(points, c, gamma).tobytes()


def test_two_widths_refined_points_narrow_exact_against_the_central_reference():
    """narrow_ratio (issue 15): the level-0 lattice keeps sigma, the points refinement adds get
    sigma / narrow_ratio; every robot agrees bit for bit and the fleet meets the central solve of
    the same two-width model (GridKernelSVC with the result's widths)."""
    from agents.estimator import GridKernelSVC

    world, spec = build_world(Options(model="svm", fleet_id="t"))
    params = fast_params(spec, narrow_ratio=3.0, max_points=50, tol=1e-3)
    cores = run_fleet(make_cores(robots_of(spec), params))
    first = cores[0]
    grid, c, gamma = first.function()
    assert all(np.array_equal(k.function()[1], c) and k.function()[2] == gamma for k in cores[1:])
    res = first.result()
    widths = np.asarray(res["widths"])
    coarse = lattice(first._box, first._h0, 0)
    on = np.sqrt(((grid[:, None] - coarse[None]) ** 2).sum(-1)).min(axis=1) < 1e-9
    assert on.any() and (~on).any()
    assert np.all(widths[on] == first.sigma) and np.allclose(widths[~on], first.sigma / 3.0, rtol=1e-15)
    assert res["grid_rank"] == len(grid) and first.margin == "hard"
    ref = GridKernelSVC(grid=grid, sigma=first.sigma, widths=widths).fit(world.points, world.labels)
    assert first._basis.function_error(c, gamma, ref.coef_, ref.intercept_) < 1e-3
    assert np.all(ref.predict(world.points) == world.labels)


def test_widths_for_data_keeps_one_width_when_few_points_are_held_out():
    """narrow_min_held (issue 15, step 6): the two widths only when the agreed tally held out at
    least that many points per fold; below it the run uses one width, the rest unchanged."""
    from agents.autogrid_rules import widths_for_data

    params = AutoGridParams(model="svm", narrow_ratio=3.0, narrow_min_held=16, validate_folds=4)
    sparse = [{"held_out": 4 * 15, "folds": 4}]  # 15 per fold
    dense = [{"held_out": 4 * 16, "folds": 4}]
    one, note = widths_for_data(params, sparse)
    assert one.narrow_ratio == 1.0 and "one width" in note
    assert dataclasses.replace(one, narrow_ratio=3.0) == params
    two, note = widths_for_data(params, dense)
    assert two is params and "two widths" in note
    assert widths_for_data(dataclasses.replace(params, narrow_min_held=0), sparse)[0].narrow_ratio == 3.0
    assert widths_for_data(params, [])[0] is params
    with pytest.raises(ValueError):
        AutoGridParams(model="svm", narrow_min_held=-1)


def test_folds_for_data_runs_fewer_folds_below_the_unit_threshold():
    """sparse_units (issue 15, step 6): fewer held-out units than the threshold -> sparse_folds
    folds; at or above it, or with the threshold 0, the given params unchanged."""
    from agents.autogrid_rules import folds_for_data

    params = AutoGridParams(model="svm", validate_folds=4, sparse_units=60)
    few, note = folds_for_data(params, 59)
    assert few.validate_folds == 2 and "2 folds instead of 4" in note
    assert dataclasses.replace(few, validate_folds=4) == params
    assert folds_for_data(params, 60)[0] is params
    off = dataclasses.replace(params, sparse_units=0)
    assert folds_for_data(off, 10)[0] is off
    assert folds_for_data(dataclasses.replace(params, validate_folds=2), 10)[0].validate_folds == 2
    with pytest.raises(ValueError):
        AutoGridParams(model="svm", sparse_folds=0)


def test_sparse_fleet_runs_fewer_folds_one_width_and_resumes_bit_for_bit():
    """The default scenario (3 x 20 points: 30 held-out units, 8 points held out in fold 0) with
    sparse_units 60 and narrow_min_held 16: the sweep runs sparse_folds (1) of the 2 folds, the
    run keeps one width, every robot agrees, and restarts in the sweep and after the tally (the
    derived parameters re-derived from the restored counts) end bit for bit where the
    uninterrupted run ends."""
    world, spec = build_world(Options(model="svm", fleet_id="t"))
    params = fast_params(spec, validate_divisors=(4.0,), validate_folds=2, sparse_units=60, sparse_folds=1,
                         validate_rounds=60, narrow_ratio=3.0, narrow_min_held=16, max_points=60, tol=1e-3)
    robots = robots_of(spec)
    ref = run_fleet(make_cores(robots, params))
    first = ref[0]
    assert [r["folds"] for r in first.sigma_validation] == [1]
    assert "widths" not in first.result() and first.params.narrow_ratio == 1.0
    assert "1 folds instead of 2: 30 held-out units" in first.sigma_reason and "one width" in first.sigma_reason
    assert all(np.array_equal(k.function()[1], first.function()[1]) for k in ref[1:])
    stops = {"sweep": _phase_rounds(first, "validate")[0] + 5, "after": _phase_rounds(first, "vote")[0] + 1}
    for key, (_, blobs) in _checkpoints_at(robots, params, stops).items():
        resumed = _resume_from_checkpoints(None, robots, params, blobs)
        assert resumed[0].params == first.params, key
        for a, b in zip(ref, resumed):
            assert a.round == b.round and a.grid_history == b.grid_history, key
            assert np.array_equal(a.function()[1], b.function()[1]), key


def test_choose_widths_keeps_two_widths_only_when_they_make_fewer_held_out_errors():
    """narrow_by_holdout (issue 15, step 7): the rule on the agreed width tally: two widths only
    on strictly fewer held-out errors; a tie keeps one width."""
    from agents.autogrid_rules import choose_widths

    params = AutoGridParams(model="svm", narrow_ratio=3.0, narrow_by_holdout=True)
    rec = lambda e: {"errors": e, "held_out": 40}  # noqa: E731
    assert choose_widths(params, [rec(3), rec(2)])[0] is params
    one, note = choose_widths(params, [rec(2), rec(2)])
    assert one.narrow_ratio == 1.0 and "one width" in note and "2/40" in note
    assert choose_widths(params, [rec(1), rec(4)])[0].narrow_ratio == 1.0


def test_width_test_is_one_stacked_pass_agreed_by_every_robot_and_resumes_bit_for_bit():
    """narrow_by_holdout: after the seed, one width against two on the held-out folds, in two
    phases (WIDTHS: the folds on both refined grids at once; WTALLY: exact counts). Every robot
    decides the same; the counts are the folds' held-out errors of each model's iterate; the
    final grid's widths follow the decision; restarts in both phases end bit for bit."""
    from agents.autogrid_sweep import held_mask

    world, spec = build_world(Options(model="svm", fleet_id="t"))
    params = fast_params(spec, validate_divisors=(4.0,), validate_folds=2, validate_rounds=60, narrow_ratio=3.0,
                         narrow_by_holdout=True, max_points=60, tol=1e-3, max_refinements=1)
    robots = robots_of(spec)
    ref = run_fleet(make_cores(robots, params))
    first = ref[0]
    names = [p for p, _ in first.phases]
    assert names[:6] == ["bounds", "validate", "tally", "seed", "widths", "wtally"] and names[6] == "vote"
    recs = first.width_validation
    assert [r["divisor"] for r in recs] == [1.0, 3.0] and all(r["folds"] == 2 for r in recs)
    assert all(k.width_validation == recs and k.params == first.params for k in ref[1:])
    held = sum(int(np.sum(held_mask(holdout_units(p, y), f, params))) for _, p, y in robots.values() for f in range(2))
    assert recs[0]["held_out"] == recs[1]["held_out"] == held > 0
    two = recs[1]["errors"] < recs[0]["errors"]
    assert (first.params.narrow_ratio == 3.0) == two and ("widths" in first.result()) == two
    assert "width test: " + ("two widths" if two else "one width") in first.sigma_reason
    assert all(np.array_equal(k.function()[1], first.function()[1]) for k in ref[1:])
    w0, w1 = _phase_rounds(first, "widths")
    stops = {"widths": (w0 + w1) // 2, "wtally": _phase_rounds(first, "wtally")[0]}
    for key, (in_phase, blobs) in _checkpoints_at(robots, params, stops).items():
        assert in_phase == key
        resumed = _resume_from_checkpoints(None, robots, params, blobs)
        for a, b in zip(ref, resumed):
            assert a.round == b.round and a.grid_history == b.grid_history and a.width_validation == b.width_validation
            assert np.array_equal(a.function()[1], b.function()[1]), key


@pytest.mark.parametrize("argv", [[], ["frob"], ["collect"], ["collect", "bogus", "."], ["rank", "/nonexistent"],
                                  ["multiscale", ".", "--jobs", "0"], ["fill"], ["fill", "/nonexistent"],
                                  ["fill", ".", "--jobs", "0"]])
def test_rules_emulation_cli_exits_2_with_one_message_on_bad_use(argv, capsys):
    """benchmarks/autogrid_rules_emulation.py once raised an IndexError traceback without arguments."""
    from benchmarks import autogrid_rules_emulation as emulation

    with pytest.raises(SystemExit) as exit_info:
        emulation.main(argv)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert "error:" in err and "Traceback" not in err


@pytest.mark.parametrize("argv, says", [(["fill", ".", "--jobs", "0"], "--jobs must be >= 1"),
                                        (["fill", "/nonexistent"], "not a directory")])
def test_rules_emulation_fill_names_the_bad_argument(argv, says, capsys):
    """The fill subcommand checks its arguments itself before any data set is built (--jobs 0 would otherwise
    reach ProcessPoolExecutor as a ValueError traceback, a missing OUT a FileNotFoundError after minutes)."""
    from benchmarks import autogrid_rules_emulation as emulation

    with pytest.raises(SystemExit) as exit_info:
        emulation.main(argv)
    assert exit_info.value.code == 2 and says in capsys.readouterr().err
