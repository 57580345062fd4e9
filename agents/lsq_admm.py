"""The fleet's consensus ADMM on the LiDAR least-squares model (agents/lsq_model.py).

The round machinery is agents/admm.py's `ConsensusADMM` as it is -- the hub form with Anderson
acceleration on a complete graph, the edge form on sparse graphs, the stop rule, frames, checkpoints,
drops -- with one change: the local step. Where the SVM solves a margin QP, a robot here solves

    argmin_v  |A_l v - t_l|^2 + lam / N |x|^2 + q' v + 1/2 v' diag(prox) v

a linear system whose matrix is fixed for the run (`LsqLocalStep`: factored once, two triangular
solves a round). The shares sum to the central objective and the ADMM keeps sum of duals = 0, so
the fleet's fixed point is the exact central least-squares fit (`solve_central_lsq`). The relay hub
(sparse graphs, agents/relay_hub.py) and the SVM's end-games and certified guard are not used:
their payloads are built from margins.

No I/O, no clock.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from agents.admm import ADMMParams, ConsensusADMM
from agents.autogrid_warm import WarmADMM
from agents.lsq_model import DEFAULT_LSQ_LAMBDA, LsqLocalStep, check_lsq_lambda
from agents.params import params_from
from agents.rounds import RobotShare


@dataclass(frozen=True)
class LSQParams:
    """The least-squares fleet's parameters: the model's ridge weight and admm's consensus settings
    (the same meaning as ADMMParams', the same defaults but rho's)."""

    lam: float = DEFAULT_LSQ_LAMBDA
    # admm's 15 is the SVM's scale (1/N |x|^2); a robot's least-squares curvature 2 A'A is of its rows'
    # scale: measured on 8x6 / 12x10 grids, 8 robots complete and ring, rho 1 took 78-100 / 351-626 rounds
    # to the stop against 174 / 3004 (8x6) with 15; 0.3 was slower, 3 too but on the 12x10 ring (docs/algorithm.md)
    rho: float = 1.0
    gamma_penalty: float = 3.0
    relax: float = 1.95
    tol: float = 1e-3
    max_rounds: int = 5000
    diameter: int = 1
    anderson: int = 30
    safeguard: float = 2.0

    def __post_init__(self) -> None:
        check_lsq_lambda(self.lam)
        self.admm  # (ADMMParams' own checks, by name)

    @property
    def admm(self) -> ADMMParams:
        """The consensus settings as `ConsensusADMM` takes them: no relay hub, no end-game, no
        certified guard (all three are built on margins)."""
        return ADMMParams(
            rho=self.rho, gamma_penalty=self.gamma_penalty, relax=self.relax, tol=self.tol,
            max_rounds=self.max_rounds, diameter=self.diameter, anderson=self.anderson, safeguard=self.safeguard,
            relay=False, certify=0.0, polish=False, soft_polish=False,
        )

    @classmethod
    def from_params(cls, params: Mapping[str, Any]) -> LSQParams:
        """From a fleet file's ``params``: exactly this class's fields."""
        return params_from(cls, params, "lsq")


class ConsensusLSQ(ConsensusADMM):
    """One robot of the least-squares fleet. ``share.features`` are the features of its model rows
    (agents/lsq_model.py `lsq_rows`) and ``share.labels`` their targets (+1, 0, -1)."""

    algorithm = "lsq"

    def __init__(self, share: RobotShare, params: LSQParams, *, keep_trace: bool = True) -> None:
        self.lsq_params = params  # (before the base class builds the first local step)
        super().__init__(share, params.admm, keep_trace=keep_trace)

    def _build_qp(self) -> LsqLocalStep:  # type: ignore[override]
        """The local step of this robot's share: its rows, lam / (robots the fleet still holds)
        |x|^2 (as the SVM's soft margin weighs 1/2 |x|^2), the ADMM's proximal weights."""
        robots = len(self._hub.ids) if self._hub is not None else self._n_robots - len(self._weighed_gone())
        return LsqLocalStep(self._features, self._labels, x_weight=self.lsq_params.lam / robots,
                            prox_weight=self._prox_weight())

    def _weight_matters(self) -> bool:
        """The fit depends on lam / N: the survivors of a drop reweigh (their own problem's optimum)."""
        return True


class WarmLSQ(WarmADMM):
    """The least-squares local step in autogrid's sub-machine (agents/autogrid_warm.py `WarmADMM`):
    the sigma sweep's (candidate, fold) fits and the final fit of ``AutoGridParams(model="lsq")``.
    ``share.features`` / ``share.labels`` are the rows' features and targets, as for `ConsensusLSQ`."""

    def __init__(self, *args: Any, lam: float, **kwargs: Any) -> None:
        self.lsq_params = LSQParams(lam=lam)  # (only lam is read: the consensus settings are the given ADMMParams)
        super().__init__(*args, **kwargs)

    _build_qp = ConsensusLSQ._build_qp
    _weight_matters = ConsensusLSQ._weight_matters

    def _local_step(self) -> np.ndarray:
        """Round 0 in the edge form without a given start: the ordinary ADMM step from zero edge state (each
        robot's rows pulled towards 0 by its edges' penalty), not the robot's own fit. A robot's own fit with
        lam / N extrapolates far beyond its data on wide kernels; measured on the 8-ring the sweep took 311
        rounds from this step against 418 from the own fit, before the fits of all rows joined it (the diag/4 task the
        slowest; benchmarks/results/lsq.md).
        The hub form (complete graphs) keeps the own fit."""
        if self._hub is None and self._start is None and not self._carry and self.neighbours:
            return self._primal_step()
        return super()._local_step()


def lsq_sub_params(lam: float, *, rho: float, relax: float, tol: float, max_rounds: int, diameter: int) -> ADMMParams:
    """The consensus settings of autogrid's least-squares sub-machines: LSQParams' (no relay hub, no
    end-game, no certified guard) with autogrid's tolerance, cap and diameter."""
    return LSQParams(lam=lam, rho=rho, relax=relax, tol=tol, max_rounds=max_rounds, diameter=diameter).admm
