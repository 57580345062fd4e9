"""Session configs: discovery always off, loopback endpoints only, endpoints validated."""

from __future__ import annotations

import json
import socket

import pytest

from protocol.zenoh_config import (
    flatten,
    free_loopback_port,
    parse_endpoint,
    robot_config,
    robot_config_dict,
    router_config,
    router_config_dict,
    router_endpoint,
    validate_endpoint,
)

EP = "tcp/127.0.0.1:7447"


def _all_dicts():
    return {
        "router": router_config_dict(7447),
        "router-v6": router_config_dict(7447, "::1"),
        "robot": robot_config_dict([EP]),
        "robot-2": robot_config_dict([EP, "tcp/[::1]:7448"]),
    }


@pytest.mark.parametrize("name", list(_all_dicts()))
def test_every_dict_config_has_scouting_off(name):
    d = _all_dicts()[name]
    assert d["scouting"]["multicast"]["enabled"] is False
    assert d["scouting"]["gossip"]["enabled"] is False
    assert d["adminspace"]["enabled"] is False


@pytest.mark.parametrize(
    "conf",
    [lambda: router_config(7447), lambda: robot_config([EP]), lambda: robot_config([EP, "tcp/localhost:7000"])],
    ids=["router", "robot", "robot-2"],
)
def test_every_zenoh_config_has_scouting_off(conf):
    c = conf()
    scouting = json.loads(c.get_json("scouting"))
    assert scouting["multicast"]["enabled"] is False
    assert scouting["gossip"]["enabled"] is False


def test_router_config_listens_on_loopback_only():
    c = router_config(7450)
    assert json.loads(c.get_json("mode")) == "router"
    assert json.loads(c.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7450"]
    assert json.loads(c.get_json("connect/endpoints")) == []
    assert router_config_dict(7450, "::1")["listen"]["endpoints"] == ["tcp/[::1]:7450"]


def test_robot_config_is_a_client_of_the_router():
    c = robot_config([EP])
    assert json.loads(c.get_json("mode")) == "client"
    assert json.loads(c.get_json("connect/endpoints")) == [EP]
    assert json.loads(c.get_json("listen/endpoints")) == []
    retry = json.loads(c.get_json("connect/retry"))
    assert retry["period_init_ms"] > 0


def test_flatten_keeps_lists_and_optional_subtrees_whole():
    d = robot_config_dict([EP])
    flat = dict(flatten(d))
    assert flat["connect/endpoints"] == [EP]
    assert isinstance(flat["connect/retry"], dict)
    assert flat["scouting/multicast/enabled"] is False


@pytest.mark.parametrize(
    "endpoint, want",
    [
        ("tcp/127.0.0.1:7447", ("tcp", "127.0.0.1", 7447)),
        ("tcp/[::1]:1", ("tcp", "::1", 1)),
        ("tcp/localhost:65535", ("tcp", "localhost", 65535)),
        (" tcp/127.0.0.2:80 ", ("tcp", "127.0.0.2", 80)),
    ],
)
def test_parse_valid_endpoints(endpoint, want):
    assert parse_endpoint(endpoint) == want
    assert validate_endpoint(endpoint) == endpoint.strip()


@pytest.mark.parametrize(
    "endpoint, message",
    [
        ("127.0.0.1:7447", "not of the form"),
        ("tcp/127.0.0.1", "missing ':<port>'"),
        ("tcp/127.0.0.1:", "not a number"),
        ("tcp/127.0.0.1:http", "not a number"),
        ("tcp/127.0.0.1:0", "out of range"),
        ("tcp/127.0.0.1:70000", "out of range"),
        ("udp/127.0.0.1:7447", "protocol 'udp' not supported"),
        ("tcp/::1:7447", "brackets"),
        ("tcp/[::1:7447", "IPv6"),
        ("tcp/[zz]:7447", "not an IPv6 address"),
        ("tcp/127.0.0.1:7447?iface=lo", "not of the form"),
        ("tcp/10.0.0.5:7447", "not a loopback"),
        ("tcp/example.com:7447", "not a loopback"),
        ("tcp/[2001:db8::1]:7447", "not a loopback"),
        ("", "not of the form"),
    ],
)
def test_invalid_endpoints_raise_clear_value_error(endpoint, message):
    with pytest.raises(ValueError, match=message.replace("?", r"\?").replace("[", r"\[")):
        validate_endpoint(endpoint)
    with pytest.raises(ValueError):
        robot_config_dict([endpoint])


def test_non_loopback_allowed_only_on_request():
    assert validate_endpoint("tcp/10.0.0.5:7447", loopback_only=False) == "tcp/10.0.0.5:7447"
    assert robot_config_dict(["tcp/router:7447"], loopback_only=False)["connect"]["endpoints"] == ["tcp/router:7447"]


def test_robot_connect_list_checks():
    with pytest.raises(ValueError, match="at least one"):
        robot_config_dict([])
    with pytest.raises(ValueError, match="list of endpoints"):
        robot_config_dict(EP)  # a bare string, not a list
    with pytest.raises(ValueError, match="twice"):
        robot_config_dict([EP, EP])
    with pytest.raises(ValueError, match="must be a string"):
        robot_config_dict([7447])


@pytest.mark.parametrize("port", [0, -1, 65536, "7447", 7447.0, True])
def test_router_port_checks(port):
    with pytest.raises(ValueError, match="port"):
        router_config_dict(port)


def test_router_host_must_be_loopback():
    with pytest.raises(ValueError, match="loopback"):
        router_config_dict(7447, "0.0.0.0")


def test_free_loopback_port_is_bindable():
    port = free_loopback_port()
    assert 1024 <= port <= 65535
    with socket.socket() as s:
        s.bind(("127.0.0.1", port))
    assert router_endpoint(port) == f"tcp/127.0.0.1:{port}"
    assert router_endpoint(port, "::1") == f"tcp/[::1]:{port}"
    with pytest.raises(ValueError):
        free_loopback_port("8.8.8.8")


def test_router_and_client_talk_over_loopback():
    """One router, two clients, one sample: the configs actually work together."""
    import threading

    import zenoh

    port = free_loopback_port()
    router = zenoh.open(router_config(port))
    try:
        a = zenoh.open(robot_config([router_endpoint(port)]))
        b = zenoh.open(robot_config([router_endpoint(port)]))
        try:
            got = threading.Event()
            sub = b.declare_subscriber("shapefleet/test/cfg", lambda s: got.set())
            pub = a.declare_publisher("shapefleet/test/cfg", express=True)
            for _ in range(50):  # bounded: at most 50 puts over 5 s
                pub.put(b"x")
                if got.wait(0.1):
                    break
            assert got.is_set()
            sub.undeclare()
            pub.undeclare()
        finally:
            b.close()
            a.close()
    finally:
        router.close()


def test_client_without_router_fails_within_its_timeout(monkeypatch):
    import time

    import zenoh

    import protocol.zenoh_config as zc

    monkeypatch.setattr(zc, "CONNECT_TIMEOUT_MS", 300)
    port = free_loopback_port()  # nobody listens there
    t = time.monotonic()
    with pytest.raises(zenoh.ZError):
        zenoh.open(zc.robot_config([router_endpoint(port)]))
    assert time.monotonic() - t < 5
