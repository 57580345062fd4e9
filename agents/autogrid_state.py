"""Checkpoint of an autogrid robot: what `AdaptiveGridCore` must keep to resume bit for bit.

Derived objects (lattices, bases, features, the sweep's sub-machines) are rebuilt from the agreed
numbers, then the sub-machines' own checkpoints are restored into them.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from agents.autogrid_rules import choose_widths, folds_for_data, widths_for_data
from agents.rounds import from_bytes, to_bytes

if TYPE_CHECKING:
    from agents.autogrid import AdaptiveGridCore

#: plain fields (msgpack-able as they are)
_PLAIN = ("phase", "sigma_reason", "margin", "message", "disagreement", "_diag", "_h0", "_level", "_mode",
          "_left", "_phase_start", "_sub_converged", "_admm_rounds", "_capped", "_agreed", "_best_norm2",
          "_refinements", "_held_units", "_endgame", "_chunk")
#: float vectors (raw '<f8' bytes)
_VECTORS = ("_warm", "_own", "_final", "_seed", "_near")


def _edges_out(edges: dict[int, tuple[np.ndarray, np.ndarray]]) -> dict[int, list[bytes | None]]:
    return {int(j): [to_bytes(z), to_bytes(lam)] for j, (z, lam) in edges.items()}


def _edges_in(state: dict[Any, list[bytes]]) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    return {int(j): (from_bytes(z), from_bytes(lam)) for j, (z, lam) in state.items()}


def save_state(core: AdaptiveGridCore) -> dict[str, Any]:
    """Everything of `core` beyond RoundCore's own checkpoint."""
    return {
        **{k: getattr(core, k) for k in _PLAIN},
        **{k: to_bytes(getattr(core, k)) for k in _VECTORS},
        "bounds": None if core.bounds is None else list(core.bounds),
        "sigma": core.sigma,
        "sigma_validation": [dict(r) for r in core.sigma_validation],
        "width_validation": [dict(r) for r in core.width_validation],
        "grid": to_bytes(None if core.grid is None else core.grid.ravel()),
        "allowed": None if core._allowed is None else to_bytes(core._allowed.astype(float)),
        "carry": _edges_out(core._carry),
        "edges_out": _edges_out(core._edges_out),
        "soft_duals": None if core._soft_duals is None else [list(core._soft_duals[0]), to_bytes(core._soft_duals[1].ravel())],
        "phases": [[p, r] for p, r in core.phases],
        "residuals": to_bytes(np.asarray(core.residuals, dtype=float)),
        "sweep": None if core._sweep is None else core._sweep.checkpoint(),
        "sub": None if core._sub is None else core._sub.checkpoint(),
        "history": [
            {**{k: v for k, v in h.items() if k != "grid"}, "grid": to_bytes(np.ravel(h["grid"]))}
            for h in core.grid_history
        ],
    }


def load_state(core: AdaptiveGridCore, state: dict[str, Any]) -> None:
    """Restore `save_state` output into a freshly built core of the same robot and data."""
    for k in _PLAIN:
        setattr(core, k, state[k])
    for k in _VECTORS:
        setattr(core, k, from_bytes(state[k]))
    core.bounds = None if state["bounds"] is None else tuple(float(b) for b in state["bounds"])
    core.sigma = None if state["sigma"] is None else float(state["sigma"])
    core.sigma_validation = [dict(r) for r in state["sigma_validation"]]
    # the parameters the fleet derived from its data: folds (BOUNDS), widths (TALLY)
    if core.bounds is not None:
        core.params = folds_for_data(core._given, core._held_units)[0]
    if core.sigma_validation:
        core.params = widths_for_data(core.params, core.sigma_validation)[0]
    core.width_validation = [dict(r) for r in state.get("width_validation", [])]
    if core.width_validation:  # the width test decided (WTALLY's end)
        core.params = choose_widths(core.params, core.width_validation)[0]
    core.grid_history = [
        {**{k: v for k, v in h.items() if k != "grid"}, "grid": from_bytes(h["grid"]).reshape(-1, 2).tolist()}
        for h in state["history"]
    ]
    core.phases = [(str(p), int(r)) for p, r in state["phases"]]
    core.residuals = from_bytes(state["residuals"]).tolist()
    core._allowed = None if state["allowed"] is None else from_bytes(state["allowed"]) > 0
    core._carry = _edges_in(state["carry"])
    core._edges_out = _edges_in(state["edges_out"])
    duals = state["soft_duals"]  # (checkpoint version 4)
    core._soft_duals = None if duals is None else (
        tuple(int(i) for i in duals[0]), from_bytes(duals[1]).reshape(len(duals[0]), -1))
    grid = from_bytes(state["grid"])
    if grid is not None:
        core._box = None if core.bounds is None else _box(core)
        core._set_grid(grid.reshape(-1, 2))
    core._sweep = None
    if state["sweep"] is not None:  # the sigma sweep, or the width test (rebuilt from the agreed seed)
        core._sweep = core._new_width_sweep() if core.phase in ("widths", "wtally") else core._new_sweep()
        core._sweep.restore(state["sweep"])
    core._sub = None
    if state["sub"] is not None:
        phase, start, carry, warm, phases = core.phase, core._phase_start, core._carry, core._warm, list(core.phases)
        core._enter_admm()  # rebuild with the same data and parameters, then resume exactly
        core._sub.restore(state["sub"])
        core.phase, core._phase_start, core._carry, core._warm, core.phases = phase, start, carry, warm, phases
    if core.phase == "done":
        core.finished = True


def _box(core: AdaptiveGridCore) -> tuple[float, float, float, float]:
    from agents.autogrid_rules import lattice_box

    return lattice_box(core.bounds, core.sigma)
