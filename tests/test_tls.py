"""Zenoh TLS between router and robots: the configs, the CLI's checks, and a fleet on loopback.

The integration test follows docs/deploy.md with its own commands (certificates made by the doc's
openssl block, router and robots started by the doc's TLS blocks) on 127.0.0.1, and runs impostors
beside the fleet: a robot that trusts another CA, one whose certificate another CA signed, one with
no certificate and one speaking plain TCP. None of them gets a session, and a TLS handshake with
each one's files shows why (the router's certificate refused by the impostor, the impostor's
certificate refused by the router, no certificate, not TLS). A fifth impostor holds a *valid*
certificate of another robot (robot 1's): TLS admits it, and it republishes robot 0's frames with
x scaled; frame authentication refuses them (``auth`` in robot 1's counts). The fleet converges to
the in-process simulator's iterates, bit for bit.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import time
from pathlib import Path

import pytest

from launcher.cli import main
from protocol.zenoh_config import TLSFiles, free_loopback_port, robot_config, robot_config_dict, router_config, router_config_dict
from tests import deploy_doc as doc
from tests.conftest import skip_evidence

EVIDENCE = True  # with SHAPEFLEET_REQUIRE_EVIDENCE set a skip here fails (tests/conftest.py)

ROBOTS = ("robot0", "robot1")
CONNECT_BOUND_S = 45.0  # a robot gives up after the 10 s connect time-out, plus start-up on a busy machine


def _files(tmp: Path) -> TLSFiles:
    for name in ("ca.pem", "r.pem", "r.key"):
        (tmp / name).write_text("x")
    return TLSFiles(ca=str(tmp / "ca.pem"), cert=str(tmp / "r.pem"), key=str(tmp / "r.key"))


# -- configs --------------------------------------------------------------------------------------
def test_tls_router_config(tmp_path):
    tls = _files(tmp_path)
    d = router_config_dict(7447, "10.0.0.1", loopback_only=False, tls=tls)
    assert d["listen"]["endpoints"] == ["tls/10.0.0.1:7447"]
    link = d["transport"]["link"]
    assert link["protocols"] == ["tls"]  # plain TCP refused
    assert link["tls"] == {
        "listen_certificate": tls.cert,
        "listen_private_key": tls.key,
        "root_ca_certificate": tls.ca,
        "enable_mtls": True,
    }
    assert d["scouting"]["multicast"]["enabled"] is False and d["scouting"]["gossip"]["enabled"] is False
    server_only = router_config_dict(7447, tls=TLSFiles(cert=tls.cert, key=tls.key))
    assert "enable_mtls" not in server_only["transport"]["link"]["tls"]
    assert json.loads(router_config(7447, tls=tls).get_json("transport/link/tls/enable_mtls")) is True
    with pytest.raises(ValueError, match="certificate and private key"):
        router_config_dict(7447, tls=TLSFiles(ca=tls.ca))
    with pytest.raises(ValueError, match="not a loopback"):
        router_config_dict(7447, "10.0.0.1", tls=tls)


def test_tls_robot_config(tmp_path):
    tls = _files(tmp_path)
    d = robot_config_dict(["tls/10.0.0.1:7447"], loopback_only=False, tls=tls)
    assert d["transport"]["link"]["tls"] == {
        "root_ca_certificate": tls.ca,
        "verify_name_on_connect": True,
        "connect_certificate": tls.cert,
        "connect_private_key": tls.key,
        "enable_mtls": True,
    }
    assert d["scouting"]["multicast"]["enabled"] is False
    only_ca = robot_config_dict(["tls/127.0.0.1:7447"], tls=TLSFiles(ca=tls.ca))
    assert only_ca["transport"]["link"]["tls"] == {"root_ca_certificate": tls.ca, "verify_name_on_connect": True}
    conf = robot_config(["tls/127.0.0.1:7447"], tls=tls)
    assert json.loads(conf.get_json("transport/link/tls/root_ca_certificate")) == tls.ca
    with pytest.raises(ValueError, match="root CA"):
        robot_config_dict(["tls/127.0.0.1:7447"])
    with pytest.raises(ValueError, match="no tls/ endpoint"):
        robot_config_dict(["tcp/127.0.0.1:7447"], tls=tls)
    with pytest.raises(ValueError, match="not a loopback"):
        robot_config_dict(["tls/10.0.0.1:7447"], tls=tls)
    with pytest.raises(ValueError, match="give both or neither"):
        TLSFiles(ca=tls.ca, cert=tls.cert)


def test_tls_paths_are_made_absolute(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    tls = TLSFiles(ca="ca.pem", cert="c.pem", key="c.key")
    assert tls.ca == str(tmp_path / "ca.pem") and tls.key == str(tmp_path / "c.key")


# -- CLI checks -------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def fleet_file(tmp_path_factory) -> Path:
    tmp = tmp_path_factory.mktemp("fleetfile")
    from launcher.world import Options, build_world

    _, spec = build_world(Options(robots=2, preset="paper", fleet_id="tls-cli"))
    spec.save(tmp / "fleet.json")
    return tmp / "fleet.json"


@pytest.mark.parametrize(
    "args,needle",
    [
        (["robot", "--id", "0", "--connect", "tls/127.0.0.1:7447"], "--connect: a tls/ endpoint needs the fleet's root CA"),
        (["robot", "--id", "0", "--connect", "tls/127.0.0.1:7447", "--tls-ca", "missing.pem"], "--tls-ca: cannot read missing.pem"),
        (["robot", "--id", "0", "--connect", "tcp/127.0.0.1:7447", "--tls-ca", "FLEET"], "--connect: TLS files given but no tls/ endpoint"),
        (["robot", "--id", "0", "--connect", "tls/127.0.0.1:7447", "--tls-ca", "FLEET", "--tls-cert", "FLEET"], "--tls-cert/--tls-key: give both"),
        (["robot", "--id", "0", "--connect", "tls/10.0.0.1:7447", "--tls-ca", "FLEET"], "not a loopback address"),
        (["router", "--port", "7447", "--tls-ca", "FLEET"], "a TLS router needs its certificate and private key"),
        (["router", "--port", "7447", "--host", "10.0.0.1"], "--host: "),
    ],
    ids=["no-ca", "missing-file", "tls-files-on-tcp", "cert-without-key", "remote-without-flag", "router-ca-only", "router-remote"],
)
def test_cli_refuses_bad_tls_input(fleet_file, args, needle, capsys, monkeypatch):
    monkeypatch.chdir(fleet_file.parent)
    args = [str(fleet_file) if a == "FLEET" else a for a in args]
    if args[0] == "robot":
        args += ["--fleet-file", str(fleet_file)]
    with pytest.raises(SystemExit) as exc:  # refused before any session is opened
        main(args)
    err = capsys.readouterr().err
    assert exc.value.code == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0], err


# -- a fleet with TLS on loopback, and impostors ------------------------------------------------------
def _have_openssl() -> None:
    if shutil.which("openssl") is None:
        skip_evidence("needs the openssl command to make certificates (the doc's way)")


def _tls_of(extra: list) -> tuple[str | None, str | None, str | None]:
    """(ca, cert, key) from an impostor's --tls-* arguments."""
    args = dict(zip(extra[::2], map(str, extra[1::2]), strict=True))
    return args.get("--tls-ca"), args.get("--tls-cert"), args.get("--tls-key")


