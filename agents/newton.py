"""Distributed primal-dual interior-point method (`--algorithm newton`), one robot's state machine.

The fixed-grid SVM in the preconditioned variable v = (x, gamma) (kernel.py, problem.py):

    min 1/2 |x|^2 (+ C sum xi)   s.t.  a_i' v (+ xi_i) >= 1 for every point i of every robot  (xi >= 0)

with a_i = theta_i [phi_i', 1] (problem.margin_rows). Every robot holds the same v, bit for bit.
Its own points' slacks s_i = a_i'v (+ xi_i) - 1, multipliers mu_i (and, with a soft margin, xi_i
and their multipliers nu_i) never leave it. Eliminating them from the Newton system of the
perturbed KKT conditions (complementarity = centering * m, m the fleet's mean s*mu) leaves one
(M+1)-square system that needs only sums over robots:

    (P + sum_l H_l) dv = -P v + centering * m * sum_l u_l - sum_l g_l - alpha * (sum_l H_l) dv_prev

    H_l = A_l' diag(w~) A_l,  u_l = A_l' kappa,  g_l = A_l' (w~ r - c0)      (per-point weights below)

P = diag(1, .., 1, 0). The last term is why one reduction per direction suffices: the robot's
contribution is taken at the iterate *before* the fleet's step alpha (the minimum of every
robot's fraction-to-boundary step along dv_prev), and the step is applied to v after the
reduction, linearly. The primal step must be common (v and every robot's slacks): a robot whose
own step was longer than the fleet's moves its slacks back to the fleet's step and the sums are
taken again (a re-sync: the reduction also carries -alpha_l, so everyone knows whether one is
needed). Own slack steps let the residuals A v - 1 - s grow and the multipliers diverge on large
fleets (32 robots: "infeasible" at iteration 15 on a feasible problem). The multipliers keep
their own dual steps. Per reduction the fleet sums [alpha, -alpha (min), #pairs, s'mu, triu(H), g,
u, A'mu, sum mu] (5 + (M+1)(M+2)/2 + 3(M+1) floats).

Fixed rule, no tuning: tau 0.99, s = mu = 1 (xi = nu = 1) and v = 0 at the start; centering
(1 - alpha)^2 of the last step clipped to [0.1, 0.3]; stop when the fleet-wide mean
complementarity m < 1e-10 and the last step moved v by at most 1e-9 relative, values every robot
holds in the same round, so all stop together. After a full step with m < 1e-4 a robot lowers its
multipliers to at most 10x the step's target (RECENTER_*: a nearly active margin otherwise stalls
the fleet 2.3e-6 off the optimum). Infeasible only with a certificate: y = mu/sum(mu)
shows every separating v has |v| >= sum(mu)/|A'mu|; above 1e8 the run stops as infeasible.
The sums travel by the exact all-reduce of `agents/allreduce.py`. docs/newton.md has the why.

No I/O, no clock: frames in (`receive`), frames out (`outgoing`, `advance`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from agents.allreduce import SCHEDULES, AllReduce, ReducePlan, frame_slots
from agents.problem import INFEASIBLE_ADVICE, margin_rows
from agents.params import check_counts, check_positive, params_from
from agents.rounds import RobotShare, RoundCore, from_bytes, to_bytes

@dataclass(frozen=True)
class NewtonParams:
    """The fixed interior-point rule (the same on every robot; defaults are the tested rule)."""

    centering: float = 0.3  # the centering at the start and after a short step (the largest used)
    min_centering: float = 0.1  # the centering after a full step (sigma = (1 - alpha)^2 clipped to these two)
    tau: float = 0.99
    stop_mu: float = 1e-10  # stop when the fleet's mean complementarity is below
    stop_step: float = 1e-9  # ... and the last step moved no entry of v by more than this x max(1, |v|max)
    max_iterations: int = 100  # not converged after this many: infeasible (hard margin) or stalled
    max_rounds: int = 5000
    allreduce: str = "gather"  # or "tree" (agents/allreduce.py): gather takes D rounds, tree 2h

    def __post_init__(self) -> None:
        if self.allreduce not in SCHEDULES:
            raise ValueError(f"allreduce must be one of {', '.join(SCHEDULES)}, got {self.allreduce!r}")
        if not 0 < self.centering < 1:
            raise ValueError(f"centering must be in (0, 1), got {self.centering}")
        if not 0 < self.min_centering <= self.centering:
            raise ValueError(f"min_centering must be in (0, centering], got {self.min_centering}")
        if not 0 < self.tau < 1:
            raise ValueError(f"tau must be in (0, 1), got {self.tau}")
        check_positive(self, "stop_mu")
        check_positive(self, "stop_step")
        check_counts(self, "max_iterations", "max_rounds")

    @classmethod
    def from_params(cls, params: Mapping[str, Any]) -> NewtonParams:
        """From a fleet file's ``params``: exactly this class's fields; any other key is an
        error naming it."""
        return params_from(cls, params, "newton")


#: leading entries of a contribution that the all-reduce combines by minimum: the robot's primal
#: step and its negation (the fleet's min and max step)
_N_MIN = 2


def payload_size(dim: int) -> int:
    """Floats of one robot's contribution for (x, gamma) of length dim: alpha, -alpha, #pairs, s'mu,
    triu(H), g, u, A'mu, sum mu."""
    return _N_MIN + 2 + dim * (dim + 1) // 2 + 3 * dim + 1


