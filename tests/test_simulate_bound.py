"""`simulate` refuses a fleet this machine's memory cannot hold, before building anything, unless
--max-robots (the option `launch` reads too) says more: exit 2, one line naming --robots, the bound,
why, and the override. The bound is launcher/simulate.py's fitted peak memory
(benchmarks/results/simulate_cost.md)."""

from __future__ import annotations

import json

import pytest

from launcher import cli, fleet
from launcher import simulate as sim
from launcher.world import Options, resolve_options

from .conftest import cli_exit_and_stderr

PAPER = ["--preset", "paper"]


def _no_world(*_args, **_kwargs):
    raise AssertionError("the world was built: the refusal must come before anything is allocated")


def _papercli_exit_and_stderr() -> dict[str, int]:
    """The round cap and grid points of `simulate --preset paper` (what its bound counts)."""
    rounds, grid_points = cli._rounds_and_grid(resolve_options(Options(preset="paper")))
    return {"rounds": rounds, "grid_points": grid_points}


def _memory(monkeypatch: pytest.MonkeyPatch, robots: int) -> None:
    """This machine as one whose available memory holds exactly `robots` robots of the paper's run."""
    need = sim.simulate_memory_mb(robots, "complete", "admm", **_papercli_exit_and_stderr()) / sim.SIMULATE_MEMORY_SHARE
    monkeypatch.setattr(fleet, "_available_memory_mb", lambda: need)


@pytest.mark.parametrize("sync", ["lockstep", "free"])
def test_a_fleet_past_the_memory_is_refused_before_the_world_is_built(sync, tmp_path, capsys, monkeypatch):
    """--robots 100000 (the audit's: it would take the machine's 24 GB and more) is one line, exit 2,
    naming the flag, the bound, why and the override; no world built, no run folder."""
    monkeypatch.setattr(cli, "build_world", _no_world)
    monkeypatch.setattr(fleet, "_available_memory_mb", lambda: 24000.0)  # the audit's machine, fixed
    out = tmp_path / "run"
    code, err = cli_exit_and_stderr(["simulate", *PAPER, "--robots", "100000", "--sync", sync, "--out", str(out)], capsys)
    bound, why = sim.simulate_max_robots("complete", "admm", **_papercli_exit_and_stderr())
    assert code == 2 and len(err) == 1, err
    assert err[0].startswith("shapefleet: error: --robots: 100000 robots is more than simulate holds")
    assert f"({bound}: {why})" in err[0] and "24000 MB available" in err[0] and "--max-robots 100000" in err[0]
    assert bound < 100000 and not out.exists()


@pytest.mark.parametrize("topology", ["complete", "geometric", "ring", "line"])
@pytest.mark.parametrize("algorithm", ["admm", "ct-admm", "newton", "autogrid", "pkg.mod:Mine"])
def test_the_bound_is_the_largest_fleet_within_the_memory_share(topology, algorithm):
    """The bound is the last N whose fitted peak fits half the available memory (a user's algorithm:
    the dearest fit)."""
    run = {"rounds": 1000, "grid_points": 15}
    bound, why = sim.simulate_max_robots(topology, algorithm, **run, available_mb=8000.0)
    budget = sim.SIMULATE_MEMORY_SHARE * 8000.0
    assert sim.simulate_memory_mb(bound, topology, algorithm, **run) <= budget
    assert sim.simulate_memory_mb(bound + 1, topology, algorithm, **run) > budget
    assert "8000 MB available" in why and "1000 rounds" in why


def test_the_bound_falls_with_neighbours_rounds_grid_and_memory():
    """A complete graph (and a geometric one, counted as complete: its degree grows with N) holds fewer
    robots than a ring; a longer cap, a larger grid or less memory, fewer; one robot is always allowed."""
    def bound(topology="complete", rounds=1000, grid_points=15, mb=8000.0):
        return sim.simulate_max_robots(topology, "admm", rounds=rounds, grid_points=grid_points, available_mb=mb)[0]

    assert bound() == bound("geometric") < bound("ring") == bound("line")
    assert bound(rounds=5000) < bound() < bound(rounds=2)
    assert bound(grid_points=300) < bound()
    assert bound(mb=4000.0) < bound()
    assert bound(mb=0.0) == 1


def test_max_robots_overrides_the_bound_and_the_run_goes_on(tmp_path, capsys, monkeypatch):
    """On a machine that holds 4 robots, 5 are refused naming the bound 4; with --max-robots 5 the same
    run is made (the option launch reads too), and its result is the fleet's."""
    _memory(monkeypatch, 4)
    code, err = cli_exit_and_stderr(["simulate", *PAPER, "--robots", "5", "--out", str(tmp_path / "refused")], capsys)
    assert code == 2 and len(err) == 1 and "--robots: 5 robots" in err[0] and "(4: " in err[0], err
    assert not (tmp_path / "refused").exists()
    out = tmp_path / "run"
    code, err = cli_exit_and_stderr(["simulate", *PAPER, "--robots", "5", "--max-robots", "5", "--out", str(out)], capsys)
    result = json.loads((out / "result.json").read_text())
    assert code == 0 and result["converged"] and len(result["robots"]) == 5, err
    code, err = cli_exit_and_stderr(["simulate", *PAPER, "--robots", "6", "--max-robots", "5", "--out", str(tmp_path / "six")], capsys)
    assert code == 2 and "(5: --max-robots)" in err[0] and "--max-robots 6" in err[0]


def test_the_bound_counts_the_robots_of_a_data_file(tmp_path, capsys, monkeypatch):
    """--data: the robots are the file's, not --robots' default of 3."""
    _memory(monkeypatch, 3)
    monkeypatch.setattr(cli, "build_world", _no_world)
    data = tmp_path / "data.csv"
    rows = [f"{r},{x},{y},{label}" for r in range(4) for x, y, label in ((r, 0.0, -1), (r, 9.0, 1))]
    data.write_text("robot,x,y,label\n" + "\n".join(rows) + "\n")
    code, err = cli_exit_and_stderr(["simulate", *PAPER, "--data", str(data), "--out", str(tmp_path / "run")], capsys)
    assert code == 2 and "--robots: 4 robots" in err[0] and "(3: " in err[0], err


def test_max_robots_is_one_option_of_both_shells():
    """One row of the options table: simulate and launch read the same --max-robots."""
    from launcher.options import OPTIONS

    rows = [o for o in OPTIONS if o.name == "max-robots"]
    assert len(rows) == 1 and {"simulate", "launch"} <= set(rows[0].commands)
