"""Zenoh session configurations for the fleet: one router, robots as clients.

Every configuration built here

* has multicast scouting **off** (``scouting/multicast/enabled = false``) and gossip scouting off:
  nodes only ever talk to the endpoints written in the configuration;
* listens / connects on explicit endpoints only, by default restricted to loopback
  (``127.0.0.1``, ``::1``, ``localhost``);
* disables the admin space and shared memory (nothing to leak in ``/dev/shm`` if a robot is killed).

TLS (``tls/`` endpoints, :class:`TLSFiles`): the router listens with its certificate and key; robots
verify it against the fleet's root CA (``verify_name_on_connect``: the router's certificate must
name the address robots connect to). With a CA on the router and a certificate + key on each robot,
the router verifies the robots too (mutual TLS): a robot without a certificate from the fleet's CA
cannot open a session. A TLS router accepts TLS links only (``transport/link/protocols``).

Latency: frames are small (a few hundred bytes), so batching is the main source of delay; the robot
shell declares its publisher with ``express=True`` (no batching for that message) rather than
switching the whole transport to ``lowlatency`` (which must match on both ends and disables QoS).

Each configuration exists twice: as a plain nested ``dict`` (``*_config_dict``, what tests inspect
and what ``docker/`` can render to a JSON5 file) and as a ``zenoh.Config`` built from that dict leaf
by leaf (``router_config``, ``robot_config``).
"""

from __future__ import annotations

import ipaddress
import json
import os
import re
import socket
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

__all__ = [
    "DEFAULT_PORT",
    "TLSFiles",
    "LOOPBACK_HOSTS",
    "free_loopback_port",
    "parse_endpoint",
    "validate_endpoint",
    "router_endpoint",
    "router_config_dict",
    "robot_config_dict",
    "router_config",
    "robot_config",
    "to_zenoh_config",
    "flatten",
]

DEFAULT_PORT = 7447
LOOPBACK_HOSTS = ("127.0.0.1", "::1", "localhost")

# What every node shares: no discovery of any kind, no admin space, no shared memory; and room
# for bursts of express frames (below).
TX_QUEUE_BATCHES = 16  # zenoh's maximum (default 2)
_COMMON: dict[str, Any] = {
    "scouting": {
        "multicast": {"enabled": False},
        "gossip": {"enabled": False},
    },
    "adminspace": {"enabled": False},
    "transport": {
        "shared_memory": {"enabled": False},
        # Room for a burst of express frames: a process of 16 robots publishes 16 frames in one
        # pass of its loop, and the router forwards ~32 a round to each process, whose reading
        # thread waits for the GIL. With zenoh's defaults (2 batches per priority, dropped after
        # 1 ms without room) a loaded 2-core machine dropped frames: 32 robots, 300 rounds, 5120
        # gaps in the neighbours' seqs (each drop seen by up to 16 robots of a process), 1568 with
        # 16 batches (224 with wait_before_drop 5 ms as well, not taken: a full queue would then
        # hold up the router's forwarding to the others for that long). Every drop costs
        # resends and a round's wait. Lazy allocation: memory is taken only when a burst comes.
        "link": {"tx": {"queue": {"size": {"data": TX_QUEUE_BATCHES}}}},
    },
}

# Robots wait this long for the router at start-up (the launcher may start them a little before the
# router is listening) and retry with this back-off.
CONNECT_TIMEOUT_MS = 10_000
# The launcher starts robots together with the router (they import while it starts), so a robot
# usually finds it listening or within a few retries: keep the back-off short (a refused
# connection on loopback costs microseconds).
CONNECT_RETRY = {"period_init_ms": 20, "period_max_ms": 100, "period_increase_factor": 1.5}

_ENDPOINT_RE = re.compile(r"^(?P<proto>[a-z0-9]+)/(?P<addr>[^?#]+)$")
_SUPPORTED_PROTOCOLS = ("tcp", "tls")


