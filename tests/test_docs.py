"""The docs a newcomer reads (README.md, docs/*.md, examples/) against the options table.

Every ``--flag`` they name exists (an option of launcher/options.py, or a flag of one of the
project's other programs: the robot process, the router, the pytest plugin, a benchmark); every
``shapefleet COMMAND ...`` line uses only that command's flags; every default a doc states next to a
flag is the table's (or the algorithm parameter's it feeds); a list of values given for a flag
(`--shape a|b|c`) is all of them; docs/scenario-file.md lists exactly the TOML keys of each section;
every command-line-only option is named somewhere; every key of result.json is in
docs/result-schema.md. Each check is a function of the text, so the tests below also show that it
fails on a made-up stale flag, default, value or key.
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import pytest

from agents.spec import PARAMS_CLASSES
from launcher.options import ALGORITHM_CHOICES, BY_NAME, OPTIONS, SECTIONS, Option, options_of, param_default
from launcher.scenario import shape_names

ROOT = Path(__file__).resolve().parent.parent
USER_DOCS = (ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")))
EXAMPLES = tuple(sorted((ROOT / "examples").rglob("*.py")))
#: the project's programs other than `shapefleet` whose flags the docs may quote
OTHER_PROGRAMS = (
    ROOT / "agents" / "robot.py", ROOT / "agents" / "free_robot.py", ROOT / "launcher" / "router.py",
    ROOT / "launcher" / "pytest_plugin.py", *sorted((ROOT / "benchmarks").glob("*.py")),
    *sorted((ROOT / "docker").glob("*.py")),
)
#: flags of other tools quoted in the docs (docker, dockerd, debootstrap in docs/deploy.md; pytest-xdist's
#: --dist in docs/testing.md; --help)
EXTERNAL_FLAGS = frozenset({
    "help", "dist", "mount", "build", "build-arg", "rm", "network", "variant", "storage-driver", "iptables",
    "ip6tables", "bridge", "data-root", "exec-root", "pidfile",
})
#: the shapefleet subcommands: every command some option of the table belongs to
COMMANDS = tuple(sorted({command for o in OPTIONS for command in o.commands}))

_FLAG = re.compile(r"(?<![\w-])--([a-zA-Z][\w-]*)")


def declared_elsewhere() -> frozenset[str]:
    """Flags the other programs declare: add_argument / addoption, or a literal "--name" they read."""
    found: set[str] = set()
    for path in OTHER_PROGRAMS:
        text = path.read_text(encoding="utf-8")
        found.update(re.findall(r"""(?:add_argument|addoption)\(\s*(?:[\w.]+\s*,\s*)?["']--([\w-]+)""", text))
        found.update(re.findall(r"""["']--([a-zA-Z][\w-]*)["']""", text))
    return frozenset(found)


def unknown_flags(text: str, known: frozenset[str]) -> list[tuple[int, str]]:
    """(line, flag) for every ``--flag`` in ``text`` that is not in ``known``."""
    return [(n, m.group(1)) for n, line in enumerate(text.splitlines(), 1)
            for m in _FLAG.finditer(line) if m.group(1) not in known]


def command_lines(text: str) -> list[tuple[int, str, str]]:
    """(line, command, its arguments) for every `shapefleet COMMAND ...` a user could copy: a line of
    a code block (fenced or indented; up to a `#` comment, with `\\` continuations), or the rest of
    an inline code span of the prose (which may wrap onto the next line)."""
    found = []
    lines = text.splitlines()
    call = re.compile(rf"(?:^|[\s`/])shapefleet\s+({'|'.join(COMMANDS)})\b")
    prose = []  # the text outside code blocks, line for line (code lines blanked)
    fenced = False
    for n, line in enumerate(lines, 1):
        fence = line.lstrip().startswith("```")
        if fence:
            fenced = not fenced
        if fence or fenced or line.startswith("    "):
            prose.append("")
            if fence:
                continue
            full, k = line, n
            while full.rstrip().endswith("\\") and k < len(lines):
                full = full.rstrip()[:-1] + " " + lines[k]
                k += 1
            m = call.search(full)
            if m:
                found.append((n, m.group(1), full[m.end():].split(" #", 1)[0]))
        else:
            prose.append(line)
    joined = "\n".join(prose)
    for span in re.finditer(r"`([^`]+)`", joined):
        m = call.search(span.group(1))
        if m:
            found.append((joined.count("\n", 0, span.start()) + 1, m.group(1), span.group(1)[m.end():]))
    return sorted(found)


