"""What one robot is told at start: the shared problem, its own data and its neighbours.

A `FleetSpec` is the single hand-over between the launcher and the robots (in-process or as
processes). It is plain JSON on disk, so a robot on another host needs only this file.
`build_core` turns it into the robot's algorithm state machine; shells never see the maths.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, replace
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from agents.admm import FRAME_BUDGET, ADMMParams, ConsensusADMM, hub_form, hub_frame_dim, polish_max_dim
from agents.autogrid import AdaptiveGridCore, AutoGridParams
from agents.ct_admm import ContinuousTimeADMM, CTADMMParams
from agents.extension import load_algorithm
from agents.kernel import GridBasis
from agents.lsq_admm import ConsensusLSQ, LSQParams
from agents.lsq_model import lsq_rows, model_words, solve_central_lsq
from agents.newton import DistributedNewton, NewtonParams, frame_size
from agents.relay_hub import RelayHubADMM, relay_form, relay_frame_dim
from agents.params import params_from
from agents.problem import CentralSolution, solve_central
from agents.rounds import RobotShare
from protocol.auth import FLEET_SECRET_BYTES, FrameAuth, new_fleet_secret
from protocol.frames import config_tag as make_config_tag
from protocol.keys import validate_fleet_id
from protocol.links import LinkFaults

ALGORITHMS = ("admm", "ct-admm", "autogrid", "newton", "lsq")
#: algorithms whose grid and sigma are fixed by the launcher (autogrid's fleet chooses its own)
FIXED_GRID_ALGORITHMS = ("admm", "ct-admm", "newton", "lsq")
#: each algorithm's typed parameters: the fleet file's ``params`` are the fields of its class
PARAMS_CLASSES: dict[str, type] = {
    "admm": ADMMParams, "ct-admm": CTADMMParams, "autogrid": AutoGridParams, "newton": NewtonParams,
    "lsq": LSQParams,
}


@dataclass(frozen=True)
class Timing:
    """Shell time-outs (seconds): never part of the mathematics."""

    retransmit_s: float = 0.02
    dead_after_s: float = 6.0
    max_wall_s: float = 600.0
    linger_s: float = 1.0


@dataclass(frozen=True)
class RobotSpec:
    """One robot's data and neighbour list."""

    id: int
    neighbours: tuple[int, ...]
    points: np.ndarray
    labels: np.ndarray


