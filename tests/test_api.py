"""launcher/api.py: the CLI without the shell -- same options, same runs, a typed result (issue 17)."""

from __future__ import annotations

import asyncio
import importlib.metadata
import json
from pathlib import Path

import numpy as np
import pytest

from launcher import api, cli
from launcher.options import BY_NAME, SECTION_OF, options_of

AVERAGE = "examples.average_consensus:Average"
#: a sample of options over every section, with the values written as a user would in each door
SAMPLE = {
    "simulate": {"robots": 4, "points": 15, "seed": 2, "preset": "paper", "topology": "ring", "tol": 1e-4,
                 "max_rounds": 300, "loss": 0.2, "delay": "5ms", "range": 3.5, "crash": ["2@30"]},
    "launch": {"robots": 4, "points": 15, "seed": 2, "preset": "paper", "tol": 1e-4, "loss": 0.2,
               "delay": "5ms", "crash": ["1@40"], "no_restart": True, "dead_after": "2s", "fleet_id": "same",
               "restart_after": 0.5},
}


def _toml(options: dict) -> str:
    """The scenario file holding ``options`` (each key in its table of launcher/options.py)."""
    sections: dict[str, list[str]] = {}
    for key, value in options.items():
        name = key.replace("_", "-")
        sections.setdefault(SECTION_OF[name], []).append(f"{name} = {json.dumps(value)}")
    return "\n".join(f"[{s}]\n" + "\n".join(lines) + "\n" for s, lines in sections.items())


@pytest.mark.parametrize("mode", api.MODES)
def test_api_cli_and_toml_accept_the_same_options(mode, tmp_path):
    """One table (launcher/options.py) -> the API's keywords, the CLI's flags, the TOML keys."""
    names = api.option_names(mode)
    parser = cli._subparser(cli.build_parser(), mode)
    flags = {f[2:].replace("-", "_") for a in parser._actions for f in a.option_strings if f.startswith("--")}
    assert names == flags - {"help"}
    toml_keys = {k.replace("-", "_") for k in SECTION_OF if BY_NAME[k] in options_of(mode)}
    assert toml_keys == names - {"config", "out"}  # where the file is, and where to write: not in it
    # and the three doors give the same options for the same values
    sample = SAMPLE[mode]
    assert set(sample) <= toml_keys
    path = tmp_path / "scenario.toml"
    path.write_text(_toml(sample))
    from_api = cli._options(api._parse(mode, sample))
    from_cli = cli._options(cli.parse_args(api.argv(mode, sample)))
    from_toml = cli._options(cli.parse_args([mode, "--config", str(path)]))
    assert from_api == from_cli == from_toml
    assert from_api.robots == 4 and from_api.faults.loss == 0.2 and from_api.faults.delay == 0.005
    args = api._parse(mode, sample)
    assert args.crash == sample["crash"] and args.no_restart is sample.get("no_restart", False)


def test_result_is_the_cli_run(tmp_path, capsys):
    """The API runs the CLI's own code: the same result.json figures as `shapefleet simulate`."""
    options = {"preset": "paper", "tol": 1e-4, "loss": 0.3, "seed": 1}
    r = api.simulate(out=tmp_path / "api", **options)
    assert cli.main(api.argv("simulate", {**options, "out": tmp_path / "cli"})) == 0 == r.exit_code
    assert capsys.readouterr().out  # the CLI printed its summary; the API (quiet) printed nothing else
    want = json.loads((tmp_path / "cli" / "result.json").read_text())
    assert r.converged and r.verdict == want["verdict"] and r.rounds == want["rounds"]
    assert r.error == want["metrics"]["function_error"] < 1e-3
    assert r.participants == (0, 1, 2) and r.absent == ()
    for robot, row in zip(r.robots, want["robots"]):
        assert robot.row["c"] == row["c"] and robot.values[-1] == row["gamma"]
        assert robot.rounds == row["rounds"] and robot.error == row["function_error"]
        assert robot.counters["frames_lost"] == row["frames_lost"] and robot.counters["frames_sent"] > 0
        assert sorted(robot.trace) == list(range(robot.rounds + 1))
    assert (r.out / "result.json").exists() and r.mode == "simulate" and r.pids == ()


