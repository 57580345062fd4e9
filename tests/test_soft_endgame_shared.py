"""The exact end-game's shared fold (agents/soft_endgame.py `_SHARED_FOLDS`): what every copy computes alike
-- the sums, the grown Krylov span, the Galerkin solve -- is computed once per process and adopted by the
process's other robots, with its exactly rounded sums batched side by side. Neither may move a bit: checked
against the fold as it was before (a copy of it here, one `_dots` call per sum, every copy on its own) robot by
robot and round by round, with the sharing on and off, beside the hub and in the relay hub's paused end-game;
and the cache stays bounded."""

from __future__ import annotations

import math

import numpy as np
import pytest

import agents.soft_endgame as se
from agents.admm import _dots, _pairwise_sum, _spd_factor, _spd_solve
from agents.spec import build_core

from .conftest import make_run, step_all


class _BeforeSharing(se.SoftEndgame):
    """The fold before the sharing (main c709aaf): every copy computes every sum itself, one call each."""

    grows = 0  # folds that grew the span (`_grow_before` calls)

    def _fold(self, payloads, v_own):
        if self.kind == "wait" or not np.all(np.isfinite(payloads)):
            self.guess(v_own)
            return None
        d = self.dim
        sums = _pairwise_sum(np.ascontiguousarray(payloads))
        at = se._scalars(self.block)
        images = [sums[at + j * d : at + (j + 1) * d] for j in range(self.sent)]
        if self.kind == "start":
            self.g = sums[-d:].copy()
            self.v = np.append(self.g[:-1], 0.0)
            ur = [float(sums[3 + j]) - float(_dots(s[:-1], self.g[:-1])) for j, s in enumerate(images)]
            first = True
        else:
            if bool(np.all(payloads[:, 0] == 1.0)):
                self.result = self.v.copy()
                self._next(np.zeros(se.payload_size(d, self.block)), "done")
                return self.result
            residual = float(payloads[:, 2].max())
            self.refined = self.refined + 1 if self.sent == 0 else 0
            if residual <= se.EQ or self.solve_rounds >= se.SOLVE_ROUNDS or self.refined > se.REFINE:
                self._correct(payloads, v_own)
                return None
            self.Pr = sums[-d:][: self.S.shape[1]].copy()
            ur = [float(sums[3 + j]) for j in range(self.sent)]
            first = False
        added = self._grow_before(images, ur)
        if added is None:
            self.guess(v_own)
            return None
        self._verdict(added, first)
        return None

    def _grow_before(self, images, ur):
        self.grows += 1
        added = []
        for j, s in enumerate(images):
            s, u, r = s.copy(), self.U[:, j].copy(), ur[j]
            norm0 = math.sqrt(float(_dots(s[:-1], s[:-1])))
            for _ in range(2):
                if self.S.shape[1]:
                    c = _dots(self.S[:-1].T, s[:-1])
                    s = s - _dots(self.S, c)
                    u = u - self.P @ c
                    r = r - float(_dots(self.Pr, c))
            norm = math.sqrt(float(_dots(s[:-1], s[:-1])))
            if not norm > se.DROP * norm0:
                continue
            self.S = np.column_stack([self.S, s / norm])
            self.P = np.column_stack([self.P, u / norm])
            self.Pr = np.append(self.Pr, r / norm)
            self.y = np.append(self.y, 0.0)
            added.append(self.S[:, -1])
        if self.S.shape[1] == 0:
            return None
        Sx, h = self.S[:-1], self.S[-1]
        try:
            factor = _spd_factor(_dots(Sx.T[:, None, :], Sx.T[None, :, :]))
        except np.linalg.LinAlgError:
            return None
        z1, z2 = _spd_solve(factor, self.Pr), _spd_solve(factor, h)
        hz2 = float(_dots(h, z2))
        if not abs(hz2) > 0:
            return None
        rho = -self.g[-1] - float(_dots(h, self.y))
        dmu = (float(_dots(h, z1)) - rho) / hz2
        self.y = self.y + (z1 - dmu * z2)
        self.mu = self.mu + dmu
        self.v = np.append(self.g[:-1] + _dots(Sx, self.y), self.mu)
        return added


def _endgame(core) -> se.SoftEndgame:
    """A robot's end-game: beside the hub (complete graphs) or the relay hub's paused one (sparse graphs)."""
    return getattr(core, "_polish", None) or core._endgame