@dataclass
class FleetSpec:
    """Everything every robot must agree on, plus each robot's own part.

    For ``admm`` and ``ct-admm`` ``grid`` and ``sigma`` are the shared basis. For ``autogrid``
    the fleet chooses them: ``grid`` is the optional *start* grid (empty, shape (0, 2): the
    fleet's own lattice) and ``sigma`` a fixed width or None (chosen by the fleet); each robot's
    result then holds the final grid and sigma.
    """

    fleet: str
    algorithm: str
    sigma: float | None
    C: float | None
    grid: np.ndarray
    robots: dict[int, RobotSpec]
    params: dict[str, Any] = field(default_factory=dict)
    faults: LinkFaults = field(default_factory=LinkFaults.none)
    seed: int = 0
    timing: Timing = field(default_factory=Timing)
    owner: int | None = None  # set in a per-robot fleet file (for_robot): the one robot whose data it holds
    # frame authentication (protocol/auth.py): the full file holds the fleet secret, a per-robot
    # file only the keys of its owner's edges (neighbour id -> key)
    secret: bytes | None = field(default_factory=new_fleet_secret, repr=False)
    edge_keys: dict[int, bytes] | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        validate_fleet_id(self.fleet)
        if self.secret is None and (self.edge_keys is None or self.owner is None):
            raise ValueError("no frame keys: a fleet file needs the fleet secret, or its robot's edge keys")
        if self.secret is not None and len(self.secret) != FLEET_SECRET_BYTES:
            raise ValueError(f"the fleet secret must be {FLEET_SECRET_BYTES} bytes")
        if self.secret is None:
            FrameAuth(self.owner, self.edge_keys)  # ValueError names a bad key
        if self.owner is not None and self.owner not in self.robots:
            raise ValueError(f"fleet file is for robot {self.owner}, which is not in the fleet (robots {sorted(self.robots)})")
        if self.algorithm not in ALGORITHMS:
            try:
                load_algorithm(self.algorithm)  # a user's fleet algorithm (agents/extension.py)
            except ValueError as exc:
                raise ValueError(f"unknown algorithm {self.algorithm!r} ({exc}); choose from "
                                 f"{', '.join(ALGORITHMS)} or name your own (agents/extension.py)") from None
        self.grid = np.asarray(self.grid, dtype=float).reshape(-1, 2)
        if self.algorithm in FIXED_GRID_ALGORITHMS and (self.sigma is None or len(self.grid) == 0):
            raise ValueError(f"{self.algorithm} needs a grid and a sigma (only autogrid chooses them itself)")

    @property
    def graph(self) -> dict[int, tuple[int, ...]]:
        """Every robot's neighbour list (each robot knows the whole communication graph)."""
        return {i: r.neighbours for i, r in self.robots.items()}

    @property
    def robot_ids(self) -> tuple[int, ...]:
        return tuple(sorted(self.robots))

    @property
    def n_robots(self) -> int:
        return len(self.robots)

    @property
    def custom(self) -> bool:
        """True for a user's fleet algorithm (a dotted path or entry point: agents/extension.py)."""
        return self.algorithm not in ALGORITHMS

    @property
    def fixed_grid(self) -> bool:
        """True when grid and sigma are the shared basis (not chosen by the fleet)."""
        return self.algorithm in FIXED_GRID_ALGORITHMS

    @cached_property
    def basis(self) -> GridBasis:
        if not self.fixed_grid:
            raise ValueError("an autogrid fleet chooses its own grid and sigma: each robot's result holds them")
        return GridBasis(self.grid, self.sigma)

    @cached_property
    def autogrid_params(self) -> AutoGridParams:
        """The autogrid robots' parameters: ``params`` (AutoGridParams' fields, strictly) with
        ``sigma`` and ``C`` from the fleet file's own fields. ValueError names a bad key or value."""
        if "sigma" in self.params or "C" in self.params:
            raise ValueError("autogrid parameters sigma and C are the fleet file's own fields, not params")
        if "hub_frames" in self.params:
            raise ValueError("autogrid parameter hub_frames follows from the graph, it is not a params key")
        return AutoGridParams.from_params(
            {**self.params, "sigma": self.sigma, "C": self.C, "hub_frames": self._hub_form(ADMMParams())}
        )

    @property
    def algorithm_params(self) -> Any:
        """The typed parameters of this fleet's algorithm (PARAMS_CLASSES: ADMMParams,
        CTADMMParams, AutoGridParams or NewtonParams), read strictly from ``params``."""
        if self.algorithm == "autogrid":
            return self.autogrid_params
        if self.custom:  # a user's fleet algorithm: its own params_class, read as strictly
            return params_from(load_algorithm(self.algorithm).params_class, self.params, self.algorithm)
        params = PARAMS_CLASSES[self.algorithm].from_params(self.params)
        if self.algorithm == "admm" and endgame_default(params, self.C, self.params, self._hub_form(params)):
            return replace(params, soft_polish=True, hard_endgame=params.hard_endgame or self.C is None)
        return params

    def _hub_form(self, params: ADMMParams) -> bool:
        """True when the fleet's ADMM runs the hub form, whose frames carry [v; w]."""
        if not self.robots:
            return False
        r = self.robots[self.robot_ids[0]]
        degrees = {j: len(self.robots[j].neighbours) for j in r.neighbours if j in self.robots}
        return hub_form(params, self.n_robots, r.neighbours, degrees)

    def polish_refusal(self) -> str | None:
        """Why admm's exact end-game (ADMMParams.polish) cannot run on this fleet, or None: it
        certifies a hard margin, in the hub form (a complete graph), within the frame budget."""
        if self.C is not None:
            return "needs a hard margin (the end-game certifies margins held); drop --C"
        if not self._hub_form(self.algorithm_params):
            return (f"needs a complete graph (the hub form); this graph of {self.n_robots} robots is not complete, "
                    "(the relay hub of sparse fleets runs its own exact end-game, hard margins: docs/algorithm.md)")
        dim = len(self.grid) + 1
        if dim > polish_max_dim():
            frame = hub_frame_dim(replace(self.algorithm_params, polish=True), dim)
            return (f"the grid has {len(self.grid)} points; the end-game's frames would carry {frame} numbers, "
                    f"more than the budget of {FRAME_BUDGET} x {dim}; use a grid of at most {polish_max_dim() - 1} points")
        return None

    @property
    def dim(self) -> int:
        """Length of the vector robots exchange: (x, gamma), autogrid's padded frame, or
        newton's reduction payload, or a user algorithm's frame_dim."""
        if self.custom:
            return int(load_algorithm(self.algorithm).frame_dim(self))
        if not self.fixed_grid:
            return self.autogrid_params.dim
        if self.algorithm == "newton":
            return frame_size(len(self.grid) + 1, self.graph, self.algorithm_params)
        if self.algorithm == "admm" and self._hub_form(self.algorithm_params):
            return hub_frame_dim(self.algorithm_params, len(self.grid) + 1)  # [v; w] (+ the polish's payload)
        if self.algorithm == "lsq" and self._hub_form(self.algorithm_params):
            return hub_frame_dim(self.algorithm_params.admm, len(self.grid) + 1)  # [v; w]
        if self.algorithm == "admm" and relay_form(self.algorithm_params, self.graph, len(self.grid) + 1):
            return relay_frame_dim(self.algorithm_params, self.n_robots, len(self.grid) + 1,  # [a; payload] per robot
                                   self.graph, self.C is None)  # (or the end-game's all-reduce, if larger)
        return len(self.grid) + 1

    @cached_property
    def config_tag(self) -> bytes:
        """Fingerprint of the shared problem: robots configured differently reject each other."""
        return make_config_tag(
            self.algorithm,
            -1.0 if self.sigma is None else self.sigma,
            -1.0 if self.C is None else self.C,
            self.grid,
            json.dumps(self.params, sort_keys=True),
            np.asarray(self.robot_ids, dtype=float),
        )

    def for_robot(self, robot_id: int) -> FleetSpec:
        """The fleet file of one robot host: the shared problem, every robot's neighbour list (a
        robot's update uses its neighbours' degrees), and the data of ``robot_id`` only.

        The config tag is unchanged (it never depends on the data): robots started from their own
        per-robot files and from the full file agree.
        """
        if robot_id not in self.robots:
            raise ValueError(f"robot {robot_id} is not in fleet {self.fleet} (robots {list(self.robot_ids)})")
        if self.owner is not None and self.owner != robot_id:
            raise ValueError(f"this fleet file holds robot {self.owner}'s data only, not robot {robot_id}'s")
        empty = np.zeros((0, 2))
        robots = {
            i: r if i == robot_id else RobotSpec(i, r.neighbours, empty, np.zeros(0, dtype=int))
            for i, r in self.robots.items()
        }
        keys = self.frame_auth(robot_id).keys
        return replace(self, robots=robots, owner=robot_id, secret=None, edge_keys=dict(keys))

    def frame_auth(self, robot_id: int) -> FrameAuth:
        """Robot ``robot_id``'s frame keys: one per edge to a neighbour (docs/protocol.md)."""
        if robot_id not in self.robots:
            raise ValueError(f"robot {robot_id} is not in fleet {self.fleet} (robots {list(self.robot_ids)})")
        if self.secret is not None:
            return FrameAuth.from_secret(self.secret, robot_id, self.robots[robot_id].neighbours)
        if self.owner != robot_id or self.edge_keys is None:
            raise ValueError(f"this fleet file holds robot {self.owner}'s frame keys only, not robot {robot_id}'s")
        return FrameAuth(robot_id, self.edge_keys)

    # -- JSON --------------------------------------------------------------------------------
    def to_json(self) -> dict[str, Any]:
        extra: dict[str, Any] = {} if self.owner is None else {"for": self.owner}
        if self.secret is not None:
            auth: dict[str, Any] = {"secret": self.secret.hex()}
        else:
            auth = {"edge_keys": {str(j): k.hex() for j, k in sorted((self.edge_keys or {}).items())}}
        return {
            **extra,
            "auth": auth,
            "fleet": self.fleet,
            "algorithm": self.algorithm,
            "sigma": self.sigma,
            "C": self.C,
            "grid": self.grid.tolist(),
            "params": self.params,
            "faults": asdict(self.faults),
            "seed": self.seed,
            "timing": asdict(self.timing),
            "robots": [
                {
                    "id": r.id,
                    "neighbours": list(r.neighbours),
                    "points": r.points.tolist(),
                    "labels": [int(v) for v in r.labels],
                }
                for r in self.robots.values()
            ],
        }

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> FleetSpec:
        robots = {
            int(r["id"]): RobotSpec(
                int(r["id"]),
                tuple(int(j) for j in r["neighbours"]),
                np.asarray(r["points"], dtype=float).reshape(-1, 2),
                np.asarray(r["labels"], dtype=int),
            )
            for r in data["robots"]
        }
        auth = data.get("auth")
        if not isinstance(auth, dict) or not ({"secret", "edge_keys"} & set(auth)):
            raise ValueError(
                "no frame keys (\"auth\"): it was written by a shapefleet without frame "
                "authentication; write it again (shapefleet launch / deploy)"
            )
        secret = None if auth.get("secret") is None else bytes.fromhex(auth["secret"])
        edge_keys = (
            None
            if auth.get("edge_keys") is None
            else {int(j): bytes.fromhex(k) for j, k in auth["edge_keys"].items()}
        )
        return cls(
            fleet=data["fleet"],
            algorithm=data["algorithm"],
            sigma=None if data["sigma"] is None else float(data["sigma"]),
            C=None if data["C"] is None else float(data["C"]),
            grid=np.asarray(data["grid"], dtype=float),
            robots=robots,
            params=dict(data.get("params", {})),
            faults=LinkFaults(**data.get("faults", {})),
            seed=int(data.get("seed", 0)),
            timing=Timing(**data.get("timing", {})),
            owner=None if data.get("for") is None else int(data["for"]),
            secret=secret,
            edge_keys=edge_keys,
        )

    def save(self, path: Path) -> None:
        Path(path).write_text(json.dumps(self.to_json()))

    def share(self, robot_id: int, *, points: bool = False) -> RobotShare:
        """Robot ``robot_id``'s share of the problem as its core takes it: the basis's features of
        its points (``points``: the raw points, for autogrid, which builds features per grid),
        the fleet's C and every neighbour's degree (for the hub form's verdict)."""
        me = self.robots[robot_id]
        degrees = {j: len(self.robots[j].neighbours) for j in me.neighbours}
        if self.algorithm == "lsq":  # the model's rows (a pair: outside, midpoint, inside) and their targets
            row_points, targets = lsq_rows(me.points, me.labels)
            return RobotShare(robot_id, me.neighbours, self.basis.features(row_points), targets,
                              n_robots=self.n_robots, C=None, degrees=degrees)
        rows = me.points if points else self.basis.features(me.points)
        return RobotShare(robot_id, me.neighbours, rows, me.labels, n_robots=self.n_robots, C=self.C, degrees=degrees)

    @property
    def model(self) -> str | None:
        """The model a fixed-grid fleet fits, in words (result.json's ``model``); None for autogrid
        (its margin is chosen by the fleet) and for a user's algorithm."""
        if self.algorithm == "lsq":
            return model_words(self.algorithm_params.lam)
        if not self.fixed_grid or self.custom:
            return None
        return "hard-margin SVM" if self.C is None else f"soft-margin SVM, C {self.C:g}"

    def central(self, robots: list[tuple[int, np.ndarray, np.ndarray]]) -> CentralSolution:
        """The exact reference of this fleet's model on the data of ``robots`` ((id, points, labels)
        each): the central QP of the margin, or for lsq the central least-squares fit (each robot's
        pairs read in its own data, as its share does)."""
        points = np.vstack([p for _, p, _ in robots]).reshape(-1, 2)
        labels = np.concatenate([np.asarray(lab) for _, _, lab in robots])
        if self.algorithm == "lsq":
            robot_of = np.concatenate([np.full(len(p), i) for i, p, _ in robots])
            return solve_central_lsq(self.basis, points, labels, self.algorithm_params.lam, robot_of=robot_of)
        return solve_central(self.basis, points, labels, self.C)

    @classmethod
    def load(cls, path: Path) -> FleetSpec:
        """Read a fleet file; errors name the file (the CLI turns them into exit code 2)."""
        try:
            data = json.loads(Path(path).read_text())
            return cls.from_json(data)
        except OSError as exc:
            raise ValueError(f"{path}: cannot read fleet file ({exc.strerror})") from None
        except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"{path}: not a valid fleet file ({exc})") from None


