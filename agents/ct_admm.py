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
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from protocol.frames import StateUpdate

_TINY = 1e-12
#: Parameters of a fleet file that belong to the discrete ADMM: its penalty `rho` is not the
#: flow's (that one is `ct_rho`), and relaxation has no meaning here.
_ADMM_ONLY = ("rho", "rho_gamma", "relax")


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
        if not 0 <= self.diameter <= 62:
            raise ValueError(f"diameter must be in [0, 62] (flag bits), got {self.diameter}")
        if self.max_rounds is not None and self.max_rounds < 1:
            raise ValueError(f"max_rounds must be at least 1, got {self.max_rounds}")

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
    def from_params(cls, params: dict[str, Any]) -> CTADMMParams:
        """From a fleet file's `params`: ADMM-only keys are ignored, `ct_<field>` sets <field>.

        One fleet file serves both algorithms, so the flags the CLI adds for this one can be
        namespaced (`ct_step`, `ct_period`, `ct_stop_time`, `ct_rho`, ...); a key that is
        neither ours nor the ADMM's is an error naming it.
        """
        names = {f.name for f in fields(cls)}
        kwargs: dict[str, Any] = {}
        for key, value in params.items():
            if key in _ADMM_ONLY:
                continue
            key = key.removeprefix("ct_")
            if key not in names:
                raise ValueError(f"unknown ct-admm parameter {key!r}; known: {', '.join(sorted(names))}")
            kwargs[key] = value
        return cls(**kwargs)


def _raw(a: np.ndarray | None) -> bytes | None:
    return None if a is None else np.asarray(a, "<f8").tobytes()


def _arr(b: bytes | None) -> np.ndarray | None:
    return None if b is None else np.frombuffer(b, "<f8").copy()


def _relative_gap(v: np.ndarray, w: np.ndarray) -> float:
    """Distance of (x, gamma) to w (one vector or a row per neighbour, the largest counts),
    measured like the fleet's function error, relative to v."""
    d = np.atleast_2d(w) - v
    dx = np.sqrt(np.einsum("ij,ij->i", d[:, :-1], d[:, :-1])) / max(float(np.sqrt(v[:-1] @ v[:-1])), _TINY)
    return float(np.max(dx + np.abs(d[:, -1]) / max(1.0, abs(float(v[-1])))))


@dataclass
class _Inbox:
    """Neighbour values for the current round and the next (a neighbour may be one ahead)."""

    values: dict[int, dict[int, np.ndarray]] = field(default_factory=dict)
    flags: dict[int, dict[int, int]] = field(default_factory=dict)

    def put(self, rnd: int, sender: int, values: np.ndarray, flags: int) -> None:
        self.values.setdefault(rnd, {})[sender] = values
        self.flags.setdefault(rnd, {})[sender] = flags

    def forget_before(self, rnd: int) -> None:
        for table in (self.values, self.flags):
            for old in [r for r in table if r < rnd]:
                del table[old]


