"""Warm starts of autogrid's ADMM sub-machines: a given first iterate, and edge state carried
from a coarser grid (exact on the superset lattice).

On a grid G' that contains G (new nodes appended), the function with c' = [c; 0] is the same
function, so in the preconditioned variable x = K_G^{1/2} c the primal maps by
    P = K_G'^{1/2} E K_G^{-1/2}            (E = [I; 0], the embedding of c)
and a dual lambda (paired with x: lambda' x = (K_G^{1/2} lambda)' c) maps by
    Q = K_G'^{-1/2} E K_G^{1/2}            so that (Q lambda)' (P x) = lambda' x.
Both ends of an edge apply the same matrices to the same (z, lambda), so their copies stay equal
bit for bit and lambda_lj = -lambda_jl -- the sum-of-duals-zero invariant -- holds on every edge.
The offset gamma is the same variable on both grids and is carried unchanged. The hub form's scaled
duals u_l (complete graphs: one per robot, every copy holds all of them) are duals paired with x too
and map by the same Q (`carry_hub_duals`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from agents.admm import ConsensusADMM
from agents.autogrid_rules import AUTOGRID_MAX_DIAMETER
from agents.kernel import GridBasis


class WarmADMM(ConsensusADMM):
    """ConsensusADMM whose round 0 is a given (x, gamma) instead of the robot's own solution,
    optionally with every edge's (z, lambda) given too (`edges`: neighbour -> (z, lambda)).

    Round 0's edge update (relaxation 1) sets z to the midpoint of the two ends' starts and adds
    rho (v_low - z) to lambda: from a common start that keeps the carried lambda as it is.
    """

    def __init__(
        self,
        *args: Any,
        start: np.ndarray | None = None,
        edges: dict[int, tuple[np.ndarray, np.ndarray]] | None = None,
        hub_duals: tuple[tuple[int, ...], np.ndarray] | None = None,
        gone: tuple[int, ...] = (),
        **kwargs: Any,
    ) -> None:
        self._start = None if start is None else np.asarray(start, dtype=float).copy()
        self._carry = edges or {}
        # without room for the hub's w in autogrid's frames (AutoGridParams.hub_frames False)
        # each copy computes every w itself: exact only while the copies agree
        kwargs.setdefault("hub_frames", False)
        super().__init__(*args, **kwargs)
        # who was dropped for good (edge form, `floods_gone`): autogrid's frames carry its own list and
        # it hands every neighbour's to the sub-machine with that neighbour's values; a sub-machine
        # built after a loss starts from the robots already known gone (weighed out, stop widened)
        if gone and self.floods_gone:
            self.gone = tuple(gone)
            self._gone_changed()
        # the hub form's scaled duals carried in (every robot holds the same rows, bit for bit): the hub
        # starts at z = mean w, u_l = w_l - z + (U_l - mean U) (`_Hub.start`); sum_l u_l = 0 stays, so the
        # fixed point -- the exact optimum -- does not depend on them, only where the iteration starts
        hub = self._hub
        if hub_duals is not None and hub is not None and tuple(hub_duals[0]) == hub.ids \
                and hub_duals[1].shape == (len(hub.ids), self.dim):
            hub.seed_duals(hub_duals[1])

    def _widen_stop(self, robots_left: int) -> None:
        """As ConsensusADMM's, within AUTOGRID_MAX_DIAMETER hops: the sweep's stacked frames carry the
        flags as floats (exact below 2^53), so a survivors' graph of at most 53 robots."""
        super()._widen_stop(min(robots_left, AUTOGRID_MAX_DIAMETER + 1))

    def _local_step(self) -> np.ndarray:
        for j, (z, lam) in self._carry.items():
            edge = self._edges.get(j)
            if edge is not None and len(z) == len(edge.z):
                edge.z, edge.lam = np.array(z, dtype=float), np.array(lam, dtype=float)
        self._carry = {}
        if self._start is not None and self.neighbours:  # a lone robot solves it all at round 0
            return self._start.copy()
        return super()._local_step()


def superset_maps(old: GridBasis, new: GridBasis) -> tuple[np.ndarray, np.ndarray]:
    """(P, Q): the primal and dual maps from `old`'s x to `new`'s x (new grid = old + appended)."""
    m_old, m_new = old.size, new.size
    if not np.array_equal(new.grid[:m_old], old.grid):
        raise ValueError("the new grid must start with the old grid (a superset in the same order)")
    P = new.sqrt[:, :m_old] @ old.inv_sqrt
    Q = new.inv_sqrt[:, :m_old] @ old.sqrt
    return P, Q


def carry_vector(v: np.ndarray, M: np.ndarray) -> np.ndarray:
    """(x, gamma) -> (M x, gamma)."""
    return np.append(M @ v[:-1], v[-1])


def hub_duals(sub: ConsensusADMM) -> tuple[tuple[int, ...], np.ndarray] | None:
    """A hub-form sub-machine's robot ids and scaled duals u_l (a row each, in id order), or None
    (edge form, or no step taken): every robot's copy holds them, bit for bit."""
    hub = sub._hub
    if hub is None or hub.s is None:
        return None
    return hub.ids, hub.s[hub.dim :].reshape(len(hub.ids), hub.dim).copy()


def carry_hub_duals(duals: tuple[tuple[int, ...], np.ndarray], old: GridBasis, new: GridBasis
                    ) -> tuple[tuple[int, ...], np.ndarray]:
    """Hub duals on `old` expressed on `new` (the dual map Q, row by row: exact on the superset)."""
    _, Q = superset_maps(old, new)
    ids, U = duals
    return ids, np.array([carry_vector(u, Q) for u in U])


def carry_edges(
    edges: dict[int, Any], old: GridBasis, new: GridBasis
) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Every edge's (z, lambda) of a ConsensusADMM on `old`, expressed on `new`."""
    P, Q = superset_maps(old, new)
    return {j: (carry_vector(e.z, P), carry_vector(e.lam, Q)) for j, e in edges.items()}
