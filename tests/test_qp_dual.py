"""The ADMM step's exact active-set dual (agents/qp_dual.py) against piqp and the KKT conditions."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import agents.problem as problem
from agents import qp_dual
from agents.problem import InfeasibleError, MarginQP
from agents.qp_dual import dual_hessian, solve_box_dual


def _problem(seed: int, n: int, m: int, C: float | None) -> tuple[MarginQP, np.ndarray]:
    """A random step QP with positive, unequal prox weights (x_weight 1/3 as in a 3-robot fleet)."""
    rng = np.random.default_rng(seed)
    features = rng.normal(size=(n, m))
    labels = np.where(rng.random(n) < 0.5, -1.0, 1.0)
    prox = rng.uniform(0.1, 20.0, size=m + 1)
    qp = MarginQP(features, labels, x_weight=1.0 / 3.0, prox_weight=prox, C=C)
    return qp, rng.normal(size=m + 1) * rng.choice([0.1, 1.0, 10.0])


def _objective(qp: MarginQP, q: np.ndarray, v: np.ndarray) -> float:
    hinge = qp._upper * np.maximum(0.0, 1.0 - qp._rows @ v).sum() if qp.soft else 0.0
    return float(0.5 * v @ (_weights(qp) * v) + q @ v + hinge)


def _weights(qp: MarginQP) -> np.ndarray:
    """P's diagonal on (x, gamma), whichever solver MarginQP picks."""
    return np.diag(qp._P)[: qp.dim].copy()


def _kkt_residual(qp: MarginQP, q: np.ndarray, v: np.ndarray, lam: np.ndarray) -> float:
    """Largest violation of stationarity, the multipliers' box, the margins and complementarity."""
    rows, upper = qp._rows, qp._upper
    g = rows @ v - 1.0
    station = np.abs(_weights(qp) * v + q - rows.T @ lam).max()
    box = max(0.0, -lam.min(), lam.max() - upper)
    low, high = lam == 0.0, lam == upper
    mid = ~(low | high)
    margins = max(0.0, -g[low].min(initial=0.0), g[high].max(initial=0.0), np.abs(g[mid]).max(initial=0.0))
    return float(max(station, box, margins))


CASES = [(seed, n, m, C) for seed, (n, m) in enumerate([(17, 21), (20, 43), (12, 30), (30, 15), (20, 16), (8, 40)])
         for C in (None, 0.5, 10.0, 100.0)]


@pytest.mark.parametrize("seed,n,m,C", CASES)
def test_dual_matches_piqp_and_is_an_exact_kkt_point(seed, n, m, C):
    qp, q = _problem(seed, n, m, C)
    d = _weights(qp)
    out = solve_box_dual(qp._rows, d, dual_hessian(qp._rows, d), q, qp._upper)
    try:
        ref = qp.solve_piqp(q)
    except InfeasibleError:
        assert out is None  # an infeasible hard margin is never "certified"
        return
    assert out is not None, "a well-posed random step QP must be certified"
    v, lam = out
    ref_v = np.append(ref.x, ref.gamma)
    assert _kkt_residual(qp, q, v, lam) < 1e-9 * max(1.0, np.abs(q).max())
    # piqp stops at 1e-10: the exact point is never worse, and near it
    assert _objective(qp, q, v) <= _objective(qp, q, ref_v) + 1e-9 * max(1.0, abs(_objective(qp, q, ref_v)))
    np.testing.assert_allclose(v, ref_v, atol=1e-5 * max(1.0, np.abs(ref_v).max()))


def test_soft_box_has_multipliers_at_C_and_slacks_there():
    qp, q = _problem(3, 20, 25, 0.05)  # a small C: many margins give way
    d = _weights(qp)
    out = solve_box_dual(qp._rows, d, dual_hessian(qp._rows, d), q, qp._upper)
    assert out is not None
    v, lam = out
    at_c = lam == 0.05
    assert at_c.sum() >= 3
    slack = 1.0 - qp._rows @ v
    assert np.all(slack[at_c] > 0.0) and np.all(slack[lam < 0.05] < 1e-9)  # only capped margins give way
    assert _kkt_residual(qp, q, v, lam) < 1e-9
    ref = qp.solve_piqp(q)
    np.testing.assert_allclose(v, np.append(ref.x, ref.gamma), atol=1e-6)


def test_infeasible_hard_margin_falls_back_to_piqp_which_says_so():
    features = np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # one point, both labels
    qp = MarginQP(features, np.array([1.0, -1.0, 1.0]), x_weight=0.5, prox_weight=2.0, C=None)
    q = np.zeros(qp.dim)
    assert qp._hessian is not None  # 3 rows < dim 4: the dual is tried first
    assert solve_box_dual(qp._rows, qp._d, qp._hessian, q, qp._upper) is None
    with pytest.raises(InfeasibleError):
        qp.solve(q)


