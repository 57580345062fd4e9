"""Zenoh key expressions of a fleet.

Every key lives under ``shapefleet/<fleet>/``, so fleets sharing a router never see each other's
frames, and a robot subscribes to one wildcard instead of one key per neighbour. Fleet ids are
restricted to ``[A-Za-z0-9_-]`` so they can never contain Zenoh's ``/``, ``*``, ``$``, ``?``,
``#`` and thereby widen a subscription.
"""

from __future__ import annotations

import re

from agents.messages import MAX_ROBOT_ID, check_robot_id

ROOT = "shapefleet"
MAX_FLEET_ID_LEN = 64

_FLEET_CHARS = re.compile(r"[A-Za-z0-9_-]")
_ROBOT_KEY = re.compile(
    rf"{ROOT}/[A-Za-z0-9_-]{{1,{MAX_FLEET_ID_LEN}}}/robot/(0|[1-9][0-9]{{0,9}})/(?:state|status)"
)


def validate_fleet_id(s: str) -> str:
    """Return ``s`` if it is a usable fleet id, else raise ValueError saying what is wrong."""
    if not isinstance(s, str):
        raise ValueError(f"fleet id must be a string, got {type(s).__name__}")
    if not s:
        raise ValueError("fleet id is empty")
    if len(s) > MAX_FLEET_ID_LEN:
        raise ValueError(
            f"fleet id {s[:16]!r}... is {len(s)} characters long (at most {MAX_FLEET_ID_LEN})"
        )
    for ch in s:
        if not _FLEET_CHARS.fullmatch(ch):
            raise ValueError(
                f"fleet id {s!r} contains {ch!r} (allowed: letters, digits, '_' and '-')"
            )
    return s


#: ``robot`` if it is an int in [0, 2**31), else ValueError (bool is refused): a key names a
#: robot as a message does, by one rule (agents/messages.py)
validate_robot_id = check_robot_id


def fleet_prefix(fleet: str) -> str:
    """``shapefleet/<fleet>``: everything one fleet publishes lives below it."""
    return f"{ROOT}/{validate_fleet_id(fleet)}"


def state_key(fleet: str, robot: int) -> str:
    """Key on which ``robot`` publishes its consensus frames."""
    return f"{fleet_prefix(fleet)}/robot/{validate_robot_id(robot)}/state"


def status_key(fleet: str, robot: int) -> str:
    """Key on which ``robot`` publishes its status for the launcher."""
    return f"{fleet_prefix(fleet)}/robot/{validate_robot_id(robot)}/status"


def state_wildcard(fleet: str) -> str:
    """One subscription that matches the state key of every robot of the fleet."""
    return f"{fleet_prefix(fleet)}/robot/*/state"


def status_wildcard(fleet: str) -> str:
    """One subscription that matches the status key of every robot of the fleet."""
    return f"{fleet_prefix(fleet)}/robot/*/status"


def alive_key(fleet: str, robot: int) -> str:
    """Liveliness token of a robot, declared once its subscriptions are in place."""
    return f"{fleet_prefix(fleet)}/robot/{validate_robot_id(robot)}/alive"


def alive_wildcard(fleet: str) -> str:
    return f"{fleet_prefix(fleet)}/robot/*/alive"


def robot_from_key(key: str) -> int | None:
    """Robot id of a state or status key, or None if ``key`` is not one.

    Only canonical keys (as built by :func:`state_key` / :func:`status_key`) are recognised:
    no leading zeros, no sign, id within range.
    """
    if not isinstance(key, str):
        return None
    m = _ROBOT_KEY.fullmatch(key)
    if m is None:
        return None
    robot = int(m.group(1))
    return robot if robot <= MAX_ROBOT_ID else None
