"""The hub-form ADMM after a crash that the survivors notice in different rounds.

Every robot of a complete graph runs its own copy of the fleet's hub ADMM. If the dead robot's
last frames reached some survivors and not others, they drop it in different rounds and their
copies differ. The fix (agents/admm.py, _Hub._map): the plain map is built from every robot's
own w_l = h_l + u_l (sent beside v_l), so it is the same on every copy and keeps sum u = 0;
copies that differ take plain steps until they agree. These tests drive the cores directly,
in lock step, with the drop rounds chosen per survivor.
"""

from __future__ import annotations

import msgpack
import numpy as np
import pytest

from agents import admm
from agents.admm import ADMMParams, ConsensusADMM
from agents.autogrid import AdaptiveGridCore, AutoGridParams, holdout_units
from agents.certificate import PAYLOAD
from agents.problem import solve_central
from agents.spec import build_core, restore_core
from launcher.world import Options, build_world

from .conftest import make_run, max_function_error


def lockstep_round(cores: dict, k: int, dead: int, drop_at: dict[int, int], twin=None) -> None:
    """Round k: robot `dead` lives until round max(drop_at) - 1 but its round-k frame reaches
    survivor i only while k < drop_at[i]; i drops it in round drop_at[i]. A `twin` of robot
    min(drop_at) gets that robot's frames and drops."""
    survivors = sorted(drop_at)
    live = survivors + ([dead] if k < max(drop_at.values()) else [])
    ups = {i: cores[i].outgoing() for i in live}
    for i in live:
        for j, up in ups.items():
            if j != i and not (i != dead and j == dead and k >= drop_at[i]):
                cores[i].receive(up)
                if twin is not None and i == survivors[0]:
                    twin.receive(up)
    for i in survivors:
        if k == drop_at[i]:
            cores[i].drop_neighbour(dead)
            if twin is not None and i == survivors[0]:
                twin.drop_neighbour(dead)
    for i in live:
        if not cores[i].finished:
            cores[i].advance()
    if twin is not None and not twin.finished:
        twin.advance()


def staggered_crash(cores: dict, dead: int, drop_at: dict[int, int], limit: int = 5000) -> list:
    """Run `lockstep_round` until every survivor has finished; returns the survivors."""
    survivors = [cores[i] for i in sorted(drop_at)]
    for k in range(limit):
        if all(c.finished for c in survivors):
            return survivors
        lockstep_round(cores, k, dead, drop_at)
    raise AssertionError("the survivors did not finish")


def survivors_reference(world, spec, dead: int):
    survivors = [r for r in world.robots if r.id != dead]
    ref = solve_central(spec.basis, np.vstack([r.points for r in survivors]), np.concatenate([r.labels for r in survivors]))
    assert ref.certified
    return ref


@pytest.mark.parametrize(
    "robots,crash,offsets",
    [
        (3, 15, (0, 2)),
        (3, 40, (1, 0)),
        (4, 15, (0, 1, 1)),  # the integrator's repro (error 0.19 before the fix)
        (4, 15, (0, 1, 2)),
        (4, 60, (2, 0, 1)),
        (5, 8, (0, 1, 2, 2)),
        (5, 30, (1, 0, 2, 1)),
    ],
)
def test_survivors_dropping_in_different_rounds_end_on_their_exact_answer(robots, crash, offsets):
    world, spec, _ = make_run(robots=robots, topology="complete", tol=1e-6, max_rounds=5000)
    cores = {i: build_core(spec, i) for i in spec.robot_ids}
    dead = spec.robot_ids[-1]
    drop_at = {i: crash + o for i, o in zip(spec.robot_ids[:-1], offsets)}
    survivors = staggered_crash(cores, dead, drop_at)
    assert all(c._hub is not None for c in survivors)
    assert all(c.converged for c in survivors) and len({c.round for c in survivors}) == 1
    ref = survivors_reference(world, spec, dead)
    assert max_function_error(spec, ref, [c.result() for c in survivors]) < spec.params["tol"]
    # after the resynchronisation the copies are bit-identical again
    hubs = [c._hub for c in survivors]
    assert all(h.s.tobytes() == hubs[0].s.tobytes() for h in hubs[1:])


