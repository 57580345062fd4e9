"""The command line as a person meets it: outputs of a run, and bad input refused in one line."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from launcher.cli import main

DATA = Path(__file__).parent / "data"


def run_cli(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "launcher.cli", *args], capture_output=True, text=True, timeout=300, cwd=cwd
    )


def test_simulate_writes_the_run_folder(tmp_path):
    out = tmp_path / "run"
    proc = run_cli("simulate", "--preset", "paper", "--out", str(out))
    assert proc.returncode == 0, proc.stderr
    for name in ("data.csv", "result.json", "shapes.png", "convergence.png"):
        assert (out / name).stat().st_size > 0, name
    result = json.loads((out / "result.json").read_text())
    for key in ("converged", "rounds", "wall_s", "algorithm", "sigma", "C", "grid", "robots", "central", "metrics", "history"):
        assert key in result
    assert result["converged"] and result["C"] is None and result["sigma"] == 1.0
    assert len(result["grid"]) == 15 and all(len(r["c"]) == 15 for r in result["robots"])
    m = result["metrics"]
    assert m["function_error"] < 1e-3 and m["train_accuracy"] == 1.0 and 0.5 < m["iou"] <= 1.0
    assert result["history"][0]["round"] == 0 and result["history"][-1]["round"] == result["rounds"]
    for r in result["robots"]:
        assert {"id", "c", "gamma", "rounds", "frames_sent", "frames_received"} <= r.keys()
    # the data file repeats the run exactly
    again = tmp_path / "again"
    proc = run_cli("simulate", "--preset", "paper", "--data", str(out / "data.csv"), "--out", str(again))
    assert proc.returncode == 0, proc.stderr
    assert json.loads((again / "result.json").read_text())["central"] == result["central"]


def test_central_writes_a_result(tmp_path):
    proc = run_cli("central", "--out", str(tmp_path / "c"), "--shape", "bean")
    assert proc.returncode == 0, proc.stderr
    result = json.loads((tmp_path / "c" / "result.json").read_text())
    assert result["central"]["status"] == "solved" and result["metrics"]["function_error"] == 0.0


def test_default_out_folder_is_new_under_runs(tmp_path):
    proc = run_cli("central", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    (folder,) = (tmp_path / "runs").iterdir()
    assert (folder / "result.json").exists()


BAD = [
    (["--shape", "teapot"], "--shape"),
    (["--grid", "5by3"], "--grid"),
    (["--grid", "0x3"], "--grid"),
    (["--grid-bounds", "1,0,0,1"], "--grid-bounds"),
    (["--sigma", "-1"], "--sigma"),
    (["--sigma", "nan"], "--sigma"),
    (["--robots", "0"], "--robots"),
    (["--topology", "star"], "--topology"),
    (["--topology", "geometric", "--comm-range", "0.5"], "--comm-range"),
    (["--shape-file", str(DATA / "bowtie.csv")], "self-intersecting"),
    (["--shape-file", "/nonexistent/shape.csv"], "shape.csv"),
    (["--loss", "1.5"], "--loss"),
    (["--delay", "20 parsecs"], "--delay"),
]


@pytest.mark.parametrize("args,needle", BAD, ids=[b[1] + str(i) for i, b in enumerate(BAD)])
def test_bad_input_exits_2_with_one_message(tmp_path, args, needle):
    proc = run_cli("simulate", "--out", str(tmp_path / "o"), *args)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert needle in lines[-1]
    assert len([line for line in lines if "error" in line]) == 1


DATA_CASES = [
    ("robot,x,y,label\n0,0,0,1\n0,1,1,2\n", "label"),
    ("robot,x,y,label\n0,0,nan,1\n", "finite"),
    ("robot,x,y,label\n0,0,inf,1\n", "finite"),
    ("robot,x,y\n0,0,0\n", "header"),
    ("robot,x,y,label\n", "no data"),
    ("robot,x,y,label\n0,0,0,1\n2,1,1,-1\n", "robot 1 has no data"),
    ("robot,x,y,label\n0,zero,0,1\n", "not a number"),
]


@pytest.mark.parametrize("text,needle", DATA_CASES)
def test_bad_data_files(tmp_path, text, needle):
    path = tmp_path / "d.csv"
    path.write_text(text)
    with pytest.raises(SystemExit) as exc:
        main(["central", "--data", str(path), "--out", str(tmp_path / "o")])
    assert exc.value.code == 2


def test_bad_data_messages_name_file_and_line(tmp_path, capsys):
    path = tmp_path / "d.csv"
    path.write_text("robot,x,y,label\n0,0,0,1\n0,1,1,3\n")
    with pytest.raises(SystemExit):
        main(["central", "--data", str(path), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert "d.csv line 3" in err and "label" in err


def test_infeasible_grid_is_said_in_words(tmp_path):
    proc = run_cli("simulate", "--preset", "paper", "--shape", "cross", "--grid", "2x2", "--out", str(tmp_path / "o"))
    assert proc.returncode == 2
    assert "infeasible" in proc.stderr and "Traceback" not in proc.stderr
    assert (tmp_path / "o" / "shapes.png").exists()
    result = json.loads((tmp_path / "o" / "result.json").read_text())
    assert result["central"]["status"] == "infeasible" and not result["converged"]


def test_ct_admm_writes_the_trajectory(tmp_path):
    out = tmp_path / "ct"
    proc = run_cli("simulate", "--preset", "paper", "--algorithm", "ct-admm", "--ct-stop-time", "2s", "--out", str(out))
    assert proc.returncode == 0, proc.stderr
    result = json.loads((out / "result.json").read_text())
    assert result["algorithm"] == "ct-admm" and result["rounds"] == 200  # 2 s of 10 ms periods
    assert (out / "trajectory.png").stat().st_size > 0


@pytest.mark.parametrize(
    "args,needle",
    [(["--ct-period", "10.5ms"], "whole number of steps"), (["--ct-step", "fast"], "--ct-step"), (["--ct-stop-time", "-1s"], "--ct-stop-time")],
)
def test_ct_admm_bad_flags(tmp_path, args, needle):
    proc = run_cli("simulate", "--preset", "paper", "--algorithm", "ct-admm", "--out", str(tmp_path / "o"), *args)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert needle in proc.stderr.strip().splitlines()[-1]


def test_gridstudy_says_the_shifted_grid_is_infeasible(tmp_path):
    proc = run_cli("gridstudy", "--out", str(tmp_path / "g"), "--ct-stop-time", "1s")
    assert proc.returncode == 0, proc.stderr
    assert "INFEASIBLE" in proc.stdout and "feasible" in proc.stdout
    assert (tmp_path / "g" / "grid_study.png").stat().st_size > 0
