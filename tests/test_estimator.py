"""GridKernelSVC: the centralized solve with scikit-learn's manners, against SVC itself."""

from __future__ import annotations

import numpy as np
import pytest
from sklearn.svm import SVC

from agents.estimator import GridKernelSVC
from agents.problem import InfeasibleError

from .conftest import make_run


def test_fit_matches_the_fleets_reference_and_svc(default_run):
    world, spec, central = default_run
    clf = GridKernelSVC(grid_shape=(5, 3), sigma=1.0).fit(world.points, world.labels)
    np.testing.assert_allclose(clf.grid_, spec.grid)  # the same grid as `shapefleet` builds
    assert spec.basis.function_error(clf.coef_, clf.intercept_, central.c, central.gamma) < 1e-9
    svc = SVC(kernel="linear", C=1e9, tol=1e-10).fit(spec.basis.features(world.points), world.labels)
    np.testing.assert_allclose(clf.x_, svc.coef_[0], atol=1e-4 * np.abs(svc.coef_).max())
    assert clf.score(world.points, world.labels) == 1.0
    assert set(np.unique(clf.predict(world.points))) == {-1, 1}
    f = clf.decision_function(world.points)
    assert np.all(world.labels * f >= 1 - 1e-6)  # hard margin


def test_explicit_grid_and_soft_margin():
    world, spec, _ = make_run(shape="cross", seed=3)
    clf = GridKernelSVC(grid=spec.grid, C=10.0).fit(world.points, world.labels)
    assert clf.coef_.shape == (len(spec.grid),)
    assert 0.8 < clf.score(world.points, world.labels) <= 1.0


def test_infeasible_grid_raises_in_words():
    world, _, _ = make_run(shape="cross")
    with pytest.raises(InfeasibleError, match="infeasible"):
        GridKernelSVC(grid_shape=(2, 2)).fit(world.points, world.labels)


@pytest.mark.parametrize(
    "X,y,match",
    [
        (np.zeros((3, 3)), [1, -1, 1], "shape"),
        (np.array([[0.0, np.nan], [1.0, 1.0]]), [1, -1], "NaN"),
        (np.zeros((2, 2)), [1], "one label per point"),
        (np.array([[0.0, 0.0], [1.0, 1.0]]), [1, 0], "labels"),
        (np.zeros((0, 2)), [], "no points"),
    ],
)
def test_bad_input_is_refused_with_a_reason(X, y, match):
    with pytest.raises(ValueError, match=match):
        GridKernelSVC().fit(X, y)


def test_unfitted_and_bad_hyper_parameters():
    with pytest.raises(ValueError, match="not fitted"):
        GridKernelSVC().predict([[0.0, 0.0]])
    pts, labels = np.array([[0.0, 0.0], [3.0, 0.0]]), np.array([-1, 1])
    with pytest.raises(ValueError, match="sigma"):
        GridKernelSVC(sigma=0).fit(pts, labels)
    with pytest.raises(ValueError, match="C must be"):
        GridKernelSVC(C=-1.0).fit(pts, labels)
    with pytest.raises(ValueError, match="grid_shape"):
        GridKernelSVC(grid_shape=(0, 3)).fit(pts, labels)
