"""The centralized QP against an independent reference: scikit-learn's SVC on the same basis."""

from __future__ import annotations

import numpy as np
import pytest
from sklearn.svm import SVC

from agents.kernel import GridBasis
from agents.problem import InfeasibleError, MarginQP, certify_hard_margin, margin_rows, solve_central
from launcher.scenario import make_grid

from .conftest import make_run


def reference_svc(basis: GridBasis, points, labels, C: float):
    """A linear SVM on the Nystroem features phi(d) is the same problem, solved by libsvm."""
    svc = SVC(kernel="linear", C=C, tol=1e-10, max_iter=10**7)
    svc.fit(basis.features(points), labels)
    return svc.coef_[0], float(svc.intercept_[0])


@pytest.mark.parametrize("shape,seed", [("blob", 0), ("star", 1), ("bean", 2), ("ellipse", 3), ("crescent", 4)])
def test_hard_margin_matches_svc(shape, seed):
    world, spec, central = make_run(shape=shape, seed=seed)
    assert central.solved
    x_ref, g_ref = reference_svc(spec.basis, world.points, world.labels, C=1e9)
    c_ref = spec.basis.c_from_x(x_ref)
    assert spec.basis.function_error(central.c, central.gamma, c_ref, g_ref) < 1e-4
    margins = world.labels * spec.basis.decision(world.points, central.c, central.gamma)
    assert margins.min() == pytest.approx(1.0, abs=1e-6)  # support vectors sit on the margin


def soft_objective(basis, points, labels, x, gamma, C):
    hinge = np.maximum(0.0, 1.0 - labels * (basis.features(points) @ x + gamma))
    return 0.5 * float(x @ x) + C * float(hinge.sum())


@pytest.mark.parametrize("C", [0.1, 1.0, 10.0])
def test_soft_margin_matches_svc(C):
    world, spec, central = make_run(C=C, seed=5)
    x_ref, g_ref = reference_svc(spec.basis, world.points, world.labels, C=C)
    # x is unique (strongly convex); the offset may not be when every support vector is at the
    # bound C, so compare the objective, which is what both solvers minimise
    np.testing.assert_allclose(central.x, x_ref, atol=1e-4 * max(1.0, np.abs(x_ref).max()))
    ours = soft_objective(spec.basis, world.points, world.labels, central.x, central.gamma, C)
    theirs = soft_objective(spec.basis, world.points, world.labels, x_ref, g_ref, C)
    assert ours <= theirs * (1 + 1e-6)
    assert ours == pytest.approx(theirs, rel=1e-5)


def test_infeasible_grid_is_detected_in_words():
    # the paper's Fig. 5: a coarse grid cannot separate the data with a hard margin
    world, spec, _ = make_run(shape="cross")
    basis = GridBasis(make_grid(2, 2, world.bounds), 1.0)
    sol = solve_central(basis, world.points, world.labels)
    assert sol.status == "infeasible"
    assert "infeasible" in sol.message and "--C" in sol.message
    soft = solve_central(basis, world.points, world.labels, C=10.0)
    assert soft.solved  # a soft margin is always feasible


def test_local_qp_reports_infeasibility_as_error():
    # two identical feature rows with opposite labels: no (x, gamma) puts both on their side
    qp = MarginQP(np.ones((2, 1)), np.array([1, -1]), x_weight=1.0, prox_weight=0.0, C=None)
    with pytest.raises(InfeasibleError):
        qp.solve(np.zeros(2))


def test_dense_grid_still_solves():
    world, _, _ = make_run()
    basis = GridBasis(make_grid(25, 20, world.bounds), 1.0)  # grid far denser than sigma
    sol = solve_central(basis, world.points, world.labels)
    assert sol.solved
    margins = world.labels * basis.decision(world.points, sol.c, sol.gamma)
    assert margins.min() > 1 - 1e-6


