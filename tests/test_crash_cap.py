"""--crash is refused only past the run's real round cap, not past a progress estimate.

An autogrid run's plan (AutoGridParams.planned_rounds, the progress bar's total) is an estimate:
a soft-margin fallback or a second refinement runs past it, and a crash planned there fires.
"""

import pytest

from launcher.cli import UsageError, _crash_check, _crash_plan, _options, parse_args
from launcher.world import build_world


def _check(*argv: str) -> None:
    args = parse_args(["simulate", *argv])
    _, spec = build_world(_options(args))
    _crash_check(_crash_plan(args))(spec)


def test_autogrid_crash_past_the_plan_but_before_the_cap_is_accepted():
    args = parse_args(["simulate"])
    _, spec = build_world(_options(args))
    params = spec.algorithm_params
    assert spec.algorithm == "autogrid" and params.planned_rounds < params.max_total_rounds
    _check("--crash", f"1@{params.planned_rounds + 61}")  # the run of the illcond data lasts 1100 > plan
    with pytest.raises(UsageError, match=rf"round cap is {params.max_total_rounds}\)"):
        _check("--crash", f"1@{params.max_total_rounds}")


def test_admm_crash_at_the_cap_is_refused_and_below_it_accepted():
    _check("--preset", "paper", "--crash", "1@4999")
    with pytest.raises(UsageError, match=r"1@5000 is at or past the run's last possible round \(4999"):
        _check("--preset", "paper", "--crash", "1@5000")