def frame_size(dim: int, graph: Mapping[int, Sequence[int]], params: NewtonParams) -> int:
    """Floats per frame: contributions per frame (the schedule's slots) times payload_size."""
    return frame_slots(graph, params.allreduce) * payload_size(dim)


#: the Farkas-type certificate: with y = mu / sum(mu) >= 0, every (x, gamma) that separates the
#: data (A v >= 1) has 1 <= y'A v <= |A'y| |v|, so |v| >= 1 / |A'y|. Once that bound exceeds this
#: radius the run stops as infeasible: no separating function of a norm below it exists. A
#: feasible problem can never trip it (the bound never exceeds |v*|; the optimum here is |v*| < 1e3
#: on every built-in scenario, 5e4 on the worst near-infeasible one measured)
INFEASIBLE_RADIUS = 1e8

#: after a full step of the fleet and once m is below RECENTER_BELOW, a robot lowers every
#: multiplier whose pair lies more than RECENTER_FACTOR above the step's target onto that bound:
#: mu = min(mu, 10 centering*m / s) (nu likewise with xi). Why: a margin nearly but not quite active
#: at the optimum (slack 1.7e-5 on 48 robots, bean, seed 1) otherwise keeps s and mu halving
#: together (Newton splits s*mu -> target between ds/s and dmu/mu) while m falls 5-10x per step;
#: its mu stays ~100x above m/s, pulls v off the optimum, and the active margins' slacks reach the
#: rounding floor of a'v - 1 (~1e-14, m ~ 1e-12) before it resolves: 2.3e-6 off at the stop, with
#: exactly rounded (fsum) sums too (1.9e-6) and on one robot holding all points (3.5e-6). Lowered,
#: its weight mu/s stops pulling v: 3.9e-7 (one robot: 1.1e-7). Only the robot's own multipliers
#: move (never sent); v, the slacks and the common step do not. Measured alternatives: always on
#: fools the stop rule (m falls with no progress: 1.3 off "converged"); factor 1 resolves this case
#: better (6.1e-8) but stalls three ellipse fleets 5e-6..4e-5 off (an active margin still on its
#: way down lost its weight); factor 100: 8.5e-7.
RECENTER_BELOW = 1e-4
RECENTER_FACTOR = 10.0

#: m beyond this (or not finite) with no certificate: the steps broke down numerically
_BREAKDOWN_MU = 1e12

#: the alpha a robot reports when its own numbers broke down (the fleet's min then says so)
_BROKEN = -1.0


def _max_step(x: np.ndarray, dx: np.ndarray) -> float:
    """Largest t with x + t dx >= 0 (inf when dx >= 0)."""
    neg = dx < 0
    return float(np.min(-x[neg] / dx[neg])) if neg.any() else math.inf