def test_not_converged_is_a_result_not_an_exception(tmp_path):
    r = api.simulate(preset="paper", max_rounds=3, out=tmp_path)
    assert not r.converged and r.exit_code == cli.EXIT_NOT_CONVERGED
    assert "did not meet their stopping rule" in r.verdict and r.rounds == 3


@pytest.mark.parametrize(
    "options, named",
    [({"loss": 2}, "--loss"), ({"robots": 0}, "--robots"), ({"los": 0.3}, "los: not an option of simulate"),
     ({"zenoh_port": 7447}, "zenoh_port: not an option of simulate"), ({"algorithm": "nope.mod:Average"}, "--algorithm"),
     ({"algorithm": "launcher.cli:main"}, "--algorithm"), ({"grid": "5x"}, "--grid"), ({"no_such": 1}, "no_such")],
)
def test_bad_input_is_one_usage_error_naming_it(tmp_path, options, named):
    with pytest.raises(api.UsageError) as exc:
        api.simulate(out=tmp_path / "run", **options)
    assert named in str(exc.value) and "\n" not in str(exc.value)
    assert not (tmp_path / "run").exists()  # refused before anything was written


def test_router_only_for_launch():
    with pytest.raises(api.UsageError, match="router"):
        api.run("simulate", router="tcp/127.0.0.1:7447")


async def test_run_async_leaves_the_loop_free(tmp_path):
    ticks = 0

    async def ticker() -> None:
        nonlocal ticks
        while True:
            await asyncio.sleep(0.01)
            ticks += 1

    task = asyncio.create_task(ticker())
    try:
        r = await api.run_async("simulate", preset="paper", tol=1e-4, out=tmp_path / "a")
    finally:
        task.cancel()
    assert r.converged and ticks > 5  # the loop ran while the fleet did
    assert r.rounds == api.simulate(preset="paper", tol=1e-4, out=tmp_path / "b").rounds


def test_custom_algorithm_by_entry_point_equals_dotted_path(tmp_path, monkeypatch):
    from agents import extension

    real = importlib.metadata.entry_points
    ours = importlib.metadata.EntryPoint("average", AVERAGE, extension.ENTRY_POINT_GROUP)

    def entry_points(**kw):
        return [ours] if kw.get("group") == extension.ENTRY_POINT_GROUP else real(**kw)

    monkeypatch.setattr(importlib.metadata, "entry_points", entry_points)
    monkeypatch.setattr(extension, "_CACHE", {})
    common = {"robots": 5, "topology": "ring", "tol": 1e-10}
    by_name = api.simulate(algorithm="average", out=tmp_path / "a", **common)
    by_path = api.simulate(algorithm=AVERAGE, out=tmp_path / "b", **common)
    assert by_name.converged and by_name.algorithm == "average"
    for a, b in zip(by_name.robots, by_path.robots):
        np.testing.assert_array_equal(a.answer, b.answer)
    data = np.genfromtxt(tmp_path / "a" / "data.csv", delimiter=",", names=True)
    np.testing.assert_allclose(by_name.robot(0).answer, [data["x"].mean(), data["y"].mean()], rtol=0, atol=1e-9)
    assert by_name.error < 1e-9


@pytest.mark.parametrize(
    "name, says",
    [("examples.average_consensus:Nope", "has no 'Nope'"), ("no_such_pkg.mod:X", "cannot import module"),
     ("launcher.cli:UsageError", "not a fleet algorithm"), ("bad path:X", "not a dotted path")],
)
def test_cli_bad_algorithm_exit_2_one_line(tmp_path, capsys, name, says):
    with pytest.raises(SystemExit) as exc:
        cli.main(["simulate", "--algorithm", name, "--out", str(tmp_path / "run")])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--algorithm" in err[0] and says in err[0] and "Traceback" not in err[0]
    assert not (tmp_path / "run").exists()


def test_build_gives_the_run_s_world_and_fleet_file(tmp_path):
    s = api.build("simulate", preset="paper", robots=4, seed=3)
    r = api.simulate(preset="paper", robots=4, seed=3, out=tmp_path)
    assert s.spec.robot_ids == (0, 1, 2, 3) and s.spec.algorithm == "admm"
    data = np.genfromtxt(Path(r.out) / "data.csv", delimiter=",", names=True)
    np.testing.assert_array_equal(np.column_stack([data["x"], data["y"]]), s.world.points)