class ContinuousTimeADMM:
    """One robot's sampled continuous-time ADMM; drive it with receive / ready / advance."""

    algorithm = "ct-admm"

    def __init__(
        self,
        robot_id: int,
        neighbours: tuple[int, ...],
        features: np.ndarray,
        labels: np.ndarray,
        *,
        n_robots: int,
        params: CTADMMParams,
        C: float | None = None,
        keep_trace: bool = True,
    ) -> None:
        if robot_id in neighbours:
            raise ValueError(f"robot {robot_id} lists itself as a neighbour")
        features = np.asarray(features, dtype=float)
        labels = np.asarray(labels, dtype=float)
        if features.ndim != 2 or len(features) != len(labels) or len(labels) == 0:
            raise ValueError(f"features {features.shape} and labels {labels.shape} do not match")
        if C is not None and not (math.isfinite(C) and C > 0):
            raise ValueError(f"C must be a positive number or None, got {C!r}")
        self.robot_id = robot_id
        self.neighbours = tuple(sorted(neighbours))
        self.params = params
        self.dim = features.shape[1] + 1
        self._A = labels[:, None] * np.hstack([features, np.ones((len(features), 1))])
        self._n_robots = n_robots
        # per-robot bound on the margin duals: C of the centralized problem, rescaled because
        # every robot carries beta/2 |x|^2 and the fleet's objective is N beta/2 |x|^2
        self._u_min = -math.inf if C is None else -float(C) * n_robots * params.beta
        self._sign = {j: (1.0 if robot_id < j else -1.0) for j in self.neighbours}
        self._lam = {j: np.zeros(self.dim) for j in self.neighbours}  # low end's consensus dual
        self._v = np.zeros(self.dim)
        self._y = np.zeros(len(self._A))
        self._mu = np.zeros(len(self._A))
        self._build_metric()
        self._inbox = _Inbox()
        self.dropped: list[int] = []
        self.round = 0
        self.finished = False
        self.residual = math.inf
        self._flags = 0
        self._prev_flags = 0
        self._prev_values: np.ndarray | None = None
        self._keep_trace = keep_trace
        self.trace: dict[int, np.ndarray] = {}
        self._record()

    # -- the interface the shells drive -------------------------------------------------------
    def outgoing(self) -> StateUpdate:
        """What to publish now: this round's sample, last round's piggybacked for recovery."""
        return StateUpdate(
            sender=self.robot_id,
            round=self.round,
            values=self._v.copy(),
            flags=self._flags,
            prev_values=None if self._prev_values is None else self._prev_values.copy(),
            prev_flags=self._prev_flags,
        )

    def receive(self, update: StateUpdate) -> None:
        """Keep a neighbour's exact samples for the rounds still needed; ignore the rest."""
        j = update.sender
        if j not in self._lam:
            return
        if update.values.shape != (self.dim,):
            raise ValueError(f"robot {j} sent {update.values.shape[0]} values, expected {self.dim}")
        if update.round in (self.round, self.round + 1):
            self._inbox.put(update.round, j, update.values, update.flags)
        if update.prev_values is not None and update.round - 1 in (self.round, self.round + 1):
            self._inbox.put(update.round - 1, j, update.prev_values, update.prev_flags)

    def missing(self) -> tuple[int, ...]:
        """Neighbours whose sample for the current round has not arrived."""
        have = self._inbox.values.get(self.round, {})
        return tuple(j for j in self.neighbours if j not in have)

    def ready(self) -> bool:
        """True when the next period can be integrated (every neighbour's exact sample is here)."""
        return not self.finished and not self.missing()

    def advance(self) -> StateUpdate:
        """Consume every neighbour's round-k sample; integrate one period; publish round k+1."""
        if self.finished:
            raise RuntimeError(f"robot {self.robot_id} has finished; nothing to advance")
        missing = self.missing()
        if missing:
            raise RuntimeError(f"robot {self.robot_id} round {self.round}: waiting for {missing}")
        p = self.params
        theirs = self._inbox.values.get(self.round, {})
        their_flags = self._inbox.flags.get(self.round, {})
        mine = self._v.copy()
        # consensus PI: integral part from the two exact samples (both ends compute the same
        # number, so lam_lj = -lam_jl stays exact); proportional part pulls to the midpoints
        pull = np.zeros(self.dim)
        step = p.consensus_gain * p.rho_c * 0.5
        for j in self.neighbours:
            vj = theirs[j]
            low, high = (mine, vj) if self.robot_id < j else (vj, mine)
            self._lam[j] = self._lam[j] + step * (low - high)
            pull += self._sign[j] * self._lam[j] - p.rho_c * (0.5 * (mine + vj))
        gap = _relative_gap(mine, np.array([theirs[j] for j in self.neighbours])) if self.neighbours else 0.0
        # no previous sample, no evidence of rest: round 0 never counts as converged
        change = math.inf if self._prev_values is None else _relative_gap(mine, self._prev_values)
        settle = 1.0 - self._target(self.round * p.steps_per_round)
        self.residual = max(gap, change * max(p.ref_time, p.period) / p.period, settle)
        self._flags, self._prev_flags = self._next_flags(their_flags), self._flags
        self._prev_values = mine
        self._integrate(pull)
        self.round += 1
        self._inbox.forget_before(self.round)
        self._record()
        if self._flags >> p.diameter & 1 or self.round >= p.rounds:
            self.finished = True
        return self.outgoing()

    def drop_neighbour(self, j: int) -> None:
        """Continue without a neighbour that died for good.

        Removing the edge with its dual keeps the remaining duals summing to zero, so the others
        converge to the solution of *their* data; the metric is rebuilt for the new degree.
        """
        if j not in self._lam:
            return
        del self._lam[j]
        del self._sign[j]
        self.neighbours = tuple(n for n in self.neighbours if n != j)
        self.dropped.append(j)
        for table in (self._inbox.values, self._inbox.flags):
            for per_round in table.values():
                per_round.pop(j, None)
        self._build_metric()

    @property
    def converged(self) -> bool:
        """Stopped by the residual rule (not by the stop time)."""
        return self.finished and bool(self._flags >> self.params.diameter & 1)

    @property
    def values(self) -> np.ndarray:
        """The current (x, gamma)."""
        return self._v.copy()

    @property
    def time(self) -> float:
        """Simulated time of the current sample (s): round * period."""
        return self.round * self.params.period

    @property
    def dual_norm(self) -> float:
        """Largest |margin dual|: grows without bound when the hard margin is infeasible."""
        return float(np.max(np.abs(self._mu))) if len(self._mu) else 0.0

    def status(self) -> dict[str, Any]:
        return {
            "robot": self.robot_id,
            "round": self.round,
            "residual": self.residual,
            "finished": self.finished,
            "converged": self.converged,
        }

    def result(self) -> dict[str, Any]:
        """x and gamma of this robot; the shell adds its counters, the launcher the c's."""
        return {
            "id": self.robot_id,
            "algorithm": self.algorithm,
            "x": self._v[:-1].tolist(),
            "gamma": float(self._v[-1]),
            "rounds": self.round,
            "converged": self.converged,
            "residual": self.residual,
            "neighbours": list(self.neighbours),
            "dropped": list(self.dropped),
            "time_s": self.time,
            "dual_norm": self.dual_norm,
        }

    # -- checkpoint ---------------------------------------------------------------------------
    def checkpoint(self) -> dict[str, Any]:
        """Everything needed to resume exactly (msgpack-able: floats as raw '<f8' bytes)."""
        return {
            "algorithm": self.algorithm,
            "robot": self.robot_id,
            "round": self.round,
            "finished": self.finished,
            "residual": self.residual,
            "flags": self._flags,
            "prev_flags": self._prev_flags,
            "values": _raw(self._v),
            "prev_values": _raw(self._prev_values),
            "slack": _raw(self._y),
            "duals": _raw(self._mu),
            "edges": {j: _raw(lam) for j, lam in self._lam.items()},
            "dropped": list(self.dropped),
            "inbox": [
                [rnd, j, _raw(v), self._inbox.flags[rnd][j]]
                for rnd, per in self._inbox.values.items()
                for j, v in per.items()
            ],
        }

    def restore(self, state: dict[str, Any]) -> None:
        """Resume from `checkpoint()` output (the same robot, data and parameters)."""
        if state.get("algorithm") != self.algorithm or state.get("robot") != self.robot_id:
            raise ValueError("checkpoint belongs to another robot or algorithm")
        for j in state["dropped"]:
            self.drop_neighbour(int(j))
        self.round = int(state["round"])
        self.finished = bool(state["finished"])
        self.residual = float(state["residual"])
        self._flags = int(state["flags"])
        self._prev_flags = int(state["prev_flags"])
        self._v = _arr(state["values"])
        self._prev_values = _arr(state["prev_values"])
        self._y = _arr(state["slack"])
        self._mu = _arr(state["duals"])
        for j, lam in state["edges"].items():
            self._lam[int(j)] = _arr(lam)
        self._inbox = _Inbox()
        for rnd, j, v, flags in state["inbox"]:
            self._inbox.put(int(rnd), int(j), _arr(v), int(flags))
        self.trace = {}
        self._record()

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

    def _integrate(self, pull: np.ndarray) -> None:
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
        v, y, mu = self._v, self._y, self._mu
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
        self._v, self._y, self._mu = v, y, mu

    def _next_flags(self, their_flags: dict[int, int]) -> int:
        below = self.residual < self.params.tol
        combined = self._flags
        for f in their_flags.values():
            combined &= f
        mask = (1 << (self.params.diameter + 1)) - 1
        return ((combined << 1) | int(below)) & mask

    def _record(self) -> None:
        if self._keep_trace:
            self.trace[self.round] = self._v.copy()