def test_an_uncertified_point_falls_back_to_piqp(monkeypatch):
    qp, q = _problem(1, 17, 21, None)
    exact = qp.solve(q)
    monkeypatch.setattr(qp_dual, "KKT_TOL", -1.0)  # no point passes the check
    assert solve_box_dual(qp._rows, qp._d, qp._hessian, q, qp._upper) is None
    fallback = qp.solve(q)
    ref = qp.solve_piqp(q)
    assert np.array_equal(fallback.x, ref.x) and fallback.gamma == ref.gamma
    np.testing.assert_allclose(fallback.x, exact.x, atol=1e-6)


def test_same_inputs_give_the_same_bits():
    a, q = _problem(4, 18, 31, None)
    b, _ = _problem(4, 18, 31, None)
    assert a._hessian is not None  # the dual path
    first, again, fresh = a.solve(q), a.solve(q.copy()), b.solve(q)
    for other in (again, fresh):
        assert np.array_equal(first.x, other.x) and first.gamma == other.gamma
        assert np.array_equal(first.slack, other.slack)


def test_scaling_the_objective_leaves_the_optimum():
    """min 1/2 v'Dv + q'v and its s-multiple (s D, s q, s C) have one optimum: the dual keeps it to round-off."""
    for C in (None, 10.0):
        qp, q = _problem(5, 17, 71, C)
        d, upper = _weights(qp), qp._upper
        v = solve_box_dual(qp._rows, d, dual_hessian(qp._rows, d), q, upper)[0]
        for s in (1e-3, 1e3):
            w = solve_box_dual(qp._rows, s * d, dual_hessian(qp._rows, s * d), s * q, s * upper)[0]
            np.testing.assert_allclose(w, v, rtol=1e-10, atol=1e-10 * np.abs(v).max())


@pytest.mark.parametrize(
    "n,m,C,prox,dual",
    [(17, 30, None, 5.0, True), (17, 30, None, np.linspace(1.0, 3.0, 31), True), (20, 15, None, 5.0, False),
     (16, 15, None, 5.0, False), (17, 30, None, 0.0, False), (17, 30, 10.0, 5.0, False)],
)
def test_the_dual_answers_hard_steps_with_fewer_rows_than_variables(monkeypatch, n, m, C, prox, dual):
    qp, q = _problem(6, n, m, C)
    qp.set_prox(prox)
    calls = []
    monkeypatch.setattr(problem, "solve_box_dual", lambda *a: calls.append(1) or solve_box_dual(*a))
    try:
        sol = qp.solve(q)
    except InfeasibleError:  # only n >= dim can be infeasible here; piqp answered
        assert not dual and not calls
        return
    assert bool(calls) == dual
    ref = qp.solve_piqp(q)
    np.testing.assert_allclose(np.append(sol.x, sol.gamma), np.append(ref.x, ref.gamma), atol=1e-6)


# -- the warm KKT solve on a guess's active rows (n >= dim: problem._WarmKKT) ----------------------

def _warm_case(seed: int, n: int = 20, m: int = 15) -> tuple[MarginQP, np.ndarray, np.ndarray]:
    """A feasible step QP with more rows than variables, and q from a nearby step (a warm guess)."""
    rng = np.random.default_rng(seed)
    for _ in range(50):
        qp, q = _problem(int(rng.integers(1 << 30)), n, m, None)
        try:
            guess = qp.solve_piqp(q + 0.01 * rng.normal(size=q.shape))
        except InfeasibleError:
            continue
        return qp, q, np.append(guess.x, guess.gamma)
    raise AssertionError("no feasible case")


