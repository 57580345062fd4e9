"""Autogrid's sigma sweep in one pass: every (candidate, fold) is its own ConsensusADMM
sub-machine on its own coarse lattice, all advanced in the same rounds from one stacked frame.

Frame layout (params.sweep_blocks(), candidate-major then fold): for each task a block of
slot + 3 floats -- x on its lattice (zero-padded to the slot), gamma, the sub-machine's stop
flags as an exact integer, and the task's verdict (below) -- so a frame carries function-space
vectors only. With params.hub_frames (a complete graph) the block is followed by the hub's w
(slot + 1 floats: x zero-padded, gamma), which the sub-machine sends beside v (agents/admm.py).
Every robot's sub-machine of a task stops in the same round (its own flags protocol); a stopped
sub-machine keeps sending its last value, so the sweep costs the slowest task, not the sum of all.
Issue 10's rule bounds a frame by 16 (max_points + 1) floats: where every task's block together would
not fit, the frame is sized for the first of `AutoGridParams.sweep_groups` groups of folds (the SVM model;
the lsq model's frame is `lsq_sweep_frame`, 4816 floats for the default budget, whose up to 35 tasks always
share it) and the tasks share it round by round (`_scheduled`): each task's block is its lattice's own size (2 (m + 1) + 2
floats, not the slot), and every round the tasks with the fewest rounds done (ties: candidate, then fold)
take the frame's room in that order, a task that does not fit waiting; a stopped task keeps its block D
rounds (its verdict's max-consensus) and then frees it. A waiting task is simply not advanced: every
robot pauses and resumes it in the same rounds (the order is a function of the tasks' agreed state), and
a sub-machine's round is its own, so every task is the same sub-machine as in one pass: the scores and
the choice are the same bit for bit, only the rounds change (the default run's sweep 80 rounds instead of
124 when the folds ran in two groups one after the other; one pass: 62).

Early drop (issue 10): when a task stops, each robot sets its verdict to 1 if the task's iterate
misclassifies one of its held-out points or its inside region is not one solid piece, else 0;
a max over D rounds makes it fleet-wide. A candidate whose folds all stopped with verdict 0 is
*perfect* (no held-out error anywhere, solid): `choose_sigma` (fewest errors, ties -> the smaller
sigma) can then never pick a wider candidate, so once every narrower candidate has stopped too,
the wider unfinished ones are dropped (judged on their iterate, marked `dropped`) and the sweep
ends. With `sigma_ties = "larger"` it is the mirror image: the narrower ones are dropped once every
wider candidate has stopped. The choice is the one the full sweep would make; only the rounds change.

Tally (one max-consensus): per candidate, two slots per robot id: the exact integer
errors + PACK * held_out + PACK^2 * not_solid (summed over folds by the robot) and the hinge loss.

The least-squares model (params.model "lsq", rule 2 of benchmarks/lsq_emulation.py): the same tasks and
frames, each task the least-squares fit (`WarmLSQ`) of the rows of its training pairs on its candidate's
kept level-0 lattice (spacing LSQ_SPACING_RATIO sigma, the nodes near data: `lsq_models`; candidates over the
budget have no task), the tasks always sharing the frame round by round (`lsq_sweep_frame`); holdout_every folds of whole LiDAR pairs, a robot's k-th
pair in fold (k + robot id) mod holdout_every (points in no pair always train). A task's outcome is its
held-out pairs' squared residual, (f(o) - 1)^2 + f(midpoint)^2 + (f(i) + 1)^2 summed, in the hinge slot, and
their count in the packed integer (no errors, always solid); no verdict, no early drop (a continuous score
has no perfect candidate).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from agents.admm import ADMMParams
from agents.autogrid_rules import (
    PACK,
    TALLY_BLOCKS,
    AutoGridParams,
    coarse_lattice,
    lattice_box,
    lsq_lattices,
    solid_on_raster,
    tie_sign,
)
from agents.autogrid_warm import WarmADMM
from agents.kernel import GridBasis
from agents.lsq_admm import WarmLSQ, lsq_sub_params
from agents.lsq_model import lidar_pairs, lsq_rows
from agents.rounds import RobotShare
from protocol.frames import StateUpdate


@dataclass
class SweepTask:
    """One (candidate, fold): its lattice, basis, held-out mask and ADMM sub-machine."""

    cand: int
    fold: int
    divisor: float
    sigma: float
    box: tuple[float, float, float, float]
    basis: GridBasis
    held: np.ndarray
    sub: WarmADMM
    offset: int
    slot: int
    verdict: float = 0.0  # 1: this task has a held-out error or a region not solid (max over robots)
    since: int = -1  # rounds since the task stopped (-1: running); verdict fleet-wide at >= diameter
    dropped: bool = False
    held_pairs: np.ndarray | None = None  # the lsq model: (outside, inside) of this robot's held-out pairs, (k, 2, 2)


class _RasterBasis:
    """A candidate's basis whose kernel rows k(points, G) are kept for the last points asked.

    `solid_on_raster` evaluates every iterate of a candidate on the same raster of its box (each
    fold's, at its stop and again for the tally): the kernel matrix, 8 ms for the default run's
    64 x 64 raster, is then computed once per candidate. Same numbers, same bits as the basis."""

    def __init__(self, basis: GridBasis) -> None:
        self.basis = basis
        self._points: np.ndarray | None = None
        self._kernel: np.ndarray | None = None

    def decision(self, points: np.ndarray, c: np.ndarray, gamma: float) -> np.ndarray:
        """f(points) = k(points, G) c + gamma, as GridBasis.decision."""
        if self._points is None or not np.array_equal(self._points, points):
            self._points, self._kernel = np.array(points), self.basis.kernel_to_grid(points)
        assert self._kernel is not None
        return self._kernel @ np.asarray(c, dtype=float) + float(gamma)


@dataclass
class SweepModel:
    """One model the sweep compares: a label (the candidate's divisor, or the width test's ratio),
    its width, the box its solid check rasterizes, its basis, its frame slot and an optional
    common first iterate (every robot the same)."""

    divisor: float
    sigma: float
    box: tuple[float, float, float, float]
    basis: GridBasis
    slot: int
    start: np.ndarray | None = None


def lsq_models(bounds: tuple[float, float, float, float], diag: float, params: AutoGridParams,
               marks: np.ndarray) -> tuple[list[SweepModel], list[dict[str, Any]]]:
    """Rule 2's candidates from the fleet's agreed near-data marks (`lsq_near_marks`, max-consensus): (the models
    the sweep tries, one record per candidate). A candidate's grid is its level-0 lattice's marked nodes; it is
    tried when they fit max_points. None fits: the widest candidate on its lattice coarsened to the budget
    (rule 1's `coarse_lattice`, benchmarks/lsq_emulation.py's fallback) is the only one tried."""
    models, records, start = [], [], 0
    for d, nodes in zip(params.lsq_divisors, lsq_lattices(bounds, diag, params)):
        sigma = diag / d
        kept = nodes[marks[start : start + len(nodes)] > 0]
        start += len(nodes)
        tried = 0 < len(kept) <= params.max_points
        records.append({"divisor": float(d), "sigma": sigma, "lattice_points": len(nodes), "grid_points": len(kept),
                        "grid": "near data", "tried": tried})
        if tried:
            models.append(SweepModel(float(d), sigma, lattice_box(bounds, sigma), GridBasis(kept, sigma), len(kept)))
    if not models:
        widest = min(range(len(records)), key=lambda i: records[i]["divisor"])
        sigma = records[widest]["sigma"]
        box, _, grid = coarse_lattice(bounds, sigma, params.coarse_spacing, params.max_points)
        records[widest].update(grid_points=len(grid), grid="coarsened full lattice (no near-data lattice fits)",
                               tried=True)
        models.append(SweepModel(records[widest]["divisor"], sigma, box, GridBasis(grid, sigma), len(grid)))
    return models, records


def pair_folds(labels: np.ndarray, robot_id: int, folds: int) -> tuple[np.ndarray, np.ndarray]:
    """The lsq model's folds of one robot's data: (start index of each LiDAR pair, its fold), the k-th
    pair (in data order) in fold (k + robot id) mod folds (benchmarks/lsq_emulation.py lidar_rows)."""
    starts = lidar_pairs(labels)
    return starts, (np.arange(len(starts)) + robot_id) % folds


def held_mask(units: np.ndarray, fold: int, params: AutoGridParams) -> np.ndarray:
    """The points a robot holds out in `fold` (whole units, see `holdout_units`)."""
    k = params.holdout_every
    return (units >= 0) & (units % k == k - 1 - fold)


def lsq_residual(basis: GridBasis, c: np.ndarray, gamma: float, pairs: np.ndarray) -> float:
    """sum over (outside, inside) pairs of (f(o) - 1)^2 + f(midpoint)^2 + (f(i) + 1)^2: what the held-out
    pairs say f should be (+1, 0, -1), as the lsq model's rows."""
    if not len(pairs):
        return 0.0
    o, i = pairs[:, 0], pairs[:, 1]
    fo, fm, fi = (basis.decision(q, c, gamma) for q in (o, 0.5 * (o + i), i))
    return float(np.sum((fo - 1.0) ** 2 + fm**2 + (fi + 1.0) ** 2))


class SigmaSweep:
    """One robot's share of the sweep: stacked values out, neighbours' stacked values in."""

    _given_models = False  # True for the width test's models (no early drop: they share one sigma)
    #: hops a verdict's max-consensus covers when wider than params.diameter: after a loss on a sparse
    #: graph the owner sets it (autogrid's `_reach`: the survivors' graph may be wider than D)
    reach = 0

    def __init__(
        self, share: RobotShare, units: np.ndarray, *, bounds: tuple[float, float, float, float], diag: float,
        params: AutoGridParams, dim: int | None = None, models: list[SweepModel] | None = None,
        gone: tuple[int, ...] = (),
    ) -> None:
        points, labels = share.features, share.labels  # autogrid's share: raw points
        # dim: the fleet's frame length (the given params', when folds_for_data ran fewer folds)
        self.robot_id, self.params, self.dim = share.robot_id, params, params.dim if dim is None else dim
        n_models = max(len(params.sweep_divisors), len(models or ()))
        self._slots = self.dim // (TALLY_BLOCKS * max(1, n_models))  # = the fleet's tally_slots
        self._points, self._labels = points, labels
        sub_params = ADMMParams(
            rho=params.rho, relax=params.relax, tol=params.validate_tol,
            max_rounds=params.validate_rounds, diameter=params.diameter,
            certify=0.0,  # the rule alone: the nested runs' frames have no room for the guard
        )
        if params.lsq:  # each task a least-squares fit to the answer's tolerance: its score is that fit's
            sub_params = lsq_sub_params(params.lsq_lambda, rho=params.lsq_rho, relax=params.relax, tol=params.tol,
                                        max_rounds=params.soft_rounds, diameter=params.diameter)
            starts, pair_fold = pair_folds(labels, share.robot_id, params.sweep_folds)
            # the rows each fold trains on, and all rows (the edge form's fit): the same for every candidate
            fold_rows = [lsq_rows(points, labels, keep=pair_fold != fold) for fold in range(params.sweep_folds)]
            all_rows = lsq_rows(points, labels)
        #: every lsq candidate's record, tried or not (set by autogrid.py with the models it passes)
        self.lsq_records: list[dict[str, Any]] | None = None
        self.tasks: list[SweepTask] = []
        self._raster: dict[int, _RasterBasis] = {}  # per candidate (its folds share the basis)
        self._outcomes: dict[tuple[int, int], tuple[bytes, tuple[int, int, float, bool]]] = {}  # per task: last iterate's
        # the models compared: by default one per sigma candidate on its coarse lattice; the width test
        # (autogrid.py, WIDTHS) passes its own (one width and two, on grids refined from the seed)
        self._given_models = models is not None  # early drop ranks sigma candidates only
        if models is None:
            models = []
            for d in params.validate_divisors:
                sigma = diag / d
                slot = params.sweep_slot(d)
                box, _, grid = coarse_lattice(bounds, sigma, params.coarse_spacing, slot)
                models.append(SweepModel(float(d), sigma, box, GridBasis(grid, sigma), slot))
        self.models = models
        # every task's block together over the frame: the tasks share it round by round (`_running`); the lsq
        # model's always (its frame, `lsq_sweep_frame`, is sized for no particular set of candidates)
        self._scheduled = params.lsq or (params.sweep_groups > 1 and not self._given_models)
        offset = 0
        for cand, model in enumerate(models):
            basis, slot = model.basis, model.slot
            self._raster[cand] = _RasterBasis(basis)
            for fold in range(params.sweep_folds):
                pairs = None
                if params.lsq:
                    held = np.zeros(len(points), dtype=bool)  # (unused: the pairs are held out)
                    rows, targets = fold_rows[fold]
                    feats = basis.features(rows) if len(rows) else np.zeros((0, basis.size))
                    sub: WarmADMM = WarmLSQ(share.with_data(share.neighbours, feats, targets, None), sub_params,
                                            lam=params.lsq_lambda, keep_trace=False, hub_frames=params.hub_frames,
                                            gone=gone)
                    kept = starts[pair_fold == fold]
                    pairs = np.stack([points[kept], points[kept + 1]], axis=1).reshape(-1, 2, 2)
                else:
                    held = held_mask(units, fold, params)
                    train = points[~held]
                    feats = basis.features(train) if len(train) else np.zeros((0, basis.size))
                    fold_share = share.with_data(share.neighbours, feats, labels[~held], params.soft_C)
                    sub = WarmADMM(fold_share, sub_params, keep_trace=False, hub_frames=params.hub_frames,
                                   start=model.start, gone=gone)
                task_slot = basis.size if self._scheduled else slot  # (scheduled: offsets set each round)
                self.tasks.append(SweepTask(cand, fold, model.divisor, model.sigma, model.box, basis, held, sub,
                                            offset, task_slot, held_pairs=pairs))
                offset += self._block(self.tasks[-1]) if not self._scheduled else 0
            if params.lsq and self.tasks[-1].sub._hub is None:  # the edge form: the candidate's fit of all rows too
                rows, targets = all_rows
                feats = basis.features(rows) if len(rows) else np.zeros((0, basis.size))
                sub = WarmLSQ(share.with_data(share.neighbours, feats, targets, None), sub_params,
                              lam=params.lsq_lambda, keep_trace=False, hub_frames=params.hub_frames, gone=gone)
                self.tasks.append(SweepTask(cand, params.sweep_folds, model.divisor, model.sigma, model.box, basis,
                                            np.zeros(len(points), dtype=bool), sub, 0, basis.size,
                                            held_pairs=np.zeros((0, 2, 2))))

    @property
    def finished(self) -> bool:
        """Every scored task stopped (or dropped): the lsq edge form's fits of all rows do not hold the sweep
        (the final fit goes on from where they are: `full_fit`)."""
        return all(t.sub.finished or t.dropped for t in self._folds())

    @property
    def residual(self) -> float:
        return max((t.sub.residual for t in self._running() if not t.sub.finished), default=0.0)

    def _block(self, t: SweepTask) -> int:
        """Frame length of a task's block: x, gamma, flags, verdict (and the hub's w: x and gamma)."""
        return t.slot + 3 + (t.slot + 1 if self.params.hub_frames else 0)

    def _running(self) -> list[SweepTask]:
        """The tasks in this round's frame, their offsets set. One pass: every task, in its fixed block.
        Scheduled (see the module docstring): the stopped tasks still spreading their verdict (fewer than
        D rounds since the stop: they held room the round before, so they fit), then the unfinished tasks
        by rounds done, candidate and fold, each while it fits; laid out in task order. D, not `reach`:
        a task once left is never taken up again (a verdict that needed more hops is not spread and its
        candidate is not dropped early -- the choice stays the full sweep's). A function of the tasks'
        state alone, which every robot holds alike: the same tasks in the same blocks everywhere."""
        if not self._scheduled:
            return self.tasks
        d = self.params.diameter
        spreading = [t for t in self.tasks if 0 <= t.since < d and not t.dropped]
        waiting = sorted((t for t in self.tasks if t.since < 0 and not t.dropped),
                         key=lambda t: (t.sub.round, t.cand, t.fold))
        room, chosen = self.dim, []
        for t in spreading + waiting:
            if self._block(t) <= room:
                room -= self._block(t)
                chosen.append(t)
        chosen.sort(key=lambda t: (t.cand, t.fold))
        offset = 0
        for t in chosen:
            t.offset, offset = offset, offset + self._block(t)
        return chosen

    def stacked(self) -> np.ndarray:
        """This robot's frame vector: every running task's (x, gamma, flags) in its block."""
        v = np.zeros(self.dim)
        for t in self._running():
            vals = t.sub.values
            v[t.offset : t.offset + t.basis.size] = vals[:-1]
            v[t.offset + t.slot] = vals[-1]
            out = t.sub.outgoing()
            v[t.offset + t.slot + 1] = float(out.flags)
            v[t.offset + t.slot + 2] = t.verdict
            if out.values.size > t.sub.dim:  # the hub's w, after the block
                w, o = out.values[t.sub.dim :], t.offset + t.slot + 3
                v[o : o + t.basis.size], v[o + t.slot] = w[:-1], w[-1]
        return v

    def advance(self, theirs: dict[int, np.ndarray], gone: Mapping[int, tuple[int, ...]] | None = None) -> None:
        """One round of every unfinished task from the neighbours' stacked round-k vectors (and the
        robots each neighbour knew dropped for good in that round: `gone`, for the edge form)."""
        gone = gone or {}
        for t in self._running():
            if t.since >= 0:  # stopped: spread the verdict (max-consensus)
                t.verdict = max([t.verdict, *(float(v[t.offset + t.slot + 2]) for v in theirs.values())])
                t.since += 1
                continue
            if t.dropped:
                continue
            m, o = t.basis.size, t.offset
            for j, v in theirs.items():
                vec = np.append(v[o : o + m], v[o + t.slot])
                if t.sub.frame_dim > t.sub.dim:
                    w = o + t.slot + 3
                    vec = np.concatenate([vec, v[w : w + m], v[w + t.slot : w + t.slot + 1]])
                t.sub.receive(StateUpdate(j, t.sub.round, vec, int(v[o + t.slot + 1]), None, gone=gone.get(j, ())))
            t.sub.advance()
            if t.sub.finished:
                errors, _, _, solid = self._outcome(t)
                t.verdict, t.since = float((errors > 0 or not solid) and not self.params.lsq), 0
        self._drop_decided()

    def _drop_decided(self) -> None:
        """Drop the unfinished candidates that lose every tie to a perfect one (wider ones when
        ties go to the smaller sigma, narrower ones when to the larger) once every candidate that
        would win a tie against it has stopped (see the module docstring); the same round on
        every robot."""
        if not self.params.early_drop or self._given_models or self.params.lsq:
            return
        sign = tie_sign(self.params)
        cands = sorted({t.cand for t in self.tasks}, key=lambda c: sign * self.task(c, 0).sigma)  # tie winners first
        for cand in cands:
            tasks = [t for t in self.tasks if t.cand == cand]
            if not all(t.since >= 0 or t.dropped for t in tasks):
                return  # a candidate still running that would win a tie could still win
            if all(t.since >= max(self.params.diameter, self.reach) and t.verdict == 0.0 for t in tasks):
                for t in self.tasks:
                    if sign * t.sigma > sign * tasks[0].sigma and t.since < 0:
                        t.dropped = True
                return

    def drop_neighbour(self, j: int) -> None:
        for t in self.tasks:
            t.sub.drop_neighbour(j)

    # -- the tally ------------------------------------------------------------------------------
    def _outcome(self, t: SweepTask) -> tuple[int, int, float, bool]:
        """(held-out errors, held-out points, hinge, solid) of this robot's task iterate; a task's
        outcome is asked at its stop and again for the tally, on the same iterate: kept."""
        v = t.sub.values
        key, index = v.tobytes(), (t.cand, t.fold)
        kept = self._outcomes.get(index)
        if kept is not None and kept[0] == key:
            return kept[1]
        c, gamma = t.basis.c_from_x(v[:-1]), float(v[-1])
        if t.held_pairs is not None:  # the lsq model: the held-out pairs' squared residual (no errors, no solid check)
            outcome = 0, len(t.held_pairs), lsq_residual(t.basis, c, gamma, t.held_pairs), True
            self._outcomes[index] = (key, outcome)
            return outcome
        pts, y = self._points[t.held], self._labels[t.held]
        errors, hinge = 0, 0.0
        if len(y):
            yf = y * t.basis.decision(pts, c, gamma)
            errors, hinge = int(np.sum(yf <= 0)), float(np.sum(np.maximum(0.0, 1.0 - yf)))
        raster = self._raster[t.cand]
        outcome = errors, len(y), hinge, solid_on_raster(raster, c, gamma, t.box, self.params.solid_raster,  # type: ignore[arg-type]
                                                     self.params.holes_allowed)
        self._outcomes[index] = (key, outcome)
        return outcome

    def tally_vector(self) -> np.ndarray:
        """This robot's slots of the tally (zeros elsewhere), for a max-consensus."""
        s = self._slots
        v = np.zeros(self.dim)
        for t in self._folds():
            errors, held, hinge, solid = self._outcome(t)
            base = t.cand * TALLY_BLOCKS * s + self.robot_id
            v[base] += errors + PACK * held + PACK * PACK * (0 if solid else 1)
            v[base + s] += hinge
        return v

    def records(self, tally: np.ndarray) -> list[dict[str, Any]]:
        """The fleet-wide record of every candidate from the agreed tally (identical everywhere)."""
        s = self._slots
        out = []
        for cand, model in enumerate(self.models):
            d = model.divisor
            base = cand * TALLY_BLOCKS * s
            packed = int(round(float(np.sum(tally[base : base + s]))))
            tasks = [t for t in self._folds() if t.cand == cand]
            if self.params.lsq:  # the held-out pairs' mean squared residual (the rule's score)
                held = (packed // int(PACK)) % int(PACK)
                total = float(np.sum(tally[base + s : base + 2 * s]))
                out.append({"divisor": float(d), "sigma": tasks[0].sigma, "grid_points": tasks[0].basis.size,
                            "held_out_pairs": held, "squared_residual": total, "score": total / held if held else math.inf,
                            "folds": len(tasks), "rounds": max(t.sub.round for t in tasks),
                            "converged": all(t.sub.converged or not t.sub.neighbours for t in tasks)})
                continue
            out.append(
                {
                    "divisor": float(d),
                    "sigma": tasks[0].sigma,
                    "grid_points": tasks[0].basis.size,
                    "errors": packed % int(PACK),
                    "held_out": (packed // int(PACK)) % int(PACK),
                    "hinge": float(np.sum(tally[base + s : base + 2 * s])),
                    "solid": packed // int(PACK * PACK) == 0,
                    "folds": len(tasks),
                    "rounds": max(t.sub.round for t in tasks),
                    "converged": all(t.sub.converged or not t.sub.neighbours for t in tasks),
                    "dropped": any(t.dropped for t in tasks),
                }
            )
        return out

    def task(self, cand: int, fold: int) -> SweepTask:
        return next(t for t in self.tasks if t.cand == cand and t.fold == fold)

    def _folds(self) -> list[SweepTask]:
        """The held-out folds' tasks: those the tally scores (not the lsq edge form's fits of all rows)."""
        return [t for t in self.tasks if t.fold < self.params.sweep_folds]

    def full_fit(self, cand: int) -> tuple[np.ndarray, dict[int, tuple[np.ndarray, np.ndarray]]] | None:
        """The lsq edge form's fit of all rows on a candidate's lattice, run beside its folds until they stop
        (stopped by its own rule, or not yet): this robot's last iterate and every edge's (z, lambda), the final
        fit's start (the same problem: the final fit goes on from there, or only confirms it). Every robot advanced
        the task in the same rounds and both ends of an edge hold the same (z, lambda), so lambda_lj = -lambda_jl
        carries over and the fixed point stays the exact fit. None in the hub form (no such task) or when dropped."""
        task = next((t for t in self.tasks if t.cand == cand and t.fold == self.params.sweep_folds), None)
        if task is None or task.dropped:
            return None
        return task.sub.values.copy(), {j: (e.z.copy(), e.lam.copy()) for j, e in task.sub._edges.items()}

    # -- checkpoint -----------------------------------------------------------------------------
    def checkpoint(self) -> list[dict[str, Any]]:
        return [{"sub": t.sub.checkpoint(), "verdict": t.verdict, "since": t.since, "dropped": t.dropped}
                for t in self.tasks]

    def restore(self, states: list[dict[str, Any]]) -> None:
        for t, state in zip(self.tasks, states):
            t.sub.restore(state["sub"])
            t.verdict, t.since, t.dropped = float(state["verdict"]), int(state["since"]), bool(state["dropped"])
