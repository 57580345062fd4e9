"""Every shapefleet process computes with one BLAS thread unless the user says otherwise (why: the
package __init__ files), and the setting takes effect: it must be in place before numpy loads
OpenBLAS, which a late import would silently miss."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

threadpoolctl = pytest.importorskip("threadpoolctl")


def _openblas_threads() -> list[int]:
    return [p["num_threads"] for p in threadpoolctl.threadpool_info() if p.get("internal_api") == "openblas"]


def test_this_test_process_runs_openblas_with_the_configured_thread_count():
    import numpy  # noqa: F401 - loads OpenBLAS if nothing has yet

    threads = _openblas_threads()
    assert threads, "numpy's OpenBLAS not found by threadpoolctl"
    assert set(threads) == {int(os.environ["OPENBLAS_NUM_THREADS"])}


def _threads_after(imports: str, exported: str | None = None, cwd: Path | None = None) -> str:
    """OpenBLAS's thread counts in a fresh interpreter after `imports` (Python statements), with
    OPENBLAS_NUM_THREADS exported as given (None: not set, the package's default applies)."""
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    if exported is not None:
        env["OPENBLAS_NUM_THREADS"] = exported
    code = (f"{imports}; import threadpoolctl; "
            "print(sorted({p['num_threads'] for p in threadpoolctl.threadpool_info() "
            "if p.get('internal_api') == 'openblas'}))")
    out = subprocess.run([sys.executable, "-c", code], env=env, cwd=cwd, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    return out.stdout.strip()


@pytest.mark.parametrize("module", ["agents.robot", "launcher.cli"])
def test_a_robot_process_and_the_cli_start_with_one_blas_thread(module):
    assert _threads_after(f"import {module}, numpy") == "[1]"


def test_the_autogrid_benchmark_runs_its_fleet_with_one_blas_thread():
    """benchmarks/autogrid.py runs the fleet in process: with numpy loaded before agents it had a
    thread per core, and its bits differed from simulate's (held-out 4's pliers: another outcome)."""
    root = Path(__file__).resolve().parents[1]
    assert _threads_after("import sys; sys.path.insert(0, 'benchmarks'); import autogrid", cwd=root) == "[1]"


@pytest.mark.parametrize("module", ["agents", "launcher.cli"])
def test_a_script_that_loaded_numpy_first_still_gets_one_blas_thread(module):
    """numpy first starts OpenBLAS with a thread per core, which the variable no longer changes: the
    package then limits the running pool (without it: [2] or more on a multi-core host)."""
    assert _threads_after(f"import numpy, {module}") == "[1]"


def test_a_thread_count_the_user_exported_wins_even_when_numpy_loaded_first():
    assert _threads_after("import numpy, agents", exported="2") == "[2]"
