"""Robots of one process share the hub's step (agents/admm.py, ConsensusADMM._shared_step): a copy
whose state history and inputs equal a step already taken adopts it instead of computing it.
The shared run must be the unshared run bit for bit, and a copy whose history differs (restored
from a checkpoint) must compute its own steps -- and still agree."""

from __future__ import annotations

import pytest

import agents.admm as admm
from agents.spec import build_core, restore_core

from .conftest import make_run
from .test_admm import step_all


@pytest.fixture()
def counted_steps(monkeypatch):
    """How many hub steps were computed (not adopted) so far."""
    counter = {"steps": 0}
    step = admm._Hub.step

    def counting(self, *args, **kwargs):
        counter["steps"] += 1
        return step(self, *args, **kwargs)

    monkeypatch.setattr(admm._Hub, "step", counting)
    admm._SHARED_STEPS.clear()  # steps of earlier tests (the same scenario) would be adopted
    yield counter
    admm._SHARED_STEPS.clear()


def _traces(spec, rounds, restore_at=None):
    """Every robot's iterates, and its hub copy's state at the end."""
    cores = [build_core(spec, i) for i in spec.robot_ids]
    for k in range(rounds):
        if k == restore_at:  # robot 1 resumes from its checkpoint: a copy with its own token
            cores[1] = restore_core(spec, 1, cores[1].checkpoint())
        step_all(cores)
    return [[c.trace[k].tobytes() for k in sorted(c.trace)] for c in cores], [c._hub.s.tobytes() for c in cores]


def test_shared_hub_steps_are_the_unshared_ones_bit_for_bit(counted_steps, monkeypatch):
    _, spec, _ = make_run(tol=1e-12)
    rounds = 40
    monkeypatch.setattr(admm, "SHARED_STEPS_KEPT", 0)
    alone, hubs = _traces(spec, rounds)
    assert counted_steps["steps"] == 3 * (rounds - 1)  # every copy computes (round 1 starts the hub)
    monkeypatch.setattr(admm, "SHARED_STEPS_KEPT", 64)
    counted_steps["steps"] = 0
    shared, shared_hubs = _traces(spec, rounds)
    assert counted_steps["steps"] == rounds - 1  # one copy computes, two adopt
    assert shared == alone and shared_hubs == hubs
    assert hubs[0] == hubs[1] == hubs[2] and len(alone[0]) == rounds + 1


@pytest.mark.parametrize("restore_at", [0, 15])  # 0: before the hub's first step (no state yet)
def test_a_restored_copy_computes_its_own_steps_and_agrees(counted_steps, restore_at):
    _, spec, _ = make_run(tol=1e-12)
    rounds = 40
    alone_steps = rounds - 1
    plain, plain_hubs = _traces(spec, rounds)
    counted_steps["steps"] = 0
    admm._SHARED_STEPS.clear()
    restored, hubs = _traces(spec, rounds, restore_at=restore_at)
    # the restored copy's token is its checkpoint's digest: it shares nothing after the restore
    assert counted_steps["steps"] == alone_steps + (rounds - max(restore_at, 1))  # round 0 -> 1 starts the hub
    assert hubs == plain_hubs and hubs[0] == hubs[1] == hubs[2]
    assert restored[1] == plain[1][restore_at:] and restored[0] == plain[0]


def test_messages_and_sync_test_are_the_python_float_products():
    """`_Hub.message` and `synced` multiply by relax and 1 - relax held as 0-d arrays: the same
    IEEE products as by the Python floats, bit for bit, also after the relax is set anew (a
    benchmark does so between rounds) -- random states, signed zeros, subnormals, huge values."""
    import numpy as np

    rng = np.random.default_rng(3)
    d, ids = 7, (0, 2, 5)
    hub = admm._Hub(ids, d, np.ones(d), admm.ADMMParams())
    for relax in (1.95, 1.0, 0.3, 1.999999, 1.95):
        hub.relax = relax
        for _ in range(40):
            hub.s = rng.normal(scale=10.0 ** rng.integers(-300, 300), size=d * (len(ids) + 1))
            vs = rng.normal(scale=10.0 ** rng.integers(-300, 300), size=(len(ids), d))
            vs[0, :2] = (-0.0, 5e-324)
            ws = []
            for k, (i, v) in enumerate(zip(ids, vs)):
                with np.errstate(all="ignore"):
                    want = (relax * v + (1.0 - relax) * hub.s[:d]) + hub.s[(k + 1) * d : (k + 2) * d]
                    got = hub.message(i, v)
                assert got.tobytes() == want.tobytes()
                ws.append(want)
            with np.errstate(all="ignore"):
                assert hub.synced(vs, np.array(ws))
                ws[1] = ws[1].copy()
                ws[1][3] = np.nextafter(ws[1][3], np.inf)
                assert not hub.synced(vs, np.array(ws))


def test_a_step_is_adopted_only_for_frames_equal_byte_for_byte():
    """shared_input_step (the hub's step, branch authhash) compares the frames instead of hashing
    them: the same key and the same frame bytes adopt; the same key with frames differing in one
    bit (a signed zero), or the same bytes in another shape, compute their own step."""
    import numpy as np
    from collections import OrderedDict

    cache: OrderedDict = OrderedDict()
    computed = []

    def step(label):
        return admm.shared_input_step(cache, b"k" * 20, frames[label], lambda: computed.append(label) or label, 64)

    base = np.arange(12.0).reshape(3, 4)
    flipped = base.copy()
    flipped[0, 0] = -0.0  # base[0, 0] is +0.0: equal as floats, not as bits
    frames = {"a": base, "a again": base.copy(), "signed zero": flipped, "reshaped": base.reshape(4, 3)}
    assert step("a") == ("a", False)
    assert step("a again") == ("a", True)
    assert step("signed zero") == ("signed zero", False)
    assert step("reshaped") == ("reshaped", False)
    assert computed == ["a", "signed zero", "reshaped"]
    assert step("signed zero") == ("signed zero", True) and admm.shared_input_step(
        cache, b"other key".ljust(20), base, lambda: "other", 64) == ("other", False)
