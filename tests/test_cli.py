"""The command line as a person meets it: outputs of a run, and bad input refused in one line."""

from __future__ import annotations

import json
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from agents.autogrid import AutoGridParams
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
    # --preset paper is the old default: the paper's fleet (admm, 5x3, sigma 1), iterate for iterate
    import numpy as np

    from launcher.simulate import simulate_fleet

    from .conftest import make_run

    _, spec, _ = make_run(data=str(out / "data.csv"))
    assert result["algorithm"] == "admm" and result["grid"] == spec.grid.tolist()
    want = simulate_fleet(spec).robots
    for r, w in zip(result["robots"], want, strict=True):
        assert r["rounds"] == w["rounds"] and r["c"] == spec.basis.c_from_x(np.asarray(w["x"])).tolist()


def test_central_writes_a_result(tmp_path):
    proc = run_cli("central", "--out", str(tmp_path / "c"), "--shape", "bean")
    assert proc.returncode == 0, proc.stderr
    result = json.loads((tmp_path / "c" / "result.json").read_text())
    assert result["central"]["status"] == "solved" and result["metrics"]["function_error"] == 0.0
    # the answer is checked against an independent solve of the same hard-margin QP (scipy's
    # trust-constr, not piqp): min |x|^2 / 2  s.t.  theta_i f(d_i) >= 1, with c = K_G^{+1/2} x
    import numpy as np
    from scipy.optimize import LinearConstraint, minimize

    from agents.kernel import GridBasis
    from launcher.scenario import load_data_csv

    robots = load_data_csv(tmp_path / "c" / "data.csv")
    pts = np.vstack([r.points for r in robots])
    theta = np.concatenate([r.labels for r in robots]).astype(float)
    basis = GridBasis(np.asarray(result["grid"]), result["sigma"])
    K = basis.kernel_to_grid(pts)
    A = theta[:, None] * np.column_stack([K @ basis.inv_sqrt, np.ones(len(pts))])
    m = basis.size
    sol = minimize(lambda v: 0.5 * v[:m] @ v[:m], np.zeros(m + 1), jac=lambda v: np.append(v[:m], 0.0),
                   hess=lambda v: np.diag(np.append(np.ones(m), 0.0)), constraints=[LinearConstraint(A, 1.0, np.inf)],
                   method="trust-constr", options={"gtol": 1e-12, "xtol": 1e-14, "maxiter": 5000})
    assert sol.success, sol.message
    c, gamma = np.asarray(result["central"]["c"]), result["central"]["gamma"]
    assert basis.function_error(c, gamma, basis.c_from_x(sol.x[:m]), sol.x[m]) < 1e-5
    margins = theta * basis.decision(pts, c, gamma)
    assert margins.min() > 1 - 1e-6  # every margin met


