"""Scenario files: the flags of `simulate`, `launch`, `central` and `prepare` in one TOML file.

    shapefleet simulate --config scenario.toml --loss 0.1      # flags given override the file

Every key is a command-line flag without its leading dashes, in the section listed in
:data:`SECTIONS` (docs/scenario-file.md has the whole format and docker/scenario.toml an example)::

    [world]
    shape = "blob"
    robots = 3

    [faults]
    loss = 0.1

A subcommand takes the keys it has flags for and ignores the others (a `launch` crash plan in a
file that `simulate` reads is fine). Relative paths (``shape-file``, ``data``, a ``shape`` ending in
``.csv``) are relative to the scenario file's folder. Unknown keys, keys in the wrong section, wrong
types and bad values end in :class:`ConfigError`, one message naming the file and the key; the CLI
turns it into exit code 2. The world's lengths (``standoff``, ``range``, ``offset``, ``noise``,
``comm-range``) are in the outline's unit; left out, they follow the object's size (scenario.world_lengths).

How it plugs into argparse: :func:`defaults_for` turns the file into ``dest -> value`` defaults of a
subcommand's parser (``parser.set_defaults``), leaving out what the command line gave, and the
command line is parsed again: flags given win, everything else comes from the file.
"""

from __future__ import annotations

import argparse
import difflib
import math
import tomllib
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

__all__ = ["SECTIONS", "ConfigError", "Scenario", "load_scenario", "defaults_for"]

SECTIONS: dict[str, tuple[str, ...]] = {
    "world": ("shape", "shape-file", "data", "robots", "points", "seed", "standoff", "range", "offset", "noise"),
    "model": ("grid", "grid-bounds", "sigma", "C", "preset", "max-grid-points"),
    "algorithm": (
        "topology", "comm-range", "algorithm", "rho", "relax", "tol", "max-rounds", "ct-step", "ct-period", "ct-stop-time",
    ),
    "faults": ("delay", "jitter", "loss", "duplicate", "reorder", "retransmit"),
    "fleet": ("fleet-id", "dead-after", "max-wall"),
    "launch": ("crash", "restart-after", "no-restart", "zenoh-port", "max-robots"),
}
SECTION_OF = {key: section for section, keys in SECTIONS.items() for key in keys}

# TOML types each key accepts (besides what the flag's own parser then checks)
_INT = ("robots", "points", "seed", "max-rounds", "zenoh-port", "max-grid-points", "max-robots")
_FLOAT = ("standoff", "range", "offset", "noise", "sigma", "C", "comm-range", "rho", "relax", "tol", "restart-after")
_DURATION = ("delay", "jitter", "retransmit", "dead-after", "max-wall", "ct-step", "ct-period", "ct-stop-time")
_PROBABILITY = ("loss", "duplicate", "reorder")
_BOOL = ("no-restart",)
_LIST = ("crash",)
_PATHS = ("shape-file", "data")
SOURCES = ("shape", "shape-file", "data")  # one data source: a flag given for one drops the file's others


class ConfigError(ValueError):
    """A scenario file that cannot be used; the message names the file and the key."""


@dataclass(frozen=True)
class Scenario:
    """A validated scenario file: ``values`` maps flag names (``"max-rounds"``) to TOML values."""

    path: Path
    values: dict[str, Any]

    def where(self, key: str) -> str:
        return f"{self.path}: [{SECTION_OF[key]}] {key}"


def _type_name(value: Any) -> str:
    return {bool: "a boolean", int: "an integer", float: "a number", str: "a string", list: "an array",
            dict: "a table"}.get(type(value), type(value).__name__)


def _check_type(where: str, key: str, value: Any) -> Any:
    """The value in the form argparse would see it, or ConfigError."""

    def wrong(expected: str) -> ConfigError:
        return ConfigError(f"{where}: expected {expected}, got {_type_name(value)} {value!r}")

    if key in _BOOL:
        if not isinstance(value, bool):
            raise wrong("true or false")
        return value
    if key in _INT:
        if isinstance(value, bool) or not isinstance(value, int):
            raise wrong("an integer")
        return value
    if key in _FLOAT:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise wrong("a number")
        if not math.isfinite(value):
            raise ConfigError(f"{where}: {value!r} is not a finite number")
        return float(value)
    if key in _PROBABILITY:
        if isinstance(value, bool) or not isinstance(value, (int, float, str)):
            raise wrong("a probability such as 0.3 or \"30%\"")
        return value if isinstance(value, str) else repr(float(value))
    if key in _LIST:
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            raise wrong('an array of strings such as ["1@40"]')
        return list(value)
    if not isinstance(value, str):
        raise wrong('a duration such as "20ms"' if key in _DURATION else "a string")
    return value


