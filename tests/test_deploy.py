"""Per-robot fleet files, `prepare` and `collect` (launcher/deploy.py), without any network."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from agents.spec import FleetSpec, build_core
from launcher import deploy
from launcher.cli import main
from launcher.simulate import simulate_fleet
from tests.conftest import exchange_until_finished, make_run


@pytest.fixture(scope="module")
def run():
    return make_run(robots=3, topology="line", fleet_id="deploy-test")


# -- FleetSpec.for_robot -------------------------------------------------------------------------------
def test_a_robots_file_holds_its_data_and_everyones_neighbours(run, tmp_path):
    _, spec, _ = run
    for i in spec.robot_ids:
        own = spec.for_robot(i)
        assert own.owner == i and own.config_tag == spec.config_tag and own.robot_ids == spec.robot_ids
        for j, r in own.robots.items():
            assert r.neighbours == spec.robots[j].neighbours
            assert len(r.points) == (len(spec.robots[j].points) if j == i else 0)
        np.testing.assert_array_equal(own.robots[i].points, spec.robots[i].points)
        own.save(tmp_path / f"{i}.json")
        back = FleetSpec.load(tmp_path / f"{i}.json")
        assert back.owner == i and back.config_tag == spec.config_tag
        assert json.loads((tmp_path / f"{i}.json").read_text())["for"] == i
    assert "for" not in spec.to_json()


def test_a_robots_file_cannot_run_another_robot(run):
    _, spec, _ = run
    own = spec.for_robot(0)
    with pytest.raises(ValueError, match="holds robot 0's data only"):
        build_core(own, 1)
    with pytest.raises(ValueError, match="holds robot 0's data only"):
        own.for_robot(1)
    with pytest.raises(ValueError, match="not in fleet"):
        spec.for_robot(7)


def test_robots_built_from_their_own_files_compute_the_fleets_iterates(run):
    """Each core from its own per-robot file, driven by a perfect exchange == the simulator."""
    _, spec, _ = run
    cores = {i: build_core(spec.for_robot(i), i) for i in spec.robot_ids}
    exchange_until_finished(cores, spec.params["max_rounds"] + 1)
    want = {r["id"]: r for r in simulate_fleet(spec).robots}
    for i, core in cores.items():
        got = core.result()
        assert got["rounds"] == want[i]["rounds"]
        assert list(got["x"]) == list(want[i]["x"]) and got["gamma"] == want[i]["gamma"]


# -- robot: which robot am I? ---------------------------------------------------------------------------
@pytest.fixture
def files(run, tmp_path):
    _, spec, _ = run
    spec.save(tmp_path / "full.json")
    spec.for_robot(1).save(tmp_path / "one.json")
    return tmp_path


@pytest.mark.parametrize(
    "file,flag,env,needle",
    [
        ("full.json", [], None, "--id: which robot?"),
        ("one.json", ["--id", "2"], None, "--id: "),
        ("one.json", [], "2", "SHAPEFLEET_ROBOT_ID: "),
        ("one.json", [], "two", "SHAPEFLEET_ROBOT_ID: 'two' is not a robot id"),
        ("full.json", ["--id", "9"], None, "--id: robot 9 is not in"),
    ],
    ids=["no-id", "flag-disagrees", "env-disagrees", "env-not-int", "unknown"],
)
def test_robot_id_problems_exit_2(files, monkeypatch, capsys, file, flag, env, needle):
    monkeypatch.delenv("SHAPEFLEET_ROBOT_ID", raising=False)
    if env is not None:
        monkeypatch.setenv("SHAPEFLEET_ROBOT_ID", env)
    with pytest.raises(SystemExit) as exc:
        main(["robot", "--fleet-file", str(files / file), "--connect", "tcp/127.0.0.1:9", *flag])
    err = capsys.readouterr().err.strip().splitlines()
    assert exc.value.code == 2 and len(err) == 1 and needle in err[0], err


def test_robot_id_comes_from_flag_env_or_file(files, monkeypatch):
    from launcher.cli import _robot_id, build_parser

    def rid(*argv: str) -> int:
        args = build_parser().parse_args(["robot", "--connect", "tcp/127.0.0.1:9", *argv])
        return _robot_id(args, FleetSpec.load(args.fleet_file))

    monkeypatch.delenv("SHAPEFLEET_ROBOT_ID", raising=False)
    assert rid("--fleet-file", str(files / "one.json")) == 1
    assert rid("--fleet-file", str(files / "full.json"), "--id", "2") == 2
    monkeypatch.setenv("SHAPEFLEET_ROBOT_ID", "0")
    assert rid("--fleet-file", str(files / "full.json")) == 0
    assert rid("--fleet-file", str(files / "full.json"), "--id", "2") == 2  # the flag wins


# -- prepare + collect ---------------------------------------------------------------------------------
_SIMULATED: dict[bytes, list[dict]] = {}


def _results(spec: FleetSpec, folder: Path, ids=None, fleet: str | None = None) -> None:
    """Robot result files as robot processes write them, from the in-process fleet."""
    folder.mkdir(exist_ok=True)
    key = spec.config_tag + spec.fleet.encode()
    if key not in _SIMULATED:
        _SIMULATED[key] = simulate_fleet(spec).robots
    for r in _SIMULATED[key]:
        if ids is not None and r["id"] not in ids:
            continue
        row = {k: v for k, v in r.items() if k != "trace"}
        row.update(fleet=fleet or spec.fleet, robot=r["id"], stopped="finished", x=list(r["x"]),
                   trace={str(k): list(v) for k, v in r["trace"].items()})
        (folder / f"robot-{r['id']}.json").write_text(json.dumps(row))


@pytest.fixture(scope="module")
def prepared(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("prepared")
    assert main(["prepare", "--preset", "paper", "--robots", "3", "--fleet-id", "collect-test", "--out", str(tmp / "fleet")]) == 0
    return tmp / "fleet"


def test_prepare_writes_the_fleet_folder(prepared):
    full = FleetSpec.load(prepared / "fleet.json")
    world = json.loads((prepared / "world.json").read_text())
    assert world["fleet"] == full.fleet == "collect-test" and world["shape"]["type"] == "Polygon"
    assert (prepared / "data.csv").stat().st_size > 0
    for i in full.robot_ids:
        assert FleetSpec.load(deploy.robot_fleet_file(prepared, i)).owner == i
    back = deploy.load_prepared(prepared / "fleet.json")
    assert back.topology == "complete" and set(back.world.graph.edges) == {(0, 1), (0, 2), (1, 2)}
    np.testing.assert_array_equal(back.world.points, np.vstack([full.robots[i].points for i in full.robot_ids]))


def test_collect_measures_what_arrived(prepared, tmp_path, capsys):
    full = FleetSpec.load(prepared / "fleet.json")
    results = tmp_path / "results"
    _results(full, results, ids={0, 2})
    _results(full, tmp_path / "stale", ids={1}, fleet="an-older-run")
    (results / "robot-1.json").write_text((tmp_path / "stale" / "robot-1.json").read_text())
    out = tmp_path / "run"
    assert main(["collect", "--fleet-file", str(prepared / "fleet.json"), "--results", str(results), "--out", str(out)]) == 0
    assert "robot 1: no result" in capsys.readouterr().err
    result = json.loads((out / "result.json").read_text())
    # robots 0 and 2 still list robot 1 as a neighbour: it took part, only its file is missing,
    # and the reference is the solve of all data (which is what 0 and 2 solved)
    assert result["participants"] == [0, 1, 2] and result["absent"] == [] and result["results_missing"] == [1]
    assert "reference" not in result and result["metrics"]["function_error"] < 1e-3
    assert result["fleet"] == "collect-test" and result["topology"] == "complete"
    # IoU: the worst of the two robots that arrived, recomputed here from their own answers
    from launcher import scenario

    prep = deploy.load_prepared(prepared / "fleet.json")
    b = full.basis
    rows = {r["id"]: r for r in result["robots"]}
    ious = [scenario.iou_on_raster(prep.world.shape, lambda q, r=rows[i]: b.decision(q, np.asarray(r["c"]), r["gamma"]) < 0,
                                   prep.world.bounds) for i in (0, 2)]
    assert result["metrics"]["iou"] == min(ious) and 0.5 < min(ious) <= 1.0
    for name in ("data.csv", "shapes.png", "convergence.png"):
        assert (out / name).stat().st_size > 0


def test_collect_without_a_world_file(prepared, tmp_path):
    full = FleetSpec.load(prepared / "fleet.json")
    (tmp_path / "fleet.json").write_text((prepared / "fleet.json").read_text())  # e.g. a launch run's file
    _results(full, tmp_path / "results")
    out = tmp_path / "run"
    assert main(["collect", "--fleet-file", str(tmp_path / "fleet.json"), "--results", str(tmp_path / "results"),
                 "--out", str(out)]) == 0
    result = json.loads((out / "result.json").read_text())
    assert result["converged"] and result["absent"] == [] and result["metrics"]["iou"] is None
    assert result["metrics"]["function_error"] < 1e-3  # the run's tol


@pytest.mark.parametrize("case", ["robot-file", "no-results", "not-a-folder", "world-of-another-fleet", "bad-wait"])
def test_collect_refuses_in_one_line(prepared, tmp_path, capsys, case):
    results = tmp_path / "results"
    results.mkdir()
    argv = ["collect", "--fleet-file", str(prepared / "fleet.json"), "--results", str(results), "--out", str(tmp_path / "o")]
    needle = {
        "robot-file": "robot 0's fleet file",
        "no-results": "--results: no result of fleet collect-test",
        "not-a-folder": "is not a folder",
        "world-of-another-fleet": "belongs to fleet 'other'",
        "bad-wait": "--wait: ",
    }[case]
    if case == "robot-file":
        argv[2] = str(deploy.robot_fleet_file(prepared, 0))
    elif case == "not-a-folder":
        argv[4] = str(prepared / "fleet.json")
    elif case == "world-of-another-fleet":
        world = json.loads((prepared / "world.json").read_text())
        (tmp_path / "world.json").write_text(json.dumps({**world, "fleet": "other"}))
        argv += ["--world", str(tmp_path / "world.json")]
    elif case == "bad-wait":
        argv += ["--wait", "ten minutes"]
    with pytest.raises(SystemExit) as exc:
        main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert exc.value.code == 2 and len(err) == 1 and needle in err[0], err


def test_read_results_waits_a_bounded_time(prepared, tmp_path):
    full = FleetSpec.load(prepared / "fleet.json")
    now = [0.0]
    naps: list[float] = []

    def sleep(s: float) -> None:
        naps.append(s)
        now[0] += s
        if len(naps) == 3:  # robot 0's result arrives while collect waits
            _results(full, tmp_path, ids={0})

    robots, absent = deploy.read_results(full, tmp_path, wait_s=2.0, clock=lambda: now[0], sleep=sleep)
    assert [r["id"] for r in robots] == [0] and set(absent) == {1, 2}
    assert now[0] == pytest.approx(2.0) and all(s <= deploy.POLL_S for s in naps)