def endgame_default(params: ADMMParams, C: float | None, given: Any, hub: bool) -> bool:
    """True when an admm fleet runs the exact end-game (agents/soft_endgame.py) without asking: the hub
    form (a complete graph), the fleet file silent on ``soft_polish``, no hard ``polish``; soft margins
    always, hard margins (``hard_endgame``) unless the fleet file names ``certify`` (``--certify``: the
    certified guard it asked for, or with 0 the rule alone) or sets ``hard_endgame`` false. It paid on
    every complete fleet measured, 3-48 robots, certified exact (soft: paper preset --C 10 163 -> 64
    rounds; hard: 120 -> 107, 32 robots 2219 -> 1022; benchmarks/results/rounds.md, top). Sparse fleets
    are unchanged (the flag would drop the relay hub's guard slot from their frames)."""
    if not hub or "soft_polish" in given or params.polish or params.soft_polish:
        return False
    if C is not None:
        return True
    return "certify" not in given and ("hard_endgame" not in given or params.hard_endgame)


Core = ConsensusADMM | ConsensusLSQ | RelayHubADMM | ContinuousTimeADMM | AdaptiveGridCore | DistributedNewton  # or a user's RoundCore


def build_core(spec: FleetSpec, robot_id: int, *, keep_trace: bool = True) -> Core:
    """The algorithm state machine of one robot, from the fleet file (dispatch on the algorithm).

    ``keep_trace`` (every round's exchanged vector, for the launcher's convergence history) is
    ignored for autogrid: its vectors change meaning from phase to phase and have
    ``max_points + 2`` entries over thousands of rounds; its result reports the grids instead.
    """
    if robot_id not in spec.robots:
        raise ValueError(f"robot {robot_id} is not in fleet {spec.fleet} (robots {list(spec.robot_ids)})")
    if spec.owner is not None and spec.owner != robot_id:
        raise ValueError(f"this fleet file holds robot {spec.owner}'s data only, not robot {robot_id}'s")
    if spec.custom:  # a user's fleet algorithm builds itself from the fleet file
        return load_algorithm(spec.algorithm).from_spec(spec, robot_id, keep_trace=keep_trace)
    if spec.algorithm == "autogrid":
        start_grid = spec.grid if len(spec.grid) else None
        return AdaptiveGridCore(spec.share(robot_id, points=True), spec.autogrid_params, start_grid=start_grid)
    share, params = spec.share(robot_id), spec.algorithm_params
    if spec.algorithm == "newton":
        return DistributedNewton(share, params, graph=spec.graph, keep_trace=keep_trace)
    if spec.algorithm == "ct-admm":
        return ContinuousTimeADMM(share, params, keep_trace=keep_trace)
    if spec.algorithm == "lsq":
        return ConsensusLSQ(share, params, keep_trace=keep_trace)
    if relay_form(params, spec.graph, share.dim):  # a sparse graph of <= 16 robots: the relay hub
        return RelayHubADMM(share, params, graph=spec.graph, keep_trace=keep_trace)
    return ConsensusADMM(share, params, keep_trace=keep_trace)


def restore_core(spec: FleetSpec, robot_id: int, checkpoint: dict[str, Any]) -> Core:
    """A robot restarted after a crash resumes exactly where its checkpoint left it."""
    core = build_core(spec, robot_id)
    try:
        core.restore(checkpoint)
    except KeyError as exc:  # a field this code's state has and the checkpoint's writer did not
        raise ValueError(
            f"robot {robot_id}'s checkpoint has no field {exc.args[0]!r}: it was written by another "
            "version of shapefleet; start the run afresh (delete its checkpoint directory)"
        ) from None
    return core
