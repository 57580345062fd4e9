"""The continuous-time ADMM core (agents/ct_admm.py): convergence, shape of the trajectories,
stability across scenarios, exact resumption, and the sans-IO contract.

Figures asserted here are the measured ones of docs/ct-admm.md with a margin, so a regression
fails a test. Most scenario runs drive the cores in lock-step directly (no frame codec) to keep
the file fast; `test_in_process_fleet_matches_lockstep` shows that this is the same computation.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import msgpack
import numpy as np
import pytest

from agents.ct_admm import ContinuousTimeADMM, CTADMMParams
from agents.problem import solve_central
from agents.spec import ALGORITHMS, FleetSpec, build_core, restore_core
from launcher.gridstudy import run_grid_study
from launcher.simulate import simulate_fleet
from launcher.trajectory import overshoot, plot_trajectory, trajectory_from_trace
from launcher.world import Options, build_world
from protocol.frames import StateUpdate

SHAPES = Path(__file__).resolve().parent.parent / "launcher" / "shapes"
DATA = Path(__file__).resolve().parent / "data"
TARGET = 1e-2  # function error every robot must reach within the stop time


def ct_run(params: dict | None = None, **options):
    """(world, spec, central) of a ct-admm scenario; `params` override the fleet file's."""
    options.setdefault("fleet_id", "ct-test")
    options.setdefault("preset", "paper")  # the paper's grid 5x3 and sigma 1 unless a test gives its own
    world, spec = build_world(Options(algorithm="ct-admm", **options))
    if params:
        spec = dataclasses.replace(spec, params={**spec.params, **params})
    return world, spec, solve_central(spec.basis, world.points, world.labels, spec.C)


def lockstep(spec: FleetSpec, cores: dict[int, ContinuousTimeADMM] | None = None, rounds: int | None = None):
    """Every robot advances once per round with every neighbour's exact sample (no faults)."""
    cores = cores or {r: build_core(spec, r) for r in spec.robot_ids}
    while not all(c.finished for c in cores.values()):
        if rounds is not None and min(c.round for c in cores.values()) >= rounds:
            break
        sent = {r: c.outgoing() for r, c in cores.items()}
        for c in cores.values():
            for j in c.neighbours:
                c.receive(sent[j])
        for c in cores.values():
            c.advance()
    return cores


def errors_per_round(spec: FleetSpec, central, traces: list[dict]) -> np.ndarray:
    """Largest function error over robots at every recorded round."""
    b = spec.basis
    rounds = sorted(int(k) for k in traces[0])

    def err(v) -> float:
        v = np.asarray(v, dtype=float)
        return b.function_error(b.c_from_x(v[:-1]), v[-1], central.c, central.gamma)

    return np.array([max(err(t[k] if k in t else t[str(k)]) for t in traces) for k in rounds])


@pytest.fixture(scope="module")
def full_run():
    """The default scenario through the in-process fleet, for the whole 10 s (no early stop)."""
    world, spec, central = ct_run(params={"tol": 1e-12})
    return world, spec, central, simulate_fleet(spec)


# -- parameters and registration --------------------------------------------------------------
def test_params_defaults_are_the_papers():
    p = CTADMMParams()
    assert (p.step, p.period, p.stop_time) == (1e-3, 1e-2, 10.0)
    assert p.steps_per_round == 10 and p.rounds == 1000
    assert p.dual_ratio <= p.overdamp_limit  # the local dual modes are real by default
    assert p.primal_gain <= 1 and p.consensus_gain <= 1


@pytest.mark.parametrize(
    "bad, words",
    [
        ({"period": 0.0105}, "whole number of steps"),
        ({"step": 0.0}, "step must be a positive"),
        ({"primal_gain": 1.5}, "primal_gain"),
        ({"dual_ratio": 4.0, "primal_gain": 0.5}, "dual_ratio"),
        ({"consensus_gain": 2.0}, "consensus_gain"),
        ({"ref_time": -1.0}, "ref_time"),
        ({"metric": "diagonal"}, "metric"),
        ({"stop_time": float("nan")}, "stop_time"),
    ],
)
def test_params_validation_names_the_problem(bad, words):
    with pytest.raises(ValueError, match=words):
        CTADMMParams(**bad)


