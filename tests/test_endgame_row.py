"""Plain admm's result row says how the exact end-game ended (`endgame`, docs/result-schema.md), and the run's
summary line says it in a phrase: `certified` when the run ended on its certified optimum, `not certified` when
one ran but the ADMM's own rule stopped first, null when none ran."""

from __future__ import annotations

import pytest

import agents.soft_endgame as se
from agents.spec import build_core
from launcher.report import summary_table

from .conftest import make_run, run_to_end


def _rows(params: dict | None = None, **kwargs) -> list[dict]:
    _world, spec, _central = make_run(**kwargs)
    spec.params.update(params or {})  # (as a fleet file's params)
    cores = [build_core(spec, i, keep_trace=False) for i in spec.robot_ids]
    run_to_end(cores)
    assert all(c.converged for c in cores)
    return [c.result() for c in cores]


def _title(rows: list[dict]) -> str:
    metrics = dict.fromkeys(("function_error", "consensus_error", "train_accuracy", "iou"), None)
    result = {"algorithm": "admm", "converged": True, "rounds": rows[0]["rounds"], "wall_s": 0.5, "metrics": metrics,
              "robots": rows}
    return str(summary_table(result).title)


def test_a_run_ended_by_the_end_game_is_certified():
    rows = _rows(robots=4, topology="complete")  # a complete hard fleet: the end-game by default
    assert [r["endgame"] for r in rows] == ["certified"] * 4
    assert all(r["error_bound"] is None for r in rows)  # (exact itself: no bound reported)
    assert "on the certified exact optimum" in _title(rows)


def test_an_end_game_the_admm_outran_is_not_certified(monkeypatch):
    monkeypatch.setattr(se, "EQ", -1.0)  # no verdict can pass: the ADMM's own rule ends the run
    rows = _rows(robots=4, topology="complete")
    assert [r["endgame"] for r in rows] == ["not certified"] * 4
    assert "(exact end-game not certified)" in _title(rows) and "certified exact optimum" not in _title(rows)


def test_a_relay_fleet_ended_by_its_end_game_is_certified():
    rows = _rows(robots=4, topology="ring")  # the relay hub pauses its ADMM for the end-game (branch ringend)
    assert [r["endgame"] for r in rows] == ["certified"] * 4
    assert "on the certified exact optimum" in _title(rows)


@pytest.mark.parametrize("kwargs", [{"certify": 10.0}, {"robots": 4, "topology": "ring", "params": {"relay": False}}],
                         ids=["certify", "edge form"])
def test_no_end_game_no_word(kwargs):
    rows = _rows(**kwargs)
    assert all(r.get("endgame") is None for r in rows)
    assert "certified" not in _title(rows)
