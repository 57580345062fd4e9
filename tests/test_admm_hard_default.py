"""Plain admm on a complete graph with a hard margin runs the exact end-game (agents/soft_endgame.py with
``hard_endgame``: B empty, C = inf) by default since branch hardon (agents/spec.py, `endgame_default`): the
paper preset ends certified at the exact central optimum, earlier than the certified guard's stop, with the
bits of the end-game asked for explicitly. A fleet file that names ``certify`` (``--certify``), sets
``hard_endgame`` or ``soft_polish`` false, or asks for ``polish`` keeps its choice; sparse fleets are
unchanged. Round counts are not pinned (they depend on the CPU's BLAS kernels): the stop is checked against
the exact QP and against the guard's run on the same machine."""

from __future__ import annotations

from agents.admm import ADMMParams
from agents.certificate import PAYLOAD
from agents.soft_endgame import payload_size
from agents.spec import build_core

from .conftest import make_run, run_to_end
from .test_admm_soft_default import _run  # (the fleet run to its end, with its error against the exact QP)


def test_paper_preset_hard_ends_certified_exact_and_earlier_than_the_certified_guard():
    spec, cores, error = _run()
    params = spec.algorithm_params
    assert spec.C is None and "soft_polish" not in spec.params and "certify" not in spec.params
    assert params.soft_polish and params.hard_endgame  # the end-game, without asking
    d = spec.basis.size + 1
    assert spec.dim == 2 * d + payload_size(d) == len(cores[0].outgoing().values)
    assert all(c.converged for c in cores)
    assert all(c._polish.result is not None for c in cores)  # every robot certified its own rows
    assert all(c.values.tobytes() == cores[0].values.tobytes() for c in cores)
    assert error < 1e-9  # the exact optimum (the guard's stop is a tolerance away: ~1e-5 here)
    guarded_spec, guarded, guarded_error = _run(certify=10.0)  # as `--certify 10`: the guard asked for
    assert not guarded_spec.algorithm_params.soft_polish and guarded_spec.algorithm_params.certify == 10.0
    assert guarded_spec.dim == 2 * d + PAYLOAD  # the guard's frames, as before hardon
    assert all(c.converged and c._polish is None for c in guarded)
    assert cores[0].round < guarded[0].round and error < guarded_error


def test_the_default_is_the_endgame_asked_for_bit_for_bit():
    """Silent and explicit (`soft_polish` and `hard_endgame` true in the fleet file): the same rounds and bits."""
    _spec, silent, _error = _run()
    _world, spec, _central = make_run()
    spec.params.update({"soft_polish": True, "hard_endgame": True})
    explicit = [build_core(spec, i) for i in spec.robot_ids]
    run_to_end(explicit)
    assert all(a.round == b.round and a.values.tobytes() == b.values.tobytes() for a, b in zip(silent, explicit))


def test_a_fleet_file_asking_for_the_guard_the_rule_or_the_polish_keeps_it():
    for key, value in (("certify", 10.0), ("certify", 0.0), ("hard_endgame", False), ("soft_polish", False)):
        _w, spec, _c = make_run()
        spec.params[key] = value
        params = spec.algorithm_params
        assert not params.soft_polish and not params.hard_endgame, (key, value)
        assert params.certify == spec.params.get("certify", ADMMParams().certify), (key, value)
    _w, polished, _c = make_run(polish=True)  # `--polish`: its own end-game, no clash with the default
    assert polished.algorithm_params.polish and not polished.algorithm_params.soft_polish


def test_sparse_fleets_are_unchanged():
    """The complete-graph default does not touch a sparse fleet's params: the relay hub (a ring) reads them as
    written (its own paused end-game is agents/relay_hub.py's, tests/test_relay_endgame.py)."""
    for C in (None, 10.0):
        _w, ring, _c = make_run(C=C, robots=4, topology="ring")
        assert not ring._hub_form(ring.algorithm_params)
        assert ring.algorithm_params == ADMMParams.from_params(ring.params), C