def test_without_shared_w_the_same_crash_agrees_on_a_wrong_answer():
    """The control: each copy computing every w from its own state (the old map) converges and
    agrees -- far from the survivors' answer. This is the bug the shared map removes."""
    world, spec, _ = make_run(robots=4, topology="complete", max_rounds=5000)
    params = ADMMParams(**spec.params)
    cores = {
        i: ConsensusADMM(spec.share(i), params, hub_frames=False)
        for i in spec.robots
    }
    survivors = staggered_crash(cores, 3, {0: 15, 1: 16, 2: 16})
    assert all(c.converged for c in survivors)
    ref = survivors_reference(world, spec, 3)
    assert max_function_error(spec, ref, [c.result() for c in survivors]) > 1e-2


def test_shared_map_is_the_old_map_bit_for_bit_while_copies_agree(monkeypatch):
    """No drop: the frames' w change nothing -- every round's values are the same bits as the
    map computed on each copy (so rounds and results of existing runs are unchanged). (piqp's steps
    on both sides: the guard's warm QP, which only the layout with w has room for, moves the last bits.)"""
    monkeypatch.setattr(admm, "WARM_QP", False)
    _, spec, _ = make_run(robots=3, topology="complete")
    params = ADMMParams(**spec.params)

    def fleet(hub_frames: bool) -> list[ConsensusADMM]:
        return [
            ConsensusADMM(spec.share(i), params, hub_frames=hub_frames)
            for i in spec.robots
        ]

    new, old = fleet(True), fleet(False)
    # ([v; w] and the certified guard's payload, agents/certificate.py)
    assert new[0].outgoing().values.size == 2 * new[0].dim + PAYLOAD and old[0].outgoing().values.size == new[0].dim
    for _ in range(1000):
        if all(c.finished for c in new):
            break
        for cores in (new, old):
            ups = [c.outgoing() for c in cores]
            for c in cores:
                for u in ups:
                    if u.sender != c.robot_id:
                        c.receive(u)
            for c in cores:
                c.advance()
        for a, b in zip(new, old):
            assert a.values.tobytes() == b.values.tobytes() and a.finished == b.finished
            assert not a._hub.desynced
    assert all(c.finished and c.converged for c in new + old)


def test_checkpoint_in_the_desynchronised_window_resumes_bit_for_bit():
    """A robot checkpointed while the copies differ (w, previous w and the desync flag saved)
    resumes exactly: its twin's frames equal the original's to the end."""
    _, spec, _ = make_run(robots=4, topology="complete", tol=1e-6, max_rounds=5000)
    cores = {i: build_core(spec, i) for i in spec.robot_ids}
    drop_at = {0: 15, 1: 16, 2: 17}
    for k in range(17):
        lockstep_round(cores, k, 3, drop_at)
    assert cores[0]._hub.desynced  # robot 1 and 2's copies still differ from robot 0's here
    saved = msgpack.unpackb(msgpack.packb(cores[0].checkpoint()), strict_map_key=False)
    twin = restore_core(spec, 0, saved)
    for k in range(17, 5000):
        assert twin.outgoing() == cores[0].outgoing()
        if cores[0].finished:
            break
        lockstep_round(cores, k, 3, drop_at, twin=twin)
    assert twin.finished and twin.converged and twin.values.tobytes() == cores[0].values.tobytes()


def _autogrid_fleet_into(phase: str, **params_kw):
    """A 4-robot complete autogrid fleet (star, 15 points each) run in lockstep until robot 0 is 10
    rounds into `phase`; returns (world, spec, params, cores, next round)."""
    world, spec = build_world(Options(model="svm", fleet_id="t", shape="star", points=15, robots=4))
    params = AutoGridParams(model="svm", diameter=spec.params["diameter"], tol=1e-3, max_points=60, max_refinements=0, **params_kw)
    cores = {
        i: AdaptiveGridCore(spec.share(i, points=True), params)
        for i in spec.robots
    }
    never = {i: 10**9 for i in (0, 1, 2)}
    k = 0
    while not (cores[0].phase == phase and k >= cores[0]._phase_start + 10):
        lockstep_round(cores, k, 3, never)
        k += 1
    return world, spec, params, cores, k


