"""The contract's user-facing rules, probed adversarially (the audit of 2026-11-24): bad input exits 2
with one line naming the flag or file and leaves nothing behind; a run that cannot be measured says so
in one line (exit 1), never with a traceback. Each case here failed before its fix."""

from __future__ import annotations

from pathlib import Path

import pytest

from agents.robot import CHECKPOINT_VERSION
from launcher import cli
from launcher.scenario import ScenarioError, load_data_csv

from .conftest import cli_exit_and_stderr


def _exit_and_line(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    """(exit code, the last stderr line) of ``shapefleet argv`` run in this process."""
    code, err = cli_exit_and_stderr(argv, capsys)
    return code, err[-1] if err else ""


@pytest.mark.parametrize(
    ("words", "names"),
    [
        (["--seed", "-1"], "--seed"),  # was: numpy's ValueError traceback while sampling the data
        (["--shape-file="], "--shape-file"),  # was: silently the default shape
        (["--data="], "--data"),  # was: ".: is a directory"
        (["--config="], "--config"),  # was: ".: cannot read scenario file"
        (["--shape="], "--shape"),  # was: ".: is a directory, not a CSV file"
        (["--robots", "1_0"], "--robots"),  # was: 10 robots (Python's digit separator)
        (["--sigma", "1_0"], "--sigma"),  # was: sigma 10
    ],
)
def test_bad_flag_exits_2_naming_it_and_writes_nothing(words: list[str], names: str, tmp_path: Path,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "run"
    code, line = _exit_and_line(["simulate", "--preset", "paper", "--max-rounds", "2", "--out", str(out), *words],
                                capsys)
    assert code == 2
    assert line.startswith("shapefleet: error: ") and names in line
    assert not out.exists()


def test_empty_out_is_refused_not_the_default_folder(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """--out "" used to mean "not given": the run went to runs/<stamp>-simulate/ instead."""
    monkeypatch.chdir(tmp_path)
    code, line = _exit_and_line(["simulate", "--preset", "paper", "--max-rounds", "2", "--out="], capsys)
    assert code == 2 and "--out" in line
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(("label", "said"), [("1", r"\+1 \(outside\)"), ("-1", r"-1 \(inside\)")])
def test_data_of_one_label_is_refused(label: str, said: str, tmp_path: Path) -> None:
    """All points outside (or all inside): any function of one sign fits, there is no outline; such a run
    used to report `converged` (exit 0) on a function with no zero level set."""
    path = tmp_path / "one.csv"
    path.write_text("robot,x,y,label\n" + "".join(f"{i % 2},{i}.0,{i / 3:.3f},{label}\n" for i in range(6)))
    with pytest.raises(ScenarioError, match=rf"all 6 points are labelled {said}; an outline needs points of both labels"):
        load_data_csv(path)


def test_failed_reference_solve_is_one_line_exit_1(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """--C 1e300: piqp reaches its iteration cap on the exact centralized problem; this used to end in
    a SolverError traceback."""
    code, line = _exit_and_line(["central", "--preset", "paper", "--C", "1e300", "--out", str(tmp_path / "c")], capsys)
    assert code == 1
    assert line.startswith("shapefleet: error: the exact centralized solve failed") and "--C 1e+300" in line


@pytest.mark.parametrize(
    ("words", "flag"),
    [(["--link-loss", "0-9:0.5"], "--link-loss"), (["--robot-loss", "9:0.3"], "--robot-loss"),
     (["--partition", "0,1/2,9@1s-2s"], "--partition")],
)
def test_fault_entry_for_a_robot_not_in_the_fleet_is_refused(words: list[str], flag: str, tmp_path: Path,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    """Robot 9 of a 3-robot fleet: the entry used to be ignored without a word (exit as if it applied)."""
    out = tmp_path / "run"
    code, line = _exit_and_line(["simulate", "--preset", "paper", "--max-rounds", "2", "--out", str(out), *words],
                                capsys)
    assert code == 2 and line.endswith(f"{flag}: robot 9 is not in the fleet (robots [0, 1, 2])")
    assert not out.exists()


def test_every_robot_lost_is_one_line_exit_1(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """All three robots crash for good at round 3: no participant is left; this used to end in numpy's
    'need at least one array to concatenate' traceback."""
    crashes = [w for r in range(3) for w in ("--crash", f"{r}@3")]
    code, line = _exit_and_line(["simulate", "--preset", "paper", "--max-rounds", "20", "--no-restart", *crashes,
                                 "--out", str(tmp_path / "run")], capsys)
    assert code == 1
    assert line == "shapefleet: error: no robot took part to the end (robots [0, 1, 2] all lost): no answer to measure"


@pytest.mark.parametrize(("words", "flag"), [(["--robots", "5"], "--robots"), (["--noise=0.5"], "--noise"),
                                             (["--points", "7"], "--points")])
def test_lidar_flag_with_data_is_refused_not_ignored(words: list[str], flag: str, tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """--data fixes robots and points: --robots 5 used to be dropped without a word (the run had the
    file's 3 robots and said nothing)."""
    data = tmp_path / "data.csv"
    data.write_text("robot,x,y,label\n0,0,0,1\n0,1,0,-1\n1,0,1,1\n1,1,1,-1\n")
    out = tmp_path / "run"
    code, line = _exit_and_line(["simulate", "--preset", "paper", "--data", str(data), *words, "--out", str(out)],
                                capsys)
    assert code == 2 and f"{flag}: not used with --data" in line
    assert not out.exists()


def test_a_checkpoint_that_is_not_one_exits_2_naming_the_flag(tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    """`shapefleet robot --checkpoint FILE` where FILE holds no checkpoint (here random bytes): this used
    to end in agents/robot.py's ValueError traceback, exit 1."""
    assert cli.main(["prepare", "--preset", "paper", "--out", str(tmp_path / "fleet")]) == 0
    junk = tmp_path / "junk.ckpt"
    junk.write_bytes(bytes(range(256)) * 4)
    capsys.readouterr()
    code, line = _exit_and_line(["robot", "--fleet-file", str(tmp_path / "fleet" / "fleet.json"), "--id", "0",
                                 "--connect", "tcp/127.0.0.1:1", "--checkpoint", str(junk)], capsys)
    assert code == 2
    assert line == f"shapefleet: error: --checkpoint: {junk}: no complete shapefleet robot checkpoint (version {CHECKPOINT_VERSION})"


@pytest.mark.parametrize("sigma", ["1e-300", "1e300"])
def test_a_width_that_cannot_be_squared_exits_2_naming_sigma(sigma: str, tmp_path: Path,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    """2 sigma^2 underflows to 0 (the kernel's diagonal became 0/0: an IndexError traceback) or overflows."""
    out = tmp_path / "run"
    code, line = _exit_and_line(["simulate", "--preset", "paper", "--max-rounds", "2", "--sigma", sigma,
                                 "--out", str(out)], capsys)
    assert code == 2 and "--sigma" in line and "cannot be squared" in line
    assert not out.exists()


def test_a_robot_that_heard_nobody_is_written_as_null_not_a_traceback(tmp_path: Path,
                                                                      capsys: pytest.CaptureFixture[str]) -> None:
    """--loss 1: every robot ran its round 0 alone, its residual is inf; strict JSON has no inf, so writing
    result.json raised. Now: null (not measured), the run not converged, exit 1, one line saying why."""
    import json

    out = tmp_path / "run"
    code, line = _exit_and_line(["simulate", "--preset", "paper", "--max-rounds", "5", "--loss", "1",
                                 "--out", str(out)], capsys)
    result = json.loads((out / "result.json").read_text())
    assert code == 1 and "NOT converged" in line and "isolated" in line
    assert result["converged"] is False and [r["residual"] for r in result["robots"]] == [None, None, None]


def test_a_scenario_file_with_a_byte_order_mark_is_read(tmp_path: Path) -> None:
    """Windows editors start UTF-8 files with a BOM; the CSV readers accepted it, the TOML reader did not."""
    from launcher.config import load_scenario

    path = tmp_path / "bom.toml"
    path.write_bytes(b"\xef\xbb\xbf[world]\nrobots = 4\n")
    assert load_scenario(path).values["robots"] == 4


def test_robots_without_comparable_answers_are_said_so_not_disagree_by_inf() -> None:
    """Two robots on different grids (an autogrid run stopped mid-sweep) have no finite disagreement: the
    verdict used to read "disagree by inf"; it names the pair and why, and the run is not converged."""
    from launcher.report import agreement_verdict

    rows = [{"id": 0, "neighbours": [1], "converged": True}, {"id": 1, "neighbours": [0], "converged": True}]
    v = agreement_verdict(rows, lambda a, b: float("inf"), tol=1e-3)
    assert v["converged"] is False and "robots 0 and 1 hold no comparable answers" in v["verdict"]
    assert "inf" not in v["verdict"]


def test_a_geometric_fleet_wider_than_the_stop_flags_reach_exits_2_naming_topology(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """64 robots 10 apart on a line, linked within 12: a geometric path of 63 hops. Its check stops at
    the first robot too far from another (robot 0, an end: 63 hops) and says "at least"."""
    data = tmp_path / "line.csv"
    rows = [f"{r},{10.0 * r},{dy},{label}" for r in range(64) for dy, label in ((0.0, -1), (1.0, 1))]
    data.write_text("robot,x,y,label\n" + "\n".join(rows) + "\n")
    out = tmp_path / "run"
    code, line = _exit_and_line(["simulate", "--preset", "paper", "--data", str(data), "--topology", "geometric",
                                 "--comm-range", "12", "--out", str(out)], capsys)
    assert code == 2 and line.startswith("shapefleet: error: --topology geometric: the 64 robots' graph ")
    assert "diameter of at least 63 hops" in line and "reach (62)" in line
    assert not out.exists()


@pytest.mark.parametrize(("words", "diameter", "limit"),
                         [(["--preset", "paper", "--robots", "126"], 63, 62), (["--robots", "106"], 53, 52)])
def test_a_graph_wider_than_the_stop_flags_reach_exits_2_naming_topology(
        words: list[str], diameter: int, limit: int, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A ring of 126 robots (admm) or 106 (autogrid) has a diameter past what the stop flags carry: this was
    a ValueError traceback from the parameters (or, for ct-admm, a message naming --ct-period)."""
    out = tmp_path / "run"
    code, line = _exit_and_line(["simulate", *words, "--topology", "ring", "--max-rounds", "1", "--out", str(out)],
                                capsys)
    assert code == 2 and line.startswith("shapefleet: error: --topology ring: ")
    assert f"diameter of {diameter} hops" in line and f"reach ({limit})" in line
    assert not out.exists()