def test_params_from_fleet_file():
    """The fleet file holds exactly CTADMMParams' fields (launcher/options.py); other keys fail by name."""
    p = CTADMMParams.from_params({"tol": 1e-3, "max_rounds": 5000, "diameter": 2, "step": 5e-4, "period": 0.02})
    assert (p.step, p.period, p.tol, p.diameter, p.rounds) == (5e-4, 0.02, 1e-3, 2, 500)
    assert CTADMMParams.from_params({"rho": 3.0}).rho == 3.0  # the flow's own gain
    assert CTADMMParams.from_params({"max_rounds": 40}).rounds == 40
    for key in ("stoptime", "relax", "ct_step"):  # a typo, a discrete-ADMM key, an old prefix
        with pytest.raises(ValueError, match=f"unknown ct-admm parameter '{key}'"):
            CTADMMParams.from_params({key: 3.0})


def test_registered_and_exchanges_x_gamma():
    assert "ct-admm" in ALGORITHMS
    _, spec, _ = ct_run()
    core = build_core(spec, 0)
    assert isinstance(core, ContinuousTimeADMM) and core.algorithm == "ct-admm"
    assert core.dim == spec.dim == spec.basis.size + 1
    assert core.outgoing().values.shape == (spec.dim,)


# -- the default scenario ---------------------------------------------------------------------
def test_default_scenario_reaches_target_within_stop_time():
    """Fleet-file defaults (residual rule on): ends within 10 s, every robot within 1e-2."""
    _, spec, central = ct_run()
    out = simulate_fleet(spec)
    assert all(r["rounds"] <= 1000 and r["time_s"] <= 10.0 for r in out.robots)
    errs = errors_per_round(spec, central, [r["trace"] for r in out.robots])
    assert errs[-1] < TARGET, f"final function error {errs[-1]:.2e}"
    for r in out.robots:
        assert r["algorithm"] == "ct-admm" and len(r["x"]) == spec.basis.size
        assert {"id", "x", "gamma", "rounds", "converged", "neighbours", "dropped"} <= set(r)


def test_time_to_target_is_the_papers(full_run):
    """Paper: about 500 T_sp. Measured 515 rounds (5.15 s); the last round is far below."""
    _, spec, central, out = full_run
    errs = errors_per_round(spec, central, [r["trace"] for r in out.robots])
    below = np.flatnonzero(errs < TARGET)
    assert below.size, "never reached 1e-2"
    first = int(below[0])
    assert 400 <= first <= 600, f"first reached 1e-2 at round {first}"
    assert np.all(errs[first:] < TARGET), "left the 1e-2 band after reaching it"
    assert errs[-1] < 1e-3


def test_no_overshoot_robot_1(full_run):
    """Every component of [x^1; gamma^1] passes its final value by at most 5 % of its travel."""
    _, spec, _, out = full_run
    first = min(out.robots, key=lambda r: r["id"])
    times, values = trajectory_from_trace(first["trace"], CTADMMParams().period)
    assert times[-1] == pytest.approx(10.0) and values.shape == (1001, spec.dim)
    ratios = overshoot(values)
    assert ratios.max() <= 0.05, f"component {int(ratios.argmax())} overshoots by {ratios.max():.1%}"
    # and smooth at the figure's scale: what any component walks back (total variation beyond its
    # travel, halved) is under 2 % of the largest travel -- no visible oscillation in Fig. 4
    travel = np.abs(values[-1] - values[0])
    backtrack = (np.abs(np.diff(values, axis=0)).sum(axis=0) - travel) / 2
    assert backtrack.max() <= 0.02 * travel.max(), f"component {int(backtrack.argmax())} walks back"
    assert ratios[-1] == 0.0  # gamma, drawn highlighted, approaches from one side


def test_overshoot_needs_the_prefilter():
    """Without the reference prefilter the same flow overshoots: the 5 % test can fail."""
    _, spec, _ = ct_run(params={"tol": 1e-12, "ref_time": 0.0, "stop_time": 4.0})
    cores = lockstep(spec)
    _, values = trajectory_from_trace(cores[0].trace, 0.01)
    assert overshoot(values).max() > 0.5


def test_overshoot_definition():
    values = np.array([[0.0, 0.0, 1.0, 2.0], [1.1, -0.5, 0.5, 2.0], [1.0, -1.0, 0.0, 2.0]])
    ratios = overshoot(values)
    assert ratios[0] == pytest.approx(0.1)  # went 0.1 past a travel of 1
    assert ratios[1] == 0 and ratios[2] == 0  # monotone approaches, either direction
    assert ratios[3] == 0  # never moved
    assert overshoot(np.array([[0.0], [0.3], [0.0]]))[0] == np.inf  # moved and came back: no travel
    with pytest.raises(ValueError):
        overshoot(np.zeros(3))