def _handshake(port: int, ca: str | None, cert: str | None, key: str | None) -> str:
    """Why a node with these files does (not) get a TLS link to the router, in words.

    TLS 1.3: a client learns that the router refused its certificate from the alert that follows
    the handshake, so the first read after it tells. No CA at all: a plain TCP client.
    """
    import socket
    import ssl

    sock = socket.create_connection(("127.0.0.1", port), timeout=5)
    with sock:
        if ca is None:
            sock.sendall(b"\x00" * 64)  # not a TLS ClientHello
            sock.settimeout(5)
            reply = sock.recv(16)
            return "router answered with a TLS alert: it speaks TLS only" if reply[:1] == b"\x15" else f"reply {reply!r}"
        ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
        ctx.load_verify_locations(ca)
        ctx.check_hostname = False  # the router's name is checked by Zenoh, not the question here
        if cert is not None:
            ctx.load_cert_chain(cert, key)
        try:
            tls = ctx.wrap_socket(sock, server_hostname="127.0.0.1")
        except ssl.SSLCertVerificationError as exc:
            return f"client refused the router's certificate: {exc.verify_message}"
        with tls:
            tls.settimeout(2)
            try:
                tls.recv(1)
            except TimeoutError:
                return "admitted"  # the router waits for the Zenoh handshake: TLS accepted us
            except ssl.SSLError as exc:
                if "CERTIFICATE_REQUIRED" in exc.reason:
                    return "router requires a client certificate"
                if exc.reason in ("TLSV1_ALERT_DECRYPT_ERROR", "TLSV1_ALERT_UNKNOWN_CA", "SSLV3_ALERT_BAD_CERTIFICATE"):
                    return f"router refused the client's certificate ({exc.reason})"
                return f"TLS error {exc.reason}"
            return "admitted"