def _autogrid_crash_in_sweep(hub_frames: bool, divisors=(8.0, 12.0), folds: int = 1):
    """A 4-robot complete autogrid fleet; robot 3 dies 10 rounds into the sigma sweep and the
    survivors drop it in rounds r, r + 1, r + 2. Runs until robot 0 leaves the sweep; returns
    (world, params, its sweep tasks)."""
    world, spec, params, cores, k = _autogrid_fleet_into(
        "validate", validate_divisors=divisors, validate_folds=folds, hub_frames=hub_frames)
    drop_at = {0: k, 1: k + 1, 2: k + 2}
    for k in range(k, k + params.validate_rounds + 10):
        lockstep_round(cores, k, 3, drop_at)
        if cores[0].phase != "validate":
            assert all(3 in cores[i].dropped for i in drop_at)
            return world, params, list(cores[0]._sweep.tasks)
    raise AssertionError("the sweep did not end")


def sweep_errors(world, params, tasks) -> list[tuple[bool, float]]:
    """(stopped by its rule, function error vs the exact solve of the survivors' training data)
    per sweep task. A drop reweighs the members' x_weight to 1 / (robots left), so they solve the
    soft margin at soft_C itself (before: x_weight stayed 1 / N, N = 4 at the start, and they solved
    it at C x N / (N - 1))."""
    from agents.autogrid_sweep import held_mask

    data = [r for r in world.robots if r.id != 3]
    out = []
    for t in tasks:
        held = [held_mask(holdout_units(r.points, r.labels), t.fold, params) for r in data]
        pts = np.vstack([r.points[~h] for r, h in zip(data, held)])
        lab = np.concatenate([r.labels[~h] for r, h in zip(data, held)])
        ref = solve_central(t.basis, pts, lab, C=params.soft_C)
        assert ref.solved
        v = t.sub.values
        out.append((t.sub.converged, t.basis.function_error(t.basis.c_from_x(v[:-1]), v[-1], ref.c, ref.gamma)))
    return out


def test_autogrid_crash_during_the_sigma_sweep_ends_on_the_survivors_answer():
    """Every sweep task (a hub sub-machine) that stopped by its rule ends within validate_tol of
    the exact soft-margin solve of the survivors' training data."""
    world, params, tasks = _autogrid_crash_in_sweep(True)
    errors = sweep_errors(world, params, tasks)
    assert sum(stopped for stopped, _ in errors) >= 2
    assert all(e < params.validate_tol for stopped, e in errors if stopped), errors


def test_autogrid_crash_during_its_admm_phase_ends_on_the_survivors_answer():
    """The ADMM phase's hub sub-machine (w at [max_points:] of the frame): survivors dropping in
    r, r + 1, r + 2 agree on the exact hard-margin answer of their data on the agreed grid."""
    from agents.kernel import GridBasis

    world, spec, params, cores, k = _autogrid_fleet_into("admm", sigma=0.8, hub_frames=True)
    assert cores[0]._sub._hub is not None and cores[0]._sub.frame_dim == 2 * cores[0]._sub.dim
    survivors = staggered_crash(cores, 3, {0: k, 1: k + 1, 2: k + 2})
    first = survivors[0]
    assert all(c.converged and c.margin == "hard" for c in survivors)
    grid, c, gamma = first.function()
    assert all(np.array_equal(s.function()[1], c) for s in survivors)
    basis = GridBasis(grid, first.sigma)
    data = [r for r in world.robots if r.id != 3]
    ref = solve_central(basis, np.vstack([r.points for r in data]), np.concatenate([r.labels for r in data]))
    assert ref.certified
    assert basis.function_error(c, gamma, ref.c, ref.gamma) < params.tol