@pytest.mark.parametrize("robots,topology", [(3, "complete"), (4, "ring"), (8, "ring")])
def test_central_hard_margin_is_certified_by_its_kkt_conditions(robots, topology):
    """The reference is the exact optimum: feasible, stationary with positive multipliers, and no
    worse in objective than piqp's own point (which stops at its tolerance)."""
    world, spec, central = make_run(preset="paper", robots=robots, topology=topology)
    assert central.certified
    rows = margin_rows(spec.basis.features(world.points), world.labels)
    v = np.append(central.x, central.gamma)
    assert (rows @ v).min() > 1.0 - 1e-9
    qp = MarginQP(spec.basis.features(world.points), world.labels, x_weight=1.0, prox_weight=0.0, C=None)
    raw = qp.solve(np.zeros(qp.dim))
    assert central.x @ central.x <= raw.x @ raw.x + 1e-9


def test_certification_refuses_a_point_that_is_not_optimal():
    world, spec, central = make_run(preset="paper")
    rows = margin_rows(spec.basis.features(world.points), world.labels)
    far = 3.0 * np.append(central.x, central.gamma)  # feasible, but no margin is active
    assert certify_hard_margin(rows, far) is None
    assert solve_central(spec.basis, world.points, world.labels, C=10.0).certified is False


def _fresh_piqp(qp: MarginQP, q: np.ndarray) -> np.ndarray:
    """The reference: a new piqp solver for this one solve (what every solve did before the QP
    kept its solver)."""
    import piqp

    from agents.problem import _settings

    solver = piqp.DenseSolver()
    _settings(solver)
    full_q = np.concatenate([q, qp._q_slack])
    solver.setup(qp._P, full_q, None, None, qp._G, qp._h_l, qp._h_u, qp._x_l, qp._x_u)
    assert solver.solve() == piqp.PIQP_SOLVED
    return np.array(solver.result.x)


@pytest.mark.parametrize("C", [None, 10.0])
def test_kept_piqp_solver_gives_a_fresh_solvers_bits(C):
    """The QP sets its one piqp solver up afresh per solve: whatever it solved before (other costs,
    other prox weights, an infeasible problem's failure), every answer has the bits of a new
    solver's -- a round stays a pure function of its inputs (checkpoint restores continue bit for
    bit). piqp's result is a view of the solver's memory: an earlier answer must not change."""
    rng = np.random.default_rng(3)
    features = rng.normal(size=(12, 15))
    labels = np.where(features[:, 0] + 0.3 * features[:, 1] > 0, 1.0, -1.0)
    qp = MarginQP(features, labels, x_weight=1 / 3, prox_weight=15.0, C=C)
    answers = []
    for k in range(6):
        if k == 3:
            qp.set_prox(0.0 if C is not None else np.r_[np.full(qp.dim - 1, 2.0), 0.0])  # piqp's path
        q = rng.normal(scale=3.0, size=qp.dim)
        v = qp.solve_v(q) if qp._hessian is None else qp.solve_piqp(q)
        v = v if isinstance(v, np.ndarray) else np.append(v.x, v.gamma)
        ref = _fresh_piqp(qp, q)[: qp.dim]
        assert v.tobytes() == ref.tobytes()
        answers.append((v.copy(), v))
    bad = MarginQP(np.ones((2, 1)), np.array([1, -1]), x_weight=1.0, prox_weight=0.0, C=None)
    with pytest.raises(InfeasibleError):
        bad.solve_piqp(np.zeros(2))
    q = np.ones(bad.dim)
    good = MarginQP(np.array([[1.0], [-1.0]]), np.array([1, -1]), x_weight=1.0, prox_weight=0.0, C=None)
    good._solver = bad._solver  # the solver that just failed, on a feasible problem
    assert good.solve_v(q).tobytes() == _fresh_piqp(good, q)[: good.dim].tobytes()
    assert all(kept.tobytes() == returned.tobytes() for kept, returned in answers)


def test_solve_v_is_solve_as_one_vector():
    """`solve_v` (the ADMM round's call) gives `solve`'s (x, gamma) bits on both solvers' paths:
    the exact dual (hard margin, fewer rows than variables) and piqp."""
    rng = np.random.default_rng(5)
    for n, C in ((6, None), (30, None), (30, 5.0)):
        features = rng.normal(size=(n, 15))
        labels = np.where(features[:, 0] > 0, 1.0, -1.0)
        qp = MarginQP(features, labels, x_weight=0.25, prox_weight=15.0, C=C)
        for _ in range(3):
            q = rng.normal(size=qp.dim)
            sol = qp.solve(q)
            assert qp.solve_v(q).tobytes() == np.append(sol.x, sol.gamma).tobytes()
