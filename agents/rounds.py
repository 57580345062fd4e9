"""The round protocol every per-robot algorithm shares, as a sans-IO base class.

A robot's algorithm advances in rounds. Round k's frame carries the robot's vector v^k and its
stop flags, with round k-1 piggybacked so that a receiver that lost that frame recovers the exact
value (a stale substitute would bias the answer). Advancing from k to k+1 needs the exact v_j^k of
every neighbour; neighbours are therefore at most one round apart, and the inbox keeps rounds k
and k+1 only.

Stopping: each round carries D+1 flag bits. Bit 0 says "my own stopping test passed"; bit t of
round k+1 is the AND of bit t-1 of round k over the robot and its neighbours. Bit D (D >= graph
diameter) is thus the AND over *all* robots of bit 0 from D rounds earlier: every robot sees the
same value in the same round, so all stop together. A core whose test is itself the fleet's verdict,
the same bits on every robot (`fleet_wide_verdict`: the relay hub), stops in the round it passes.

Robots dropped for good (`floods_gone`): a robot on a sparse graph learns only that its own
neighbours died, yet a soft margin's answer depends on how many robots are left (each weighs
|x|^2 by 1 / N_alive), and any margin's stop on how wide the survivors' graph became. A core that
sets `floods_gone` sends with each round the sorted ids it knows to be dropped for good (`gone`: its
own drops and those heard; round k-1's piggybacked as `prev_gone`) and, stepping from round k, adds
every neighbour's round-k set to its own: the news crosses one hop a round (everyone knows within
the survivors' diameter), the same bits in both shells. In the round its set grows, the subclass's
`_gone_changed` reweighs where the margin needs it and widens the stop (`_widen_stop`), and the
robot's stop test counts as failed: the flags cannot stop a robot before the news reached it unless
every robot had passed its test before anyone applied the news (see docs/algorithm.md, "A robot that
dies for good").

Subclasses implement the mathematics in `_step` (one round) and say what else a checkpoint holds;
they never see frames, inboxes or flags.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from agents.messages import StateUpdate
from agents.params import MAX_DIAMETER, check_diameter
from agents.problem import InfeasibleError, SolverError

_TINY = 1e-12
# An iterate this large is taken as divergence: the function values are O(1)-O(100) in any sane
# problem; far beyond that float64 arithmetic is about to lose every digit (the issue saw 1e77).
DIVERGED_ABS = 1e12


def check_iterate(values: np.ndarray) -> str | None:
    """Why ``values`` (x, gamma) cannot be a result (non-finite or exploding), or None.

    One reduction, run every round: the largest |component| is NaN when any component is NaN
    (numpy's max propagates it), inf when any is infinite and none NaN, finite exactly when every
    component is -- the verdicts of the separate isfinite test, without its two extra calls."""
    v = np.asarray(values, dtype=float)
    if not v.size:
        return None
    big = float(_max_reduce(np.abs(v), axis=None))  # (np.max's own reduction, without its Python wrapper)
    if big <= DIVERGED_ABS:
        return None
    if not math.isfinite(big):
        return "non-finite iterate (NaN or inf)"
    return f"exploding iterate (largest component {big:.3g} > {DIVERGED_ABS:g})"


_max_reduce = np.maximum.reduce


def to_bytes(a: np.ndarray | None) -> bytes | None:
    """A float vector as raw little-endian float64 (checkpoints are msgpack)."""
    return None if a is None else np.asarray(a, "<f8").tobytes()


def from_bytes(b: bytes | None) -> np.ndarray | None:
    return None if b is None else np.frombuffer(b, "<f8").copy()


def relative_gap(v: np.ndarray, w: np.ndarray) -> float:
    """Distance of (x, gamma) to w (one vector or a row per neighbour, the largest counts),
    measured like the fleet's function error, relative to v."""
    return float(np.max(relative_gaps(v, w)))


def relative_gaps(v: np.ndarray, w: np.ndarray) -> np.ndarray:
    """`relative_gap` of each row of w to v (one call for several gaps: each row's value is the
    same bits as on its own)."""
    d = np.atleast_2d(w) - v
    dx = d[:, :-1]
    x = v[:-1]
    # (math.sqrt of the float and np.sqrt of the float64: both the correctly rounded root)
    gx = np.sqrt(np.einsum("ij,ij->i", dx, dx)) / max(math.sqrt(float(x @ x)), _TINY)
    return gx + np.abs(d[:, -1]) / max(1.0, abs(float(v[-1])))


def check_neighbours(robot_id: int, neighbours: tuple[int, ...]) -> None:
    """A robot is not its own neighbour (its frames would count twice)."""
    if robot_id in neighbours:
        raise ValueError(f"robot {robot_id} lists itself as a neighbour")


def check_local_data(features: Any, labels: Any, C: float | None, *, allow_empty: bool = True) -> None:
    """Refuse a robot's share of the data that no core can use, with the same message whatever
    the algorithm: features that are not a matrix with a row per label (no rows at all unless
    ``allow_empty``: a fold of the sigma sweep may hold none), a C that is not a positive number
    (None is the hard margin)."""
    shape = np.shape(features)
    if len(shape) != 2 or shape[0] != len(labels) or not (allow_empty or len(labels)):
        raise ValueError(f"features {shape} and labels {np.shape(labels)} do not match")
    if C is not None and not (math.isfinite(C) and C > 0):
        raise ValueError(f"C must be a positive number or None (hard margin), got {C!r}")


@dataclass(frozen=True, eq=False)  # arrays inside: compared by identity
class RobotShare:
    """One robot's share of the fleet's problem, as every core takes it: who it is, whom it hears,
    the rows it fits and the fleet's constants. Checked once here, with the same messages
    whatever the algorithm, so a core's constructor takes a share and its own parameters only.

    ``features`` are the rows of the robot's margins (the basis's features of its points; raw
    points for autogrid, which builds features per grid); ``degrees`` maps a neighbour to its
    neighbour count (missing: unknown, see `agents.admm.hub_form`)."""

    robot_id: int
    neighbours: tuple[int, ...]
    features: np.ndarray
    labels: np.ndarray
    n_robots: int = 1
    C: float | None = None
    degrees: Mapping[int, int] = field(default_factory=dict)

    def __post_init__(self) -> None:
        check_local_data(self.features, self.labels, self.C)
        check_neighbours(self.robot_id, self.neighbours)
        object.__setattr__(self, "neighbours", tuple(sorted(self.neighbours)))

    @property
    def dim(self) -> int:
        """Length of (x, gamma): a weight per feature and the offset."""
        return int(np.shape(self.features)[1]) + 1

    def with_data(self, neighbours: tuple[int, ...], features: np.ndarray, labels: np.ndarray,
                  C: float | None) -> RobotShare:
        """The same robot and fleet on other rows (a sub-problem: autogrid's grid, a sweep's
        fold), among the neighbours it still has; each neighbour's degree as known, else 1."""
        degrees = {j: self.degrees.get(j, 1) for j in neighbours}
        return replace(self, neighbours=neighbours, features=features, labels=labels, C=C, degrees=degrees)


def result_row(core: Any, values: np.ndarray, *, rounds: int, dropped: list[int]) -> dict[str, Any]:
    """The result every core reports, round-based or free: (x, gamma) = ``values`` and how it
    stopped (``core``: robot_id, algorithm, converged, residual, neighbours)."""
    return {
        "id": core.robot_id,
        "algorithm": core.algorithm,
        "x": values[:-1].tolist(),
        "gamma": float(values[-1]),
        "rounds": rounds,
        "converged": core.converged,
        "residual": core.residual,
        "neighbours": list(core.neighbours),
        "dropped": list(dropped),
    }


@dataclass
class _Inbox:
    """Neighbour values for the current round and the next (a neighbour may be one ahead)."""

    values: dict[int, dict[int, np.ndarray]] = field(default_factory=dict)
    flags: dict[int, dict[int, int]] = field(default_factory=dict)
    # the robots each sender said were dropped for good with that round's values (only non-empty ones)
    gone: dict[int, dict[int, tuple[int, ...]]] = field(default_factory=dict)

    def put(self, rnd: int, sender: int, values: np.ndarray, flags: int, gone: tuple[int, ...] = ()) -> None:
        per = self.values.get(rnd)
        if per is None:  # a round's two tables are made together
            per = self.values[rnd] = {}
            self.flags[rnd] = {}
        per[sender] = values
        self.flags[rnd][sender] = flags
        if gone:
            self.gone.setdefault(rnd, {})[sender] = gone

    def forget_before(self, rnd: int) -> None:
        for table in (self.values, self.flags, self.gone):
            for old in [r for r in table if r < rnd]:
                del table[old]

    def forget_sender(self, sender: int) -> None:
        for table in (self.values, self.flags, self.gone):
            for per_round in table.values():
                per_round.pop(sender, None)


class RoundCore:
    """Frames in (`receive`), frames out (`outgoing`, `advance`); the maths is in `_step`."""

    algorithm = ""
    #: what a round may raise when its local solve fails: the session stops the robot with the
    #: reason instead of crashing (the session knows the core's interface, not its solver)
    solve_errors: tuple[type[BaseException], ...] = (
        SolverError, InfeasibleError, FloatingPointError, np.linalg.LinAlgError,
    )
    #: True where `_step`'s stop test is already the fleet's verdict -- computed by every robot from the
    #: same bits in the same round (the relay hub's identical copies of the whole fleet state) -- so
    #: flooding it for D more rounds would only repeat what every robot already knows: a robot whose test
    #: passes sets every flag bit and stops in that round, and so does every other robot
    fleet_wide_verdict = False
    #: True where the core sends and gathers the robots dropped for good (`gone`) and reweighs on news
    #: (`_gone_changed`): see the module doc. False: frames never carry them, nothing changes
    floods_gone = False

    def __init__(
        self,
        robot_id: int,
        neighbours: tuple[int, ...],
        dim: int,
        *,
        diameter: int,
        round_cap: int,
        keep_trace: bool,
    ) -> None:
        check_neighbours(robot_id, neighbours)
        check_diameter(diameter)
        self.robot_id = robot_id
        self.neighbours = tuple(sorted(neighbours))
        self._neighbour_set = frozenset(self.neighbours)  # receive's membership test, per frame
        self.dim = dim
        self.frame_dim = dim  # length of a frame's vectors (a subclass may send more than v)
        self.round = 0
        self.finished = False
        self.residual = math.inf
        self.dropped: list[int] = []
        self.trace: dict[int, np.ndarray] = {}
        self._diameter = diameter
        self._round_cap = round_cap
        self._keep_trace = keep_trace
        self._inbox = _Inbox()
        self._values = np.zeros(dim)
        self._prev_values: np.ndarray | None = None
        self._flags = 0
        self._prev_flags = 0
        self.gone: tuple[int, ...] = ()  # robots known to be dropped for good, as sent with this round
        self._prev_gone: tuple[int, ...] = ()  # ... and with the round before

    # -- the interface the shells drive -------------------------------------------------------
    def outgoing(self) -> StateUpdate:
        """What to publish now: this round's values, last round's piggybacked for recovery."""
        return StateUpdate(
            sender=self.robot_id,
            round=self.round,
            values=self._values.copy(),
            flags=self._flags,
            prev_values=None if self._prev_values is None else self._prev_values.copy(),
            prev_flags=self._prev_flags,
            gone=self.gone,
            prev_gone=self._prev_gone if self._prev_values is not None else (),
        )

    def receive(self, update: StateUpdate) -> None:
        """Keep a neighbour's exact values for the rounds still needed; ignore the rest."""
        j = update.sender
        if j not in self._neighbour_set:
            return
        if len(update.values) != self.frame_dim:  # (a StateUpdate's values are a 1-D vector)
            raise ValueError(f"robot {j} sent {update.values.shape[0]} values, expected {self.frame_dim}")
        ahead = update.round - self.round  # which of our rounds (this one, the next) it serves
        if ahead == 0 or ahead == 1:
            self._inbox.put(update.round, j, update.values, update.flags, update.gone)
        if update.prev_values is not None and (ahead == 1 or ahead == 2):
            self._inbox.put(update.round - 1, j, update.prev_values, update.prev_flags, update.prev_gone)

    def missing(self) -> tuple[int, ...]:
        """Neighbours whose value for the current round has not arrived."""
        have = self._inbox.values.get(self.round)
        if not have:
            return self.neighbours
        if len(have) == len(self.neighbours):  # the inbox holds neighbours' values only (receive,
            return ()                          # drop_neighbour): every one is there
        return tuple([j for j in self.neighbours if j not in have])

    def ready(self) -> bool:
        """True when the next round can be computed."""
        return not self.finished and not self.missing()

    def _take_round(self) -> tuple[dict[int, np.ndarray], dict[int, int]]:
        """Every neighbour's exact round-k values and flags; refuses to run ahead of them."""
        if self.finished:
            raise RuntimeError(f"robot {self.robot_id} has finished; nothing to advance")
        missing = self.missing()
        if missing:
            raise RuntimeError(f"robot {self.robot_id} round {self.round}: waiting for {missing}")
        theirs = {j: self._inbox.values[self.round][j] for j in self.neighbours}
        return theirs, self._inbox.flags.get(self.round, {})

    def advance(self) -> StateUpdate:
        """Consume every neighbour's round-k values; compute round k+1."""
        theirs, their_flags = self._take_round()
        mine = self._values
        news = self.floods_gone and self._gather_gone()
        new_values, below = self._step(mine, theirs)
        below = below and not news  # (the round the news came: its step ran on the new weights)
        combined = self._flags
        for f in their_flags.values():
            combined &= f
        mask = (1 << (self._diameter + 1)) - 1
        flags = mask if below and self.fleet_wide_verdict else ((combined << 1) | int(below)) & mask
        self._flags, self._prev_flags = flags, self._flags
        self._prev_values = mine
        self._values = new_values
        self.round += 1
        self._inbox.forget_before(self.round)
        self._record()
        if self._flags >> self._diameter & 1 or self.round >= self._round_cap:
            self.finished = True
        return self.outgoing()

    def _gather_gone(self) -> bool:
        """Round k -> k+1 with `floods_gone`: the robots dropped for good as this robot knows them now
        -- what it knew, its own drops, every neighbour's set sent with round k -- become the set it
        sends with round k+1; where that grew, the subclass reweighs before the step. True if it grew."""
        known = set(self.gone)
        known.update(self.dropped)
        for ids in self._inbox.gone.get(self.round, {}).values():
            known.update(ids)
        known.discard(self.robot_id)  # (a frame naming the receiver never gets here: the decoder refuses it)
        now = tuple(sorted(known))
        self._prev_gone = self.gone
        if now == self.gone:
            return False
        self.gone = now
        self._gone_changed()
        return True

    def _widen_stop(self, robots_left: int) -> None:
        """After a loss the survivors' graph may be wider than the diameter the flags were sized for
        (a 6-ring without robot 1 is a path of diameter 4 > 3: its ends stopped rounds apart, and
        the others dropped the one that stopped). A connected graph of n robots has a diameter
        <= n - 1, so the stop waits for that many hops (at most MAX_DIAMETER): a few rounds more."""
        self._diameter = max(self._diameter, min(MAX_DIAMETER, robots_left - 1))

    def drop_neighbour(self, j: int) -> None:
        """Continue without a neighbour that died for good (the subclass drops its edge state)."""
        if j not in self.neighbours:
            return
        self.neighbours = tuple(n for n in self.neighbours if n != j)
        self._neighbour_set = frozenset(self.neighbours)
        self.dropped.append(j)
        self._inbox.forget_sender(j)
        self._forget_edge(j)

    @property
    def converged(self) -> bool:
        """Stopped by the stopping rule (not by the round cap)."""
        return self.finished and bool(self._flags >> self._diameter & 1)

    @property
    def values(self) -> np.ndarray:
        """The current (x, gamma)."""
        return self._values.copy()

    def divergence(self) -> str | None:
        """Why the current function cannot be a result (non-finite or exploding), or None.

        The shells ask the core rather than inspect frames: a frame may carry more than a function
        (autogrid's stacked sweep holds stop flags as floats), and only the algorithm knows which
        part is the function."""
        return check_iterate(self.values)  # the subclass's function part (newton, pdmm: not the payload)

    def status(self) -> dict[str, Any]:
        """Where the robot is (its status key while it runs): round, residual, how it stopped."""
        return {"robot": self.robot_id, "round": self.round, "residual": self.residual,
                "finished": self.finished, "converged": self.converged}

    def result(self) -> dict[str, Any]:
        """x and gamma of this robot; the shell adds its counters, the launcher the c's."""
        return result_row(self, self._values, rounds=self.round, dropped=self.dropped)

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
            "values": to_bytes(self._values),
            "prev_values": to_bytes(self._prev_values),
            "dropped": list(self.dropped),
            "gone": list(self.gone),
            "prev_gone": list(self._prev_gone),
            "inbox": [
                [rnd, j, to_bytes(v), self._inbox.flags[rnd][j], list(self._inbox.gone.get(rnd, {}).get(j, ()))]
                for rnd, per in self._inbox.values.items()
                for j, v in per.items()
            ],
            "state": self._save_state(),
        }

    def restore(self, state: dict[str, Any]) -> None:
        """Resume from `checkpoint()` output (the same robot, data and parameters)."""
        if state.get("algorithm") != self.algorithm or state.get("robot") != self.robot_id:
            raise ValueError("checkpoint belongs to another robot or algorithm")
        self.gone = tuple(int(j) for j in state["gone"])  # (before the drops: they rebuild on it)
        self._prev_gone = tuple(int(j) for j in state["prev_gone"])
        for j in state["dropped"]:
            self.drop_neighbour(int(j))
        self.round = int(state["round"])
        self.finished = bool(state["finished"])
        self.residual = float(state["residual"])
        self._flags = int(state["flags"])
        self._prev_flags = int(state["prev_flags"])
        self._values = from_bytes(state["values"])
        self._prev_values = from_bytes(state["prev_values"])
        self._inbox = _Inbox()
        for rnd, j, v, flags, gone in state["inbox"]:
            self._inbox.put(int(rnd), int(j), from_bytes(v), int(flags), tuple(int(i) for i in gone))
        self._load_state(state["state"])
        if self.gone:
            self._gone_changed()
        self.trace = {}
        self._record()

    # -- what a subclass provides -------------------------------------------------------------
    def _step(self, mine: np.ndarray, theirs: dict[int, np.ndarray]) -> tuple[np.ndarray, bool]:
        """One round of the algorithm from the exact round-k values: (v^{k+1}, my stop test)."""
        raise NotImplementedError

    def _forget_edge(self, j: int) -> None:
        """Drop the state of the edge to a neighbour that died for good."""
        raise NotImplementedError

    def _gone_changed(self) -> None:
        """`floods_gone`: `gone` grew (or a restore set it) -- reweigh for the robots left and widen
        the stop (`_widen_stop`), as the algorithm needs. Called
        before the round's step, and after `restore`."""
        raise NotImplementedError

    def _save_state(self) -> dict[str, Any]:
        raise NotImplementedError

    def _load_state(self, state: dict[str, Any]) -> None:
        raise NotImplementedError

    def _record(self) -> None:
        if self._keep_trace:
            self.trace[self.round] = self._values.copy()