def foreign_flags(text: str) -> list[tuple[int, str, str]]:
    """(line, command, flag) for a flag given to a `shapefleet COMMAND` that the command lacks."""
    bad = []
    for n, command, args in command_lines(text):
        own = {o.name for o in options_of(command)} | {"help"}
        bad += [(n, command, f) for f in _FLAG.findall(args) if f not in own]
    return bad


def effective_defaults(option: Option) -> list[object]:
    """What a doc may call the option's default: the table's, each parameter's it feeds (the round
    cap's differ per algorithm), or the default of an algorithm field of the option's own name."""
    values = [option.default] + [param_default(a, p) for a, p in option.feeds.items()]
    for cls in PARAMS_CLASSES.values():
        values += [f.default for f in dataclasses.fields(cls) if f.name == option.dest]
    return [v for v in values if v is not None and v is not dataclasses.MISSING]


def same_value(option: Option, text: str) -> bool:
    """Does ``text`` (as a doc writes it: 300, 1e-4, 10ms, auto, false) equal one of the defaults?"""
    text = text.strip("`\"'")
    for default in effective_defaults(option):
        if isinstance(default, bool):
            if text.lower() == str(default).lower():
                return True
            continue
        try:
            value = option.parse(text) if option.kind not in ("flag", "list") else text
        except (ValueError, TypeError):
            try:
                value = float(text)
            except ValueError:
                continue
        if isinstance(default, (int, float)) and isinstance(value, (int, float)):
            if abs(float(value) - float(default)) <= 1e-12 * max(1.0, abs(float(default))):
                return True
        elif value == default:
            return True
    return False


_DEFAULT_NEAR_FLAG = re.compile(
    r"`--(?P<name>[a-zA-Z][\w-]*)[^`]*`[^.;\n]{0,80}?\bdefault [`\"]*(?P<value>[\w.+-]+)")
_FLAG_WITH_VALUE_IS_DEFAULT = re.compile(r"`--(?P<name>[a-zA-Z][\w-]*) (?P<value>[\w.+-]+)` \((?:the )?default\b")


_NUMERIC_KINDS = ("int", "float", "duration", "probability")
_NUMBER = re.compile(r"[-+.]?\d")


def stale_defaults(text: str) -> list[tuple[str, str]]:
    """(flag, value) where a doc says "`--flag` ... default VALUE" or "`--flag VALUE` (default)"
    and VALUE is not the option's default. Prose defaults of non-options are not read."""
    stale = []
    for pattern in (_DEFAULT_NEAR_FLAG, _FLAG_WITH_VALUE_IS_DEFAULT):
        for m in pattern.finditer(text):
            option = BY_NAME.get(m.group("name"))
            value = m.group("value").rstrip(".:")
            if option is None or (option.kind in _NUMERIC_KINDS and not _NUMBER.match(value)):
                continue  # "`--tol` 1e-3: the default run ..." states no default of --tol
            if not same_value(option, value):
                stale.append((option.flag, value))
    return stale


def scenario_table(text: str) -> dict[str, set[str]]:
    """docs/scenario-file.md's "Sections and keys" table: section -> the keys it lists."""
    keys: dict[str, set[str]] = {}
    section = None
    for line in text.splitlines():
        m = re.match(r"\|\s*(?:`\[(\w+)\]`)?\s*\|\s*([^|]*)\|", line)
        if not m:
            continue
        section = m.group(1) or section
        if section is not None:
            keys.setdefault(section, set()).update(re.findall(r"`([\w-]+)`", m.group(2)))
    return keys


def stale_table_defaults(text: str) -> list[tuple[str, str]]:
    """(key, value) for a row of that table with one key whose meaning says "default VALUE" wrongly."""
    stale = []
    for line in text.splitlines():
        m = re.match(r"\|[^|]*\|\s*`([\w-]+)`\s*\|[^|]*\|(.*)\|\s*$", line)
        if m and m.group(1) in BY_NAME:
            for value in re.findall(r"\bdefault `?([\w.+\"-]+)", m.group(2)):
                if not same_value(BY_NAME[m.group(1)], value.rstrip(".:")):
                    stale.append((m.group(1), value))
    return stale


