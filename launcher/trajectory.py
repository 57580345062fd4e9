"""The paper's Fig. 4: every component of one robot's [x; gamma] against time.

The data come from a core's trace (round -> exchanged vector (x, gamma)); for the
continuous-time ADMM a round is one communication period, so time = round * period.
Also the overshoot measure the tests and docs use, defined once here so both agree.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np


def trajectory_from_trace(trace: Mapping[Any, Sequence[float]], period: float) -> tuple[np.ndarray, np.ndarray]:
    """(times in s, values (rounds x (M+1))) from a trace whose keys are rounds (int or str)."""
    if not trace:
        raise ValueError("the trace is empty: run the core with keep_trace=True")
    if not (np.isfinite(period) and period > 0):
        raise ValueError(f"period must be a positive number of seconds, got {period!r}")
    rounds = sorted(int(k) for k in trace)
    by_round = {int(k): v for k, v in trace.items()}
    values = np.array([np.asarray(by_round[k], dtype=float) for k in rounds])
    return np.asarray(rounds, dtype=float) * period, values


def overshoot(values: np.ndarray) -> np.ndarray:
    """Per component: how far it went beyond its final value, in the direction of travel,
    as a fraction of its travel |final - initial|.

    0 means the component never passed its final value; 0.05 means it went 5 % of its travel
    past it. The direction of travel is sign(final - initial); only excursions past the final
    value in that direction count (approaching from the start side is not an overshoot). A
    component that did not move (travel 0) counts any excursion as infinite.
    """
    values = np.asarray(values, dtype=float)
    if values.ndim != 2 or len(values) < 2:
        raise ValueError(f"values must be (times, components) with at least two times, got {values.shape}")
    start, final = values[0], values[-1]
    travel = final - start
    direction = np.sign(travel)
    deviation = values - final
    beyond = np.where(direction != 0, np.max(direction * deviation, axis=0), np.max(np.abs(deviation), axis=0))
    beyond = np.maximum(beyond, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(beyond > 0, beyond / np.abs(travel), 0.0)


def plot_trajectory(
    path: str | Path,
    times: Sequence[float] | np.ndarray,
    values: np.ndarray,
    *,
    reference: Sequence[float] | np.ndarray | None = None,
    title: str = "",
) -> None:
    """One line per component of [x; gamma] against time (s); gamma drawn thick and labelled.

    `reference` (optional, length M+1): the centralized optimum, drawn as dotted levels so the
    approach can be judged by eye.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    times = np.asarray(times, dtype=float)
    values = np.asarray(values, dtype=float)
    if values.ndim != 2 or values.shape[0] != len(times) or values.shape[1] < 2:
        raise ValueError(f"values must be (len(times), M+1) with M >= 1, got {values.shape} for {len(times)} times")
    m = values.shape[1] - 1
    fig, ax = plt.subplots(figsize=(7.5, 4.5))
    cmap = matplotlib.colormaps["viridis"]
    for i in range(m):
        ax.plot(times, values[:, i], color=cmap(i / max(m - 1, 1)), lw=1.0, label="$x_i$" if i == 0 else None)
    ax.plot(times, values[:, m], color="crimson", lw=2.6, label=r"$\gamma$")
    if reference is not None:
        ref = np.asarray(reference, dtype=float)
        for i, level in enumerate(ref):
            ax.axhline(level, color="crimson" if i == m else "grey", ls=":", lw=0.8)
    ax.set_xlabel("time (s)")
    ax.set_ylabel(r"$[x^1;\ \gamma^1]$")
    ax.set_xlim(times[0], times[-1])
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=9)
    ax.set_title(title or r"trajectory of $[x^1;\ \gamma^1]$ of robot 1")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