def _twinned_fleet(**kwargs):
    """A fleet (the end-game on by default) whose every robot's end-game is shadowed by a twin running the
    fold before the sharing on the same payloads; returns (cores, twins, calls of `_common`)."""
    _world, spec, _central = make_run(**kwargs)
    cores = [build_core(spec, i) for i in spec.robot_ids]
    twins, calls = [], []
    for core in cores:
        pol = _endgame(core)
        assert isinstance(pol, se.SoftEndgame) and pol.kind != "off"
        twin = _BeforeSharing(pol.qp, pol.ids, pol.me, pol.C, block=pol.block, wide_start=pol.wide_start)
        twin.load(pol.state())
        twins.append(twin)
        step, common, guess, inside = pol.step, pol._common, pol.guess, [False]

        def shadowed(payloads, v_own, twin=twin, step=step, inside=inside):
            twin.step(payloads, v_own)
            inside[0] = True
            try:
                return step(payloads, v_own)
            finally:
                inside[0] = False

        def guessed(*args, twin=twin, guess=guess, inside=inside):
            if not inside[0]:  # the relay hub begins its attempts itself (a step's own guesses: the twin's step)
                twin.guess(*args)
            return guess(*args)

        def counted(*args, common=common):
            calls.append(1)
            return common(*args)

        pol.step, pol._common, pol.guess = shadowed, counted, guessed
    return cores, twins, calls


def _run_against_twins(cores, twins) -> None:
    """Lock-step rounds to the end; every round, each robot's end-game payload and solution are its twin's bits."""
    for _ in range(2000):
        if all(c.finished for c in cores):
            break
        step_all(cores)
        for core, twin in zip(cores, twins):
            pol = _endgame(core)
            assert pol.kind == twin.kind and pol.payload.tobytes() == twin.payload.tobytes(), (core.round, pol.me)
            assert pol.v.tobytes() == twin.v.tobytes() and pol.P.tobytes() == twin.P.tobytes()
        assert len(se._SHARED_FOLDS) <= se.SHARED_FOLDS_KEPT
    assert all(c.finished and c.converged for c in cores)
    assert _endgame(cores[0]).result is not None and twins[0].result is not None  # the end-game ended the run
    assert all(c.values.tobytes() == twins[0].result.tobytes() for c in cores)


@pytest.mark.parametrize("fleet", [{"topology": "complete"}, {"topology": "complete", "C": 10.0}, {"topology": "ring"}],
                         ids=["hard", "soft", "relay-ring"])
@pytest.mark.parametrize("kept", [se.SHARED_FOLDS_KEPT, 2, 0], ids=["shared", "kept-2", "unshared"])
def test_shared_fold_has_the_bits_of_every_copy_folding_alone(monkeypatch, fleet, kept):
    monkeypatch.setattr(se, "SHARED_FOLDS_KEPT", kept)
    se._SHARED_FOLDS.clear()
    cores, twins, calls = _twinned_fleet(robots=4, **fleet)
    _run_against_twins(cores, twins)
    folds = twins[0].grows
    assert folds > 5 and all(t.grows == folds for t in twins)
    if kept:  # once per fold in the process, not once per robot
        assert len(calls) == folds
    else:
        assert len(calls) == len(cores) * folds
        assert not se._SHARED_FOLDS


def test_the_cache_stays_bounded_and_a_missing_fold_is_computed_again(monkeypatch):
    """Kept 1: a robot whose fold was pushed out by another fleet's computes it again, the same bits."""
    monkeypatch.setattr(se, "SHARED_FOLDS_KEPT", 1)
    se._SHARED_FOLDS.clear()
    a, a_twins, a_calls = _twinned_fleet(robots=3, topology="complete", C=10.0)
    b, b_twins, _ = _twinned_fleet(robots=3, topology="complete", C=10.0, seed=1)
    for _ in range(2000):  # the two fleets' robots advance interleaved: each evicts the other's folds
        if all(c.finished for c in a + b):
            break
        for fleet in (a, b):
            updates = [c.outgoing() for c in fleet]
            for c in fleet:
                for u in updates:
                    c.receive(u)
        for pair in zip(a, b):
            for c in pair:
                if not c.finished:
                    c.advance()
        assert len(se._SHARED_FOLDS) <= 1
        for core, twin in zip(a + b, a_twins + b_twins):
            assert core._polish.payload.tobytes() == twin.payload.tobytes()
    assert all(c.converged for c in a + b) and a[0]._polish.result is not None and b[0]._polish.result is not None
    # evicted before the next robot's turn while the other fleet runs: computed again, at most once per robot
    assert a_twins[0].grows < len(a_calls) <= len(a) * a_twins[0].grows