def closed_sets(option: Option) -> tuple[str, ...] | None:
    """The values an option takes from a closed set: its choices, the built-in shapes, the algorithms."""
    if option.name == "shape":
        return tuple(shape_names())
    if option.name == "algorithm":
        return ALGORITHM_CHOICES
    return option.choices


_CHOICES_LISTED = re.compile(r"`--(?P<name>[a-zA-Z][\w-]*) (?P<values>[\w-]+(?:\|[\w-]+)+)")


def stale_choices(text: str) -> list[tuple[str, list[str], list[str]]]:
    """(flag, missing, unknown) where a doc lists "`--flag a|b|c`" and the list is not the option's
    whole closed set of values."""
    stale = []
    for m in _CHOICES_LISTED.finditer(text):
        option = BY_NAME.get(m.group("name"))
        values = closed_sets(option) if option is not None else None
        if values is None:
            continue
        listed = m.group("values").split("|")
        missing, unknown = sorted(set(values) - set(listed)), sorted(set(listed) - set(values))
        if missing or unknown:
            stale.append((option.flag, missing, unknown))
    return stale


# -- the repository's docs ------------------------------------------------------------------------
@pytest.fixture(scope="module")
def texts() -> dict[str, str]:
    return {str(p.relative_to(ROOT)): p.read_text(encoding="utf-8") for p in (*USER_DOCS, *EXAMPLES)}


def test_every_flag_the_docs_name_exists(texts):
    known = frozenset(o.name for o in OPTIONS) | declared_elsewhere() | EXTERNAL_FLAGS
    bad = [f"{path}:{n}: --{flag}" for path, text in texts.items() for n, flag in unknown_flags(text, known)]
    assert bad == []


def test_every_shapefleet_command_line_uses_its_own_flags(texts):
    lines = [(path, c) for path, text in texts.items() for c in command_lines(text)]
    assert len(lines) > 40  # the reader found the README's and docs' command lines
    bad = [f"{path}:{n}: shapefleet {cmd} --{flag}" for path, text in texts.items()
           for n, cmd, flag in foreign_flags(text)]
    assert bad == []


def test_defaults_stated_next_to_a_flag_are_the_tables(texts):
    assert [(p, s) for p, text in texts.items() for s in stale_defaults(text)] == []
    scenario = texts["docs/scenario-file.md"]
    assert stale_table_defaults(scenario) == []


def test_values_listed_for_a_flag_are_all_its_values(texts):
    assert [(p, s) for p, text in texts.items() for s in stale_choices(text)] == []


def test_scenario_file_table_lists_exactly_the_toml_keys(texts):
    documented = scenario_table(texts["docs/scenario-file.md"])
    assert {s: sorted(k) for s, k in documented.items()} == {s: sorted(k) for s, k in SECTIONS.items()}


def test_every_command_line_only_option_is_named_in_the_docs(texts):
    """Options outside scenario files are only on the command line: a reader finds them in the docs
    (besides --help)."""
    prose = "\n".join(texts.values())
    missing = [o.flag for o in OPTIONS if o.section is None and not re.search(rf"(?<![\w-]){o.flag}(?![\w-])", prose)]
    assert missing == []


# -- the checks themselves fail on stale text -------------------------------------------------------
def test_a_made_up_flag_is_reported():
    known = frozenset(o.name for o in OPTIONS)
    assert unknown_flags("run it with `--robots 4 --warp-drive 9`", known) == [(1, "warp-drive")]


def test_a_flag_of_another_command_or_a_made_up_one_on_a_command_line_is_reported():
    text = ("```sh\n.venv/bin/shapefleet central --loss 0.3   # --crash in a comment is prose\n```\n"
            "or `shapefleet launch --crash 1@40 --warp-drive` and `shapefleet simulate --robots 8`\n"
            "    shapefleet robot --fleet-file f.json \\\n        --connect tcp/127.0.0.1:7447 --grid 5x3\n")
    assert foreign_flags(text) == [(2, "central", "loss"), (4, "launch", "warp-drive"), (5, "robot", "grid")]


