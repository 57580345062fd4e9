"""Key expressions: exact strings, validation, and the key -> robot inverse."""

import pytest
from hypothesis import given
from hypothesis import strategies as st

from protocol.keys import (
    MAX_FLEET_ID_LEN,
    MAX_ROBOT_ID,
    fleet_prefix,
    robot_from_key,
    state_key,
    state_wildcard,
    status_key,
    status_wildcard,
    validate_fleet_id,
    validate_robot_id,
)

fleet_ids = st.text(
    alphabet="abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_-",
    min_size=1,
    max_size=MAX_FLEET_ID_LEN,
)
robot_ids = st.integers(0, MAX_ROBOT_ID)


def test_exact_key_strings():
    assert fleet_prefix("demo") == "shapefleet/demo"
    assert state_key("demo", 3) == "shapefleet/demo/robot/3/state"
    assert status_key("demo", 3) == "shapefleet/demo/robot/3/status"
    assert state_wildcard("demo") == "shapefleet/demo/robot/*/state"
    assert status_wildcard("demo") == "shapefleet/demo/robot/*/status"


@pytest.mark.parametrize("fleet", ["a", "Fleet_01", "x-y", "z" * MAX_FLEET_ID_LEN])
def test_valid_fleet_ids(fleet):
    assert validate_fleet_id(fleet) == fleet


@pytest.mark.parametrize(
    ("fleet", "problem"),
    [
        ("", "empty"),
        ("z" * (MAX_FLEET_ID_LEN + 1), "65 characters"),
        ("a/b", "'/'"),
        ("a*", "'*'"),
        ("a b", "' '"),
        ("café", "'é'"),
        ("a$b", "'$'"),
        (7, "string"),
        (None, "string"),
    ],
)
def test_invalid_fleet_ids_name_the_problem(fleet, problem):
    with pytest.raises(ValueError, match=problem.replace("*", r"\*").replace("$", r"\$")):
        validate_fleet_id(fleet)


@pytest.mark.parametrize("robot", [-1, MAX_ROBOT_ID + 1, True, 1.0, "1", None])
def test_invalid_robot_ids(robot):
    with pytest.raises(ValueError, match="robot id"):
        validate_robot_id(robot)
    with pytest.raises(ValueError):
        state_key("demo", robot)


def test_key_builders_validate_fleet():
    for build in (fleet_prefix, state_wildcard, status_wildcard):
        with pytest.raises(ValueError):
            build("a/b")
    with pytest.raises(ValueError):
        status_key("", 1)


@given(fleet_ids, robot_ids)
def test_robot_from_key_inverts_builders(fleet, robot):
    assert robot_from_key(state_key(fleet, robot)) == robot
    assert robot_from_key(status_key(fleet, robot)) == robot


@pytest.mark.parametrize(
    "key",
    [
        "shapefleet/demo/robot/*/state",
        "shapefleet/demo/robot/03/state",
        "shapefleet/demo/robot/-3/state",
        "shapefleet/demo/robot/+3/state",
        "shapefleet/demo/robot/3/other",
        "shapefleet/demo/robot/3/state/extra",
        "shapefleet/demo/robot/3",
        "shapefleet/demo/robot//state",
        f"shapefleet/demo/robot/{MAX_ROBOT_ID + 1}/state",
        "shapefleet/demo/robot/99999999999/state",
        "shapefleet/a/b/robot/3/state",
        "shapefleet//robot/3/state",
        "other/demo/robot/3/state",
        " shapefleet/demo/robot/3/state",
        "shapefleet/demo/robot/3/state\n",
        "shapefleet/demo/robot/٣/state",  # non-ASCII digit
        "",
        None,
        b"shapefleet/demo/robot/3/state",
    ],
)
def test_robot_from_key_rejects_non_canonical(key):
    assert robot_from_key(key) is None


def _canonical_key(fleet: str, robot: int, kind: str) -> str:
    return state_key(fleet, robot) if kind == "state" else status_key(fleet, robot)


canonical_keys = st.builds(_canonical_key, fleet_ids, st.integers(0, MAX_ROBOT_ID), st.sampled_from(["state", "status"]))
# near misses: a canonical key with a character inserted, removed or replaced somewhere
near_keys = st.tuples(canonical_keys, st.integers(0, 200), st.integers(0, 2), st.characters()).map(
    lambda t: t[0][: t[1]] + (t[3] if t[2] != 1 else "") + t[0][t[1] + (t[2] != 0):]
)


@given(fleet_ids, st.integers(0, MAX_ROBOT_ID), st.sampled_from(["state", "status"]))
def test_robot_from_key_inverts_the_key_builders(fleet, robot, kind):
    assert robot_from_key(_canonical_key(fleet, robot, kind)) == robot


@given(st.one_of(st.text(max_size=80), canonical_keys, near_keys))
def test_robot_from_key_total(key):
    """Whatever the string: None, or the id of the canonical key it is (the equality branch is
    reached by the canonical keys and by near misses that are still canonical)."""
    result = robot_from_key(key)
    if result is None:
        return
    fleet = key.split("/")[1]
    assert key in (state_key(fleet, result), status_key(fleet, result))


def test_robot_from_key_total_reaches_both_branches():
    """The strategy above really produces keys that are recognised and keys that are not."""
    seen = {"id": 0, "none": 0}

    @given(st.one_of(st.text(max_size=80), canonical_keys, near_keys))
    def probe(key):
        seen["id" if robot_from_key(key) is not None else "none"] += 1

    probe()
    assert seen["id"] > 0 and seen["none"] > 0, seen


def test_alive_keys_live_beside_the_state_keys():
    from protocol.keys import alive_key, alive_wildcard

    assert alive_key("f-1", 7) == "shapefleet/f-1/robot/7/alive"
    assert alive_wildcard("f-1") == "shapefleet/f-1/robot/*/alive"
    with pytest.raises(ValueError):
        alive_key("f-1", -1)