@dataclass(frozen=True)
class TLSFiles:
    """PEM files of one node's TLS link (paths; made absolute when a config is built).

    ``ca``: the fleet's root CA certificate. A robot verifies the router with it; on the router it
    turns on mutual TLS (robots must present a certificate signed by it).
    ``cert`` / ``key``: this node's certificate and private key. Required on the router; on a robot
    both or neither (both: the robot authenticates itself, needed when the router has a CA).
    """

    ca: str | None = None
    cert: str | None = None
    key: str | None = None

    def __post_init__(self) -> None:
        for name in ("ca", "cert", "key"):
            value = getattr(self, name)
            if value is not None and (not isinstance(value, (str, os.PathLike)) or not str(value)):
                raise ValueError(f"TLS {name} must be a file path, got {value!r}")
            if value is not None:
                object.__setattr__(self, name, os.path.abspath(os.fspath(value)))
        if (self.cert is None) != (self.key is None):
            raise ValueError("TLS certificate and private key go together: give both or neither")


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def parse_endpoint(endpoint: str) -> tuple[str, str, int]:
    """Split ``"tcp/127.0.0.1:7447"`` / ``"tcp/[::1]:7447"`` into ``(protocol, host, port)``.

    Raises ``ValueError`` naming the problem when the endpoint is malformed.
    """
    if not isinstance(endpoint, str):
        raise ValueError(f"endpoint must be a string like 'tcp/127.0.0.1:7447', got {endpoint!r}")
    m = _ENDPOINT_RE.match(endpoint.strip())
    if m is None:
        raise ValueError(
            f"endpoint {endpoint!r} is not of the form '<protocol>/<host>:<port>', "
            "e.g. 'tcp/127.0.0.1:7447' (no '?metadata' or '#config' suffix)"
        )
    proto, addr = m.group("proto"), m.group("addr")
    if proto not in _SUPPORTED_PROTOCOLS:
        raise ValueError(
            f"endpoint {endpoint!r}: protocol {proto!r} not supported, use one of {_SUPPORTED_PROTOCOLS}"
        )
    if addr.startswith("["):
        close = addr.find("]")
        if close < 0 or addr[close + 1 : close + 2] != ":":
            raise ValueError(f"endpoint {endpoint!r}: IPv6 address must be written '[addr]:port'")
        host, port_s = addr[1:close], addr[close + 2 :]
        try:
            ipaddress.IPv6Address(host)
        except ValueError:
            raise ValueError(f"endpoint {endpoint!r}: {host!r} is not an IPv6 address") from None
    else:
        host, sep, port_s = addr.rpartition(":")
        if not sep or not host:
            raise ValueError(f"endpoint {endpoint!r}: missing ':<port>' after the host")
        if ":" in host:
            raise ValueError(f"endpoint {endpoint!r}: write IPv6 addresses in brackets, '[{host}]:{port_s}'")
    if not port_s.isdigit():
        raise ValueError(f"endpoint {endpoint!r}: port {port_s!r} is not a number")
    port = int(port_s)
    if not 1 <= port <= 65535:
        raise ValueError(f"endpoint {endpoint!r}: port {port} out of range 1..65535")
    return proto, host, port


def validate_endpoint(endpoint: str, *, loopback_only: bool = True) -> str:
    """Return the endpoint (stripped) if valid, else raise ``ValueError``.

    With ``loopback_only`` (the default) the host must be 127.0.0.0/8, ::1 or localhost.
    """
    proto, host, port = parse_endpoint(endpoint)
    if loopback_only and not _is_loopback(host):
        raise ValueError(
            f"endpoint {endpoint!r}: host {host!r} is not a loopback address "
            "(127.0.0.1, ::1, localhost); pass loopback_only=False to allow it"
        )
    return endpoint.strip()


def router_endpoint(port: int, host: str = "127.0.0.1", protocol: str = "tcp") -> str:
    """The endpoint string of a router listening on ``host:port`` (``tcp`` or ``tls``)."""
    if protocol not in _SUPPORTED_PROTOCOLS:
        raise ValueError(f"protocol {protocol!r} not supported, use one of {_SUPPORTED_PROTOCOLS}")
    return f"{protocol}/[{host}]:{port}" if ":" in host else f"{protocol}/{host}:{port}"


def _merge(base: Mapping[str, Any], extra: Mapping[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {k: (_merge(v, {}) if isinstance(v, Mapping) else v) for k, v in base.items()}
    for k, v in extra.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), Mapping):
            out[k] = _merge(out[k], v)
        else:
            out[k] = _merge(v, {}) if isinstance(v, Mapping) else v
    return out


def robot_common_name(robot: int) -> str:
    """The certificate common name of robot ``robot`` (docs/deploy.md's openssl block)."""
    return f"shapefleet robot {robot}"