def test_a_stale_default_is_reported_and_the_true_ones_pass():
    true = ("`--max-grid-points` (default 300); `--max-rounds` caps autogrid's rounds (default 50000); "
            "`--ct-tol`, default 1e-4; `--algorithm auto` (the default); `--period`, default 10ms.")
    assert stale_defaults(true) == []
    stale = "`--max-grid-points` (default 200); `--sync free` (the default)."
    assert stale_defaults(stale) == [("--max-grid-points", "200"), ("--sync", "free")]
    row = "| | `certify` | float | a stop needs the bound (`--certify`, default 3) |"
    assert stale_table_defaults(row) == [("certify", "3")]
    assert stale_table_defaults('| | `max-wall` | string (duration) | cap (default `"60s"`) |') == [("max-wall", '"60s"')]
    assert stale_table_defaults('| | `max-wall` | string (duration) | cap (default `"600s"`) |') == []


def test_a_value_list_missing_a_shape_or_naming_a_made_up_one_is_reported():
    names = "|".join(n for n in shape_names() if n != "kidney")
    assert stale_choices(f"`--shape {names}`") == [("--shape", ["kidney"], [])]
    assert stale_choices("`--topology complete|ring|line|geometric|torus`") == [("--topology", [], ["torus"])]
    assert stale_choices("`--over inprocess|zenoh` and `--grid 5x3`") == []


def test_a_key_missing_from_the_scenario_table_is_seen():
    text = "| `[world]` | `shape` | string | x |\n| | `robots`, `points` | integer | y |\n| `[fleet]` | `max-wall` | d | z |\n"
    assert scenario_table(text) == {"world": {"shape", "robots", "points"}, "fleet": {"max-wall"}}


# -- docs/result-schema.md against the result.json the reports write ------------------------------
def undocumented_keys(result: dict, schema: str) -> list[str]:
    """The keys of ``result`` (top level, robots' rows, metrics, agreement, world) that the schema
    does not name in backticks."""
    named = set(re.findall(r"`([A-Za-z_]\w*)`", schema))
    keys = [f"top.{k}" for k in result if k not in named]
    for row in result.get("robots", []):
        keys += [f"robots[].{k}" for k in row if k not in named]
    for part in ("metrics", "agreement", "world"):
        keys += [f"{part}.{k}" for k in (result.get(part) or {}) if k not in named]
    return sorted(set(keys))


RUNS = {  # in-process runs of about a second, one per kind of result.json
    "admm (paper preset)": ("simulate", {"preset": "paper"}),
    "autogrid (small)": ("simulate", {"robots": 2, "points": 8, "max_grid_points": 16}),
    "autogrid, least-squares model": ("simulate", {"model": "lsq", "robots": 2, "points": 8}),
    "free sync": ("simulate", {"preset": "paper", "sync": "free"}),
    "a user's fleet algorithm": ("simulate", {"algorithm": "examples.average_consensus:Average"}),
    "central": ("central", {}),
}


@pytest.mark.parametrize("name", RUNS)
def test_every_key_of_result_json_is_in_the_schema(name, tmp_path, monkeypatch):
    import json

    from launcher import cli

    monkeypatch.chdir(ROOT)  # the example algorithm is imported from the checkout
    command, options = RUNS[name]
    argv = [command, "--out", str(tmp_path / "run")]
    for key, value in options.items():
        argv += [f"--{key.replace('_', '-')}", str(value)]
    assert cli.main(argv) == 0
    result = json.loads((tmp_path / "run" / "result.json").read_text())
    assert result["robots"] or command == "central"
    assert undocumented_keys(result, (ROOT / "docs" / "result-schema.md").read_text()) == []


def test_an_undocumented_result_key_is_reported():
    schema = "| `converged` | bool |\n| `id` | robot id |\n`metrics`: `iou`"
    result = {"converged": True, "robots": [{"id": 0, "warp": 1}], "metrics": {"iou": 0.9, "speed": 2}}
    assert undocumented_keys(result, schema) == ["metrics.speed", "robots[].warp", "top.robots"]


def test_the_checkpoint_format_names_the_current_version():
    """docs/robot.md spells the checkpoint map's "v"; a version bump must update it (it said 4 at version 5)."""
    import re

    from agents.robot import CHECKPOINT_VERSION

    text = (ROOT / "docs" / "robot.md").read_text()
    assert re.findall(r'\{"v": (\d+),', text) == [str(CHECKPOINT_VERSION)]