def _solve_equilibrated(matrix: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Solve the Newton system after symmetric diagonal scaling (D M D, D = diag(M)^-1/2).

    Near the end the weights mu/s of the active margins reach 1e20 and more while P's are 1; the
    scaling keeps the small directions from drowning (64 robots, bean, seed 2: 4.3e-7 instead of
    2.0e-6 at the stop). A matrix singular to working precision is solved by least squares (the
    same bits on every robot) rather than ending the run.
    """
    d = 1.0 / np.sqrt(np.diag(matrix))
    scaled, b = d[:, None] * matrix * d[None, :], d * rhs
    try:
        return d * np.linalg.solve(scaled, b)
    except np.linalg.LinAlgError:
        return d * np.linalg.lstsq(scaled, b, rcond=None)[0]


class DistributedNewton(RoundCore):
    """One robot's distributed interior-point method; drive it with receive / ready / advance."""

    algorithm = "newton"

    def __init__(
        self, share: RobotShare, params: NewtonParams, *, graph: Mapping[int, Sequence[int]], keep_trace: bool = True
    ) -> None:
        robot_id, n = share.robot_id, share.dim
        plan = ReducePlan.build(graph, robot_id, params.allreduce)
        super().__init__(
            robot_id, share.neighbours, plan.slots * payload_size(n), diameter=0, round_cap=params.max_rounds,
            keep_trace=keep_trace,
        )
        features, labels, C = share.features, share.labels, share.C
        if tuple(sorted(graph.get(robot_id, ()))) != self.neighbours:
            raise ValueError(f"robot {robot_id}: neighbours {self.neighbours} differ from the graph's {graph.get(robot_id)}")
        self.params = params
        self.n = n
        self._C = None if C is None else float(C)
        self._rows = margin_rows(features, labels)
        k = len(self._rows)
        self._P = np.eye(n)
        self._P[-1, -1] = 0.0
        self._triu = np.triu_indices(n)
        self.plan = plan
        self._reduce = AllReduce(plan, payload_size(n), n_min=_N_MIN)
        self._v = np.zeros(n)
        self._dv = np.zeros(n)
        self._alpha = 1.0  # own (tentative) primal step along dv (none taken yet)
        self._s = np.ones(k)
        self._mu = np.ones(k)
        self._xi = np.ones(k if self._C is not None else 0)
        self._nu = np.ones(k if self._C is not None else 0)
        # the primal point before the tentative step and the direction: a re-sync moves from here
        self._s0, self._ds = self._s.copy(), np.zeros(k)
        self._xi0, self._dxi = self._xi.copy(), np.zeros(len(self._xi))
        self._last_step = 0.0  # the fleet's last primal step (0: none yet, full centering)
        self._moved = 0.0  # how far v moved along the last direction before a re-sync
        self.iterations = 0
        self.resyncs = 0
        self.mean_complementarity = math.inf
        self.separation_bound = 0.0  # no separating (x, gamma) has a norm below this (certificate)
        self._status = "running"  # running | converged | failed
        self.message = ""
        self._values = self._reduce.begin(self._contribution())
        self._record()

    # -- what the shells and the launcher read ------------------------------------------------
    @property
    def converged(self) -> bool:
        """Stopped by the stopping rule (not by the round cap, a failure or a lost robot)."""
        return self.finished and self._status == "converged"

    @property
    def values(self) -> np.ndarray:
        """The current (x, gamma) (the frames carry the reduction's payload instead)."""
        return self._v.copy()

    def status(self) -> dict[str, Any]:
        return {
            **super().status(),
            "iterations": self.iterations,
            "resyncs": self.resyncs,
            "mean_complementarity": self.mean_complementarity,
            "message": self._message(),
        }

    def _message(self) -> str:
        if self.finished and self._status == "running":  # stopped by RoundCore's round cap
            return (
                f"round cap {self.params.max_rounds} reached after {self.iterations} interior-point iterations "
                f"(mean s*mu {self.mean_complementarity:.1e}, the stop needs {self.params.stop_mu:g})"
            )
        return self.message

    def result(self) -> dict[str, Any]:
        res = super().result()
        res.update(
            x=self._v[:-1].tolist(),
            gamma=float(self._v[-1]),
            iterations=self.iterations,
            resyncs=self.resyncs,
            mean_complementarity=self.mean_complementarity,
            message=self._message(),
            # one publication per round (round 0 included); retransmissions and the piggybacked
            # previous round are the shell's, and frame overhead is not counted
            frame_floats=self.dim,
            payload_bytes_sent=8 * self.dim * (self.round + 1),
            allreduce=self.plan.describe(),
        )
        return res

    # -- one round ----------------------------------------------------------------------------
    def _step(self, mine: np.ndarray, theirs: dict[int, np.ndarray]) -> tuple[np.ndarray, bool]:
        frame = self._reduce.step(theirs)
        if not self._reduce.done:
            return frame, False
        total = self._reduce.total
        assert total is not None
        n, nh = self.n, len(self._triu[0])
        alpha, alpha_max = float(total[0]), -float(total[1])
        pairs, comp = float(total[2]), float(total[3])
        step = alpha * self._dv
        self._v = self._v + step
        m = comp / pairs if pairs > 0 else 0.0
        if alpha < 0:
            return self._fail(
                f"interior-point iteration {self.iterations}: a robot's slacks underflowed (mean s*mu {m:.1e}): "
                + self._breakdown()
            )
        if alpha != alpha_max:
            # the robots' own steps differed: their sums were taken at slacks that do not match
            # the fleet's step alpha. Every robot moves its primal point by alpha instead and the
            # sums are taken again (one more reduction, no new direction): the primal step stays
            # common, which is what keeps the residuals A v - 1 - s shrinking by (1 - alpha)
            self._s = self._s0 + alpha * self._ds
            self._xi = self._xi0 + alpha * self._dxi
            self._dv = np.zeros(n)
            self._alpha = 1.0
            self._last_step = alpha
            self._moved = float(np.max(np.abs(step)))  # the step of this direction (for the stop)
            self.resyncs += 1
            return self._reduce.begin(self._contribution()), False
        self.iterations += 1
        self.mean_complementarity = m
        self.residual = m
        aty, ysum = total[4 + nh + 2 * n : 4 + nh + 3 * n], float(total[-1])
        norm = float(np.linalg.norm(aty))
        if self._C is None and ysum > 0 and norm * INFEASIBLE_RADIUS < ysum:
            self.separation_bound = math.inf if norm == 0 else ysum / norm
            return self._fail(
                f"interior-point iteration {self.iterations}: infeasibility certificate: multipliers y >= 0 with "
                f"|A'y| / sum(y) = {norm / ysum:.1e}, so every separating (x, gamma) has a norm above "
                f"{INFEASIBLE_RADIUS:.0e}: {INFEASIBLE_ADVICE}"
            )
        if self._C is None and ysum > 0 and norm > 0:
            self.separation_bound = ysum / norm
        moved, self._moved = max(self._moved, float(np.max(np.abs(step)))), 0.0
        if m < self.params.stop_mu and self._settled(moved):
            self._status = "converged"
            return frame, True
        if m > _BREAKDOWN_MU or not math.isfinite(m):
            return self._fail(f"interior-point iteration {self.iterations}: mean s*mu {m:.1e}: " + self._breakdown())
        if self.iterations >= self.params.max_iterations:
            return self._fail(
                f"no convergence after {self.iterations} interior-point iterations (mean s*mu {m:.1e}): "
                + self._breakdown()
            )
        H = np.zeros((n, n))
        H[self._triu] = total[4 : 4 + nh]
        H = H + np.triu(H, 1).T
        g = total[4 + nh : 4 + nh + n]
        u = total[4 + nh + n : 4 + nh + 2 * n]
        centering = self._centering()
        rhs = -self._P @ self._v + centering * m * u - g - alpha * (H @ self._dv)
        dv = _solve_equilibrated(self._P + H, rhs)
        if not np.all(np.isfinite(dv)):
            return self._fail("the Newton step is not finite: " + self._breakdown())
        self._dv = dv
        self._last_step = alpha
        self._alpha = self._local_step(dv, centering * m, recenter=alpha == 1.0 and m < RECENTER_BELOW)
        return self._reduce.begin(self._contribution()), False

    def _settled(self, moved: float) -> bool:
        """The last step moved v by at most stop_step relative: m alone is not enough, because on
        a degenerate problem (a margin active with a vanishing multiplier) v's error falls only
        like sqrt(m) (measured: 48 robots, bean, seed 1: 3e-6 off when m < 1e-10)."""
        scale = max(1.0, float(np.max(np.abs(self._v))))
        return moved <= self.params.stop_step * scale

    def _centering(self) -> float:
        """sigma = (1 - alpha)^2 of the fleet's last primal step, clipped to [min_centering,
        centering]: full steps mean the iterate is near the central path and may aim lower."""
        p = self.params
        if self.iterations <= 1:
            return p.centering
        return min(p.centering, max(p.min_centering, (1.0 - self._last_step) ** 2))

    def _breakdown(self) -> str:
        """Why a run stops without a solution: a certificate-backed bound if there is one, never
        a claim of infeasibility without one."""
        if self._C is not None:
            return "the Newton steps broke down"
        return (
            f"the steps broke down before converging or certifying infeasibility (no separating function of a norm "
            f"below {self.separation_bound:.1e} exists); if the data cannot be separated: {INFEASIBLE_ADVICE}"
        )

    def _fail(self, message: str) -> tuple[np.ndarray, bool]:
        self._status = "failed"
        self.message = message
        self.finished = True
        return self._values.copy(), False

    def _forget_edge(self, j: int) -> None:
        """Every robot's points are in the fleet's sums: without robot j there is no exact sum."""
        self._status = "failed"
        self.message = f"robot {j} dropped out: the fleet-wide sums would miss its data (the all-reduce needs every robot)"
        self.finished = True

    def _record(self) -> None:
        if self._keep_trace:
            self.trace[self.round] = self._v.copy()

    # -- the robot's own points ---------------------------------------------------------------
    def _weights(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per point: effective weight w~, kappa (the coefficient of centering*m), c0 (the C term).

        Hard margin: w~ = mu/s, kappa = 1/s, c0 = 0. Soft margin (xi eliminated too), with
        w = mu/s and q = nu/xi: w~ = wq/(w+q), kappa = 1/s - w/(w+q) (1/s + 1/xi), c0 = wC/(w+q).
        """
        with np.errstate(all="ignore"):
            return self._weights_unchecked()

    def _weights_unchecked(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        w = self._mu / self._s
        if self._C is None:
            return w, 1.0 / self._s, np.zeros_like(w)
        q = self._nu / self._xi
        share = w / (w + q)
        return share * q, 1.0 / self._s - share * (1.0 / self._s + 1.0 / self._xi), share * self._C

    def _primal_residual(self) -> np.ndarray:
        r = self._rows @ self._v - 1.0 - self._s
        return r + self._xi if self._C is not None else r

    def _contribution(self) -> np.ndarray:
        """[alpha, -alpha, #pairs, s'mu (+ xi'nu), triu(A' W~ A), A'(w~ r - c0), A' kappa, A'mu, sum mu]
        at the current v."""
        wt, kappa, c0 = self._weights()
        A = self._rows
        pairs = len(self._s) + len(self._xi)
        with np.errstate(all="ignore"):
            H = A.T @ (wt[:, None] * A)
            comp = float(self._s @ self._mu) + float(self._xi @ self._nu)
            out = np.concatenate(
                [
                    [self._alpha, -self._alpha, pairs, comp],
                    H[self._triu],
                    A.T @ (wt * self._primal_residual() - c0),
                    A.T @ kappa,
                    A.T @ self._mu,
                    [float(np.sum(self._mu))],
                ]
            )
        if not np.all(np.isfinite(out)):  # slacks underflowed: tell the fleet (alpha < 0 wins the min)
            out = np.zeros_like(out)
            out[0] = _BROKEN
        return out

    def _local_step(self, dv: np.ndarray, target: float, recenter: bool = False) -> float:
        """Move the own multipliers along the Newton direction (own dual step) and the own slacks
        by the own primal step, tentatively: the fleet's step (the minimum) arrives with the next
        sums, and a robot whose step was longer moves back to it (a re-sync). With `recenter`, a
        multiplier whose pair ends above the target s*mu = target is lowered onto it (see
        RECENTER_BELOW). Returns the own step."""
        with np.errstate(all="ignore"):
            return self._local_step_unchecked(dv, target, recenter)

    def _local_step_unchecked(self, dv: np.ndarray, sm: float, recenter: bool) -> float:
        tau = self.params.tau
        adv = self._rows @ dv
        r = self._primal_residual()
        s, mu = self._s, self._mu
        if self._C is None:
            dxi = np.zeros(0)
            ds = adv + r
        else:
            xi, nu = self._xi, self._nu
            w, q = mu / s, nu / xi
            b = (sm / s - mu) + (sm / xi - nu) - (self._C - mu - nu) - w * r
            dxi = (b - w * adv) / (w + q)
            ds = adv + dxi + r
        dmu = (sm - s * mu - mu * ds) / s
        primal = min(1.0, tau * min(_max_step(s, ds), _max_step(self._xi, dxi)))
        if self._C is None:
            dual = min(1.0, tau * _max_step(mu, dmu))
        else:
            dnu = (sm - self._xi * self._nu - self._nu * dxi) / self._xi
            dual = min(1.0, tau * min(_max_step(mu, dmu), _max_step(self._nu, dnu)))
            self._nu = self._nu + dual * dnu
        self._s0, self._ds = s, ds
        self._xi0, self._dxi = self._xi, dxi
        self._xi = self._xi + primal * dxi
        self._s = s + primal * ds
        self._mu = mu + dual * dmu
        if recenter:
            self._mu = np.minimum(self._mu, RECENTER_FACTOR * sm / self._s)
            self._nu = np.minimum(self._nu, RECENTER_FACTOR * sm / self._xi)
        return primal

    # -- checkpoint ---------------------------------------------------------------------------
    def _save_state(self) -> dict[str, Any]:
        return {
            "v": to_bytes(self._v),
            "dv": to_bytes(self._dv),
            "alpha": self._alpha,
            "s": to_bytes(self._s),
            "mu": to_bytes(self._mu),
            "xi": to_bytes(self._xi),
            "nu": to_bytes(self._nu),
            "s0": to_bytes(self._s0),
            "ds": to_bytes(self._ds),
            "xi0": to_bytes(self._xi0),
            "dxi": to_bytes(self._dxi),
            "last_step": self._last_step,
            "moved": self._moved,
            "iterations": self.iterations,
            "resyncs": self.resyncs,
            "bound": self.separation_bound,
            "m": self.mean_complementarity,
            "status": self._status,
            "message": self.message,
            "reduce": self._reduce.save(),
        }

    def _load_state(self, state: dict[str, Any]) -> None:
        self._v, self._dv = from_bytes(state["v"]), from_bytes(state["dv"])
        self._alpha = float(state["alpha"])
        self._s, self._mu = from_bytes(state["s"]), from_bytes(state["mu"])
        self._xi, self._nu = from_bytes(state["xi"]), from_bytes(state["nu"])
        self._s0, self._ds = from_bytes(state["s0"]), from_bytes(state["ds"])
        self._xi0, self._dxi = from_bytes(state["xi0"]), from_bytes(state["dxi"])
        self._last_step = float(state["last_step"])
        self._moved = float(state["moved"])
        self.iterations = int(state["iterations"])
        self.resyncs = int(state["resyncs"])
        self.separation_bound = float(state["bound"])
        self.mean_complementarity = float(state["m"])
        self._status = str(state["status"])
        self.message = str(state["message"])
        self._reduce.load(state["reduce"])