def _warm_multipliers(qp: MarginQP, q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The KKT multipliers of v on its tight rows (least squares of D v + q = A' lam)."""
    tight = qp._rows @ v - 1.0 <= 1e-9
    lam = np.zeros(len(qp._rows))
    lam[tight] = np.linalg.lstsq(qp._rows[tight].T, _weights(qp) * v + q, rcond=None)[0]
    return lam


@pytest.mark.parametrize("seed", range(8))
def test_warm_solve_from_a_nearby_answer_is_the_exact_optimum(seed):
    qp, q, guess = _warm_case(seed)
    assert qp._hessian is None and qp._warm is not None  # n >= dim: piqp's QPs, the warm path
    v = qp._warm.solve(q, guess)
    assert v is not None, "a nearby step's active set must be certified within WARM_TRIES corrections"
    assert _kkt_residual(qp, q, v, _warm_multipliers(qp, q, v)) < 1e-8 * max(1.0, np.abs(q).max())
    ref = qp.solve_piqp(q)
    ref_v = np.append(ref.x, ref.gamma)
    assert _objective(qp, q, v) <= _objective(qp, q, ref_v) + 1e-9 * max(1.0, abs(_objective(qp, q, ref_v)))
    np.testing.assert_allclose(v, ref_v, atol=1e-5 * max(1.0, np.abs(ref_v).max()))
    out = qp.solve_v(q, guess=guess.copy())  # MarginQP answers with it (a fresh guess array: the same bits)
    assert np.array_equal(out, v)


def test_warm_solve_is_a_pure_function_of_q_and_the_guess():
    """The cached margins of the last answer (the next round's guess, by identity) give the bits of
    the guess computed afresh -- a robot resumed from its checkpoint has only the latter."""
    qp, q, guess = _warm_case(11)
    first = qp.solve_v(q, guess=guess)
    q2 = q * (1.0 + 1e-3)
    chained = qp.solve_v(q2, guess=first)  # first is the QP's last answer: its margins reused
    other, _, _ = _warm_case(11)  # a fresh QP (nothing cached), the same data
    assert np.array_equal(other.solve_v(q2, guess=first.copy()), chained)
    assert np.array_equal(other.solve_v(q, guess=guess.copy()), first)


def test_a_bad_guess_never_gives_a_wrong_point(monkeypatch):
    """Every row active, none, or a far point: the warm path answers the optimum or nothing (piqp)."""
    qp, q, _ = _warm_case(3)
    ref = qp.solve_piqp(q)
    ref_v = np.append(ref.x, ref.gamma)
    d = qp.dim
    for guess in (np.zeros(d), np.full(d, 1e3), np.linalg.lstsq(qp._rows, np.ones(len(qp._rows)), rcond=None)[0]):
        v = qp._warm.solve(q, guess)
        if v is not None:
            np.testing.assert_allclose(v, ref_v, atol=1e-5 * max(1.0, np.abs(ref_v).max()))
    monkeypatch.setattr(problem, "WARM_TRIES", 0)
    monkeypatch.setattr(problem, "KKT_TOL", -1.0)  # nothing certifies: MarginQP falls back to piqp's bits
    out = qp.solve_v(q, guess=ref_v)
    assert np.array_equal(out, ref_v)


def test_warm_solve_only_for_weighted_hard_steps_with_n_at_least_dim():
    qp, _, _ = _warm_case(5)
    assert qp._warm is not None
    qp.set_prox(0.0)  # a robot's own solve: gamma unweighted, piqp
    assert qp._warm is None
    soft, _ = _problem(5, 20, 15, 10.0)
    fewer, _ = _problem(5, 12, 30, None)
    assert soft._warm is None and fewer._warm is None and fewer._hessian is not None


def test_warm_solve_calls_numpys_solve_routine():
    """`_gesv` (the gufunc under np.linalg.solve, without its wrapper) gives np.linalg.solve's bits:
    a numpy whose solve took another route would fail here, not move a robot's steps silently."""
    rng = np.random.default_rng(7)
    for n in (1, 2, 5, 9, 16):
        a = rng.normal(size=(n, n))
        h, b = a @ a.T + 0.1 * np.eye(n), rng.normal(size=n)
        assert problem._gesv(h, b, signature="dd->d").tobytes() == np.linalg.solve(h, b).tobytes()


def test_warm_solve_on_dependent_rows_gives_nothing_and_no_warning():
    """A guess whose tight rows are linearly dependent (an exactly singular H_WW): None (piqp
    answers), as np.linalg.solve's LinAlgError gave, with no floating-point warning on the way."""
    rows = np.array([[1.0, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, 1.0, 1.0], [-1.0, 0.0, 1.0]])
    warm = problem._WarmKKT(rows, np.ones(3))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert warm.solve(np.zeros(3), np.array([0.0, 0.0, 1.0])) is None  # rows 0 and 1 tight: equal


def test_warm_solve_keeps_a_bounded_set_of_subsystems():
    """The per-active-set copies of A_W D^-1 and H_WW: at most WARM_SUBSETS, and answers equal to
    those of a QP that kept none."""
    qp, q, guess = _warm_case(4)
    fresh, _, _ = _warm_case(4)
    rng = np.random.default_rng(1)
    for _ in range(3 * problem.WARM_SUBSETS):
        g = guess + 0.05 * rng.normal(size=guess.shape)
        a = qp._warm.solve(q, g.copy())
        fresh._warm._subs.clear()
        b = fresh._warm.solve(q, g.copy())
        assert (a is None and b is None) or a.tobytes() == b.tobytes()
    assert 0 < len(qp._warm._subs) <= problem.WARM_SUBSETS


def _numpy_warm_solve(rows: np.ndarray, d: np.ndarray, q: np.ndarray, guess: np.ndarray):
    """`_WarmKKT.solve` as it was with numpy's reductions for every test (main 9061995, no cache):
    the reference for the Python-float comparisons that replaced them. (v, W, lam_W) or None."""
    rows_d, hessian = rows / d, dual_hessian(rows, d)
    free = (rows @ guess <= 1.0 + problem.WARM_ACTIVE).nonzero()[0]
    q_d = q / d
    with np.errstate(all="ignore"):
        for _ in range(problem.WARM_TRIES + 1):
            if len(free):
                a_wd = rows_d.take(free, 0)
                b_w = a_wd @ q
                b_w += 1.0
                lam_f = problem._gesv(hessian.take(free, 0).take(free, 1), b_w, signature="dd->d")
                low = float(np.minimum.reduce(lam_f))
                if not low >= 0.0:
                    if low != low:
                        return None
                    free = np.delete(free, int(lam_f.argmin()))
                    continue
                v = a_wd.T @ lam_f
                v -= q_d
            else:
                v, lam_f = -q_d, np.zeros(0)
            g = rows @ v
            if float(np.minimum.reduce(g)) >= 1.0 - problem.KKT_TOL:
                if len(free) and not float(np.maximum.reduce(g.take(free))) <= 1.0 + problem.KKT_TOL:
                    return None
                return v, free, lam_f
            free = np.union1d(free, [int(g.argmin())])
    return None


def test_warm_solve_decides_as_numpys_reductions_did():
    """Every answer (None or v's bits, W, lam_W) of the warm solve -- W and its tests on Python floats --
    equals the numpy-reduction form's, along chains of steps (the cached margins), from far, bad and
    NaN / inf guesses and q (the multi-try, dropped-multiplier, added-row and give-up paths)."""
    paths = {"none": 0, "answer": 0}
    for seed in range(12):
        qp, q, guess = _warm_case(seed)
        warm, rng = qp._warm, np.random.default_rng(seed)
        rows, d = warm.rows, warm.d
        prev = guess
        for k in range(30):
            if k % 6 == 5:  # a guess from elsewhere: far, scaled, a NaN / inf entry, all rows active
                pick = rng.integers(4)
                g = [np.full(len(guess), 1e3), guess * rng.uniform(-2, 3), np.where(rng.random(len(guess)) < 0.2, np.nan, guess),
                     np.linalg.lstsq(rows, np.ones(len(rows)), rcond=None)[0]][pick]
                step_q = q if pick != 2 else np.where(rng.random(len(q)) < 0.1, np.inf, q)
            else:  # the next step from the last answer (identity: the cached margins)
                g, step_q = prev, q * (1.0 + 0.05 * rng.normal()) + 0.02 * rng.normal(size=q.shape)
            ref = _numpy_warm_solve(rows, d, step_q, g if g is not prev else g.copy())
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # (an inf q's products: the same warnings or none in both)
                out = warm.solve(step_q, g)
            assert (out is None) == (ref is None)
            if out is not None:
                assert out.tobytes() == ref[0].tobytes()
                assert warm._lam[0] == ref[1].tolist() and warm._lam[1].tobytes() == ref[2].tobytes()
                assert warm.multipliers()[ref[1]].tobytes() == ref[2].tobytes()
                prev = out
            paths["none" if out is None else "answer"] += 1
    assert paths["none"] >= 5 and paths["answer"] >= 200  # both outcomes exercised


def test_warm_solve_boundaries_are_numpys(monkeypatch):
    """On the exact boundaries -- a multiplier exactly 0.0, a margin exactly at the held and tight
    limits (KKT_TOL 0) -- the Python-float tests accept as numpy's `min >= 0` / `max <= limit` did."""
    monkeypatch.setattr(problem, "KKT_TOL", 0.0)
    rows, d = np.array([[1.0, 0.0, 0.0], [2.0, 0.0, 0.0]]), np.ones(3)
    q, guess = np.array([-1.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0])  # W = {0}: lam_0 = (a_0 q + 1) / 1 = 0.0
    warm = problem._WarmKKT(rows, d)
    out, ref = warm.solve(q, guess), _numpy_warm_solve(rows, d, q, guess)
    assert out is not None and ref is not None and out.tobytes() == ref[0].tobytes()
    assert (rows @ out).tolist() == [1.0, 2.0]  # row 0 exactly at the limits
    assert warm._lam[0] == ref[1].tolist() == [0] and warm._lam[1].tolist() == [0.0]
    monkeypatch.setattr(problem, "WARM_ACTIVE", 1.0)  # row 1's margin 2.0 exactly at the active limit:
    fresh = problem._WarmKKT(rows, d)  # W = {0, 1}, dependent rows: nothing, as numpy's `<=` gave
    assert fresh.solve(q, guess) is None and _numpy_warm_solve(rows, d, q, guess) is None
