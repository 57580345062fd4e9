"""Your own per-robot algorithm on the fleet: the extension point (issue 17).

The built-in algorithms (admm, ct-admm, newton, autogrid) are sans-IO state machines on the
round protocol of :class:`agents.rounds.RoundCore`: the shells feed neighbours' frames in and take
frames out; exact recovery of lost frames, resend, dedup, authentication, neighbour death,
checkpoints and the stop flags are the session's and the base class's. A user algorithm plugs into
the same machinery, so it runs in ``simulate`` and ``launch`` with the same faults, crashes,
checkpoints and reports.

A fleet algorithm is a subclass of :class:`FleetAlgorithm` (itself a ``RoundCore``) that provides

* ``from_spec(spec, robot_id, *, keep_trace)`` (classmethod): build robot ``robot_id``'s core from
  the fleet file: its data ``spec.robots[robot_id]`` (points, labels), its neighbours, the graph
  ``spec.graph`` and its typed parameters ``spec.algorithm_params`` (an instance of
  ``params_class``);
* ``params_class``: a dataclass of its parameters (default :class:`FleetParams`: ``tol``,
  ``max_rounds``, ``diameter``). The options table (launcher/options.py) fills each field from
  the option that feeds the admm parameter of the same name (``--tol``, ``--max-rounds``,
  ``--rho``, ``--relax``) or, for ``diameter``, from the graph; other fields keep their default;
* ``frame_dim(spec)`` (classmethod): the length of the vector robots exchange each round;
* ``reference(spec)`` (classmethod): the exact centralized answer of the data in ``spec`` (the
  launcher measures every robot against it; with robots absent for good, ``spec`` holds the
  participants only);
* ``answer(self)``: this robot's answer as a vector (default: the exchanged vector);
* the RoundCore hooks: ``_step(mine, theirs) -> (new vector, my stop test)``,
  ``_forget_edge(j)`` (a neighbour died for good), ``_save_state()`` / ``_load_state(state)``
  (msgpack-able: what a checkpoint holds beyond the base class's).

It is named on the command line (``--algorithm``), in a TOML file or in the API by

* a dotted path ``package.module:ClassName`` (installed, on ``PYTHONPATH`` or in the current
  folder; ``shapefleet launch`` puts the module's root on the robot processes' PYTHONPATH), or
* an entry-point name in the group ``shapefleet.algorithms`` (``name = "package.module:ClassName"``
  in the ``[project.entry-points."shapefleet.algorithms"]`` table of your pyproject.toml).

The core stays pure: no I/O, no clock, no sockets (the loader imports; the core never does).
"""

from __future__ import annotations

import importlib
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from agents.rounds import RoundCore

#: the entry-point group a package registers its fleet algorithms in
ENTRY_POINT_GROUP = "shapefleet.algorithms"
#: the class methods a fleet algorithm must have (RoundCore's hooks come on top)
REQUIRED = ("from_spec", "frame_dim", "reference", "answer")


@dataclass(frozen=True)
class FleetParams:
    """The parameters every fleet algorithm gets unless it declares its own ``params_class``."""

    tol: float = 1e-3  # stop when the own stopping test is below this (the run's agreement tol too)
    max_rounds: int = 5000  # round cap
    diameter: int = 1  # at least the graph's diameter: rounds of stop flags (RoundCore)

    def __post_init__(self) -> None:
        if not self.tol > 0:
            raise ValueError(f"tol must be positive, got {self.tol!r}")
        if self.max_rounds < 1:
            raise ValueError(f"max_rounds must be at least 1, got {self.max_rounds!r}")


