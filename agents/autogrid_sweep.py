"""Autogrid's sigma sweep in one pass: every (candidate, fold) is its own ConsensusADMM
sub-machine on its own coarse lattice, all advanced in the same rounds from one stacked frame.

Frame layout (params.sweep_blocks(), candidate-major then fold): for each task a block of
slot + 2 floats -- x on its lattice (zero-padded to the slot), gamma, and the sub-machine's stop
flags as an exact integer -- so a frame carries function-space vectors only. With
params.hub_frames (a complete graph) the block is followed by the hub's w (slot + 1 floats:
x zero-padded, gamma), which the sub-machine sends beside v (agents/admm.py). Every robot's
sub-machine of a task stops in the same round (its own flags protocol); a stopped sub-machine
keeps sending its last value, so the sweep costs the slowest task, not the sum of all.

Tally (one max-consensus): per candidate, two slots per robot id: the exact integer
errors + PACK * held_out + PACK^2 * not_solid (summed over folds by the robot) and the hinge loss.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from agents.admm import ADMMParams
from agents.autogrid_rules import PACK, TALLY_BLOCKS, AutoGridParams, coarse_lattice, solid_on_raster
from agents.autogrid_warm import WarmADMM
from agents.kernel import GridBasis
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


def held_mask(units: np.ndarray, fold: int, params: AutoGridParams) -> np.ndarray:
    """The points a robot holds out in `fold` (whole units, see `holdout_units`)."""
    k = params.holdout_every
    return (units >= 0) & (units % k == k - 1 - fold)


class SigmaSweep:
    """One robot's share of the sweep: stacked values out, neighbours' stacked values in."""

    def __init__(
        self,
        robot_id: int,
        neighbours: tuple[int, ...],
        points: np.ndarray,
        labels: np.ndarray,
        units: np.ndarray,
        *,
        bounds: tuple[float, float, float, float],
        diag: float,
        params: AutoGridParams,
        n_robots: int,
        degrees: dict[int, int],
    ) -> None:
        self.robot_id, self.params, self.dim = robot_id, params, params.dim
        self._points, self._labels = points, labels
        sub_params = ADMMParams(
            rho=params.rho, relax=params.relax, tol=params.validate_tol,
            max_rounds=params.validate_rounds, diameter=params.diameter,
        )
        self.tasks: list[SweepTask] = []
        offset = 0
        for cand, d in enumerate(params.validate_divisors):
            sigma = diag / d
            slot = params.sweep_slot(d)
            box, _, grid = coarse_lattice(bounds, sigma, params.spacing_ratio, slot)
            basis = GridBasis(grid, sigma)
            for fold in range(params.validate_folds):
                held = held_mask(units, fold, params)
                train = points[~held]
                feats = basis.features(train) if len(train) else np.zeros((0, len(grid)))
                sub = WarmADMM(
                    robot_id, neighbours, feats, labels[~held], n_robots=n_robots, params=sub_params,
                    C=params.soft_C, neighbour_degrees={j: degrees.get(j, 1) for j in neighbours}, keep_trace=False,
                    hub_frames=params.hub_frames,
                )
                self.tasks.append(SweepTask(cand, fold, float(d), sigma, box, basis, held, sub, offset, slot))
                offset += (2 if params.hub_frames else 1) * (slot + 1) + 1

    @property
    def finished(self) -> bool:
        return all(t.sub.finished for t in self.tasks)

    @property
    def residual(self) -> float:
        return max((t.sub.residual for t in self.tasks if not t.sub.finished), default=0.0)

    def stacked(self) -> np.ndarray:
        """This robot's frame vector: every task's (x, gamma, flags) in its block."""
        v = np.zeros(self.dim)
        for t in self.tasks:
            vals = t.sub.values
            v[t.offset : t.offset + t.basis.size] = vals[:-1]
            v[t.offset + t.slot] = vals[-1]
            out = t.sub.outgoing()
            v[t.offset + t.slot + 1] = float(out.flags)
            if out.values.size > t.sub.dim:  # the hub's w, after the block
                w, o = out.values[t.sub.dim :], t.offset + t.slot + 2
                v[o : o + t.basis.size], v[o + t.slot] = w[:-1], w[-1]
        return v

    def advance(self, theirs: dict[int, np.ndarray]) -> None:
        """One round of every unfinished task from the neighbours' stacked round-k vectors."""
        for t in self.tasks:
            if t.sub.finished:
                continue
            m, o = t.basis.size, t.offset
            for j, v in theirs.items():
                vec = np.append(v[o : o + m], v[o + t.slot])
                if t.sub.frame_dim > t.sub.dim:
                    w = o + t.slot + 2
                    vec = np.concatenate([vec, v[w : w + m], v[w + t.slot : w + t.slot + 1]])
                t.sub.receive(StateUpdate(j, t.sub.round, vec, int(v[o + t.slot + 1]), None))
            t.sub.advance()

    def drop_neighbour(self, j: int) -> None:
        for t in self.tasks:
            t.sub.drop_neighbour(j)

    # -- the tally ------------------------------------------------------------------------------
    def _outcome(self, t: SweepTask) -> tuple[int, int, float, bool]:
        """(held-out errors, held-out points, hinge, solid) of this robot's task iterate."""
        v = t.sub.values
        c, gamma = t.basis.c_from_x(v[:-1]), float(v[-1])
        pts, y = self._points[t.held], self._labels[t.held]
        errors, hinge = 0, 0.0
        if len(y):
            yf = y * t.basis.decision(pts, c, gamma)
            errors, hinge = int(np.sum(yf <= 0)), float(np.sum(np.maximum(0.0, 1.0 - yf)))
        return errors, len(y), hinge, solid_on_raster(t.basis, c, gamma, t.box, self.params.solid_raster)

    def tally_vector(self) -> np.ndarray:
        """This robot's slots of the tally (zeros elsewhere), for a max-consensus."""
        s = self.params.tally_slots
        v = np.zeros(self.dim)
        for t in self.tasks:
            errors, held, hinge, solid = self._outcome(t)
            base = t.cand * TALLY_BLOCKS * s + self.robot_id
            v[base] += errors + PACK * held + PACK * PACK * (0 if solid else 1)
            v[base + s] += hinge
        return v

    def records(self, tally: np.ndarray) -> list[dict[str, Any]]:
        """The fleet-wide record of every candidate from the agreed tally (identical everywhere)."""
        s = self.params.tally_slots
        out = []
        for cand, d in enumerate(self.params.validate_divisors):
            base = cand * TALLY_BLOCKS * s
            packed = int(round(float(np.sum(tally[base : base + s]))))
            tasks = [t for t in self.tasks if t.cand == cand]
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
                }
            )
        return out

    def task(self, cand: int, fold: int) -> SweepTask:
        return next(t for t in self.tasks if t.cand == cand and t.fold == fold)

    # -- checkpoint -----------------------------------------------------------------------------
    def checkpoint(self) -> list[dict[str, Any]]:
        return [t.sub.checkpoint() for t in self.tasks]

    def restore(self, states: list[dict[str, Any]]) -> None:
        for t, state in zip(self.tasks, states):
            t.sub.restore(state)
