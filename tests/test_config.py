"""Scenario files (launcher/config.py): the flags in TOML, flags overriding them, errors in one line."""

from __future__ import annotations

from pathlib import Path

import pytest

from launcher import config
from launcher.cli import _options, _subparser, build_parser, parse_args

ROOT = Path(__file__).resolve().parent.parent
EXAMPLE = ROOT / "docker" / "scenario.toml"
SCENARIO_COMMANDS = ("simulate", "launch", "central", "prepare")


def write(tmp_path: Path, text: str, name: str = "scenario.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def fails(capsys, argv: list[str]) -> str:
    """The one error line of a command line that must end with exit code 2."""
    with pytest.raises(SystemExit) as exc:
        parse_args(argv)
    assert exc.value.code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1, lines
    return lines[0]


# -- the schema ---------------------------------------------------------------------------------------
def test_every_flag_has_a_key_and_every_key_a_flag():
    parser = build_parser()
    flags = set().union(*(config.flags_of(_subparser(parser, c)) for c in SCENARIO_COMMANDS))
    assert flags - {"help", "config", "out"} == set(config.SECTION_OF)


def test_the_example_file_holds_every_section_and_parses():
    scenario = config.load_scenario(EXAMPLE)
    assert {config.SECTION_OF[k] for k in scenario.values} == set(config.SECTIONS)
    for command in SCENARIO_COMMANDS:
        args = parse_args([command, "--config", str(EXAMPLE)])
        assert args.robots == scenario.values["robots"] and args.grid == "5x3"


# -- values, overrides ----------------------------------------------------------------------------------
FILE = """
[world]
shape = "bean"
robots = 4
points = 12
seed = 7
range = 3.5

[model]
grid = "4x4"
sigma = 0.8
C = 10

[algorithm]
topology = "ring"
rho = 12
max-rounds = 300

[faults]
delay = "5ms"
loss = 0.1
duplicate = "2%"
retransmit = "30ms"

[fleet]
fleet-id = "from-file"
dead-after = "20s"
max-wall = "90s"

[launch]
crash = ["1@40"]
restart-after = 0.5
no-restart = true
zenoh-port = 17447
"""


def test_the_file_gives_the_same_options_as_the_flags(tmp_path):
    path = write(tmp_path, FILE)
    flags = ["--shape", "bean", "--robots", "4", "--points", "12", "--seed", "7", "--range", "3.5", "--grid", "4x4",
             "--sigma", "0.8", "--C", "10", "--topology", "ring", "--rho", "12", "--max-rounds", "300",
             "--delay", "5ms", "--loss", "0.1", "--duplicate", "2%", "--retransmit", "30ms"]
    assert _options(parse_args(["simulate", "--config", str(path)])) == _options(parse_args(["simulate", *flags]))
    scenario_flags = flags[: flags.index("--delay")]  # central has no fault flags: the file's are ignored
    assert _options(parse_args(["central", "--config", str(path)])) == _options(parse_args(["central", *scenario_flags]))
    timing = ["--fleet-id", "from-file", "--dead-after", "20s", "--max-wall", "90s"]
    from_file = parse_args(["launch", "--config", str(path)])
    from_flags = parse_args(["launch", *flags, *timing, "--crash", "1@40", "--restart-after", "0.5", "--no-restart",
                             "--zenoh-port", "17447"])
    assert _options(from_file, fleet_id=from_file.fleet_id) == _options(from_flags, fleet_id=from_flags.fleet_id)
    for key in ("crash", "restart_after", "no_restart", "zenoh_port", "fleet_id"):
        assert getattr(from_file, key) == getattr(from_flags, key), key
    opts = _options(parse_args(["prepare", "--config", str(path)]))
    assert (opts.timing.dead_after_s, opts.timing.max_wall_s, opts.timing.retransmit_s) == (20.0, 90.0, 0.03)
    assert opts.faults.loss == 0.1 and opts.faults.duplicate == 0.02 and opts.C == 10.0


def test_flags_override_the_file(tmp_path):
    path = write(tmp_path, FILE)
    args = parse_args(["launch", "--robots", "2", "--config", str(path), "--crash", "0@3", "--loss", "0", "--tol", "1e-2"])
    assert (args.robots, args.crash, args.loss, args.tol) == (2, ["0@3"], 0.0, 1e-2)
    assert (args.points, args.shape, args.no_restart) == (12, "bean", True)  # the rest from the file


def test_a_data_source_on_the_command_line_replaces_the_files(tmp_path):
    shape = write(tmp_path, "x,y\n0,0\n2,0\n2,1\n0,1\n", "box.csv")
    path = write(tmp_path, '[world]\nshape-file = "box.csv"\n')
    args = parse_args(["simulate", "--config", str(path)])
    assert args.shape_file == str(shape)  # relative to the scenario file, not the working folder
    args = parse_args(["simulate", "--config", str(path), "--shape", "bean"])
    assert (args.shape, args.shape_file) == ("bean", None)


def test_preset_and_grid_budget_from_the_file(tmp_path):
    path = write(tmp_path, '[model]\npreset = "paper"\nmax-grid-points = 80\n')
    from_file = _options(parse_args(["simulate", "--config", str(path)]))
    assert from_file == _options(parse_args(["simulate", "--preset", "paper", "--max-grid-points", "80"]))
    assert (from_file.preset, from_file.max_grid_points) == ("paper", 80)
    assert _options(parse_args(["simulate", "--config", str(path), "--max-grid-points", "70"])).max_grid_points == 70


def test_relative_paths_are_relative_to_the_file(tmp_path, monkeypatch):
    (tmp_path / "conf").mkdir()
    write(tmp_path / "conf", '[world]\ndata = "../data.csv"\n')
    monkeypatch.chdir(tmp_path)
    assert parse_args(["central", "--config", "conf/scenario.toml"]).data == str(tmp_path / "conf" / ".." / "data.csv")


def test_keys_a_command_has_no_flag_for_are_ignored(tmp_path):
    path = write(tmp_path, '[launch]\ncrash = ["1@4"]\n[fleet]\ndead-after = "9s"\n')
    args = parse_args(["simulate", "--config", str(path)])
    assert not hasattr(args, "crash") and not hasattr(args, "dead_after")


def test_defaults_for_leaves_given_dests_alone(tmp_path):
    scenario = config.load_scenario(write(tmp_path, "[world]\nrobots = 5\npoints = 9\n"))
    sub = _subparser(build_parser(), "simulate")
    assert config.defaults_for(sub, scenario, given={"robots"}) == {"points": 9}


# -- errors: exit 2, one line naming the file and the key --------------------------------------------------
BAD = [
    ("[world]\nrobot = 3\n", "[world] robot: unknown key (did you mean 'robots'?)"),
    ("[wrld]\nrobots = 3\n", "wrld: unknown section (did you mean 'world'?)"),
    ("robots = 3\n", "robots: this key belongs in the [world] section"),
    ("[model]\nrobots = 3\n", "[model] robots: this key belongs in the [world] section"),
    ("world = 3\n", "world: [world] must be a table"),
    ('[world]\nrobots = "three"\n', "[world] robots: expected an integer, got a string 'three'"),
    ("[world]\nrobots = 2.5\n", "[world] robots: expected an integer, got a number 2.5"),
    ("[world]\nrobots = true\n", "[world] robots: expected an integer, got a boolean True"),
    ("[algorithm]\nrho = \"x\"\n", "[algorithm] rho: expected a number, got a string 'x'"),
    ("[model]\nsigma = nan\n", "[model] sigma: nan is not a finite number"),
    ("[launch]\nno-restart = \"yes\"\n", "[launch] no-restart: expected true or false"),
    ('[launch]\ncrash = "1@4"\n', "[launch] crash: expected an array of strings"),
    ('[launch]\ncrash = ["one at four"]\n', "[launch] crash: 'one at four' is not ID@ROUND"),
    ("[faults]\nloss = true\n", "[faults] loss: expected a probability"),
    ("[faults]\nloss = 1.5\n", "[faults] loss: '1.5' is outside [0, 1]"),
    ("[faults]\ndelay = 20\n", "[faults] delay: expected a duration such as \"20ms\", got an integer 20"),
    ('[faults]\ndelay = "20 parsecs"\n', "[faults] delay: '20 parsecs' is not a duration"),
    ('[model]\ngrid = "5by3"\n', "[model] grid: "),
    ('[model]\npreset = "fast"\n', "[model] preset: 'fast' is not a preset (choose from paper)"),
    ("[model]\nmax-grid-points = 3\n", "[model] max-grid-points: '3' must be at least 4"),
    ('[model]\nmax-grid-points = "60"\n', "[model] max-grid-points: expected an integer"),
    ("[algorithm]\npreset = \"paper\"\n", "[algorithm] preset: this key belongs in the [model] section"),
    ('[algorithm]\ntopology = "star"\n', "[algorithm] topology: 'star' is not one of complete, ring, line, geometric"),
    ('[algorithm]\nalgorithm = "sgd"\n', "[algorithm] algorithm: 'sgd' is not one of"),
    ("[world]\nrobots = 0\n", "[world] robots: '0' must be at least 1"),
    ('[fleet]\nfleet-id = "a/b"\n', "[fleet] fleet-id: "),
    ('[world]\nshape = "bean"\ndata = "d.csv"\n', "[world] data: give one data source, not both shape and data"),
    ("[world]\nrobots = 3\nrobots = 4\n", "not valid TOML"),
    ("[world\n", "not valid TOML"),
]


@pytest.mark.parametrize("text,needle", BAD, ids=[str(i) for i in range(len(BAD))])
def test_bad_files_end_with_one_message(tmp_path, capsys, text, needle):
    path = write(tmp_path, text)
    message = fails(capsys, ["simulate", "--config", str(path)])
    assert message.startswith(f"shapefleet: error: {path}: "), message
    assert needle in message, message


def test_a_missing_file_is_named(tmp_path, capsys):
    message = fails(capsys, ["central", "--config", str(tmp_path / "nope.toml")])
    assert f"{tmp_path / 'nope.toml'}: cannot read scenario file" in message


def test_value_checks_use_the_flags_own_parser_only_for_commands_that_have_it(tmp_path, capsys):
    path = write(tmp_path, "[launch]\nzenoh-port = 7447\n[world]\npoints = 0\n")
    assert "[world] points: '0' must be at least 1" in fails(capsys, ["launch", "--config", str(path)])


def test_bad_values_on_the_command_line_still_name_the_flag(tmp_path, capsys):
    path = write(tmp_path, "[world]\nrobots = 3\n")
    with pytest.raises(SystemExit) as exc:
        parse_args(["simulate", "--config", str(path), "--robots", "0"])
    assert exc.value.code == 2 and "--robots" in capsys.readouterr().err


def test_world_lengths_left_out_follow_the_outline_and_given_ones_keep_its_unit(tmp_path):
    """Issue 19: a millimetre outline in a scenario file gets millimetre lengths unless the file says otherwise."""
    from launcher.world import build_world

    write(tmp_path, "x,y\n0,0\n4000,0\n4000,3000\n0,3000\n", "part_mm.csv")  # diagonal 5000: x1000 the paper's world
    path = write(tmp_path, '[world]\nshape-file = "part_mm.csv"\n\n[model]\npreset = "paper"\n\n[algorithm]\ntopology = "geometric"\n')
    opts = _options(parse_args(["simulate", "--config", str(path)]))
    assert (opts.standoff, opts.lidar_range, opts.offset, opts.noise, opts.comm_range) == (None,) * 5
    lengths = build_world(opts)[0].lengths
    assert (lengths.standoff, lengths.lidar_range, lengths.offset, lengths.noise, lengths.comm_range) == (
        1500.0, 4000.0, 300.0, 10.0, 12000.0,
    )
    path = write(tmp_path, path.read_text().replace("[model]", "standoff = 1000\nnoise = 0\n\n[model]")
                 + "comm-range = 9000\n")
    opts = _options(parse_args(["simulate", "--config", str(path), "--offset", "200"]))
    lengths = build_world(opts)[0].lengths
    assert (lengths.standoff, lengths.lidar_range, lengths.offset, lengths.noise, lengths.comm_range) == (
        1000.0, 4000.0, 200.0, 0.0, 9000.0,
    )
    assert lengths.given == ("standoff", "offset", "noise", "comm-range")
