"""Scenario files: the flags of `simulate`, `launch`, `central` and `prepare` in one TOML file.

    shapefleet simulate --config scenario.toml --loss 0.1      # flags given override the file

Every key is a command-line flag without its leading dashes, in the section the options table
(launcher/options.py, the one place each option, its type, default and check are declared) gives it,
listed in :data:`SECTIONS` (docs/scenario-file.md has the whole format and docker/scenario.toml an example)::

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
import tomllib
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from launcher.options import BY_NAME, OPTIONS, PATH, SECTION_OF, SECTIONS, toml_value

__all__ = ["SECTIONS", "ConfigError", "Scenario", "load_scenario", "defaults_for"]

#: data sources: a flag given for one drops the file's others; two in one file conflict
SOURCES = tuple(o.name for o in OPTIONS if o.exclusive == "source")


class ConfigError(ValueError):
    """A scenario file that cannot be used; the message names the file and the key."""


@dataclass(frozen=True)
class Scenario:
    """A validated scenario file: ``values`` maps flag names (``"max-rounds"``) to checked values."""

    path: Path
    values: dict[str, Any]

    def where(self, key: str) -> str:
        return f"{self.path}: [{SECTION_OF[key]}] {key}"


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
        text = path.read_bytes().decode("utf-8-sig")  # (a BOM, as Windows editors write, is dropped)
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
            try:  # the option's TOML types, parse and check: the table's (launcher/options.py)
                values[key] = toml_value(BY_NAME[key], value)
            except ValueError as exc:
                raise ConfigError(f"{path}: [{section}] {key}: {exc}") from None
    for group in {o.exclusive for o in OPTIONS if o.exclusive}:
        both = [o.name for o in OPTIONS if o.exclusive == group and o.name in values]
        if len(both) > 1:
            raise ConfigError(f"{path}: [{SECTION_OF[both[1]]}] {both[1]}: give one data source, not both "
                              f"{both[0]} and {both[1]}")
    base = path.resolve().parent
    for key in (*(o.name for o in OPTIONS if o.kind == PATH and o.section), "shape"):
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
        out[action.dest] = value  # parsed and checked by load_scenario, as the flag would be
    return out


def flags_of(parser: argparse.ArgumentParser) -> set[str]:
    """The long flags of a parser without dashes (for the coverage test of the schema)."""
    return {flag[2:] for a in parser._actions for flag in a.option_strings if flag.startswith("--")}