@pytest.mark.integration
def test_tls_fleet_converges_and_impostors_cannot_join(tmp_path):
    from agents.spec import FleetSpec
    from launcher.simulate import simulate_fleet

    _have_openssl()
    port = free_loopback_port()
    env = doc.environment(tmp_path, ROUTER_IP="127.0.0.1", ROUTER_PORT=str(port))
    hub, rogue = tmp_path / "hub", tmp_path / "rogue"
    for d in (hub, rogue):
        d.mkdir()
        doc.run("certs", d, env)  # rogue: the same commands make another CA
    # frames delayed 50 ms on every link: the fleet's ~110 rounds then last ~6 s, so the forger (its TLS
    # session opens late) sees robot 0's frames for long; undelayed the fleet ended in ~0.2 s and the
    # forger caught only its last ~10 frames (forged <= 20: the test failed 3 runs in 7)
    scenario = doc.SCENARIO.read_text()
    assert 'delay = "0ms"' in scenario
    (hub / "scenario.toml").write_text(scenario.replace('delay = "0ms"', 'delay = "50ms"', 1))
    doc.run("prepare", hub, env)
    doc.run("copy-fleet", hub, env)
    doc.run("copy-certs", hub, env)

    good, bad = hub / "certs", rogue / "certs"
    impostors = {
        "trusts-another-ca": ["--tls-ca", bad / "ca.pem", "--tls-cert", good / "robot-0.pem", "--tls-key", good / "robot-0.key"],
        "foreign-certificate": ["--tls-ca", good / "ca.pem", "--tls-cert", bad / "robot-0.pem", "--tls-key", bad / "robot-0.key"],
        "no-certificate": ["--tls-ca", good / "ca.pem"],
        "plain-tcp": [],
    }
    started: list[subprocess.Popen] = []
    forger = None
    try:
        router = doc.start("router-tls", hub, env)
        started.append(router)
        lines = doc.Lines(router)
        assert lines.wait_for('"ready"', 30), f"router not ready: {lines.seen}"
        fleet = []
        for host in ROBOTS:
            cwd = doc.host_dir(tmp_path, host)
            fleet.append(doc.start("robot-tls", cwd, env, log=cwd / "robot.log"))
            started.append(fleet[-1])
        from tests.test_impostor import Impostor

        stolen = TLSFiles(ca=str(good / "ca.pem"), cert=str(good / "robot-1.pem"), key=str(good / "robot-1.key"))
        forger = Impostor(f"tls/127.0.0.1:{port}", json.loads((hub / "fleet" / "fleet.json").read_text())["fleet"],
                          1.02, robot=0, session=robot_config_dict([f"tls/127.0.0.1:{port}"], tls=stolen))
        forger.__enter__()
        fakes = {}
        t0 = time.monotonic()
        for name, extra in impostors.items():
            d = tmp_path / "impostors" / name
            d.mkdir(parents=True)
            shutil.copy(hub / "fleet" / "robot-0" / "fleet.json", d / "fleet.json")
            proto = "tcp" if name == "plain-tcp" else "tls"
            argv = ["shapefleet", "robot", "--fleet-file", "fleet.json", "--connect", f"{proto}/127.0.0.1:{port}",
                    "--result", "result.json", *map(str, extra)]
            fakes[name] = doc.spawn(argv, d, env, log=d / "robot.log")
            started.append(fakes[name])
        codes = doc.wait_all(fleet, 120)
        forger.__exit__(None, None, None)
        why = {name: _handshake(port, *_tls_of(extra)) for name, extra in impostors.items()}
        why["valid-certificate-of-robot-1"] = _handshake(port, stolen.ca, stolen.cert, stolen.key)
        logs = {h: (doc.host_dir(tmp_path, h) / "robot.log").read_text()[-2000:] for h in ROBOTS}
        assert codes == [0, 0], f"robot exit codes {codes}; logs {logs}"
        fake_codes = dict(zip(fakes, doc.wait_all(list(fakes.values()), max(5.0, CONNECT_BOUND_S - (time.monotonic() - t0))), strict=True))
    finally:
        if forger is not None:
            forger._stop.set()  # its thread ends within 0.1 s (bounded anyway by IMPOSTOR_S)
        for proc in reversed(started):
            doc.stop(proc)

    for name, code in fake_codes.items():
        d = tmp_path / "impostors" / name
        log = (d / "robot.log").read_text()
        assert code == 1, f"{name}: exit {code}, log {log[-1500:]}"
        assert "no Zenoh session" in log, f"{name}: {log[-1500:]}"
        assert not (d / "result.json").exists()
    # why: each refusal is the one its files call for, and TLS itself admits a valid certificate
    assert why["trusts-another-ca"].startswith("client refused the router's certificate"), why
    assert why["foreign-certificate"].startswith("router refused the client's certificate"), why
    assert why["no-certificate"] == "router requires a client certificate", why
    assert why["plain-tcp"] == "router answered with a TLS alert: it speaks TLS only", why
    assert why["valid-certificate-of-robot-1"] == "admitted", why
    assert not forger.errors and forger.forged > 20, (forger.errors, forger.forged)

    spec = FleetSpec.load(hub / "fleet" / "fleet.json")
    want = {r["id"]: r for r in simulate_fleet(spec).robots}
    for k, host in enumerate(ROBOTS):
        got = json.loads((doc.host_dir(tmp_path, host) / "result.json").read_text())
        assert got["converged"] and got["rounds"] == want[k]["rounds"]
        assert got["x"] == list(want[k]["x"]) and got["gamma"] == want[k]["gamma"]
        # robot 1 listens to robot 0's key, where the impostor with robot 1's certificate forged
        if k == 1:
            assert got["frames_rejected"]["by_reason"].get("auth", 0) > 0, got["frames_rejected"]
            assert set(got["frames_rejected"]["by_reason"]) == {"auth"}, got["frames_rejected"]
        else:
            assert got["frames_rejected"]["total"] == 0


