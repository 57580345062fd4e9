"""The fleet chooses its own grid and kernel width: one robot's sans-IO state machine.

`AdaptiveGridCore` has the interface of `ConsensusADMM` (frames in with `receive`, frames out
with `outgoing` / `advance`, the stop-flag protocol of `agents/rounds.py`) but needs no grid,
no sigma and no bounds from the launcher. Every robot runs the same phases, in the same rounds,
through the same frames (D = the `diameter` parameter, >= the graph diameter). The phases and
what ends each of them are the table `TRANSITIONS`; the rules are in agents/autogrid_rules.py,
the sweep in agents/autogrid_sweep.py, warm starts in agents/autogrid_warm.py and checkpoints
in agents/autogrid_state.py. docs/autogrid.md tells the whole story; in short:

1. BOUNDS (D rounds): max-consensus on (-xmin, xmax, -ymin, ymax): every robot holds the same
   data box bit for bit; diag = its diagonal; every length below is proportional to diag.
2. VALIDATE (unless sigma is given): every candidate sigma = diag / d and held-out fold is its
   own soft-margin ADMM on its coarse lattice, all advanced in the same rounds from one stacked
   frame; TALLY (D rounds) sums held-out errors and "not solid" flags exactly; `choose_sigma`.
   With `narrow_by_holdout` (off by default), where two widths would be used: WIDTHS solves every
   fold on the seed refined at one width and at two in one stacked pass, WTALLY counts their
   held-out errors, `choose_widths` keeps two widths only on strictly fewer.
3. VOTE (D rounds): each robot checks its own data is separable (hard margin) and marks the
   level-0 lattice nodes near its data; a max-consensus tells every robot both.
4. ADMM: `ConsensusADMM` as a sub-machine on the grid, warm-started (the chosen candidate's
   sweep solution, or the previous grid's function and edge duals carried exactly onto the
   refined grid; a soft solve on a complete graph also the last soft hub duals, the seed task's at first).
   The answer's stop reads its rate within one stretch of Anderson (`ADMMParams.settled_rate`). A hard margin not converged within `hard_rounds` is declared infeasible and
   the soft margin is solved on the same grid; so is one whose iterate's |x|^2 passes the bound
   `ill_conditioned_norm2` (an ill-conditioned hard margin: multipliers far above soft_C), the
   same round on every robot (a max-consensus of the earliest round it was passed, slot -1).
5. FLOOD (D + 1 rounds): every robot measures its relative gap to its neighbours' final values;
   a max-consensus of those gaps runs alongside a flood of the lowest id's vector. Only when the
   fleet's largest gap is within `tol` does every robot adopt the flooded vector; otherwise each
   keeps its own, the run stops, and the result says it did not converge.
6. REFINE (no communication): from the agreed f, every robot computes the same superset grid
   (nodes near the zero level set, in cells marked near data, no finer than the kernel can use).

The least-squares model (params.model "lsq", rule 2 of benchmarks/lsq_emulation.py): BOUNDS, then MARKS
(D rounds per chunk of the frame): a max-consensus of every robot's marks of the nodes of every candidate's
level-0 lattice within lsq_near sigma of its data; VALIDATE / TALLY on the candidates whose kept nodes fit the
budget; one ADMM fit of all rows on the chosen candidate's kept nodes; FLOOD.

Frames have a fixed length per fleet (`AutoGridParams.dim`): on a grid, x in the first M
entries, zeros, then the flood's gap (-3), gamma (-2) and a meta slot (-1: the vote, or the
flooded vector's robot id). No I/O, no clock.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from agents.admm import ADMMParams, complete_graph
from agents.autogrid_rules import (  # noqa: F401 -- re-exported: the public names of autogrid
    AUTOGRID_MAX_DIAMETER,
    MIN_SPACING,
    SIGMA_DIVISOR,
    SPACING_RATIO,
    AutoGridParams,
    choose_lsq_sigma,
    choose_sigma,
    choose_widths,
    coarse_lattice,
    holdout_units,
    is_solid,
    lattice,
    lattice_box,
    lsq_lattices,
    lsq_near_marks,
    near_data_marks,
    refine_grid,
    folds_for_data,
    grid_widths,
    hinge_sum,
    ill_conditioned_norm2,
    widths_for_data,
    scale_from_bounds,
)
from agents.autogrid_state import load_state, save_state
from agents.autogrid_sweep import SigmaSweep, SweepModel, lsq_models
from agents.autogrid_warm import WarmADMM, carry_edges, carry_hub_duals, carry_vector, hub_duals, superset_maps
from agents.kernel import GridBasis
from agents.lsq_admm import WarmLSQ, lsq_sub_params
from agents.lsq_model import lsq_rows
from agents.problem import InfeasibleError, MarginQP
from agents.rounds import RobotShare, RoundCore, relative_gap
from agents.soft_endgame import payload_size as endgame_payload_size
from protocol.frames import StateUpdate

#: stands for "no data" in the max-consensus on bounds (frames carry finite values only)
_NO_DATA = -1e300

BOUNDS, MARKS, VALIDATE, TALLY, SEED, WIDTHS, WTALLY, VOTE, ADMM, FLOOD, DONE = (
    "bounds", "marks", "validate", "tally", "seed", "widths", "wtally", "vote", "admm", "flood", "done"
)

#: how a phase's rounds are computed: a max-consensus, the stacked sweep, the ADMM sub-machine,
#: or the flood (lowest id's vector, largest gap)
EXCHANGE = {BOUNDS: "max", MARKS: "max", VALIDATE: "sweep", TALLY: "max", SEED: "flood", WIDTHS: "sweep", WTALLY: "max",
            VOTE: "max", ADMM: "admm", FLOOD: "flood"}

#: (phase, outcome of its last round) -> next phase. Counted phases (max, flood) end after their
#: rounds, VALIDATE and ADMM when their sub-machines stop (the same round on every robot).
TRANSITIONS = {
    (BOUNDS, "sweep sigma"): VALIDATE,
    (BOUNDS, "sigma by rule"): VOTE,
    (VALIDATE, "solved"): TALLY,
    (TALLY, "sigma chosen"): VOTE,  # a start grid given: solve on it first
    (TALLY, "seed"): SEED,  # agree on the chosen candidate's sweep function, refine from it
    (SEED, "refined"): VOTE,
    (SEED, "not refined"): VOTE,
    (SEED, "width test"): WIDTHS,  # narrow_by_holdout: one width or two, by the folds' held-out errors
    (WIDTHS, "solved"): WTALLY,
    (WTALLY, "width chosen"): VOTE,
    (VOTE, "separable"): ADMM,  # hard margin
    (VOTE, "inseparable"): ADMM,  # a robot's own data not separable: soft margin
    (VOTE, "soft"): ADMM,  # soft margin asked for (C given)
    (VOTE, "ill-conditioned"): ADMM,  # a robot's own hard margin already past the multiplier bound: soft
    (ADMM, "solved"): FLOOD,
    (ADMM, "stopped at its cap"): FLOOD,  # a soft margin (or validation) at its round cap
    (ADMM, "hard cap"): ADMM,  # hard margin not converged: declared infeasible, soft on the same grid
    (ADMM, "ill-conditioned"): ADMM,  # hard iterate past the multiplier bound: soft on the same grid
    (FLOOD, "refined"): VOTE,
    (FLOOD, "final"): DONE,
    (FLOOD, "disagree"): DONE,
    # the least-squares model (params.model "lsq"): no vote, no margin, no refinement
    (BOUNDS, "least squares"): ADMM,  # sigma given
    (BOUNDS, "near-data marks"): MARKS,  # rule 2: every candidate's lattice nodes near some robot's data
    (MARKS, "next chunk"): MARKS,  # the marks did not fit one frame: the next dim of them
    (MARKS, "sweep sigma"): VALIDATE,  # the candidates whose kept nodes fit the budget
    (TALLY, "least squares"): ADMM,  # sigma by the held-out squared residual
}


class AdaptiveGridCore(RoundCore):
    """One robot: agree on bounds, choose sigma and grid, solve, agree on f, refine, repeat."""

    algorithm = "autogrid"

    def __init__(
        self, share: RobotShare, params: AutoGridParams, *, start_grid: np.ndarray | None = None,
        keep_trace: bool = False,
    ) -> None:
        robot_id = share.robot_id
        super().__init__(
            robot_id, share.neighbours, params.dim, diameter=params.diameter,
            round_cap=params.max_total_rounds, keep_trace=keep_trace,
        )
        points, labels = share.features, share.labels  # raw points: features are built per grid
        points = np.asarray(points, dtype=float).reshape(-1, 2)
        labels = np.asarray(labels)
        if len(labels) != len(points):
            raise ValueError(f"{len(points)} points but {len(labels)} labels")
        if start_grid is not None:
            start_grid = np.asarray(start_grid, dtype=float).reshape(-1, 2)
            if not 1 <= len(start_grid) <= params.max_points:
                raise ValueError(f"start grid has {len(start_grid)} points, budget is {params.max_points}")
        if params.validates and not 0 <= robot_id < params.tally_slots:
            raise ValueError(
                f"robot id {robot_id}: the sigma sweep tallies one slot per id, ids must be in "
                f"[0, {params.tally_slots}) (raise max_points)"
            )
        self.params = self._given = params  # _given, then as derived from the data (folds_for_data, widths_for_data)
        self._points, self._labels = points, labels
        self._share = share
        self._n_robots = share.n_robots
        # a sparse graph's robots see only their neighbours die: its frames flood who was dropped for good
        # (agents/rounds.py) and the edge-form sub-machines take every neighbour's list with its values
        # (weighed out with a soft margin, their stop widened); a complete graph's hub sees every drop
        self.floods_gone = not complete_graph(share.n_robots, share.neighbours, dict(share.degrees))
        self._start_grid = start_grid
        self._units = holdout_units(points, labels)
        # the lsq model's rows of this robot's data (outside +1, return 0, inside -1): its final fit's
        self._rows, self._targets = lsq_rows(points, labels) if params.lsq else (np.zeros((0, 2)), np.zeros(0))
        self._reset_agreed_state()
        self._enter_bounds()
        self._settle()
        self._record()

    def _reset_agreed_state(self) -> None:
        """Everything the fleet agrees on, before it has agreed on anything."""
        self.phase = BOUNDS
        self.bounds: tuple[float, float, float, float] | None = None
        self.sigma: float | None = None
        self.sigma_reason = ""
        self.sigma_validation: list[dict[str, Any]] = []
        self.grid: np.ndarray | None = None
        self.grid_history: list[dict[str, Any]] = []
        self.margin = "lsq" if self.params.lsq else "hard" if self.params.C is None else "soft"
        self.message = ""
        self.disagreement: float | None = None  # the fleet's largest gap before the last flood
        self._diag = 0.0
        self._held_units = 0  # held-out units of the whole fleet (BOUNDS), for folds_for_data
        self._box: tuple[float, float, float, float] | None = None
        self._h0, self._level = 0.0, 0
        self._allowed: np.ndarray | None = None  # level-0 nodes marked near data by some robot
        # the lsq model's rule 2: every candidate's near-data marks agreed so far (MARKS, chunk by chunk)
        self._near: np.ndarray | None = None
        self._chunk = 0
        self._mode = self.margin  # margin of the current ADMM phase
        self._left, self._phase_start = 0, 0
        self._sweep: SigmaSweep | None = None
        self._seed: np.ndarray | None = None  # the agreed seed (x, gamma) while the width test runs
        self.width_validation: list[dict[str, Any]] = []  # the width test's records (one width, two)
        self._sub: WarmADMM | None = None
        self._warm: np.ndarray | None = None  # first iterate of the next ADMM
        self._carry: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # its edges' (z, lambda)
        self._edges_out: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # last ADMM's edges
        # the last soft-margin hub duals (robot ids, u_l rows) on the current grid: the next soft solve's start.
        # A soft margin's duals travel far (multipliers at C = 1e3 against a penalty of 15): from zero, held-out
        # 4's pliers does not converge in 3000 rounds even when started at the exact optimum
        self._soft_duals: tuple[tuple[int, ...], np.ndarray] | None = None
        self._own: np.ndarray | None = None  # this robot's (x, gamma) entering the flood
        self._sub_converged = False
        # a soft answer solve with the exact end-game: "certified" when every robot certified its rows (the
        # stop is the exact optimum), "not certified" when the ADMM's own rule stopped it first; "" without
        self._endgame = ""
        self._ill_norm2 = 0.0  # the next hard ADMM's bound on |x|^2 (0: no test); in its frames at slot -3
        self._admm_rounds = 0
        self._capped = ""  # why the answer is not a converged solve ("" when it is)
        self._agreed = False
        self._best_norm2: float | None = None
        self._refinements = 0
        self._final: np.ndarray | None = None  # (x, gamma) agreed by the fleet
        self.phases: list[tuple[str, int]] = []  # (phase, first round), for the convergence plot
        self.residuals: list[float] = []  # per round: the ADMM residual (the largest in the sweep), else nan

    # -- vectors ------------------------------------------------------------------------------
    def _pad(self, x: np.ndarray, gamma: float, meta: float = 0.0) -> np.ndarray:
        v = np.zeros(self.dim)
        v[: len(x)] = x
        v[-2], v[-1] = gamma, meta
        return v

    def _unpad(self, v: np.ndarray) -> np.ndarray:
        """(x, gamma) on the current grid from a padded frame vector."""
        return np.append(v[: len(self.grid)], v[-2])

    def _mark(self, phase: str) -> None:
        self.phase, self._phase_start = phase, self.round
        self.phases.append((phase, self.round))

    def _counted(self, phase: str, values: np.ndarray, rounds: int | None = None) -> None:
        self._mark(phase)
        self._left = self._reach() if rounds is None else rounds
        self._values, self._flags = values, 0

    # -- entering phases ----------------------------------------------------------------------
    def _enter_bounds(self) -> None:
        v = np.zeros(self.dim)
        if len(self._points):
            lo, hi = self._points.min(axis=0), self._points.max(axis=0)
            v[:4] = (-lo[0], hi[0], -lo[1], hi[1])
        else:
            v[:4] = _NO_DATA
        if self._given.validates and self._given.sparse_units > 0:  # held-out units: one slot per id (< tally_slots)
            v[4 + self.robot_id] = float(np.max(self._units, initial=-1) + 1)
        self._counted(BOUNDS, v)

    def _enter_marks(self) -> None:
        """Chunk `_chunk` of this robot's near-data marks on every lsq candidate's full lattice (one frame's
        worth, dim floats; all seven candidates' ~1600-2500 nodes fit the default frame): a max-consensus."""
        own = lsq_near_marks(self._points, lsq_lattices(self.bounds, self._diag, self.params), self._diag, self.params)
        if self._near is None:
            self._near = np.zeros(len(own))
        part = own[self._chunk * self.dim : (self._chunk + 1) * self.dim]
        v = np.zeros(self.dim)
        v[: len(part)] = part
        self._counted(MARKS, v)

    def _finish_marks(self) -> str:
        start = self._chunk * self.dim
        end = min(len(self._near), start + self.dim)
        self._near[start:end] = self._values[: end - start]
        self._chunk += 1
        return "next chunk" if end < len(self._near) else "sweep sigma"

    def _enter_validate(self) -> None:
        self._sweep = self._new_sweep()
        self._mark(VALIDATE)
        self._values, self._flags = self._sweep.stacked(), 0

    def _new_sweep(self) -> SigmaSweep:
        share = self._share.with_data(self.neighbours, self._points, self._labels, None)
        models, records = lsq_models(self.bounds, self._diag, self.params, self._near) if self.params.lsq else (None, None)
        sweep = SigmaSweep(share, self._units, bounds=self.bounds, diag=self._diag, params=self.params, dim=self.dim,
                           models=models, gone=self.gone)
        sweep.reach = self._reach()
        sweep.lsq_records = records  # every lsq candidate, tried or not (`_choose_lsq`: no second lsq_models)
        return sweep

    def _enter_tally(self) -> None:
        self._counted(TALLY, self._sweep.tally_vector())

    def _enter_vote(self) -> None:
        """This robot's separability (hard margin) and its near-data marks on the level-0 lattice."""
        infeasible, own_norm2 = 0.0, 0.0
        if self.margin == "hard" and len(self._points):
            qp = MarginQP(self._features, self._labels, x_weight=1.0 / self._n_robots, prox_weight=0.0, C=None)
            try:
                x = qp.solve(np.zeros(qp.dim)).x
                with np.errstate(over="ignore", invalid="ignore"):
                    own_norm2 = float(x @ x)
                own_norm2 = own_norm2 if math.isfinite(own_norm2) else 0.0  # (frames carry finite numbers)
            except InfeasibleError:
                infeasible = 1.0
        v = self._pad(np.zeros(0), 0.0, infeasible)
        if self._tests_conditioning():  # (max-consensus) the warm start's slack on my data: a bound of the
            v[-3] = hinge_sum(self._features, self._labels, self._warm)  # soft objective; and my own hard
            v[-2] = own_norm2  # margin's |x|^2: the fleet's hard margin (more constraints) needs at least that
        coarse = lattice(self._box, self._h0, 0)
        if len(coarse) <= self.dim - 3:  # the cell of a node: within h0 / sqrt(2) of it
            radius = self.params.near_data * self.sigma + self._h0 / math.sqrt(2.0)
            v[: len(coarse)] = near_data_marks(self._points, coarse, radius)
        self._counted(VOTE, v)

    def _enter_admm(self) -> None:
        p, mode = self.params, self._mode
        if p.lsq:
            self._enter_lsq_fit()
            return
        sub_params = ADMMParams(
            rho=p.rho, relax=p.relax, tol=p.tol, diameter=p.diameter,
            max_rounds=p.hard_rounds if mode == "hard" else p.soft_rounds,
            certify=0.0,  # the nested runs keep the rule alone (their frames have no room for the guard)
            settled_rate=True,  # ... so its rate is read within one stretch of Anderson (admm.settled)
            # the exact end-game (agents/soft_endgame.py): soft answer solves, and hard ones with hard_endgame
            soft_polish=(mode == "soft" or p.hard_endgame) and self._endgame_fits(),
            hard_endgame=mode == "hard" and p.hard_endgame,
        )
        C = None if mode == "hard" else (p.C if p.C is not None else p.soft_C)
        self._sub = WarmADMM(
            self._share.with_data(self.neighbours, self._features, self._labels, C), sub_params, keep_trace=False,
            start=self._warm, edges=self._carry if p.warm_duals else None, hub_frames=p.hub_frames,
            # (the carried duals are soft_C's: a user's other C starts from zero)
            hub_duals=self._soft_duals if mode == "soft" and p.warm_duals and C == p.soft_C else None,
            gone=self._known_gone(),  # a soft margin weighs |x|^2 by 1 / (robots left)
        )
        self._carry = {}
        self._mark(ADMM)
        self._values, self._flags = self._sub_frame(), 0
        if mode == "hard":  # the bound rides in every frame of the phase: a restart re-derives the test from it
            self._values[-3] = self._ill_norm2

    def _known_gone(self) -> tuple[int, ...]:
        """The robots this robot knows dropped for good, for a sub-machine it builds now: the flooded list on a
        sparse graph; on a complete graph, where no list travels (every robot saw the drops itself), its own
        drops -- a sub-machine built after one runs the edge form among the survivors, weighed by this list."""
        return self.gone if self.floods_gone else tuple(sorted(self.dropped))

    def _enter_lsq_fit(self) -> None:
        """The lsq model's one fit: every row of every robot on the chosen level-0 lattice; on a complete graph
        from each robot's own fit, on a sparse one from the iterate and edge states of the same fit run in the
        sweep (`SigmaSweep.full_fit`: the edge form's rounds, benchmarks/results/lsq.md)."""
        p = self.params
        feats = self._basis.features(self._rows) if len(self._rows) else np.zeros((0, len(self.grid)))
        self._sub = WarmLSQ(
            self._share.with_data(self.neighbours, feats, self._targets, None),
            lsq_sub_params(p.lsq_lambda, rho=p.lsq_rho, relax=p.relax, tol=p.tol, max_rounds=p.soft_rounds,
                           diameter=p.diameter),
            lam=p.lsq_lambda, keep_trace=False, hub_frames=p.hub_frames,
            gone=self._known_gone(),  # lam / (robots left)
            start=self._warm, edges=self._carry,  # (None, {} but on a sparse graph: `_choose_lsq`)
        )
        self._carry = {}
        self._mark(ADMM)
        self._values, self._flags = self._sub_frame(), 0

    def _endgame_fits(self) -> bool:
        """True when an answer solve may run the exact end-game (AutoGridParams.soft_polish; hard ones
        also need hard_endgame): hub frames, and its payload fits between w and the frame's last three
        slots on this grid."""
        p = self.params
        return p.soft_polish and p.hub_frames and 2 * p.max_points + 1 + endgame_payload_size(len(self.grid) + 1) <= p.dim - 3

    def _sub_frame(self) -> np.ndarray:
        """The ADMM sub-machine's message as a frame: v padded, and in the hub form its w at
        [max_points : max_points + M] and [2 max_points] (room: params.hub_frames), then the soft
        end-game's payload from [2 max_points + 1] (`_endgame_fits`)."""
        msg, d = self._sub.outgoing().values, self._sub.dim
        out = self._pad(msg[: d - 1], msg[d - 1])
        if msg.size > d:
            mp = self.params.max_points
            out[mp : mp + d - 1], out[2 * mp] = msg[d : 2 * d - 1], msg[2 * d - 1]
            out[2 * mp + 1 : 2 * mp + 1 + msg.size - 2 * d] = msg[2 * d :]
        return out

    def _sub_message(self, v: np.ndarray) -> np.ndarray:
        """A neighbour's frame as the sub-machine's message (`_sub_frame` inverted)."""
        if self._sub.frame_dim == self._sub.dim:
            return self._unpad(v)
        mp, m = self.params.max_points, len(self.grid)
        extra = self._sub.frame_dim - 2 * self._sub.dim
        return np.concatenate([self._unpad(v), v[mp : mp + m], v[2 * mp : 2 * mp + 1 + extra]])

    def _enter_flood(self) -> None:
        v = self._own
        reach = self._reach()
        rounds = reach + 1 if reach > 0 else 0
        self._counted(FLOOD, self._pad(v[:-1], v[-1], float(self.robot_id)), rounds)

    def _enter_done(self) -> None:
        if self._agreed and self._mode == "soft" and self.params.C is None:
            self.margin = "soft"
            statuses = {h["status"] for h in self.grid_history}
            why = "; ".join(
                text for status, text in (
                    ("hard-infeasible", "a robot's own data not separable on the grid"),
                    ("hard-not-converged", f"its ADMM not converged within {self.params.hard_rounds} rounds "
                                           "(infeasible, or too slow to tell)"),
                    ("hard-ill-conditioned", "its solution ill-conditioned: |x|^2 past the bound of every hard "
                                             f"solution with multipliers <= {self.params.ill_multiplier:g} x soft_C"))
                if status in statuses)
            self.message = (
                "the hard margin was not reached within the budget of "
                f"{self.params.max_points} grid points / {self.params.max_refinements} refinements"
                f"{f' ({why})' if why else ''}: fell back to a soft margin (C = {self.params.soft_C:g})"
            )
        if self._capped:
            self.message = (self.message + "; " if self.message else "") + self._capped
        self._mark(DONE)
        self.finished = True
        x, gamma = self._final[:-1], self._final[-1]
        self._values, self._flags = self._pad(x, gamma, float(self.robot_id)), 0
        self.residual = 0.0 if self.disagreement is None else self.disagreement

    # -- finishing phases (each returns its outcome, the key into TRANSITIONS) ----------------
    def _finish_bounds(self) -> str:
        nx0, nx1, ny0, ny1 = (float(t) for t in self._values[:4])
        self.bounds = (-nx0, nx1, -ny0, ny1)
        x0, x1, y0, y1 = self.bounds
        self._diag = math.hypot(x1 - x0, y1 - y0)
        if self.params.validates and self._diag > 0:
            self._held_units = int(np.sum(self._values[4 : 4 + self.params.tally_slots]))
            self.params = folds_for_data(self._given, self._held_units)[0]
            return "near-data marks" if self.params.lsq else "sweep sigma"
        self.sigma, self.sigma_reason = scale_from_bounds(self.bounds, self.params)
        self._first_grid()
        return "least squares" if self.params.lsq else "sigma by rule"

    def _finish_validate(self) -> str:
        return "solved"

    def _finish_tally(self) -> str:
        sweep, self._sweep = self._sweep, None
        self.sigma_validation = sweep.records(self._values)
        if self.params.lsq:
            return self._choose_lsq(sweep)
        self.sigma, self.sigma_reason = choose_sigma(self.sigma_validation, self._diag, self.params)
        self.params, note = widths_for_data(self.params, self.sigma_validation)
        self.sigma_reason += folds_for_data(self._given, self._held_units)[1] + note
        self._first_grid()
        cand = next(i for i, r in enumerate(self.sigma_validation) if r["sigma"] == self.sigma)
        task = sweep.task(cand, 0)
        if self._start_grid is not None or not np.array_equal(task.basis.grid, self.grid):
            return "sigma chosen"
        # the same lattice: the fold-0 solve seeds the refinement (after a flood makes it common)
        self._own = task.sub.values
        self._edges_out = {}  # its duals belong to another problem (soft, 4/5 of the data): not carried
        self._soft_duals = hub_duals(task.sub)  # ... except into a soft solve: its hub duals (the same C)
        return "seed"

    def _choose_lsq(self, sweep: SigmaSweep) -> str:
        """Rule 2's choice from the agreed tally; the final fit's grid is the chosen candidate's (its kept nodes),
        or a given start grid (as rule 1's)."""
        scores = {r["divisor"]: r for r in sweep.records(self._values)}
        self.sigma_validation = [{**r, **scores.get(r["divisor"], {"score": None})} for r in sweep.lsq_records]
        self.sigma, self.sigma_reason = choose_lsq_sigma(self.sigma_validation, self._diag, self.params)
        cand, model = next((i, m) for i, m in enumerate(sweep.models) if m.sigma == self.sigma)
        self._box, self._h0 = model.box, self.params.coarse_spacing * self.sigma
        self._set_grid(model.basis.grid if self._start_grid is None else self._start_grid.copy())
        self._mode = self.margin
        warm = sweep.full_fit(cand) if self._start_grid is None else None
        if warm is not None:  # a sparse graph: the final fit starts where the sweep's fit of all rows ended
            self._warm, self._carry = warm
        return "least squares"

    def _enter_seed(self) -> None:
        """Flood the lowest id's fold-0 vector; max-consensus of the near-data marks beside it."""
        v, m = self._own, len(self.grid)
        out = self._pad(v[:-1], v[-1], float(self.robot_id))
        if 2 * m + 3 <= self.dim:
            radius = self.params.near_data * self.sigma + self._h0 / math.sqrt(2.0)
            out[m : 2 * m] = near_data_marks(self._points, self.grid, radius)
        self._counted(SEED, out)

    def _finish_seed(self) -> str:
        m = len(self.grid)
        self._allowed = self._values[m : 2 * m] > 0 if 2 * m + 3 <= self.dim else None
        seed = self._unpad(self._values)
        if self._width_test_applies() and self.params.max_refinements >= 1:
            self._seed = seed
            self._sweep = self._new_width_sweep()
            if self._sweep is not None:
                return "width test"
            self._seed = None
        if self.params.max_refinements < 1 or not self._move_to_refined(seed[:-1], float(seed[-1])):
            self._warm = seed
            return "not refined"
        return "refined"

    def _width_test_applies(self) -> bool:
        return self.params.narrow_by_holdout and self.params.narrow_ratio > 1 and bool(self.params.width_blocks())

    def _width_models(self) -> list[SweepModel] | None:
        """The width test's two models (one width: refined points at sigma; two: at sigma /
        narrow_ratio), each the seed's grid refined from the agreed seed, the seed carried on as
        the common first iterate; None when either refinement adds nothing."""
        seed, models = self._seed, []
        c = self._basis.c_from_x(seed[:-1])
        for ratio in (1.0, self.params.narrow_ratio):
            params = dataclasses.replace(self.params, narrow_ratio=ratio)
            grid, _ = refine_grid(self.grid, self._basis, c, float(seed[-1]), self._box, self._h0, self._level,
                                  params, self._allowed)
            if len(grid) == len(self.grid):
                return None
            basis = GridBasis(grid, self.sigma, widths=grid_widths(grid, self._box, self._h0, self.sigma, params,
                                                                    self._start_grid))
            start = carry_vector(seed, superset_maps(self._basis, basis)[0])
            models.append(SweepModel(ratio, self.sigma, self._box, basis, self.params.max_points, start))
        return models

    def _new_width_sweep(self) -> SigmaSweep | None:
        models = self._width_models()
        if models is None:
            return None
        share = self._share.with_data(self.neighbours, self._points, self._labels, None)
        sweep = SigmaSweep(share, self._units, bounds=self.bounds, diag=self._diag, params=self.params, dim=self.dim,
                           models=models, gone=self.gone)
        sweep.reach = self._reach()
        return sweep

    def _enter_widths(self) -> None:
        self._mark(WIDTHS)
        self._values, self._flags = self._sweep.stacked(), 0

    def _finish_widths(self) -> str:
        return "solved"

    def _enter_wtally(self) -> None:
        self._counted(WTALLY, self._sweep.tally_vector())

    def _finish_wtally(self) -> str:
        sweep, self._sweep = self._sweep, None
        self.width_validation = sweep.records(self._values)
        self.params, note = choose_widths(self.params, self.width_validation)
        self.sigma_reason += note
        seed, self._seed = self._seed, None
        self._move_to_refined(seed[:-1], float(seed[-1]))
        return "width chosen"

    def _finish_vote(self) -> str:
        coarse = lattice(self._box, self._h0, 0)
        if self._allowed is None and len(coarse) <= self.dim - 3:
            self._allowed = self._values[: len(coarse)] > 0
        if self.margin == "soft":
            return "soft"
        if self._values[-1] > 0:
            self._note(status="hard-infeasible", detected_by="vote (a robot's own data not separable)", rounds=self.params.diameter)
            self._mode = "soft"
            return "inseparable"
        self._ill_norm2 = 0.0
        if self._tests_conditioning():
            self._ill_norm2 = bound = ill_conditioned_norm2(self._warm, float(self._values[-3]), self._n_robots,
                                                            self.params)
            if self._values[-2] > bound:  # known before any ADMM round: some robot's own hard margin is past it
                self._note(status="hard-ill-conditioned", rounds=self.params.diameter, bound_norm2=bound,
                           detected_by=f"vote (a robot's own hard margin has |x|^2 = {self._values[-2]:.6g} > "
                                       f"{bound:.6g}: the fleet's, if any, needs a multiplier > "
                                       f"{self.params.ill_multiplier:g} x soft_C)")
                self._mode = "soft"
                return "ill-conditioned"
        self._mode = "hard"
        return "separable"

    def _tests_conditioning(self) -> bool:
        """The hard margin's conditioning is tested when there is a warm start (a function every robot
        holds, whose soft objective bounds the soft margin's) and the test is on."""
        return self.margin == "hard" and self._warm is not None and self.params.ill_multiplier > 0

    def _finish_admm(self) -> str:
        sub, rounds = self._sub, self.round - self._phase_start
        if self._ill_due():
            # some robot's iterate passed the bound: a hard solution there has a multiplier > K soft_C
            # (ill_conditioned_norm2); the fleet takes the soft margin it would fall back to anyway
            bound, k = float(self._values[-3]), self.params.ill_multiplier
            passed = self._alarm_base() - float(self._values[-1]) - self._phase_start
            self._note(status="hard-ill-conditioned", rounds=rounds, bound_norm2=bound,
                       detected_by=f"a robot's ADMM iterate had |x|^2 > {bound:.6g} in round {passed:.0f} of the "
                                   f"hard margin: a hard solution, if any, needs a multiplier > {k:g} x soft_C")
            self._mode = "soft"
            return "ill-conditioned"
        converged = sub.converged or not sub.neighbours
        if not converged and self._mode == "hard":
            # the rule: a hard margin that does not converge within hard_rounds is treated as infeasible --
            # but it may be feasible and only slow (held-out 4's pliers: |x|^2 3e7), so it is noted as such
            self._note(status="hard-not-converged", detected_by=f"ADMM not converged in {rounds} rounds", rounds=rounds)
            if self._best_norm2 is not None:  # a subset grid was separable: a cap, not infeasibility
                self._capped = f"the hard margin stopped at its round cap ({rounds}) on a refined grid"
            self._mode = "soft"
            return "hard cap"
        self._sub_converged, self._admm_rounds = converged, rounds
        pol = sub._polish if sub.params.soft_polish else None
        self._endgame = "" if pol is None else "certified" if pol.result is not None else "not certified"
        self._own = sub.values
        self._edges_out = {j: (e.z.copy(), e.lam.copy()) for j, e in sub._edges.items()}
        if self._mode == "soft":
            self._soft_duals = hub_duals(sub) or self._soft_duals
        self._sub = None
        return "solved" if converged else "stopped at its cap"

    def _finish_flood(self) -> str:
        v = self._values
        self.disagreement = float(v[-3])
        agreed = self._unpad(v)
        model = "least-squares" if self.params.lsq else f"{self._mode}-margin"
        status = f"{model} solved" if self._sub_converged else f"{model} round cap"
        endgame = {"endgame": self._endgame} if self._endgame else {}
        if not self.disagreement <= self.params.tol:
            self._note(status=status, rounds=self._admm_rounds, disagreement_before_flood=self.disagreement, **endgame)
            self._final, self._agreed = self._own, False
            self._capped = (
                f"the robots disagree by {self.disagreement:.3g} (largest relative gap to a neighbour) "
                f"> tol {self.params.tol:g}: not flooded, each robot keeps its own function"
            )
            return "disagree"
        x, gamma = agreed[:-1], float(agreed[-1])
        norm2 = float(x @ x)
        self._note(status=status, rounds=self._admm_rounds, norm2=norm2, agreed_from=int(v[-1]),
                   disagreement_before_flood=self.disagreement, **endgame)
        self._final, self._agreed = agreed, True
        if not self._sub_converged:
            what = "least-squares fit" if self.params.lsq else f"{self._mode} margin"
            self._capped = f"the {what} stopped at its round cap ({self._admm_rounds} rounds)"
            return "final"
        return "refined" if not self.params.lsq and self._refine(x, gamma, norm2) else "final"

    def _refine(self, x: np.ndarray, gamma: float, norm2: float) -> bool:
        """Move to the refined grid with warm starts; False when refining no longer helps."""
        helps = True
        if self._mode == "hard":
            self.margin = "hard"
            if self._best_norm2 is not None and norm2 > (1.0 - self.params.improve_tol) * self._best_norm2:
                helps = False
            self._best_norm2 = norm2 if self._best_norm2 is None else min(norm2, self._best_norm2)
        if not helps or self._refinements >= self.params.max_refinements:
            return False
        min_new = max(1, math.ceil(self.params.min_growth * len(self.grid))) if self._mode == "hard" else 1
        if not self._move_to_refined(x, gamma, min_new):
            return False
        if self._mode == "soft" and self.params.C is None:
            self.margin = "hard"  # the refined grid may separate the data: try the hard margin again
        self._mode = self.margin
        return True

    def _move_to_refined(self, x: np.ndarray, gamma: float, min_new: int = 1) -> bool:
        """The refined grid, the function (x, gamma) and the last ADMM's edges carried onto it."""
        c = self._basis.c_from_x(x)
        new_grid, level = refine_grid(self.grid, self._basis, c, gamma, self._box, self._h0, self._level,
                                      self.params, self._allowed, min_new)
        if len(new_grid) == len(self.grid):
            return False
        old = self._basis
        self._level, self._refinements = level, self._refinements + 1
        self._set_grid(new_grid)
        P, _ = superset_maps(old, self._basis)
        self._warm = carry_vector(np.append(x, gamma), P)
        self._carry = carry_edges({j: _EdgeView(z, lam) for j, (z, lam) in self._edges_out.items()}, old, self._basis)
        if self._soft_duals is not None:
            self._soft_duals = carry_hub_duals(self._soft_duals, old, self._basis)
        return True

    _ENTER = {MARKS: _enter_marks, VALIDATE: _enter_validate, TALLY: _enter_tally, SEED: _enter_seed, WIDTHS: _enter_widths,
              WTALLY: _enter_wtally, VOTE: _enter_vote, ADMM: _enter_admm, FLOOD: _enter_flood, DONE: _enter_done}

    _FINISH = {BOUNDS: _finish_bounds, MARKS: _finish_marks, VALIDATE: _finish_validate, TALLY: _finish_tally, SEED: _finish_seed,
               WIDTHS: _finish_widths, WTALLY: _finish_wtally, VOTE: _finish_vote,
               ADMM: _finish_admm, FLOOD: _finish_flood}

    # -- grids ------------------------------------------------------------------------------------
    def _first_grid(self) -> None:
        """The run on all data at the agreed sigma: the level-0 lattice (or the start grid)."""
        self._box, self._h0, grid = coarse_lattice(self.bounds, self.sigma, self.params.coarse_spacing, self.params.max_points)
        if self._start_grid is not None:
            grid = self._start_grid.copy()
        self._set_grid(grid)
        self._mode = self.margin
        self._soft_duals = None  # (a new first grid: duals of another grid do not apply)

    def _set_grid(self, grid: np.ndarray) -> None:
        self.grid = grid
        widths = grid_widths(grid, self._box, self._h0, self.sigma, self.params, self._start_grid)
        self._basis = GridBasis(grid, self.sigma, widths=widths)
        self._features = self._basis.features(self._points) if len(self._points) else np.zeros((0, len(grid)))

    def _note(self, **fields: Any) -> None:
        self.grid_history.append(
            {"size": len(self.grid), "level": self._level, "margin": self._mode, "grid": self.grid.tolist(),
             "rank": self._basis.rank, **fields}
        )

    def _ended(self) -> bool:
        if EXCHANGE[self.phase] in ("max", "flood"):
            return self._left == 0
        if self.phase == ADMM and self._ill_due():
            return True
        return (self._sweep if self.phase in (VALIDATE, WIDTHS) else self._sub).finished

    def _settle(self) -> None:
        """Leave every phase that is complete (also length-0 phases: D = 0, a lone robot)."""
        while not self.finished and self._ended():
            outcome = self._FINISH[self.phase](self)
            self._ENTER[TRANSITIONS[(self.phase, outcome)]](self)

    # -- the round ----------------------------------------------------------------------------
    def advance(self) -> StateUpdate:
        theirs, their_flags = self._take_round()
        mine, flags, kind = self._values, 0, EXCHANGE[self.phase]
        # (the sub-machines gather the same lists from the updates they are handed)
        their_gone = self._inbox.gone.get(self.round, {}) if self.floods_gone else {}
        if self.floods_gone and self._gather_gone() and self._sweep is not None:
            self._sweep.reach = self._reach()
        if kind == "max":
            new = np.max(np.vstack([mine, *theirs.values()]), axis=0)
            self._left -= 1
        elif kind == "flood":
            new = self._flood_round(mine, theirs)
        elif kind == "sweep":
            self._sweep.advance(theirs, their_gone)
            self.residual = self._sweep.residual
            new = self._sweep.stacked()
        else:  # ADMM: hand the neighbours' exact round values to the sub-machine
            sub = self._sub
            for j, v in theirs.items():
                sub.receive(StateUpdate(j, sub.round, self._sub_message(v), int(their_flags.get(j, 0)), None,
                                        gone=their_gone.get(j, ())))
            sub.advance()
            self.residual = sub.residual
            new, flags = self._sub_frame(), sub.outgoing().flags
            if mine[-3] > 0:  # a hard margin under the conditioning test: carry the bound, spread the alarm
                new[-3], new[-1] = mine[-3], self._alarm(mine, theirs, new)
        self._prev_values, self._prev_flags = mine, self._flags
        self._values, self._flags = new, flags
        self.round += 1
        self._inbox.forget_before(self.round)
        self.residuals.append(self.residual if kind in ("sweep", "admm") else math.nan)
        self._settle()
        if not self.finished and self.round >= self._round_cap:
            self.finished = True
            self.message = f"stopped at the round cap {self._round_cap} in phase {self.phase}"
        self._record()
        return self.outgoing()

    def _alarm_base(self) -> float:
        """Slot -1 of a hard ADMM's frames holds base - (the round some robot's iterate passed the bound):
        positive, larger for earlier rounds, so a max-consensus keeps the earliest; 0: not passed."""
        return float(self.params.max_total_rounds + 1)

    def _alarm(self, mine: np.ndarray, theirs: dict[int, np.ndarray], new: np.ndarray) -> float:
        """The earliest round any robot's iterate is known here to have passed the bound (slot -1, max of
        this robot's and its neighbours' last frames), or this round if this robot's new iterate passes it."""
        heard = max(float(v[-1]) for v in (mine, *theirs.values()))
        x = new[: len(self.grid)]
        with np.errstate(over="ignore", invalid="ignore"):  # (a diverging iterate passes the bound, quietly)
            norm2 = float(x @ x)
        if norm2 > float(mine[-3]):
            heard = max(heard, self._alarm_base() - self.round)
        return heard

    def _ill_due(self) -> bool:
        """True in the round every robot acts on the alarm: D + 1 rounds after the earliest round r* any
        iterate passed the bound. By then the max-consensus has brought r* to every robot (D >= the graph's
        diameter), and no robot can act earlier: it would need an earlier r than r*. The same round
        everywhere, from the frame alone (a restart re-derives it)."""
        v = self._values
        if self.phase != ADMM or not v[-3] > 0 or not v[-1] > 0:
            return False
        return self.round >= self._alarm_base() - float(v[-1]) + 1 + self._reach()

    def _reach(self) -> int:
        """Hops a max-consensus, the flood or the alarm must cover: D, or after a loss (`gone`, sparse
        graphs) the bound on the survivors' graph's diameter the sub-machines' stop waits for -- a ring
        that lost a robot is a path wider than D. The same on every robot once the news reached it (see
        docs/algorithm.md, "autogrid after a loss", for a phase entered before it did)."""
        d = self.params.diameter
        if not self.gone:
            return d
        return max(d, min(AUTOGRID_MAX_DIAMETER, self._n_robots - len(self.gone) - 1))

    def _flood_round(self, mine: np.ndarray, theirs: dict[int, np.ndarray]) -> np.ndarray:
        """The lowest id's vector wins; slot -3 carries the largest gap, measured in round 1
        from the neighbours' own final values (they enter the flood with them)."""
        new = min([mine, *theirs.values()], key=lambda v: v[-1]).copy()
        gap = max(float(v[-3]) for v in [mine, *theirs.values()])
        if self.phase == FLOOD and self.round == self._phase_start and theirs:
            own = self._unpad(mine)
            gap = max(gap, relative_gap(own, np.array([self._unpad(v) for v in theirs.values()])))
        new[-3] = gap
        if self.phase == SEED and self._allowed is None:  # the near-data marks ride beside the seed
            m = len(self.grid)
            if 2 * m + 3 <= self.dim:
                new[m : 2 * m] = np.max(np.vstack([v[m : 2 * m] for v in [mine, *theirs.values()]]), axis=0)
        self._left -= 1
        return new

    def drop_neighbour(self, j: int) -> None:
        super().drop_neighbour(j)
        for machine in (self._sub, self._sweep):
            if machine is not None:
                machine.drop_neighbour(j)

    def _forget_edge(self, j: int) -> None:
        self._edges_out.pop(j, None)
        self._carry.pop(j, None)

    def _gone_changed(self) -> None:
        """Nothing to rebuild here: its sub-machines reweigh and widen their stop themselves (they are handed
        the lists), and its counted phases, the flood and the alarm read `_reach()` when they begin (a phase
        begun before the news arrived keeps its length: docs/algorithm.md, autogrid after a loss)."""

    # -- what the fleet learned ---------------------------------------------------------------
    @property
    def converged(self) -> bool:
        """Done, every robot agreed within tol before the flood, and the answer's ADMM stopped
        by its stopping rule (not by a round cap)."""
        return self.phase == DONE and self._agreed and not self._capped

    def divergence(self) -> str | None:
        """Only the functions being solved can diverge (the sweep's tasks or the current ADMM);
        bounds, tallies, flags and the flood are bookkeeping of finite agreed numbers."""
        if self._sweep is not None:
            for t in self._sweep.tasks:
                why = t.sub.divergence()
                if why is not None:
                    return f"sigma sweep (diag/{t.divisor:g}, fold {t.fold}): {why}"
            return None
        return None if self._sub is None else self._sub.divergence()

    def function(self) -> tuple[np.ndarray, np.ndarray, float]:
        """(grid, c, gamma) of the agreed function (after the run) or of the current iterate."""
        if self.phase == DONE:
            v = self._final
        elif self.grid is not None and self.phase in (ADMM, FLOOD):
            v = self._unpad(self._values)
        else:
            raise RuntimeError("no function yet: the fleet has not chosen a grid")
        return self.grid.copy(), self._basis.c_from_x(v[:-1]), float(v[-1])

    def decision(self, points: np.ndarray) -> np.ndarray:
        grid, c, gamma = self.function()
        return self._basis.decision(points, c, gamma)

    def status(self) -> dict[str, Any]:
        m = None if self.grid is None else len(self.grid)
        return {**super().status(), "phase": self.phase, "grid_points": m, "margin": self.margin}

    def result(self) -> dict[str, Any]:
        out = {
            "id": self.robot_id, "algorithm": self.algorithm, "rounds": self.round,
            "converged": self.converged, "residual": self.residual, "neighbours": list(self.neighbours),
            "dropped": list(self.dropped), "phase": self.phase,
            "bounds": None if self.bounds is None else list(self.bounds),
            "sigma": self.sigma, "sigma_reason": self.sigma_reason,
            "sigma_validation": [dict(r) for r in self.sigma_validation],
            "width_validation": [dict(r) for r in self.width_validation],
            "margin": self.margin, "message": self.message,
            "disagreement_before_flood": self.disagreement, "agreed": self._agreed,
            "grid_history": [dict(h) for h in self.grid_history],
            "phases": [[p, r] for p, r in self.phases],
            "residuals": [None if not math.isfinite(r) else r for r in self.residuals],
        }
        if self.params.lsq:  # (an SVM robot's row is as it was: no model key)
            out.update(model="lsq", lsq_lambda=self.params.lsq_lambda)
        if self.phase == DONE:
            grid, c, gamma = self.function()
            out.update(grid=grid.tolist(), x=self._final[:-1].tolist(), c=c.tolist(), gamma=gamma,
                       grid_rank=self._basis.rank)
            if self._basis.widths is not None:  # the kernel width of every grid point (two widths)
                out["widths"] = self._basis.widths.tolist()
        return out

    # -- checkpoint (agents/autogrid_state.py) --------------------------------------------------
    def _save_state(self) -> dict[str, Any]:
        return save_state(self)

    def _load_state(self, state: dict[str, Any]) -> None:
        load_state(self, state)

    def restore(self, state: dict[str, Any]) -> None:
        super().restore(state)
        # RoundCore.restore set values and flags before _load_state; rebuilding overwrote them
        from agents.rounds import from_bytes

        self._values = from_bytes(state["values"])
        self._flags = int(state["flags"])
        self.finished = bool(state["finished"])
        self.trace = {}
        self._record()


class _EdgeView:
    """(z, lambda) of an edge of a finished ADMM, in the shape `carry_edges` reads."""

    def __init__(self, z: np.ndarray, lam: np.ndarray) -> None:
        self.z, self.lam = z, lam