def test_in_process_fleet_matches_lockstep(full_run):
    """The frame codec and the fleet loop do not perturb a single bit of the flow."""
    _, spec, _, out = full_run
    cores = lockstep(spec, rounds=200)
    for r in out.robots:
        for k in range(0, 201, 50):
            assert np.asarray(r["trace"][k]).tobytes() == cores[r["id"]].trace[k].tobytes()


# -- stability across scenarios ---------------------------------------------------------------
SCENARIOS = {
    "star": {"shape": "star"},
    "crescent": {"shape": "crescent"},
    "bean": {"shape": "bean"},
    "polygon-csv-l-block": {"shape_file": str(SHAPES / "l_block.csv")},
    "polygon-csv-notch": {"shape_file": str(DATA / "notch.csv")},
    "3-line": {"topology": "line"},
    "8-complete": {"robots": 8, "stop_time": 6.0},
    "8-ring": {"robots": 8, "topology": "ring", "stop_time": 6.0},
    "16-line": {"robots": 16, "topology": "line", "stop_time": 6.0},
    "16-ring": {"robots": 16, "topology": "ring", "stop_time": 6.0},
    "16-complete": {"robots": 16, "stop_time": 3.0},
    "soft-margin": {"C": 1.0},
}


@pytest.mark.parametrize("name", list(SCENARIOS))
def test_stable_across_scenarios(name):
    """Finite, bounded, and converging: the largest error of each quarter of the run is below
    that of the quarter before, so the error envelope shrinks all the way to the end.

    Three robots also reach the 1e-2 target within the 10 s (measured: 4.4-7.3 s); 8 and 16
    robots are slower (the discrete ADMM needs hundreds of rounds there too) and run a shorter
    horizon to keep this file fast: there the claim is the shrinking envelope, not a level.
    """
    options = dict(SCENARIOS[name])
    stop = options.pop("stop_time", 10.0)
    _, spec, central = ct_run(params={"tol": 1e-12, "stop_time": stop}, **options)
    assert central.solved
    cores = lockstep(spec)
    v_star = np.append(central.x, central.gamma)
    for c in cores.values():
        values = np.array(list(c.trace.values()))
        assert np.all(np.isfinite(values)) and np.isfinite(c.dual_norm)
        assert np.abs(values).max() < 5 * np.abs(v_star).max() + 10
    errs = errors_per_round(spec, central, [c.trace for c in cores.values()])
    mid, end = errs[len(errs) // 2], errs[-1]
    assert end < mid, f"error {mid:.2e} at mid-run, {end:.2e} at the end"
    quarters = [q.max() for q in np.array_split(errs[1:], 4)]
    assert all(b < a for a, b in zip(quarters, quarters[1:])), f"quarter maxima {quarters}"
    if spec.n_robots == 3:
        assert end < TARGET, f"3 robots: {end:.2e} after {stop:g} s"


def test_lone_robot_solves_its_own_problem():
    _, spec, central = ct_run(params={"tol": 1e-12}, robots=1)
    core = lockstep(spec)[0]
    assert core.neighbours == () and core.round == 1000
    b = spec.basis
    v = core.values
    assert b.function_error(b.c_from_x(v[:-1]), v[-1], central.c, central.gamma) < 1e-3


def test_scalar_metric_from_norm_bounds_is_stable():
    """The plain gradient flow with steps from |A_l|^2 and the degree: stable, only slower."""
    _, spec, central = ct_run(params={"tol": 1e-12, "metric": "scalar"})
    errs = errors_per_round(spec, central, [c.trace for c in lockstep(spec).values()])
    assert np.all(np.isfinite(errs)) and errs[-1] < errs[len(errs) // 2] < errs[0]


# -- invariants and the sans-IO contract ------------------------------------------------------
def test_consensus_duals_stay_antisymmetric():
    """Both ends of an edge hold bit-identical duals: the fleet's duals sum to zero exactly."""
    _, spec, _ = ct_run(params={"tol": 1e-12}, robots=4, topology="ring")
    cores = lockstep(spec, rounds=57)
    for l, c in cores.items():
        for j in c.neighbours:
            assert c._lam[j].tobytes() == cores[j]._lam[l].tobytes()


def test_checkpoint_restore_resumes_bit_identically():
    _, spec, _ = ct_run(params={"tol": 1e-12, "stop_time": 0.8})
    straight = lockstep(spec)
    half = lockstep(spec, rounds=33)
    saved = {r: msgpack.unpackb(msgpack.packb(c.checkpoint()), strict_map_key=False) for r, c in half.items()}
    resumed = lockstep(spec, {r: restore_core(spec, r, s) for r, s in saved.items()})
    for r, c in straight.items():
        assert resumed[r].round == c.round == 80
        assert resumed[r].values.tobytes() == c.values.tobytes()
        assert resumed[r].checkpoint() == c.checkpoint()
    with pytest.raises(ValueError, match="another robot"):
        build_core(spec, 1).restore(saved[0])


def test_missing_neighbour_blocks_advance():
    """No stale substitute: without a neighbour's exact sample of this round nothing moves."""
    _, spec, _ = ct_run()
    cores = {r: build_core(spec, r) for r in spec.robot_ids}
    me = cores[0]
    me.receive(cores[1].outgoing())
    assert me.missing() == (2,) and not me.ready()
    with pytest.raises(RuntimeError, match="waiting for"):
        me.advance()
    before = me.checkpoint()
    # a sample from a round too far ahead, or from a stranger, does not count
    far = StateUpdate(sender=2, round=2, values=np.ones(spec.dim), flags=0, prev_values=np.ones(spec.dim))
    me.receive(far)
    me.receive(StateUpdate(sender=7, round=0, values=np.ones(spec.dim), flags=0, prev_values=None))
    assert me.missing() == (2,)
    assert me.checkpoint()["values"] == before["values"]
    # the exact round-0 sample recovered from robot 2's next frame (piggybacked) unblocks it
    cores[2].receive(cores[0].outgoing())
    cores[2].receive(cores[1].outgoing())
    me.receive(cores[2].advance())
    assert me.ready()
    me.advance()
    assert me.round == 1


def test_finished_core_refuses_to_advance():
    _, spec, _ = ct_run(params={"stop_time": 0.05})
    cores = lockstep(spec)
    assert all(c.finished and c.round == 5 and not c.converged for c in cores.values())
    with pytest.raises(RuntimeError, match="finished"):
        cores[0].advance()


def test_drop_neighbour_converges_on_the_survivors_data():
    """Dropping a dead robot's edges keeps the survivors' duals summing to zero, so they converge
    on the central solution of *their* data (slowly: the 1e-2 target is reached near 30 s)."""
    world, spec, _ = ct_run(params={"tol": 1e-12, "stop_time": 40.0}, robots=4)
    cores = {r: build_core(spec, r) for r in spec.robot_ids}
    lockstep(spec, cores, rounds=20)
    dead = cores.pop(3)
    for c in cores.values():
        c.drop_neighbour(dead.robot_id)
    survivors = lockstep(spec, cores)
    assert all(c.round == 4000 and 3 in c.dropped for c in survivors.values())
    kept = [r for r in world.robots if r.id != dead.robot_id]
    ref = solve_central(spec.basis, np.vstack([r.points for r in kept]), np.concatenate([r.labels for r in kept]))
    assert ref.solved
    errs = errors_per_round(spec, ref, [c.trace for c in survivors.values()])
    assert errs[-1] < TARGET, f"survivors {errs[-1]:.2e} from their own central solution"


# -- pictures and the grid study --------------------------------------------------------------
def test_plot_trajectory_from_trace(full_run, tmp_path):
    _, spec, central, out = full_run
    times, values = trajectory_from_trace(out.robots[0]["trace"], 0.01)
    path = tmp_path / "trajectory.png"
    plot_trajectory(path, times, values, reference=np.append(central.x, central.gamma))
    assert path.stat().st_size > 10_000
    with pytest.raises(ValueError):
        plot_trajectory(path, times[:-1], values)


def test_grid_study_shows_the_infeasible_grid(tmp_path):
    study = run_grid_study(tmp_path, quiet=True)
    assert study.good.central_status == "solved" and study.good.separates
    assert study.good.function_error < TARGET
    bad = study.bad
    assert bad.central_status == "infeasible"
    assert "INFEASIBLE" in study.message and "wrong side" in study.message
    assert not bad.separates and bad.duals_growing  # says so, and the curves show it
    assert all(np.all(np.isfinite(r["x"])) for r in bad.robots)  # bounded long enough to draw
    assert study.png.exists() and study.png.stat().st_size > 20_000