def test_default_out_folder_is_new_under_runs(tmp_path):
    proc = run_cli("central", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    (folder,) = (tmp_path / "runs").iterdir()
    assert (folder / "result.json").exists()
    # with no grid and sigma, central solves on the paper's and says so
    assert "paper's setting" in proc.stdout and "grid 5x3, sigma 1" in proc.stdout
    result = json.loads((folder / "result.json").read_text())
    assert result["sigma"] == 1.0 and len(result["grid"]) == 15 and result["algorithm"] == "central"


def _bad_flags() -> list[tuple[list[str], str]]:
    """The rows of data/bad_flags.txt: (flags as shell words, needle of the one-line error)."""
    fill = {"data": str(DATA), "tally_slots": str(AutoGridParams(max_points=4).tally_slots)}
    rows = []
    for line in (DATA / "bad_flags.txt").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            flags, needle = (part.strip().format(**fill) for part in line.split(" | ", 1))
            rows.append((shlex.split(flags), needle))
    return rows


BAD = _bad_flags()


# every row in process (test_bad_flags_exit_2_with_one_line); two through the installed command
@pytest.mark.parametrize("args,needle", [row for row in BAD if row[1] in ("--shape", "--delay")], ids=["--shape", "--delay"])
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
def test_bad_data_files(tmp_path, capsys, text, needle):
    path = tmp_path / "d.csv"
    path.write_text(text)
    with pytest.raises(SystemExit) as exc:
        main(["central", "--data", str(path), "--out", str(tmp_path / "o")])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert needle in err and "d.csv" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()  # a refused run leaves nothing behind


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


def test_a_fleet_that_only_ran_out_of_rounds_is_told_what_to_try(tmp_path):
    """admm stopped by its cap with nothing else wrong: exit 1 and one hint (--max-rounds, newton);
    a run that converges prints none."""
    proc = run_cli("simulate", "--preset", "paper", "--max-rounds", "30", "--out", str(tmp_path / "o"))
    assert proc.returncode == 1, proc.stderr
    assert "NOT converged" in proc.stderr and "Traceback" not in proc.stderr
    hints = [line for line in proc.stderr.splitlines() if line.startswith("shapefleet: hint:")]
    assert len(hints) == 1 and "cap of 30 rounds" in hints[0] and "--algorithm newton" in hints[0]
    proc = run_cli("simulate", "--preset", "paper", "--out", str(tmp_path / "ok"))
    assert proc.returncode == 0, proc.stderr
    assert "hint" not in proc.stderr


def test_ct_admm_writes_the_trajectory(tmp_path):
    out = tmp_path / "ct"
    proc = run_cli("simulate", "--preset", "paper", "--algorithm", "ct-admm", "--ct-stop-time", "2s", "--out", str(out))
    # 2 s of flow is not enough to agree within tol (issue 11: success means agreement): exit 1
    assert proc.returncode == 1, proc.stderr
    assert "NOT converged" in proc.stderr and "Traceback" not in proc.stderr
    result = json.loads((out / "result.json").read_text())
    assert result["algorithm"] == "ct-admm" and result["rounds"] == 200  # 2 s of 10 ms periods
    assert result["converged"] is False and result["agreement"]["disagreement"] > result["agreement"]["tol"]
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


# -- automatic grid and sigma (the default) and the paper's preset ------------------------------
SMALL_AUTO = ("--points", "15", "--max-grid-points", "60")  # 3 robots x 15 points, budget 60: a few seconds


def test_svm_simulate_chooses_grid_and_sigma_and_reaches_the_central_solve(tmp_path):
    """autogrid --model svm (the default model is lsq: tests/test_autogrid_lsq.py) with no grid and no sigma."""
    import numpy as np

    from agents.kernel import GridBasis
    from agents.problem import solve_central
    from launcher import scenario

    out = tmp_path / "auto"
    proc = run_cli("simulate", *SMALL_AUTO, "--model", "svm", "--out", str(out))
    assert proc.returncode == 0, proc.stderr
    result = json.loads((out / "result.json").read_text())
    assert result["algorithm"] == "autogrid" and result["converged"] and result["robots_agree"] is True
    assert result["margin"] == "hard" and result["C"] is None and result["message"] == ""
    assert result["sigma"] > 0 and "diag" in result["sigma_reason"] and len(result["sigma_validation"]) >= 1
    assert 4 <= len(result["grid"]) <= 60 and result["history"] == []
    history = result["grid_history"]
    assert history and all({"size", "level", "margin", "status", "grid"} <= h.keys() for h in history)
    assert all(len(h["grid"]) == h["size"] for h in history) and history[-1]["grid"] == result["grid"]
    # every robot holds the same grid, sigma and function, within 1e-3 of the central solve there
    robots = result["robots"]
    assert all(r["grid"] == result["grid"] and r["sigma"] == result["sigma"] for r in robots)
    points = scenario.load_data_csv(str(out / "data.csv"))
    pts = np.vstack([r.points for r in points])
    labels = np.concatenate([r.labels for r in points])
    basis = GridBasis(np.asarray(result["grid"]), result["sigma"])
    central = solve_central(basis, pts, labels)
    assert central.solved and result["central"]["c"] == central.c.tolist()
    for r in robots:
        assert basis.function_error(np.asarray(r["c"]), r["gamma"], central.c, central.gamma) < 1e-3
        assert r["function_error"] < 1e-3
    assert result["metrics"]["function_error"] < 1e-3 and result["metrics"]["train_accuracy"] == 1.0
    assert (out / "shapes.png").stat().st_size > 0 and (out / "convergence.png").stat().st_size > 0


def test_preset_paper_flags_override_it():
    """--preset paper = --grid 5x3 --sigma 1 --algorithm admm (its run: test_simulate_writes_the_run_folder)."""
    opts = _resolved("--preset", "paper")
    assert (opts.algorithm, opts.grid, opts.sigma, opts.grid_bounds) == ("admm", "5x3", 1.0, None)
    opts = _resolved("--preset", "paper", "--algorithm", "autogrid")
    assert (opts.algorithm, opts.grid, opts.sigma) == ("autogrid", "5x3", 1.0)
    opts = _resolved("--preset", "paper", "--grid", "4x4")
    assert (opts.algorithm, opts.grid, opts.sigma) == ("admm", "4x4", 1.0)


def _resolved(*argv: str):
    from launcher.cli import _options, parse_args
    from launcher.world import resolve_options

    return resolve_options(_options(parse_args(["simulate", *argv])))


def test_algorithm_resolution():
    assert _resolved().algorithm == "autogrid" and _resolved().grid is None and _resolved().sigma is None
    assert (_resolved("--grid", "5x3", "--sigma", "1").algorithm) == "admm"
    assert (_resolved("--sigma", "0.5").algorithm, _resolved("--sigma", "0.5").sigma) == ("autogrid", 0.5)
    for algo in ("admm", "ct-admm"):  # a fixed grid: the paper's unless given
        opts = _resolved("--algorithm", algo)
        assert (opts.algorithm, opts.grid, opts.sigma) == (algo, "5x3", 1.0)
    opts = _resolved("--algorithm", "admm", "--sigma", "0.7")
    assert (opts.grid, opts.sigma) == ("5x3", 0.7)


@pytest.mark.parametrize("args,needle", BAD, ids=[str(i) for i in range(len(BAD))])
def test_bad_flags_exit_2_with_one_line(tmp_path, capsys, args, needle):
    with pytest.raises(SystemExit) as exc:
        main(["simulate", "--out", str(tmp_path / "o"), *args])
    err = capsys.readouterr().err.strip().splitlines()
    assert exc.value.code == 2 and len(err) == 1 and needle in err[0], err


def test_fig5_coarse_start_grid_is_refined_until_it_separates_the_data(tmp_path):
    """The paper's Fig. 5 with the fleet's refinement: its 4x2 grid shifted by half a cell is
    infeasible; `--algorithm autogrid` keeps it as the start grid and adds points."""
    import numpy as np

    from launcher.gridstudy import _shifted_bounds
    from launcher.world import Options, build_world

    world, _ = build_world(Options(fleet_id="t", preset="paper"))
    bounds = _shifted_bounds(world.bounds, "4x2", (0.5, 0.0))
    out = tmp_path / "fig5"
    proc = run_cli("simulate", "--algorithm", "autogrid", "--grid", "4x2", f"--grid-bounds={bounds}", "--sigma", "1",
                   "--max-grid-points", "60", "--model", "svm", "--out", str(out))
    assert proc.returncode == 0, proc.stderr
    result = json.loads((out / "result.json").read_text())
    history = result["grid_history"]
    assert history[0]["size"] == 8 and history[0]["status"] == "hard-not-converged"
    assert len(result["grid"]) > 8 and result["grid"][:8] == history[0]["grid"]  # the start grid is kept
    assert result["sigma"] == 1.0 and result["sigma_validation"] == [] and result["margin"] == "hard"
    assert result["robots_agree"] and result["metrics"]["function_error"] < 1e-3
    assert result["metrics"]["train_accuracy"] == 1.0
    assert np.asarray(result["grid"]).shape == (len(result["grid"]), 2)