# -- access control: a robot's certificate publishes only on its own keys -----------------------------
_ACL_ROUTER = """
import sys, time
import zenoh
from protocol.zenoh_config import TLSFiles, robot_access_control, router_config_dict, to_zenoh_config
certs, port, acl, wall = sys.argv[1], int(sys.argv[2]), sys.argv[3] == "acl", float(sys.argv[4])
tls = TLSFiles(ca=certs + "/ca.pem", cert=certs + "/router.pem", key=certs + "/router.key")
session = zenoh.open(to_zenoh_config(router_config_dict(
    port, tls=tls, access_control=robot_access_control("acl-test", [0, 1]) if acl else None)))
print("ready", flush=True)
time.sleep(wall)  # bounded; the test stops it by PID long before
session.close()
"""


@pytest.mark.integration
@pytest.mark.parametrize("acl", [True, False], ids=["acl", "no-acl"])
def test_access_control_lets_a_certificate_publish_only_on_its_robots_keys(tmp_path, acl):
    """Robot 0's valid certificate puts on robot 0's and on robot 1's state key and declares both
    liveliness tokens; a subscriber with robot 1's certificate sees only robot 0's own (with the
    ACL), both (without it: the control that shows the test can fail)."""
    import sys
    import threading

    import zenoh

    _have_openssl()
    env = doc.environment(tmp_path, ROUTER_IP="127.0.0.1", ROUTER_PORT="1")
    doc.run("certs", tmp_path, env)
    certs = tmp_path / "certs"
    port = free_loopback_port()
    router = doc.spawn([sys.executable, "-c", _ACL_ROUTER, str(certs), str(port), "acl" if acl else "none", "60"],
                       tmp_path, env, log=tmp_path / "router.log")
    sessions = []
    try:
        deadline = time.monotonic() + 30
        while "ready" not in (tmp_path / "router.log").read_text():
            assert router.poll() is None and time.monotonic() < deadline, (tmp_path / "router.log").read_text()
            time.sleep(0.05)

        def session(i: int):
            tls = TLSFiles(ca=str(certs / "ca.pem"), cert=str(certs / f"robot-{i}.pem"), key=str(certs / f"robot-{i}.key"))
            sessions.append(zenoh.open(robot_config([f"tls/127.0.0.1:{port}"], tls=tls)))
            return sessions[-1]

        r0, r1 = session(0), session(1)
        got: set[tuple[str, bytes]] = set()
        tokens: set[str] = set()
        lock = threading.Lock()

        def on_state(s) -> None:
            with lock:
                got.add((str(s.key_expr), s.payload.to_bytes()))

        def on_alive(s) -> None:
            with lock:
                tokens.add(str(s.key_expr))

        subs = [r1.declare_subscriber("shapefleet/acl-test/robot/*/state", on_state),
                r1.liveliness().declare_subscriber("shapefleet/acl-test/robot/*/alive", on_alive)]
        time.sleep(0.5)
        toks = [r0.liveliness().declare_token(f"shapefleet/acl-test/robot/{i}/alive") for i in (0, 1)]
        for _ in range(10):  # bounded
            r0.put("shapefleet/acl-test/robot/0/state", b"own")
            r0.put("shapefleet/acl-test/robot/1/state", b"forged")
            time.sleep(0.05)
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and len(got) < (1 if acl else 2):
            time.sleep(0.05)
        time.sleep(0.5)  # anything else that was going to arrive has
        for ent in (*toks, *subs):
            ent.undeclare()
        with lock:
            got_now, tokens_now = set(got), set(tokens)
    finally:
        for s in sessions:
            s.close()
        doc.stop(router)
    own = {("shapefleet/acl-test/robot/0/state", b"own")}
    forged = {("shapefleet/acl-test/robot/1/state", b"forged")}
    if acl:
        assert got_now == own and tokens_now == {"shapefleet/acl-test/robot/0/alive"}, (got_now, tokens_now)
    else:
        assert got_now == own | forged, got_now
        assert tokens_now == {f"shapefleet/acl-test/robot/{i}/alive" for i in (0, 1)}, tokens_now


