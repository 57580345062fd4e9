"""The in-process fleet: every robot reaches the centralized solution, with and without faults."""

from __future__ import annotations

import numpy as np
import pytest

from launcher.scenario import write_data_csv
from launcher.simulate import simulate_fleet
from protocol.links import LinkFaults

from .conftest import make_run, max_function_error

BOUND = 1e-3  # the bound on every robot's function error against the central solve


def check_answer(world, spec, central, outcome):
    assert central.solved
    robots = outcome.robots
    assert all(r["converged"] for r in robots), [r["rounds"] for r in robots]
    assert len({r["rounds"] for r in robots}) == 1  # all stop in the same round
    assert max_function_error(spec, central, robots) < BOUND
    basis = spec.basis
    if spec.C is not None:
        return  # a soft margin may leave points on the wrong side by design
    for r in robots:  # every training point of every robot on the right side of every curve
        f = basis.decision(world.points, basis.c_from_x(np.asarray(r["x"])), r["gamma"])
        assert np.all(np.sign(f) == world.labels)


def test_default_is_the_papers_setting_and_converges(default_run):
    world, spec, central = default_run
    assert spec.n_robots == 3 and all(len(r.labels) == 20 for r in world.robots) and spec.sigma == 1.0
    outcome = simulate_fleet(spec)
    check_answer(world, spec, central, outcome)
    print(f"default scenario: {outcome.robots[0]['rounds']} rounds")


@pytest.mark.parametrize(
    "kwargs",
    [
        {"shape": "bean", "seed": 1},
        {"shape": "star", "seed": 2},
        {"shape": "crescent", "seed": 3},
        {"shape": "ellipse", "seed": 4, "topology": "line"},
        {"robots": 4, "topology": "ring", "seed": 5},
        {"robots": 5, "topology": "line"},
        {"robots": 8, "topology": "ring", "points": 14},
        {"robots": 16, "topology": "geometric", "comm_range": 3.0, "points": 10},
        {"C": 10.0, "shape": "cross", "seed": 6},
    ],
    ids=lambda kw: "-".join(f"{k}={v}" for k, v in kw.items()),
)
def test_fleet_reaches_the_central_solution(kwargs):
    world, spec, central = make_run(**kwargs)
    check_answer(world, spec, central, simulate_fleet(spec))


def test_data_file_and_shape_file(tmp_path, default_run):
    world, _, _ = default_run
    data = tmp_path / "data.csv"
    write_data_csv(data, world.robots)
    w2, spec2, central2 = make_run(data=str(data))
    assert w2.shape is None
    np.testing.assert_array_equal(w2.points, world.points)  # bit-exact round trip
    check_answer(w2, spec2, central2, simulate_fleet(spec2))

    shape = tmp_path / "l.csv"
    shape.write_text("x,y\n-2,-1.5\n2,-1.5\n2,0\n0,0\n0,1.5\n-2,1.5\n")
    w3, spec3, central3 = make_run(shape_file=str(shape))
    check_answer(w3, spec3, central3, simulate_fleet(spec3))


FAULTS = [
    LinkFaults(loss=0.3, delay=0.02, jitter=0.01, duplicate=0.05, reorder=0.1),
    LinkFaults(loss=0.5),
]


@pytest.fixture(scope="module")
def clean_ring():
    """The perfect-network run both fault cases below compare with (deterministic: run once)."""
    _, clean_spec, _ = make_run(robots=4, topology="ring", max_rounds=120, tol=1e-12)
    return simulate_fleet(clean_spec)


@pytest.mark.parametrize("faults", FAULTS, ids=["mixed", "loss50"])
def test_faults_change_time_not_iterates(clean_ring, faults):
    """Exact recovery: under loss, delay, duplication and reordering every robot computes the
    very same iterates as on a perfect network -- so the same answer, not a biased one."""
    _, faulty_spec, _ = make_run(robots=4, topology="ring", max_rounds=120, tol=1e-12, faults=faults, seed=0)
    clean = clean_ring
    faulty = simulate_fleet(faulty_spec)
    for a, b in zip(clean.robots, faulty.robots, strict=True):
        assert a["trace"].keys() == b["trace"].keys()
        for k in a["trace"]:
            assert a["trace"][k] == b["trace"][k]
    assert sum(r["frames_lost"] for r in faulty.robots) > 0
    assert faulty.virtual_s > clean.virtual_s
    if faults.delay:
        assert faulty.virtual_s >= 120 * faults.delay * 0.5


@pytest.mark.parametrize("bad", [np.nan, 3e77], ids=["nan", "exploding"])
def test_diverging_iterate_is_an_error_not_a_result(monkeypatch, bad):
    """Issue 11: a non-finite or exploding iterate ends the in-process run with FleetFailure
    (one line naming robot and round), never a result that could read as converged."""
    from agents.admm import ConsensusADMM
    from launcher.simulate import FleetFailure

    step = ConsensusADMM._step

    def poisoned(self, mine, theirs):
        new, below = step(self, mine, theirs)
        if self.robot_id == 1 and self.round == 4:
            new = new.copy()
            new[0] = bad
        return new, below

    monkeypatch.setattr(ConsensusADMM, "_step", poisoned)
    _world, spec, _central = make_run()
    with pytest.raises(FleetFailure, match=r"^robot 1 round 5: diverged: (non-finite|exploding) iterate"):
        simulate_fleet(spec)


def test_solver_failure_is_an_error_not_a_result(monkeypatch):
    from agents.admm import ConsensusADMM
    from agents.problem import SolverError
    from launcher.simulate import FleetFailure

    step = ConsensusADMM._step

    def failing(self, mine, theirs):
        if self.robot_id == 2 and self.round == 7:
            raise SolverError("piqp returned PIQP_MAX_ITER_REACHED")
        return step(self, mine, theirs)

    monkeypatch.setattr(ConsensusADMM, "_step", failing)
    _world, spec, _central = make_run()
    with pytest.raises(FleetFailure, match=r"^robot 2 round 7: local solver failed: piqp returned PIQP_MAX_ITER_REACHED$"):
        simulate_fleet(spec)
