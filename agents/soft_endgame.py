"""The soft margin's exact end-game on a complete graph (`ADMMParams.soft_polish`; docs/algorithm.md,
"The soft end-game").

A soft solve's multipliers sit at the box C on the points it gives up, and the ADMM spends thousands
of rounds on them (held-out 4's pliers 2713, the castellated nut > 3000: benchmarks/results/autogrid.md).
Its active sets settle much earlier. Beside the ADMM, every robot guesses them for its own rows from
its own step -- B (multiplier at C), E (on the margin), N (the rest) -- and the fleet solves the
reduced problem exactly:

    x = A_Ex' alpha + g_x,   A_E v = 1 (v = (x, gamma)),   t' alpha = -g_gamma   (t = A_E's gamma column)

with g = C sum_B a_i. Its dual is G alpha + t gamma = 1 - A_Ex g_x with G = A_Ex A_Ex', solved by a
block Krylov (Galerkin) method whose every round is one all-reduce of BLOCK + 1 function-space vectors
and a few scalars -- issue 10's frame rule: no point, no per-point row, no Gram sum leaves a robot:

* robot l holds the basis P_l (its own E rows of the fleet's Krylov vectors) and its multipliers
  alpha_l = P_l y; every copy holds S = A_E' P (the vectors' images, (M+1)-vectors), y and gamma;
* a round sends A_E,l' U_l for the new block U_l = diag(1/|a_i|^2) A_E,l,x s (s: last round's new
  images; the first block: the preconditioned 1 and t, then g's image), U_l' r_l and P_l' r_l (r_l
  = 1 - A_E,l v: its margins' residuals) and a verdict [ok, worst violation, residual] (`wide_start`, the
  relay fleets': the first block also holds the robot's step multipliers on its E rows, and more up to the
  block -- a step's block is never wider than the first, whatever BLOCK: `_start_block`);
* every copy orthogonalises the new images on the shared S (the G inner product of two Krylov
  vectors is the dot product of their images) and takes the exact Galerkin correction on the grown
  span from the shared Gram S_x' S_x (a Cholesky solve, exactly rounded: the same bits on every
  copy); the old columns' P' r makes it an iterative refinement too.

Each robot then checks its own rows: E multipliers in [0, C] and margins 1 within EQ, B margins
<= 1 + EQ, N margins >= 1 - EQ. All ok: every copy holds the certified optimum bit for bit and the
fleet stops, as with the hard polish (`agents.admm._Polish`). A solved but violated set moves the
fleet's single worst row (PDAS, one row a correction: all at once diverged in the replays); after CAP
corrections, a fresh guess. Pure: no I/O, no clock; the ADMM runs on meanwhile, so a failed attempt
costs bytes, not rounds.

What every copy computes alike in a round (the sums, the span's growth, the Galerkin solve: `_grow`) is
computed once per process and adopted by the process's other robots (`_SHARED_FOLDS`, keyed by a digest
of the copy's shared state and the round's payloads, as the hub's step); each robot then replays the
orthogonalisation's coefficients on its own P and judges its own rows. The same bits as every copy
folding alone (tests/test_soft_endgame_shared.py).

Hard margins (`ADMMParams.hard_endgame`, C = inf) are the same problem with B empty: the guess labels N
below GUESS x the robot's own largest step multiplier, and also every row its own step leaves off the
margin (|a_i' v - 1| > GUESS at the step's solution v: complementarity says such a multiplier is the
solver's residue -- on 8 robots one robot's step left all 20 rows 0.5-4 off the margin with multipliers
1e-5 x its largest, 33-42 E rows for 16 unknowns, and the end-game never certified); g = 0, and the
verdict has no upper bound (E multipliers >= 0; the worst violation compares raw multipliers with margin
violations). Autogrid's hard answer solves run it (docs/autogrid.md, "Hard answer solves end exactly too").
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

import numpy as np

from agents.admm import (
    POLISH_EQ, _digest, _dots, _Endgame, _pairwise_sum, _spd_factor, _spd_solve, shared_step,
)
from agents.rounds import from_bytes, to_bytes

#: Krylov vectors per round: the frame carries BLOCK + 1 vectors of M + 1 floats (the last: P' r); the
#: default, sized for the complete graphs' frames (the payload rides beside the ADMM); `SoftEndgame(block=...)`
#: takes another, which pays only with a start block as wide (`wide_start`; agents/relay_hub.py RELAY_ENDGAME_BLOCK)
BLOCK = 3
#: single-row corrections per attempt before a fresh guess (replays: 2-8 needed, 8 reached 212 / 739)
CAP = 8
#: rounds one solve may take before its set is judged as it stands (solves took 10-13 rounds)
SOLVE_ROUNDS = 40
#: rounds of iterative refinement alone once the span is exhausted (castellated: 1 took 4e-9 to 2e-13)
REFINE = 3
#: a robot's verdict: E margins equal 1, B margins at most 1, N margins at least 1, within EQ (the hard polish's)
EQ = POLISH_EQ
#: the guess from a robot's own step multipliers: at the bound when >= (1 - GUESS) C, off when <= GUESS C
#: (hard: off when <= GUESS x its largest, or when its margin at the step is off 1 by more than GUESS)
GUESS = 1e-6
#: a new Krylov vector is dropped when orthogonalisation leaves less than DROP of its image's norm
DROP = 1e-8
#: row labels
N_ROW, E_ROW, B_ROW = 0, 1, 2


def _scalars(block: int) -> int:
    """ok, worst violation, residual; then U' r (or 1' U in a start round) per block vector."""
    return 3 + block


def payload_size(dim: int, block: int = BLOCK) -> int:
    """Floats of the end-game's part of a hub frame: the verdict and residual, `block` scalars, `block`
    images A_E' u and one vector P' r (in a start round: g_l)."""
    return _scalars(block) + (block + 1) * dim


@dataclass(frozen=True)
class _Fold:
    """The part of an end-game round every copy computes alike (`SoftEndgame._common`): the shared state
    after it (S, P' r, y, gamma, v, g, the Gram S_x' S_x; arrays read-only: the process's copies hold the
    same objects), whether the Galerkin solve went through (`solved`; not: the set is singular, a fresh
    guess), per new image the orthogonalisation's coefficients and its norm (None: dropped), from
    which each copy grows its own P, and the images added (each the last column of S as it was appended:
    the copies' products with it are then the same BLAS calls on the same layout as before the sharing)."""

    S: np.ndarray
    Pr: np.ndarray
    y: np.ndarray
    mu: float
    v: np.ndarray
    g: np.ndarray
    gram: np.ndarray | None
    steps: tuple[tuple[tuple[np.ndarray, ...], float | None], ...]
    added: tuple[np.ndarray, ...]
    solved: bool


#: end-game rounds' shared parts taken lately in this process (`SoftEndgame._fold`), by the digest of the
#: copy's shared state and the round's payloads: computed once per process and adopted by its other
#: robots, as the hub's step (agents/admm.py `_SHARED_STEPS`); a part no longer here is computed again.
#: SHARED_FOLDS_KEPT = 0 turns the sharing off (the same bits: tests/test_soft_endgame_shared.py).
_SHARED_FOLDS: OrderedDict[bytes, _Fold] = OrderedDict()
SHARED_FOLDS_KEPT = 64


def _frozen(a: np.ndarray) -> np.ndarray:
    a.flags.writeable = False
    return a


def _grow(S: np.ndarray, Pr: np.ndarray, y: np.ndarray, mu: float, v: np.ndarray, g: np.ndarray,
          gram: np.ndarray | None, images: list[np.ndarray], ur: list[float]) -> _Fold:
    """Orthogonalise the new images on S (twice), append them, and take the Galerkin correction on the
    grown span (module docstring). Pure; the exactly rounded sums of one step run side by side in one
    `_dots` call where they share a length (each column's sum depends on that column alone: the bits of
    one call per sum), and the Gram grows by the new columns' entries only (an entry is the sum of its
    two columns' products, whatever else is computed beside it). v: the solution before (kept when the
    solve does not go through)."""
    d = len(g)
    k_old = S.shape[1]
    steps: list[tuple[tuple[np.ndarray, ...], float | None]] = []
    added = []
    for j, s in enumerate(images):
        s, r, coefs = s.copy(), ur[j], []
        k = S.shape[1]
        if k:  # the first coefficients and |s|^2 in one sum: rows S_x' and s_x against s_x
            both = _dots(np.vstack([S[:-1].T, s[None, :-1]]), s[:-1])
            c, norm0 = both[:k].copy(), math.sqrt(float(both[k]))
            with_pr = np.vstack([S, Pr[None, :]])  # S c and (P' r)' c in one sum
            for step in range(2):
                if step:
                    c = _dots(S[:-1].T, s[:-1])
                sc = _dots(with_pr, c)
                s = s - sc[:d]
                r = r - float(sc[d])
                coefs.append(c)
        else:
            norm0 = math.sqrt(float(_dots(s[:-1], s[:-1])))
        norm = math.sqrt(float(_dots(s[:-1], s[:-1])))
        if not norm > DROP * norm0:
            steps.append((tuple(coefs), None))
            continue
        S = np.column_stack([S, s / norm])
        added.append(_frozen(S)[:, -1])
        Pr = np.append(Pr, r / norm)
        y = np.append(y, 0.0)
        steps.append((tuple(coefs), norm))
    k = S.shape[1]
    fold = {"S": _frozen(S), "Pr": _frozen(Pr), "steps": tuple(steps), "added": tuple(added), "g": _frozen(g)}

    def failed() -> _Fold:
        return _Fold(y=_frozen(y), mu=mu, v=_frozen(v), gram=None, solved=False, **fold)

    if k == 0:
        return failed()
    Sx, h = S[:-1], S[-1]
    if gram is None or gram.shape[0] != k_old:  # (after a checkpoint: from S anew)
        gram = _dots(Sx.T[:k_old, None, :], Sx.T[None, :k_old, :]) if k_old else np.zeros((0, 0))
    if k > k_old:  # the new columns' entries against every column (the symmetric ones are the same products)
        new = _dots(Sx.T[k_old:, None, :], Sx.T[None, :, :])
        gram = np.block([[gram, new[:, :k_old].T], [new]])
    try:
        factor = _spd_factor(gram)
    except np.linalg.LinAlgError:
        return failed()
    z1, z2 = _spd_solve(factor, Pr), _spd_solve(factor, h)
    hz = _dots(np.array([z2, z1, y]), h)  # h' z2, h' z1, h' y
    hz2 = float(hz[0])
    if not abs(hz2) > 0:
        return failed()
    rho = -g[-1] - float(hz[2])  # t' alpha + g_gamma must vanish
    dmu = (float(hz[1]) - rho) / hz2
    y = y + (z1 - dmu * z2)
    mu = mu + dmu
    v = np.append(g[:-1] + _dots(Sx, y), mu)
    return _Fold(y=_frozen(y), mu=mu, v=_frozen(v), gram=_frozen(gram), solved=True, **fold)


class SoftEndgame(_Endgame):
    """One robot's part of the soft end-game (module docstring). Drive it with `step` once a hub
    round, after the robot's own step (`qp.multipliers` are that step's); `payload` goes into its
    next frame."""

    def __init__(self, qp: Any, ids: tuple[int, ...], me: int, C: float, block: int = BLOCK,
                 wide_start: bool = False) -> None:
        if block < 2:  # a start round sends two vectors (the preconditioned 1 and t)
            raise ValueError(f"the end-game's block must be at least 2, not {block}")
        self.qp = qp
        self.block = block
        # wide_start: the start block fills the whole block (`_start_block`); off, it is the preconditioned 1
        # and t alone, and the block never grows past them (each step's new vectors are the images of the
        # last step's: at most 2 a step on hard margins, 3 on soft ones, whatever the block)
        self.wide_start = wide_start
        self.narrow = False  # this attempt's solves start narrow: a wide one ended off the answer (`_correct`)
        self.rows = qp._rows
        self.ids = ids
        self.me = me
        self.C = float(C)
        self.hard = math.isinf(self.C)  # a hard margin (C = inf): B stays empty, E multipliers only >= 0
        self.dim = self.rows.shape[1]
        self.labels = np.zeros(len(self.rows), dtype=np.int8)
        self.kind = "wait"  # wait (no multipliers yet), start, grow, done, off
        self.payload = np.zeros(payload_size(self.dim, self.block))
        self.prev_payload: np.ndarray | None = np.zeros(payload_size(self.dim, self.block))
        self.result: np.ndarray | None = None
        self.attempts = 0
        self.corrections = 0
        self._reset_solve()

    # -- an attempt and its solves ---------------------------------------------------------------
    def _reset_solve(self) -> None:
        d = self.dim
        n_e = int(np.count_nonzero(self.labels == E_ROW))
        self.S = np.zeros((d, 0))  # shared: the Krylov vectors' images A_E' P, one column each
        self.P = np.zeros((n_e, 0))  # own: those vectors on this robot's E rows
        self.Pr = np.zeros(0)  # shared: P' r at the current solution (r: the E margins' residuals)
        self.y = np.zeros(0)
        self._gram: np.ndarray | None = None  # shared: S_x' S_x, kept to grow it (None: from S anew)
        self.mu = 0.0  # the offset gamma of the current solution
        self.g = np.zeros(d)
        self.v = np.zeros(d)
        self.U = np.zeros((n_e, 0))  # own: the block sent this round (a column each)
        self.sent = 0  # block vectors in the frame sent this round
        self.solve_rounds = 0
        self.refined = 0  # rounds of refinement alone (the span exhausted: no block sent)
        self.move: tuple[int, int] | None = None  # this robot's worst row and its new label

    def _size(self) -> int:
        return payload_size(self.dim, self.block)

    def guess(self, v_own: np.ndarray | None = None) -> None:
        """A fresh attempt from this robot's own step multipliers and (hard) the step's solution v_own
        (none yet: wait)."""
        lam = self.qp.multipliers
        if lam is None or len(lam) != len(self.rows):
            self._next(np.zeros(payload_size(self.dim, self.block)), "wait")
            return
        labels = np.full(len(self.rows), E_ROW, dtype=np.int8)
        if self.hard:  # no bound: N below GUESS x its own largest multiplier
            labels[lam <= GUESS * max(float(lam.max(initial=0.0)), 0.0)] = N_ROW
            if v_own is not None:  # and off the margin at its own step: complementarity fails, residue
                labels[np.abs(self.rows @ v_own - 1.0) > GUESS] = N_ROW
        else:
            labels[lam >= (1.0 - GUESS) * self.C] = B_ROW
            labels[lam <= GUESS * self.C] = N_ROW
        self.labels = labels
        self.attempts += 1
        self.corrections = 0
        self.narrow = False
        self._start()

    def _own_e(self) -> tuple[np.ndarray, np.ndarray]:
        """This robot's E rows and their Jacobi weights 1 / |a_i,x|^2."""
        A = self.rows[self.labels == E_ROW]
        return A, 1.0 / np.maximum(np.einsum("ij,ij->i", A[:, :-1], A[:, :-1]), 1e-300)

    def _start(self) -> None:
        """A start round: g_l = C sum of its B rows, and the first block: the preconditioned 1 and t."""
        self._reset_solve()
        A, w = self._own_e()
        self.U = self._start_block(A, w)
        out = np.zeros(payload_size(self.dim, self.block))
        self._put_block(out, A, self.U.sum(axis=0))
        if not self.hard:  # (hard: B is empty, g = 0)
            out[-self.dim :] = self.C * self.rows[self.labels == B_ROW].sum(axis=0)
        self._next(out, "start")

    def _start_block(self, A: np.ndarray, w: np.ndarray) -> np.ndarray:
        """The first block on this robot's E rows: the preconditioned 1 and t; with wide_start, then its
        step's multipliers (the ADMM's estimate of alpha) and the preconditioned x columns w * A_E[:, j]
        (j = 0, 1, ..., the images of unit vectors), up to the block. Every Krylov vector's image lies in
        the M-dimensional x space, so a solve's span is exhausted after about M / width steps: a wider
        start block takes fewer steps."""
        cols = [w, w * A[:, -1]]
        if self.wide_start and not self.narrow:
            lam = self.qp.multipliers
            own = lam is not None and len(lam) == len(self.rows)
            cols.append(np.asarray(lam, dtype=float)[self.labels == E_ROW] if own else np.zeros(len(A)))
            cols += [w * A[:, j] for j in range(min(self.block - len(cols), A.shape[1] - 1))]
        cols = cols[: self.block]
        return np.column_stack(cols) if len(A) else np.zeros((0, len(cols)))

    def _put_block(self, out: np.ndarray, A: np.ndarray, scalars: np.ndarray) -> None:
        d, k, at = self.dim, self.U.shape[1], _scalars(self.block)
        self.sent = k
        out[3 : 3 + k] = scalars
        for j in range(k):
            out[at + j * d : at + (j + 1) * d] = A.T @ self.U[:, j]

    # -- one round ---------------------------------------------------------------------------------
    def _fold(self, payloads: np.ndarray, v_own: np.ndarray) -> np.ndarray | None:
        if self.kind == "wait":
            self.guess(v_own)
            return None
        if not np.all(np.isfinite(payloads)):  # a bad payload fails the attempt on every copy alike
            self.guess(v_own)
            return None
        d = self.dim
        first = self.kind == "start"
        if not first:
            if bool(np.all(payloads[:, 0] == 1.0)):  # every robot certified its rows: the optimum
                self.result = self.v.copy()
                self._next(np.zeros(payload_size(d, self.block)), "done")
                return self.result
            residual = float(payloads[:, 2].max())
            self.refined = self.refined + 1 if self.sent == 0 else 0
            if residual <= EQ or self.solve_rounds >= SOLVE_ROUNDS or self.refined > REFINE:
                self._correct(payloads, v_own)  # solved (or as far as it goes) and violated: move a row
                return None
        payloads = np.ascontiguousarray(payloads)
        k_old = self.S.shape[1]
        key = _digest(b"soft-fold", b"s" if first else b"g", repr((self.sent, d, k_old, self.mu, payloads.shape)).encode(),
                      np.ascontiguousarray(self.S), self.Pr, self.y, self.g, self.v, payloads)
        fold, _ = shared_step(_SHARED_FOLDS, key, lambda: self._common(payloads, first), SHARED_FOLDS_KEPT)
        if first:
            self.g = fold.g
        self._take(fold)
        if not fold.solved:  # the reduced system is singular on this set: a fresh guess
            self.guess(v_own)
            return None
        self._verdict(list(fold.added), first)
        return None

    def _common(self, payloads: np.ndarray, first: bool) -> _Fold:
        """What every copy computes alike from the round's payloads and the shared state (S, P' r, y,
        gamma, g): the sums, the grown span and the Galerkin correction (`_grow`). Reads this copy,
        changes nothing: the value is adopted by the process's other copies (`_SHARED_FOLDS`)."""
        d = self.dim
        sums, at = _pairwise_sum(payloads), _scalars(self.block)
        images = [sums[at + j * d : at + (j + 1) * d] for j in range(self.sent)]
        if first:
            g = sums[-d:].copy()
            # U' r at v = (g_x, 0): 1' u - (A_x' u)' g_x, from the sums alone (one batched sum)
            gx = _dots(np.array([s[:-1] for s in images]).reshape(len(images), d - 1), g[:-1])
            ur = [float(sums[3 + j]) - float(gx[j]) for j in range(len(images))]
            Pr, v = self.Pr, np.append(g[:-1], 0.0)
        else:
            g, v = self.g, self.v
            Pr = sums[-d:][: self.S.shape[1]].copy()
            ur = [float(sums[3 + j]) for j in range(self.sent)]
        return _grow(self.S, Pr, self.y, self.mu, v, g, self._gram, images, ur)

    def _take(self, fold: _Fold) -> None:
        """Adopt a round's shared part and replay its orthogonalisation on this robot's own basis P
        and block U (the same coefficients, in the same order, as `_grow` took them)."""
        P = self.P
        for j, (coefs, norm) in enumerate(fold.steps):
            u = self.U[:, j].copy()
            for c in coefs:
                u = u - P @ c
            if norm is not None:
                P = np.column_stack([P, u / norm])
        self.P = P
        self.S, self.Pr, self.y, self._gram = fold.S, fold.Pr, fold.y, fold.gram
        self.mu, self.v = fold.mu, fold.v

    def _verdict(self, added: list[np.ndarray], first: bool) -> None:
        """This robot's check of its own rows at the new solution, its worst violation, and the next
        frame: the verdict, the next block (images of the new vectors; the first also g's) and P' r."""
        C, d = self.C, self.dim
        A, w = self._own_e()
        e_rows = np.flatnonzero(self.labels == E_ROW)
        alpha = self.P @ self.y if len(e_rows) else np.zeros(0)
        m = self.rows @ self.v
        r = 1.0 - m[e_rows]
        residual = float(np.abs(r).max()) if len(r) else 0.0
        worst, self.move = 0.0, None
        for i, a in zip(e_rows, alpha):
            for value, label in ((-a, N_ROW),) if self.hard else ((-a / C, N_ROW), ((a - C) / C, B_ROW)):
                if value > worst:
                    worst, self.move = value, (int(i), label)
        for label, sign, new in ((B_ROW, 1.0, E_ROW), (N_ROW, -1.0, E_ROW)):
            idx = np.flatnonzero(self.labels == label)
            if len(idx):
                viol = sign * (m[idx] - 1.0)
                k = int(np.argmax(viol))
                if viol[k] > EQ and viol[k] > worst:
                    worst, self.move = float(viol[k]), (int(idx[k]), new)
        ok = residual <= EQ and worst == 0.0
        blocks = [w * (A[:, :-1] @ s[:-1]) for s in added]
        if first:
            blocks.append(w * (A[:, :-1] @ self.g[:-1]))
        self.U = np.column_stack(blocks[: self.block]) if blocks else np.zeros((len(A), 0))
        out = np.zeros(payload_size(d, self.block))
        out[:3] = [1.0 if ok else 0.0, worst, residual]
        self._put_block(out, A, self.U.T @ r if self.U.size else np.zeros(self.U.shape[1]))
        out[-d:][: self.P.shape[1]] = self.P.T @ r if len(e_rows) else 0.0
        self.solve_rounds += 1
        self._next(out, "grow")

    def _correct(self, payloads: np.ndarray, v_own: np.ndarray) -> None:
        """The fleet's single worst row changes sides (its owner moves it); after CAP corrections, or
        with nothing to move, a fresh guess -- but a wide start's solve with nothing to move first solves its
        set again from the narrow start: its span can fill the x space off the answer (the extra vectors are
        outside the Krylov space of 1 and t, which holds it), leaving no multiplier or margin violated."""
        worst = payloads[:, 1]
        k = int(np.argmax(worst))  # ties: the lowest id
        if not worst[k] > 0.0 and self.wide_start and not self.narrow:
            self.narrow = True
            self._start()
            return
        if not worst[k] > 0.0 or self.corrections >= CAP:
            self.guess(v_own)
            return
        self.corrections += 1
        if self.ids[k] == self.me and self.move is not None:
            self.labels[self.move[0]] = self.move[1]
        self._start()

    # -- checkpoints -------------------------------------------------------------------------------
    def state(self) -> dict[str, Any]:
        return {
            "labels": self.labels.tolist(), "kind": self.kind, "attempts": self.attempts,
            "corrections": self.corrections, "payload": to_bytes(self.payload),
            "prev_payload": to_bytes(self.prev_payload), "result": to_bytes(self.result),
            "S": to_bytes(self.S.ravel()), "P": to_bytes(self.P.ravel()), "P_cols": self.P.shape[1],
            "Pr": to_bytes(self.Pr), "y": to_bytes(self.y), "mu": self.mu, "g": to_bytes(self.g),
            "v": to_bytes(self.v), "U": to_bytes(self.U.ravel()), "U_cols": self.U.shape[1], "sent": self.sent,
            "solve_rounds": self.solve_rounds, "refined": self.refined, "move": None if self.move is None else list(self.move),
            "narrow": self.narrow,
        }

    def load(self, state: dict[str, Any]) -> None:
        def arr(key: str) -> np.ndarray:
            a = from_bytes(state[key])
            return np.zeros(0) if a is None else a

        self.labels = np.array(state["labels"], dtype=np.int8)
        self.kind, self.attempts, self.corrections = state["kind"], int(state["attempts"]), int(state["corrections"])
        self.payload, self.prev_payload = from_bytes(state["payload"]), from_bytes(state["prev_payload"])
        self.result = from_bytes(state["result"])
        self.S = arr("S").reshape(self.dim, -1)
        n_e = int(np.sum(self.labels == E_ROW))
        self.P = arr("P").reshape(n_e, int(state["P_cols"]))
        self.Pr, self.y, self.mu = arr("Pr"), arr("y"), float(state["mu"])
        self.g, self.v = arr("g"), arr("v")
        self.U = arr("U").reshape(n_e, int(state["U_cols"]))
        self._gram = None  # (computed from S anew: the same bits, each entry its own sum)
        self.sent, self.solve_rounds, self.refined = int(state["sent"]), int(state["solve_rounds"]), int(state["refined"])
        self.move = None if state["move"] is None else (int(state["move"][0]), int(state["move"][1]))
        self.narrow = bool(state["narrow"])
