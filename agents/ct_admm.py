"""The paper's continuous-time ADMM as one robot's sans-IO state machine (`--algorithm ct-admm`).

Same surface as :class:`agents.admm.ConsensusADMM` -- the in-process fleet and the Zenoh robot
drive either unchanged -- but each round integrates a primal-dual *flow* instead of solving a QP.
The derivation, the stability and no-overshoot arguments and the measured figures are in
``docs/ct-admm.md``; in short, robot l (data A_l = Theta_l [Phi_l 1], n_l rows, degree d_l):

    w_l = A_l v_l - s(t) 1                              margins minus the (filtered) target
    y_l = w_l + mu_l/rho - u_l/rho,  u_l = rho clip(w_l + mu_l/rho, -C'/rho, 0)
                                                        slack: exact projected step (prox) on y >= 0
    P_l dv_l/dt = -alpha [beta D v_l + A_l' u_l + sum_j (s_lj lam_lj + rho_c (v_l - z_lj))]
    dmu_l/dt    = kappa rho (A_l v_l - s(t) 1 - y_l)    PI dual: u = mu + rho r (integral + proportional)
    lam_lj     += gc rho_c (v_low - v_high) / 2         consensus PI dual, once per period, from samples
    ds/dt       = (1 - s) / tau                          reference prefilter (feed-forward), s(0) = 0

with v = (x, gamma), D = diag(1, .., 1, 0), z_lj = (v_l + v_j)/2 of the last samples (held for a
period), s_lj = +1 if l < j else -1, and the metric P_l = beta D + rho A_l'A_l + rho_c d_l I built
from the robot's own data. Forward Euler at step h; one round = one communication period T =
h * steps (neighbour values held). With alpha h <= 1 the Euler step never overshoots in the metric
(the curvature is <= P_l), kappa <= alpha/4 keeps every local dual mode real (overdamped), and
gc <= 1 makes the consensus modes monotone; see the docs for the inequalities.

Why the prefilter: the hard-margin problem is homogeneous -- the solution for margin s is
s * (the solution for margin 1), duals included -- so with s(t) rising smoothly from 0 every
variable of the fleet travels along a straight line to its optimum; the feedback only has to
remove a small lag. Without it the proportional kick of all violated margins at t = 0 makes
components overshoot by several times their travel (measured, see docs).

No I/O, no clock, no randomness: time is round * period, frames in (`receive`), frames out.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from agents.params import check_counts, check_diameter, params_from
from agents.rounds import RobotShare, RoundCore, check_local_data, from_bytes, relative_gap, to_bytes

@dataclass(frozen=True)
class CTADMMParams:
    """Integration, sampling and gains (the same on every robot: they are in the fleet file).

    Gains are dimensionless design numbers; the data-dependent part of every step (the metric
    P_l) is computed by each robot from its own data, so no robot needs another's data.
    """

    step: float = 1e-3  # h: Euler step of the flow (s)
    period: float = 1e-2  # T_sp: neighbours' values are sampled (and held) every period (s)
    stop_time: float = 10.0  # the flow stops at this time (s) unless the residual rule stops it first
    tol: float = 1e-4  # residual rule, as admm: below tol everywhere for `diameter` rounds
    diameter: int = 1
    max_rounds: int | None = None  # extra cap on rounds (None: stop_time / period)
    beta: float = 0.04  # beta_x: objective weight per robot (sets the duals' scale, see docs)
    rho: float = 16.0  # proportional gain of the margin duals (augmented-Lagrangian penalty)
    rho_c: float = 1.0  # proportional gain of the consensus duals
    primal_gain: float = 0.5  # eta = alpha h: Euler step in the metric P_l; stable and monotone <= 1
    dual_ratio: float = 0.3  # kappa / alpha: PI corner of the margin duals; real modes <= overdamp_limit
    consensus_gain: float = 1.0  # gc: consensus-dual increment per period (x rho_c); monotone <= 1, stable < 2
    ref_time: float = 1.0  # tau of the reference prefilter (s); 0 switches it off (step target)
    metric: str = "matrix"  # "matrix": P_l as above; "scalar": P_l = L_l I from norm bounds (slower)

    def __post_init__(self) -> None:
        for name in ("step", "period", "stop_time", "tol", "beta", "rho", "rho_c"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value!r}")
        ratio = self.period / self.step
        if abs(ratio - round(ratio)) > 1e-9 * ratio or round(ratio) < 1:
            raise ValueError(
                f"period ({self.period:g} s) must be a whole number of steps ({self.step:g} s), "
                f"got {ratio:g} steps"
            )
        if not 0 < self.primal_gain <= 1:
            raise ValueError(
                f"primal_gain (alpha h) must be in (0, 1] for a monotone Euler step, got {self.primal_gain}"
            )
        if not 0 < self.dual_ratio * self.primal_gain**2 < 1:
            raise ValueError(
                f"dual_ratio * primal_gain^2 must be in (0, 1) for a stable dual step, "
                f"got {self.dual_ratio} * {self.primal_gain}^2"
            )
        if not 0 < self.consensus_gain < 2:
            raise ValueError(f"consensus_gain must be in (0, 2) for a stable consensus dual, got {self.consensus_gain}")
        if not (math.isfinite(self.ref_time) and self.ref_time >= 0):
            raise ValueError(f"ref_time must be >= 0 (0 = no prefilter), got {self.ref_time!r}")
        if self.metric not in ("matrix", "scalar"):
            raise ValueError(f"metric must be 'matrix' or 'scalar', got {self.metric!r}")
        check_diameter(self.diameter)
        check_counts(self, "max_rounds")

    @property
    def steps_per_round(self) -> int:
        """Euler steps per communication period."""
        return int(round(self.period / self.step))

    @property
    def rounds(self) -> int:
        """Rounds until the stop time (or the round cap)."""
        by_time = max(1, int(math.ceil(self.stop_time / self.period - 1e-9)))
        return by_time if self.max_rounds is None else min(by_time, self.max_rounds)

    @property
    def overdamp_limit(self) -> float:
        """Largest dual_ratio whose discrete local modes are all real: ((1 - sqrt(1 - eta)) / eta)^2."""
        eta = self.primal_gain
        return ((1.0 - math.sqrt(1.0 - eta)) / eta) ** 2

    @classmethod
    def from_params(cls, params: Mapping[str, Any]) -> CTADMMParams:
        """From a fleet file's ``params``: exactly this class's fields (``rho`` is the flow's
        gain, not the discrete ADMM's); any other key is an error naming it."""
        return params_from(cls, params, "ct-admm")


class ContinuousTimeADMM(RoundCore):
    """One robot's sampled continuous-time ADMM; drive it with receive / ready / advance."""

    algorithm = "ct-admm"

    def __init__(self, share: RobotShare, params: CTADMMParams, *, keep_trace: bool = True) -> None:
        features = np.asarray(share.features, dtype=float)
        labels = np.asarray(share.labels, dtype=float)
        check_local_data(features, labels, share.C, allow_empty=False)  # the flow needs a margin
        robot_id, n_robots, C = share.robot_id, share.n_robots, share.C
        super().__init__(
            robot_id, share.neighbours, share.dim, diameter=params.diameter, round_cap=params.rounds,
            keep_trace=keep_trace,
        )
        self.params = params
        self._A = labels[:, None] * np.hstack([features, np.ones((len(features), 1))])
        self._n_robots = n_robots
        # per-robot bound on the margin duals: C of the centralized problem, rescaled because
        # every robot carries beta/2 |x|^2 and the fleet's objective is N beta/2 |x|^2
        self._C = C
        self._u_min = -math.inf if C is None else -float(C) * n_robots * params.beta
        # who was dropped for good fleet-wide (agents/rounds.py): a soft margin's bound depends on how
        # many robots are left (`_gone_changed` rescales it); either margin's stop must reach across
        # the survivors' graph, which can be wider than the fleet's
        self.floods_gone = True
        self._sign = {j: (1.0 if robot_id < j else -1.0) for j in self.neighbours}
        self._lam = {j: np.zeros(self.dim) for j in self.neighbours}  # low end's consensus dual
        self._y = np.zeros(len(self._A))
        self._mu = np.zeros(len(self._A))
        self._build_metric()
        self._record()

    @property
    def time(self) -> float:
        """Simulated time of the current sample (s): round * period."""
        return self.round * self.params.period

    @property
    def dual_norm(self) -> float:
        """Largest |margin dual|: grows without bound when the hard margin is infeasible."""
        return float(np.max(np.abs(self._mu))) if len(self._mu) else 0.0

    def result(self) -> dict[str, Any]:
        return {**super().result(), "time_s": self.time, "dual_norm": self.dual_norm}

    # -- one period ---------------------------------------------------------------------------
    def _step(self, mine: np.ndarray, theirs: dict[int, np.ndarray]) -> tuple[np.ndarray, bool]:
        p = self.params
        # consensus PI: integral part from the two exact samples (both ends compute the same
        # number, so lam_lj = -lam_jl stays exact); proportional part pulls to the midpoints
        pull = np.zeros(self.dim)
        step = p.consensus_gain * p.rho_c * 0.5
        for j in self.neighbours:
            vj = theirs[j]
            low, high = (mine, vj) if self.robot_id < j else (vj, mine)
            self._lam[j] = self._lam[j] + step * (low - high)
            pull += self._sign[j] * self._lam[j] - p.rho_c * (0.5 * (mine + vj))
        gap = relative_gap(mine, np.array([theirs[j] for j in self.neighbours])) if self.neighbours else 0.0
        # no previous sample, no evidence of rest: round 0 never counts as converged
        change = math.inf if self._prev_values is None else relative_gap(mine, self._prev_values)
        settle = 1.0 - self._target(self.round * p.steps_per_round)
        self.residual = max(gap, change * max(p.ref_time, p.period) / p.period, settle)
        return self._integrate(mine, pull), self.residual < p.tol

    def _forget_edge(self, j: int) -> None:
        """Removing the edge with its dual keeps the remaining duals summing to zero, so the others
        converge to the solution of *their* data; the metric is rebuilt for the new degree."""
        del self._lam[j]
        del self._sign[j]
        self._build_metric()

    def _gone_changed(self) -> None:
        """Robots were dropped for good (`gone`): the stop flags reach across the survivors' graph; with a
        soft margin the survivors carry (N - lost) beta/2 |x|^2, so the duals' bound is C (N - lost) beta
        -- else they solve C x N / N_alive. A hard margin's steps never read the lists."""
        left = self._n_robots - len(self.gone)
        if self._C is not None:
            self._u_min = -float(self._C) * left * self.params.beta
        self._widen_stop(left)

    def _save_state(self) -> dict[str, Any]:
        return {
            "slack": to_bytes(self._y),
            "duals": to_bytes(self._mu),
            "edges": {j: to_bytes(lam) for j, lam in self._lam.items()},
        }

    def _load_state(self, state: dict[str, Any]) -> None:
        self._y = from_bytes(state["slack"])
        self._mu = from_bytes(state["duals"])
        for j, lam in state["edges"].items():
            self._lam[int(j)] = from_bytes(lam)

    # -- internals ----------------------------------------------------------------------------
    def _build_metric(self) -> None:
        """P_l and the Euler matrices; only this robot's data and degree enter.

        v+ = v - eta P^-1 (beta D v + rho_c d v + pull + A'u) is written as G v - B u - P^-1 pull
        eta, with G = I - eta P^-1 (beta D + rho_c d I) and B = eta P^-1 A', so a step costs three
        small mat-vecs.
        """
        p = self.params
        m = self.dim
        diag = np.full(m, p.beta)
        diag[-1] = 0.0  # gamma is free of cost
        degree = len(self.neighbours)
        curvature = np.diag(diag + p.rho_c * degree)  # beta D + rho_c d I
        if p.metric == "matrix":
            # positive definite for any data: v'Pv = 0 forces x = 0 (beta > 0), then gamma = 0
            # (the last column of A is the labels)
            inv = np.linalg.inv(curvature + p.rho * (self._A.T @ self._A))
        else:
            # L_l bounds the curvature's largest eigenvalue from norms alone
            sigma2 = float(np.linalg.norm(self._A, 2) ** 2)
            bound = p.beta + p.rho * sigma2 + p.rho_c * degree
            inv = np.eye(m) / bound
        self._G = np.eye(m) - p.primal_gain * inv @ curvature
        self._B = p.primal_gain * inv @ self._A.T
        self._Pinv_eta = p.primal_gain * inv

    def _target(self, step_index: int) -> float:
        """s(t) = 1 - exp(-t / tau): the prefiltered margin, from the step count (no clock)."""
        return float(self._targets(step_index, 1)[0])

    def _targets(self, first: int, count: int) -> np.ndarray:
        """s(t) at `count` consecutive steps from step `first`."""
        p = self.params
        if p.ref_time <= 0:
            return np.ones(count)
        t = (first + np.arange(count)) * p.step
        return -np.expm1(-t / p.ref_time)

    def _integrate(self, v: np.ndarray, pull: np.ndarray) -> np.ndarray:
        """One period of forward-Euler steps with the neighbours' samples held.

        Per step: the slack's exact projected step, the margin duals' PI output u, the primal
        step in the metric, then the integral part of the duals with the new margins.
        """
        p = self.params
        rho = p.rho
        inv_rho = 1.0 / rho
        dual_step = p.dual_ratio * p.primal_gain * rho
        hard = math.isinf(self._u_min)
        low = self._u_min * inv_rho
        A, G, B = self._A, self._G, self._B
        offset = self._Pinv_eta @ pull
        y, mu = self._y, self._mu
        av = A @ v
        for s in self._targets(self.round * p.steps_per_round, p.steps_per_round):
            shifted = av - s + mu * inv_rho
            if hard:
                y = np.maximum(shifted, 0.0)  # projection of the slack on y >= 0
            else:
                y = np.maximum(shifted, 0.0) + np.minimum(shifted - low, 0.0)  # prox of the hinge
            u = rho * (shifted - y)  # = mu + rho (w - y): the PI output, in [u_min, 0]
            v = G @ v - B @ u - offset
            av = A @ v
            mu = mu + dual_step * (av - s - y)
        if not (np.all(np.isfinite(v)) and np.all(np.isfinite(mu))):
            raise FloatingPointError(f"robot {self.robot_id}: the flow left the finite numbers at round {self.round}")
        self._y, self._mu = y, mu
        return v