def _check_value(where: str, key: str, value: Any) -> None:
    """Checks a flag's own parser does only later (and then names the flag, not the file)."""
    from launcher import scenario, topology
    from protocol.keys import validate_fleet_id
    from protocol.links import parse_duration, parse_probability

    try:
        if key in _DURATION:
            parse_duration(value, flag=key)
        elif key in _PROBABILITY:
            parse_probability(value, flag=key)
        elif key == "crash":
            from launcher.fleet import parse_crash

            for text in value:
                parse_crash(text)
        elif key == "grid":
            scenario.parse_grid(value)
        elif key == "grid-bounds":
            scenario.parse_bounds(value)
        elif key == "preset":
            from launcher.world import PRESETS

            if value not in PRESETS:
                raise ValueError(f"{value!r} is not a preset (choose from {', '.join(PRESETS)})")
        elif key == "max-grid-points" and value < 4:
            raise ValueError(f"{value!r} must be at least 4")
        elif key == "topology" and value not in topology.TOPOLOGIES:
            raise ValueError(f"{value!r} is not one of {', '.join(topology.TOPOLOGIES)}")
        elif key == "fleet-id":
            validate_fleet_id(value)
    except ValueError as exc:  # ScenarioError and TopologyError are ValueErrors too
        message = str(exc)
        for prefix in (f"--{key}: ", f"{key}: "):
            message = message.removeprefix(prefix)
        raise ConfigError(f"{where}: {message}") from None


def _unknown(path: Path, key: str, section: str | None) -> ConfigError:
    where = f"{path}: [{section}] {key}" if section else f"{path}: {key}"
    if key in SECTION_OF:
        return ConfigError(f"{where}: this key belongs in the [{SECTION_OF[key]}] section")
    if section is None and key in SECTIONS:
        return ConfigError(f"{where}: [{key}] must be a table (a section), not a value")
    pool = SECTIONS[section] if section in SECTIONS else list(SECTIONS) + list(SECTION_OF)
    close = difflib.get_close_matches(key.lstrip("-").replace("_", "-"), pool, n=1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    kind = "section" if section is None else "key"
    return ConfigError(f"{where}: unknown {kind}{hint}; see docs/scenario-file.md")


def load_scenario(path: str | Path) -> Scenario:
    """Read and validate a scenario file (see the module doc); ConfigError names file and key."""
    path = Path(path)
    try:
        text = path.read_bytes().decode("utf-8")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read scenario file ({exc.strerror})") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not a UTF-8 text file") from None
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    values: dict[str, Any] = {}
    for section, table in doc.items():
        if section not in SECTIONS or not isinstance(table, dict):
            raise _unknown(path, section, None)
        for key, value in table.items():
            if key not in SECTIONS[section]:
                raise _unknown(path, key, section)
            where = f"{path}: [{section}] {key}"
            value = _check_type(where, key, value)
            _check_value(where, key, value)
            values[key] = value
    sources = [k for k in SOURCES if k in values]
    if len(sources) > 1:
        raise ConfigError(f"{path}: [world] {sources[1]}: give one data source, not both {sources[0]} and {sources[1]}")
    base = path.resolve().parent
    for key in (*_PATHS, "shape"):
        value = values.get(key)
        if value is None or (key == "shape" and not value.lower().endswith(".csv")):
            continue
        values[key] = str(base / Path(value).expanduser()) if not Path(value).expanduser().is_absolute() else value
    return Scenario(path, values)


def defaults_for(parser: argparse.ArgumentParser, scenario: Scenario, given: Iterable[str] = ()) -> dict[str, Any]:
    """``dest -> value`` defaults of ``parser`` (one subcommand) from ``scenario``.

    Keys the parser has no flag for are left out; so are flags whose ``dest`` is in ``given`` (the
    command line wins, also for repeatable flags such as ``--crash``) and, when the command line
    names a data source (``--shape``, ``--shape-file``, ``--data``), the file's data source.
    Values go through the flag's own type (e.g. ``--robots 0`` and ``robots = 0`` fail alike).
    """
    given = set(given)
    actions = {  # by long flag: --range has dest lidar_range
        flag[2:]: a for a in parser._actions for flag in a.option_strings if flag.startswith("--")
    }
    source_given = any(actions[k].dest in given for k in SOURCES if k in actions)
    out: dict[str, Any] = {}
    for key, value in scenario.values.items():
        action = actions.get(key)
        if action is None or action.dest in given or (key in SOURCES and source_given):
            continue
        if callable(action.type) and not isinstance(value, (list, bool)):
            try:
                value = action.type(str(value))
            except (argparse.ArgumentTypeError, ValueError, TypeError) as exc:
                raise ConfigError(f"{scenario.where(key)}: {exc}") from None
        if action.choices is not None and value not in action.choices:
            choices = ", ".join(map(str, action.choices))
            raise ConfigError(f"{scenario.where(key)}: {value!r} is not one of {choices}")
        out[action.dest] = value
    return out


def flags_of(parser: argparse.ArgumentParser) -> set[str]:
    """The long flags of a parser without dashes (for the coverage test of the schema)."""
    return {flag[2:] for a in parser._actions for flag in a.option_strings if flag.startswith("--")}