class FleetAlgorithm(RoundCore):
    """Base class of a user's per-robot algorithm (module doc): RoundCore plus four hooks."""

    algorithm = "custom"
    params_class: type = FleetParams

    @classmethod
    def from_spec(cls, spec: Any, robot_id: int, *, keep_trace: bool = True) -> FleetAlgorithm:
        """Robot ``robot_id``'s core from the fleet file ``spec`` (agents.spec.FleetSpec)."""
        raise NotImplementedError

    @classmethod
    def frame_dim(cls, spec: Any) -> int:
        """Length of the vector exchanged each round (the frame codec checks it)."""
        raise NotImplementedError

    @classmethod
    def reference(cls, spec: Any) -> np.ndarray | None:
        """The exact centralized answer of the data in ``spec`` (None: not known)."""
        return None

    def answer(self) -> np.ndarray:
        """This robot's answer (compared with ``reference`` and with its neighbours')."""
        return self.values

    def result(self) -> dict[str, Any]:
        """RoundCore's result plus ``answer`` (x and gamma keep the base layout)."""
        res = super().result()
        res["answer"] = [float(a) for a in np.asarray(self.answer(), dtype=float).ravel()]
        return res


_CACHE: dict[str, type] = {}


def load_algorithm(name: str) -> type:
    """The class named by a dotted path ``pkg.mod:Class`` or an entry-point name.

    ValueError with one line naming what is wrong (bad syntax, module not importable, no such
    class, not a fleet algorithm); callers prefix the flag or file.
    """
    if name in _CACHE:
        return _CACHE[name]
    target = name if ":" in name else _entry_point_target(name)
    module_name, _, attr = target.partition(":")
    if not module_name or not attr or not all(p.isidentifier() for p in module_name.split(".") + attr.split(".")):
        raise ValueError(f"{name!r} is not a dotted path package.module:ClassName")
    try:
        obj: Any = _import(module_name)
    except ImportError as exc:
        raise ValueError(f"{name!r}: cannot import module {module_name!r} ({exc})") from None
    except Exception as exc:  # noqa: BLE001 - a user module may fail any way at import
        raise ValueError(f"{name!r}: importing {module_name!r} failed ({type(exc).__name__}: {exc})") from None
    for part in attr.split("."):
        if not hasattr(obj, part):
            raise ValueError(f"{name!r}: module {module_name!r} has no {attr!r}")
        obj = getattr(obj, part)
    if not (isinstance(obj, type) and issubclass(obj, RoundCore)):
        raise ValueError(f"{name!r} is not a fleet algorithm (a subclass of agents.rounds.RoundCore)")
    missing = [m for m in REQUIRED if not callable(getattr(obj, m, None))]
    if missing:
        raise ValueError(f"{name!r} lacks {', '.join(missing)} (see agents/extension.py)")
    _CACHE[name] = obj
    return obj


def _import(module_name: str) -> Any:
    """Import ``module_name``; like uvicorn's app loader, a module in the current folder is
    found too (appended to sys.path, after everything else, only when not found otherwise)."""
    try:
        return importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        cwd = str(Path.cwd())
        if exc.name != module_name.split(".")[0] or cwd in sys.path or "" in sys.path:
            raise
        sys.path.append(cwd)
        return importlib.import_module(module_name)


def _entry_point_target(name: str) -> str:
    """``pkg.mod:Class`` of entry point ``name`` in ENTRY_POINT_GROUP (ValueError if none)."""
    import importlib.metadata  # here, not at the top: ~25-35 ms of every robot's start-up otherwise

    found = [ep for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP) if ep.name == name]
    if not found:
        raise ValueError(
            f"{name!r} is neither a built-in algorithm, nor a dotted path package.module:ClassName, "
            f"nor an entry point of group {ENTRY_POINT_GROUP!r}"
        )
    return str(found[0].value).replace(" ", "")


def import_root(name: str) -> Path | None:
    """The sys.path folder the module of algorithm ``name`` was imported from (robot processes
    need it on PYTHONPATH), or None when it cannot be told (e.g. a namespace without a file)."""
    cls = load_algorithm(name)
    module = sys.modules.get(cls.__module__)
    path = getattr(module, "__file__", None)
    if path is None:
        return None
    root = Path(path).resolve().parent
    if Path(path).name == "__init__.py":  # a package: its folder is one level of the name
        root = root.parent
    for _ in range(cls.__module__.count(".")):
        root = root.parent
    return root