def test_access_control_config_names_each_robots_own_keys():
    from protocol.zenoh_config import robot_access_control, router_config_dict

    acl = robot_access_control("f-1", [1, 0])
    assert acl["default_permission"] == "deny" and acl["enabled"] is True
    own = {r["id"]: r["key_exprs"] for r in acl["rules"] if r["id"].startswith("own-")}
    assert own == {"own-0": ["shapefleet/f-1/robot/0/**"], "own-1": ["shapefleet/f-1/robot/1/**"]}
    assert [s["cert_common_names"] for s in acl["subjects"]] == [["shapefleet robot 0"], ["shapefleet robot 1"]]
    assert [p["rules"] for p in acl["policies"]] == [["fleet-in", "fleet-out", "own-0"], ["fleet-in", "fleet-out", "own-1"]]
    # publishing (put) is allowed into the router only by the own-<id> rules
    assert [r["id"] for r in acl["rules"] if "put" in r["messages"] and "ingress" in r["flows"]] == ["own-0", "own-1"]
    tls = TLSFiles(ca="ca.pem", cert="r.pem", key="r.key")
    assert router_config_dict(7447, tls=tls, access_control=acl)["access_control"] == acl
    with pytest.raises(ValueError, match="needs a mutual-TLS router"):
        router_config_dict(7447, access_control=acl)
    with pytest.raises(ValueError, match="needs a mutual-TLS router"):
        router_config_dict(7447, tls=TLSFiles(cert="r.pem", key="r.key"), access_control=acl)
    with pytest.raises(ValueError):
        robot_access_control("bad/fleet", [0])
