"""Plain admm on a complete graph with a soft margin runs the soft end-game (agents/soft_endgame.py) by
default (agents/spec.py, `endgame_default`): the run ends at the certified exact soft optimum, earlier
than the ADMM's own stop, and a fleet file that names ``soft_polish`` keeps its choice. Hard margins run
the hard end-game by default since branch hardon (tests/test_admm_hard_default.py)."""

from __future__ import annotations

from agents.admm import hub_frame_dim
from agents.soft_endgame import payload_size
from agents.spec import build_core, restore_core

from .conftest import make_run, run_to_end, step_all


def _run(**kwargs):
    world, spec, central = make_run(**kwargs)
    cores = [build_core(spec, i) for i in spec.robot_ids]
    run_to_end(cores)
    b = spec.basis
    error = max(b.function_error(b.c_from_x(c.values[:-1]), c.values[-1], central.c, central.gamma) for c in cores)
    return spec, cores, error


def test_soft_margin_runs_the_endgame_by_default_and_ends_exact_and_earlier():
    spec, cores, error = _run(C=10.0)
    assert "soft_polish" not in spec.params and spec.algorithm_params.soft_polish
    d = spec.basis.size + 1
    assert spec.dim == 2 * d + payload_size(d) == len(cores[0].outgoing().values)
    assert all(c.converged for c in cores)
    assert cores[0]._polish.result is not None  # every robot certified its own rows
    assert all(c.values.tobytes() == cores[0].values.tobytes() for c in cores)
    assert error < 1e-6  # against the exact central QP (piqp's own accuracy: ~1e-9 here)


def test_a_fleet_file_naming_soft_polish_keeps_its_choice_and_stops_later():
    world, spec, central = make_run(C=10.0)
    spec.params["soft_polish"] = False  # as a fleet file written with the key
    assert not spec.algorithm_params.soft_polish
    d = spec.basis.size + 1
    assert spec.dim == hub_frame_dim(spec.algorithm_params, d) != 2 * d + payload_size(d)
    plain = [build_core(spec, i) for i in spec.robot_ids]
    run_to_end(plain)
    assert plain[0]._polish is None
    _spec, cores, _error = _run(C=10.0)
    assert cores[0].round < plain[0].round  # the end-game ends the run before the ADMM's own stop


def test_the_hard_polish_and_sparse_graphs_are_unchanged():
    _w, polished, _c = make_run(C=10.0)
    polished.params["polish"] = True  # a fleet file asking for the hard polish: no clash with the soft default
    assert polished.algorithm_params.polish and not polished.algorithm_params.soft_polish
    _w, ring, _c = make_run(C=10.0, robots=4, topology="ring")  # the relay hub: no end-game, the same frames
    default_dim = ring.dim
    ring.params["soft_polish"] = False
    assert not ring._hub_form(ring.algorithm_params) and ring.dim == default_dim


def test_a_restart_inside_the_endgame_resumes_bit_for_bit():
    """Every robot restored from its checkpoint in a round of a solve ends with the same rounds and bits."""
    spec, ref, _error = _run(C=10.0)
    cores = [build_core(spec, i) for i in spec.robot_ids]
    while cores[0]._polish.kind != "grow" or cores[0]._polish.attempts < 2:  # (the first attempt fails here)
        step_all(cores)
    resumed = [restore_core(spec, c.robot_id, c.checkpoint()) for c in cores]
    assert resumed[0]._polish.kind == "grow" and resumed[0]._polish.result is None
    run_to_end(resumed)
    assert resumed[0]._polish.result is not None
    assert all(a.round == b.round and a.values.tobytes() == b.values.tobytes() for a, b in zip(ref, resumed))
