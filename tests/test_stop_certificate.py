"""benchmarks/stop_certificate.py, the guard's measurement: its runs are the cores' own (the bound every
robot reports), checked against the exact solve on every robot-round."""

from __future__ import annotations

from benchmarks.stop_certificate import FLEETS, run


def test_the_benchmark_measures_the_paper_fleet_and_checks_every_round():
    kwargs = dict(FLEETS)["paper setting: 3 robots, blob, complete"]
    rule = run(kwargs, certify=0.0, warm=False, max_rounds=400)
    assert (rule.rounds, rule.bound, rule.checked) == (120, None, 0)
    guarded = run(kwargs, certify=1.0, warm=False, max_rounds=400, check=True)
    # measured: certify 1 holds the paper preset to round 147 (error 2.1e-9, bound 3.0e-4)
    assert guarded.converged and guarded.rounds > rule.rounds and guarded.error <= guarded.bound <= 1e-3
    assert guarded.unsafe == 0 and guarded.checked > 3 * 100
