"""What branch hubactive's measurements of the 16-ring (benchmarks/relay_anderson.py --identify, --cut-model)
rest on: from the values every relay copy holds (t_l and the relayed a_l, x_l = (a_l + t_l) / 2), robot l's
step reveals W_l = A_l' lam_l, a combination of its active margin rows; its cut is valid for the fleet's
problem; a change of its active set is visible between two steps; and the cut model's fixed point is the
relay map's when the model holds the robots' rows. The core does not use them (docs/algorithm.md: both
levers measured worse or unfinished)."""

from __future__ import annotations

import numpy as np
import pytest

from agents.relay_hub import RelayHubADMM
from agents.spec import build_core
from benchmarks.relay_anderson import cut_model, model_state, piece_changed, step_cuts, step_normals

from .conftest import make_run


@pytest.fixture(scope="module")
def ring():
    """The issue's 16-ring (paper preset, seed 0): its cores and the exact optimum v* = (x*, gamma*)."""
    _, spec, central = make_run(preset="paper", robots=16, topology="ring")
    cores = [build_core(spec, i, keep_trace=False) for i in spec.robot_ids]
    assert isinstance(cores[0], RelayHubADMM)
    return cores, np.append(spec.basis.x_from_c(central.c), central.gamma)


def _steps(cores, T):
    return np.array([c._solve(T[l]) for l, c in enumerate(cores)])


def _centres(cores, optimum, scale, seed):
    """Centres t_l around P^-1 (P + 1/N) v*, where steps land near the optimum with some rows active."""
    copy = cores[0]
    rng = np.random.default_rng(seed)
    return copy._pdiag * optimum / copy._P + scale * rng.normal(size=(copy.n, copy.dim))


def test_the_cuts_from_held_values_hold_at_the_exact_optimum(ring):
    """Every cut w_l . v >= 1 (w_l = W_l / (W_l . x_l)) is tight at its own step and holds at the central
    optimum (feasible for every robot's rows): an outer approximation of the fleet's feasible set, to the
    step solver's complementarity (piqp's lam_i (a_i . x - 1): measured <= 1.7e-5 here). A sign slip in W
    or the normalisation would give no cut or cut the optimum off by O(1)."""
    cores, optimum = ring
    copy = cores[0]
    for seed in range(3):
        T = _centres(cores, optimum, 0.5, seed)
        X = _steps(cores, T)
        W = step_normals(copy, X, T)
        cuts, owners = step_cuts(X, W)
        assert len(cuts) >= 4  # (steps with active rows: the test is not vacuous)
        assert np.allclose(np.sum(cuts * X[owners], axis=1), 1.0, atol=1e-9)
        assert np.all(cuts @ optimum >= 1.0 - 1e-4)
        # and each is the combination of its robot's active rows: inside the span of those rows (active to
        # piqp's complementarity: a row with a multiplier can sit 1.7e-5 above its margin)
        for w, l in zip(cuts, owners):
            rows = cores[l]._qp._rows
            active = rows[rows @ X[l] < 1.0 + 1e-4]
            coef, *_ = np.linalg.lstsq(active.T, w, rcond=None)
            assert np.linalg.norm(active.T @ coef - w) <= 1e-4 * np.linalg.norm(w)  # (measured <= 5e-6)


def _clear_sets(cores, *steps):
    """Per robot: its active rows at each step, and whether every row is clearly active (margin within
    1e-7 of 1: piqp's answers) or clearly not (above 1 + 1e-3) at every step -- where the truth is not the
    solver's noise."""
    sets, clear = [], []
    for c, xs in zip(cores, zip(*steps)):
        margins = [c._qp._rows @ x for x in xs]
        sets.append([tuple(np.nonzero(m < 1.0 + 1e-7)[0]) for m in margins])
        clear.append(all(np.all((np.abs(m - 1.0) < 1e-7) | (m > 1.0 + 1e-3)) for m in margins))
    return sets, np.array(clear)


def test_the_piece_test_sees_an_active_set_change_and_not_a_move_within_a_piece(ring):
    """Two steps on one affine piece (a small move of the centres) pass the test; where a robot's active
    set changed between two steps (a large move) it is flagged -- checked against the rows themselves on
    the robots whose rows are clearly in or out at both steps."""
    cores, optimum = ring
    copy = cores[0]
    T = _centres(cores, optimum, 0.5, 7)
    X = _steps(cores, T)
    W = step_normals(copy, X, T)
    T_near = T + 1e-4 * np.random.default_rng(8).normal(size=T.shape)
    X_near = _steps(cores, T_near)
    T_far = _centres(cores, optimum, 0.5, 9)
    X_far = _steps(cores, T_far)
    sets, clear = _clear_sets(cores, X, X_near, X_far)
    same = clear & np.array([a == b for a, b, _ in sets])
    changed = clear & np.array([a != c for a, _, c in sets])
    assert same.sum() >= 8 and changed.sum() >= 4  # (not vacuous)
    assert not piece_changed(X, W, X_near, step_normals(copy, X_near, T_near))[same].any()
    assert piece_changed(X, W, X_far, step_normals(copy, X_far, T_far))[changed].all()


def test_the_cut_model_on_the_robots_rows_gives_the_relay_maps_fixed_point(ring):
    """With each robot's own rows active at the optimum as the model's cuts, the relaxed QP is the
    problem near v*, and `model_state` is a fixed point of the relay map: every robot's step at its
    t_l returns v* (so a model step lands on the exact fixed point when its model is right)."""
    cores, optimum = ring
    copy = cores[0]
    rows = [c._qp._rows[c._qp._rows @ optimum < 1.0 + 1e-7] for c in cores]
    cuts, owners = np.vstack(rows), np.repeat(np.arange(copy.n), [len(r) for r in rows])
    solved = cut_model(cuts)
    assert solved is not None
    z, mu = solved
    assert np.linalg.norm(z - optimum) <= 1e-6 * np.linalg.norm(optimum)
    S = model_state(copy, z, mu, cuts, owners)
    X = _steps(cores, S.reshape(copy.n, copy.dim))
    assert np.max(np.abs(X - z)) <= 1e-6 * np.linalg.norm(z)
    assert np.allclose(S.reshape(copy.n, copy.dim).sum(axis=0), copy.n * z, rtol=1e-9, atol=1e-9)
