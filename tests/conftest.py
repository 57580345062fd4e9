"""Shared fixtures: small scenarios built through the same code path as the CLI."""

from __future__ import annotations

import numpy as np
import pytest

from agents.problem import solve_central
from launcher.world import Options, build_world


def make_run(**kwargs):
    """(world, spec, central) for Options(**kwargs) with a fixed fleet id."""
    kwargs.setdefault("fleet_id", "test")
    world, spec = build_world(Options(**kwargs))
    central = solve_central(spec.basis, world.points, world.labels, spec.C)
    return world, spec, central


@pytest.fixture(scope="session")
def default_run():
    return make_run()


def max_function_error(spec, central, robots) -> float:
    """Largest ||f_l - f*||_H/||f*||_H + |gamma_l - gamma*|/max(1,|gamma*|) over robots."""
    b = spec.basis
    return max(
        b.function_error(b.c_from_x(np.asarray(r["x"])), r["gamma"], central.c, central.gamma) for r in robots
    )
