"""The options table (launcher/options.py): the CLI, the TOML keys, Options and each algorithm's
typed parameters are derived from it and agree with it."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import pytest

from agents.spec import PARAMS_CLASSES
from launcher import config
from launcher.cli import _options, _subparser, build_parser, parse_args
from launcher.options import (
    DURATION,
    FILE,
    FLAG,
    FLOAT,
    INT,
    LIST,
    OPTIONS,
    PATH,
    PROBABILITY,
    SECTION_OF,
    Option,
    Options,
    algorithm_params,
    fed_parameters,
    options_of,
    param_default,
)
from launcher.scenario import ScenarioError
from launcher.world import build_world
from protocol.links import LinkFaults

TABLE_COMMANDS = sorted({c for o in OPTIONS for c in o.commands})

#: a valid non-default value of each option, as a command-line word and as a TOML value
_TEXT = {"shape": "bean", "grid": "4x4", "grid-bounds": "0,1,0,1", "preset": "paper", "topology": "ring",
         "fleet-id": "opt-test", "bad-grid": "3x2", "algorithm": "admm", "crash": "1@4",
         "connect": "tcp/127.0.0.1:7447", "robots-per-process": "4",
         # issue 13 (free sync, fault models)
         "sync": "free", "delay-dist": "pareto", "link-loss": "0-1:0.5", "robot-loss": "2:0.3",
         "partition": "0,1/2,3@2s-5s", "delays": "0ms,5ms", "losses": "0,0.2", "syncs": "free"}
_BY_KIND = {INT: ("7", 7), FLOAT: ("0.5", 0.5), DURATION: ("30ms", "30ms"), PROBABILITY: ("0.25", 0.25)}


def sample(option: Option) -> tuple[list[str], object]:
    """(command-line words, TOML value) of a valid non-default value of ``option``."""
    if option.kind == FLAG:
        return [option.flag], True
    if option.kind == LIST:
        return [option.flag, _TEXT[option.name]], [_TEXT[option.name]]
    if option.name == "narrow-ratio":  # at least 1
        return [option.flag, "3"], 3.0
    if option.kind in _BY_KIND:
        text, toml = _BY_KIND[option.kind]
        return [option.flag, text], toml
    if option.name not in _TEXT and option.choices:
        text = next(c for c in reversed(option.choices) if c != option.default)
        return [option.flag, text], text
    text = _TEXT.get(option.name, "/tmp/x.csv" if option.kind in (PATH, FILE) else "abc")
    return [option.flag, text], text


def required(command: str, but: Option | None = None) -> list[str]:
    """Words for the required flags of ``command`` (robot: --fleet-file, --connect), except ``but``."""
    return [w for o in options_of(command) if o.required and o is not but for w in sample(o)[0]]


def _long_flags(parser: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    return {f[2:]: a for a in parser._actions for f in a.option_strings if f.startswith("--")}


# -- the CLI ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("command", TABLE_COMMANDS)
def test_each_command_has_exactly_the_table_flags_with_their_dest_and_default(command):
    actions = _long_flags(_subparser(build_parser(), command))
    assert set(actions) - {"help"} == {o.name for o in options_of(command)}
    for option in options_of(command):
        action = actions[option.name]
        assert action.dest == option.dest
        assert action.default == ([] if option.kind == LIST and not option.required else option.default), option.name
        assert action.help and action.help.startswith(option.help.split(" (default")[0][:20])


@pytest.mark.parametrize("option", [o for o in OPTIONS if o.name != "config"], ids=lambda o: o.name)
def test_a_flag_and_its_toml_key_give_the_same_value(option, tmp_path):
    command = next(c for c in option.commands if c in TABLE_COMMANDS)
    words, toml = sample(option)
    from_flag = getattr(parse_args([command, *required(command, option), *words]), option.dest)
    assert from_flag != option.default, "the sample must differ from the default"
    if option.section is None:
        return
    assert SECTION_OF[option.name] == option.section
    text = f"[{option.section}]\n{option.name} = {_toml(toml)}\n"
    path = tmp_path / "s.toml"
    path.write_text(text)
    from_file = getattr(parse_args([command, "--config", str(path)]), option.dest)
    assert from_file == from_flag


def _toml(value: object) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, list):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    if isinstance(value, str):
        return f'"{value}"'
    return repr(value)


def test_the_toml_schema_is_the_table():
    assert set(SECTION_OF) == {o.name for o in OPTIONS if o.section is not None}
    assert config.SECTIONS == {s: tuple(o.name for o in OPTIONS if o.section == s) for s in config.SECTIONS}
    assert len({o.name for o in OPTIONS}) == len(OPTIONS), "each option once"


def test_a_bad_value_has_one_check_for_flag_file_and_code(tmp_path, capsys):
    """max-grid-points >= 4 is checked in one place: the command line, the file and Options built
    in code give the same message."""
    with pytest.raises(SystemExit):
        parse_args(["simulate", "--max-grid-points", "3"])
    flag = capsys.readouterr().err
    path = tmp_path / "s.toml"
    path.write_text("[model]\nmax-grid-points = 3\n")
    with pytest.raises(SystemExit):
        parse_args(["simulate", "--config", str(path)])
    file = capsys.readouterr().err
    with pytest.raises(ScenarioError) as exc:
        build_world(Options(max_grid_points=3))
    message = "'3' must be at least 4"
    assert message in flag and message in file and str(exc.value) == f"--max-grid-points: {message}"


def test_conflicting_data_sources_in_a_file_are_an_error(tmp_path, capsys):
    path = tmp_path / "s.toml"
    path.write_text('[world]\nshape-file = "a.csv"\ndata = "b.csv"\n')
    with pytest.raises(SystemExit) as exc:
        parse_args(["simulate", "--config", str(path)])
    assert exc.value.code == 2 and "give one data source, not both shape-file and data" in capsys.readouterr().err


# -- Options -----------------------------------------------------------------------------------------
def test_options_fields_and_defaults_are_the_tables():
    fields = {f.name: f for f in dataclasses.fields(Options)}
    plain = [o for o in OPTIONS if o.target == "options"]
    assert set(fields) == {o.dest for o in plain} | {"faults", "timing"}
    for option in plain:
        assert fields[option.dest].default == option.default, option.name
    defaults = Options()
    for option in OPTIONS:
        if option.target and "." in option.target:
            part, name = option.target.split(".")
            assert getattr(getattr(defaults, part), name) == option.default, option.name


def test_every_flag_reaches_options():
    for option in OPTIONS:
        if option.target is None:
            continue
        command = next(c for c in option.commands if c in TABLE_COMMANDS)
        words, _ = sample(option)
        opts = _options(parse_args([command, *words]))
        if option.target == "options":
            got = getattr(opts, option.dest)
        else:
            part, name = option.target.split(".")
            got = getattr(getattr(opts, part), name)
        want = getattr(parse_args([command, *words]), option.dest)
        if option.target.startswith("faults."):  # LinkFaults reads "0-1:0.5" as (0, 1, 0.5): compare what it stores
            want = getattr(LinkFaults(**{name: want}), name)
        assert got == want and got != option.default, option.name


# -- the algorithms' typed parameters ---------------------------------------------------------------------
def test_each_feed_is_a_field_and_one_default_serves_every_algorithm_it_feeds():
    for option, algorithm, param in fed_parameters():
        assert param in {f.name for f in dataclasses.fields(PARAMS_CLASSES[algorithm])}, (option.name, param)
        if option.default is not None:
            assert param_default(algorithm, param) == option.default, (option.name, algorithm)


@pytest.mark.parametrize("algorithm", sorted(PARAMS_CLASSES))
def test_the_params_of_the_defaults_are_the_algorithms_own_defaults(algorithm):
    params = algorithm_params(Options(), algorithm, diameter=1)
    assert all("_" not in k or not k.startswith(("ct_", "newton_")) for k in params)
    cls = PARAMS_CLASSES[algorithm]
    built = cls(**params)
    for f in dataclasses.fields(cls):
        if f.name != "diameter":
            assert getattr(built, f.name) == f.default, (algorithm, f.name)


@pytest.mark.parametrize("algorithm", ["admm", "ct-admm", "newton", "autogrid"])
def test_flags_reach_the_typed_params_of_the_fleet_file(algorithm):
    fed = [(o, p) for o, a, p in fed_parameters() if a == algorithm]
    words = ["--algorithm", algorithm]
    expected = {}
    for option, param in fed:
        value = {"relax": "1.5", "max-grid-points": "120", "ct-period": "20ms", "ct-step": "2ms",
                 "narrow-ratio": "3", "model": "svm"}.get(option.name)  # (narrow-ratio 3: the svm model's)
        text = value or {INT: "900", FLOAT: "0.002", DURATION: "4s"}[option.kind]
        words += [option.flag, text]
        expected[param] = option.parse(text)
    if algorithm != "autogrid":
        words += ["--preset", "paper"]
    _, spec = build_world(_options(parse_args(["simulate", *words]), fleet_id="t"))
    typed = spec.algorithm_params
    assert isinstance(typed, PARAMS_CLASSES[algorithm])
    for param, value in expected.items():
        assert getattr(typed, param) == value, param


def test_ct_admm_keeps_its_own_tolerance_and_ignores_admm_keys():
    """Issue 12: ADMM's --tol (1e-3) used to replace CT-ADMM's own default (1e-4)."""
    _, spec = build_world(Options(algorithm="ct-admm", preset="paper", tol=1e-2, rho=3.0, fleet_id="t"))
    assert spec.algorithm_params.tol == param_default("ct-admm", "tol") == 1e-4
    assert spec.algorithm_params.rho == param_default("ct-admm", "rho")  # the flow's gain, not --rho
    assert set(spec.params) == {"diameter", "step", "period", "stop_time", "tol"}


def test_gridstudy_stop_time_is_the_one_given(tmp_path, monkeypatch):
    """Issue 12: gridstudy added ``stop_time`` beside ``ct_stop_time``; which won depended on order."""
    from launcher import gridstudy

    seen = []
    real = gridstudy.simulate_fleet

    def spy(spec, **kw):
        seen.append(spec.algorithm_params.stop_time)
        return real(spec, **kw)

    monkeypatch.setattr(gridstudy, "simulate_fleet", spy)
    gridstudy.run_grid_study(tmp_path, options=Options(ct_stop_time=0.4), quiet=True)
    assert seen == [0.2, 0.4, 0.2, 0.4]
    assert Path(tmp_path / "grid_study.png").stat().st_size > 0