def robot_access_control(fleet: str, robots: Iterable[int]) -> dict[str, Any]:
    """Zenoh access control for a mutual-TLS router: robot i's certificate may publish only on its
    own keys ``shapefleet/<fleet>/robot/<i>/**`` (state, status, liveliness token), subscribe to
    the fleet's keys, and receive what is published there; everything else is denied.

    Subjects are the certificates' common names (:func:`robot_common_name`), so this needs
    ``enable_mtls``. It complements frame authentication (docs/protocol.md): a stolen certificate
    alone can no longer even put frames on another robot's key.
    """
    from protocol.keys import fleet_prefix, validate_robot_id

    prefix = fleet_prefix(fleet)
    ids = sorted({validate_robot_id(i) for i in robots})
    rules: list[dict[str, Any]] = [
        {
            "id": "fleet-in",
            "messages": ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"],
            "flows": ["ingress"],
            "permission": "allow",
            "key_exprs": [f"{prefix}/**"],
        },
        {
            "id": "fleet-out",
            "messages": ["put", "delete", "liveliness_token", "declare_subscriber",
                         "declare_liveliness_subscriber", "liveliness_query"],
            "flows": ["egress"],
            "permission": "allow",
            "key_exprs": [f"{prefix}/**"],
        },
    ]
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    for i in ids:
        rules.append({
            "id": f"own-{i}",
            "messages": ["put", "delete", "liveliness_token"],
            "flows": ["ingress"],
            "permission": "allow",
            "key_exprs": [f"{prefix}/robot/{i}/**"],
        })
        subjects.append({"id": f"robot-{i}", "cert_common_names": [robot_common_name(i)]})
        policies.append({"id": f"robot-{i}", "rules": ["fleet-in", "fleet-out", f"own-{i}"], "subjects": [f"robot-{i}"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


def router_config_dict(
    port: int,
    host: str = "127.0.0.1",
    *,
    loopback_only: bool = True,
    tls: TLSFiles | None = None,
    access_control: Mapping[str, Any] | None = None,
    peers: Iterable[str] = (),
) -> dict[str, Any]:
    """Router listening on ``tcp/host:port`` (``tls/host:port`` with ``tls``) only, no scouting,
    connecting to nobody -- or to the routers in ``peers`` (endpoints, validated like the listen
    one): linked routers route the fleet's keys between their clients, so robots can be split
    between hosts, each host with its own router (docs/scaling.md). A peer that is not up yet is
    retried (it may start later); a router never exits for want of one.
    ``access_control``: e.g. :func:`robot_access_control` (needs mutual TLS)."""
    if isinstance(port, bool) or not isinstance(port, int) or not 1 <= port <= 65535:
        raise ValueError(f"router port must be an int in 1..65535, got {port!r}")
    endpoint = validate_endpoint(router_endpoint(port, host, "tls" if tls else "tcp"), loopback_only=loopback_only)
    if isinstance(peers, str):
        raise ValueError(f"peers must be a list of router endpoints, got the string {peers!r}")
    peer_eps = [validate_endpoint(e, loopback_only=loopback_only) for e in peers]
    if endpoint in peer_eps:
        raise ValueError(f"a router cannot connect to its own endpoint {endpoint}")
    connect: dict[str, Any] = {"endpoints": peer_eps}
    if peer_eps:
        connect.update(timeout_ms=-1, exit_on_failure=False, retry=dict(CONNECT_RETRY))
    extra: dict[str, Any] = {
        "mode": "router",
        "listen": {"endpoints": [endpoint]},
        "connect": connect,
        # zenoh.open would otherwise wait 0.5 s after it already listens and routes before it
        # returns, and readiness is announced after open: fast robots ran 8 rounds through a router
        # the launcher still took for "starting" (and a router killed then failed the launch).
        # Linked peers connect (and retry) in the background either way.
        "scouting": {"delay": 0},
    }
    if tls is not None:
        if tls.cert is None:
            raise ValueError("a TLS router needs its certificate and private key")
        link: dict[str, Any] = {"listen_certificate": tls.cert, "listen_private_key": tls.key}
        if tls.ca is not None:  # mutual TLS: robots must show a certificate signed by this CA
            link.update(root_ca_certificate=tls.ca, enable_mtls=True)
        extra["transport"] = {"link": {"protocols": ["tls"], "tls": link}}
    if access_control is not None:
        if tls is None or tls.ca is None:
            raise ValueError("access control by certificate needs a mutual-TLS router (--tls-ca)")
        extra["access_control"] = dict(access_control)
    return _merge(_COMMON, extra)


def robot_config_dict(
    connect: Iterable[str], *, loopback_only: bool = True, tls: TLSFiles | None = None
) -> dict[str, Any]:
    """Robot session: client of the router endpoint(s) in ``connect``; listens nowhere.

    ``tls``: required for ``tls/`` endpoints (its ``ca`` verifies the router; ``cert`` + ``key``
    authenticate the robot to a mutual-TLS router), refused for ``tcp/`` ones.
    """
    if isinstance(connect, str):
        raise ValueError(f"connect must be a list of endpoints, got the string {connect!r}; wrap it in a list")
    endpoints = [validate_endpoint(e, loopback_only=loopback_only) for e in connect]
    if not endpoints:
        raise ValueError("connect must name at least one router endpoint, e.g. ['tcp/127.0.0.1:7447']")
    if len(set(endpoints)) != len(endpoints):
        raise ValueError(f"connect lists an endpoint twice: {endpoints}")
    protocols = {parse_endpoint(e)[0] for e in endpoints}
    extra: dict[str, Any] = {
        "mode": "client",
        "connect": {
            "endpoints": endpoints,
            "timeout_ms": CONNECT_TIMEOUT_MS,
            "exit_on_failure": True,
            "retry": dict(CONNECT_RETRY),
        },
        "listen": {"endpoints": []},
    }
    if "tls" in protocols:
        if tls is None or tls.ca is None:
            raise ValueError("a tls/ endpoint needs the fleet's root CA certificate to verify the router")
        link: dict[str, Any] = {"root_ca_certificate": tls.ca, "verify_name_on_connect": True}
        if tls.cert is not None:
            link.update(connect_certificate=tls.cert, connect_private_key=tls.key, enable_mtls=True)
        extra["transport"] = {"link": {"tls": link}}
    elif tls is not None:
        raise ValueError(f"TLS files given but no tls/ endpoint to use them on: {endpoints}")
    return _merge(_COMMON, extra)


# Sub-trees that are ``null`` in zenoh's default config: they must be inserted whole.
_ATOMIC_PATHS = frozenset({"connect/retry", "listen/retry"})


def flatten(d: Mapping[str, Any], prefix: str = "") -> list[tuple[str, Any]]:
    """``{"a": {"b": 1}}`` -> ``[("a/b", 1)]``; lists (and a few optional sub-trees) are leaves."""
    out: list[tuple[str, Any]] = []
    for k, v in d.items():
        path = f"{prefix}/{k}" if prefix else k
        if isinstance(v, Mapping) and v and path not in _ATOMIC_PATHS:
            out.extend(flatten(v, path))
        else:
            out.append((path, v))
    return out


def to_zenoh_config(d: Mapping[str, Any]):
    """Build a ``zenoh.Config`` from a plain dict, inserting leaf by leaf (defaults kept elsewhere)."""
    import zenoh  # imported lazily: the dict helpers stay usable without the binding

    conf = zenoh.Config()
    for path, value in flatten(d):
        try:
            conf.insert_json5(path, json.dumps(value))
        except Exception as exc:  # zenoh.ZError
            raise ValueError(f"zenoh rejected config {path} = {value!r}: {exc}") from exc
    return conf


def router_config(port: int, host: str = "127.0.0.1", *, loopback_only: bool = True, tls: TLSFiles | None = None,
                  peers: Iterable[str] = ()):
    """``zenoh.Config`` of :func:`router_config_dict`."""
    return to_zenoh_config(router_config_dict(port, host, loopback_only=loopback_only, tls=tls, peers=peers))


def robot_config(connect: Iterable[str], *, loopback_only: bool = True, tls: TLSFiles | None = None):
    """``zenoh.Config`` of :func:`robot_config_dict`."""
    return to_zenoh_config(robot_config_dict(connect, loopback_only=loopback_only, tls=tls))


def free_loopback_port(host: str = "127.0.0.1") -> int:
    """A TCP port free on the loopback interface right now (the OS picks it; small race by nature)."""
    if not _is_loopback(host):
        raise ValueError(f"free_loopback_port: {host!r} is not a loopback address")
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]
