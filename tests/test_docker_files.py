"""docker/: the compose files, the router config, the certificates and the Dockerfile, checked
without a Docker engine (`make docker-test`, docker/e2e.py, builds and runs them for real).

Every command in compose.yaml (and with compose.tls.yaml over it) goes through the CLI's own parser
(with the service's environment), the compose flow is replayed on local folders (prepare's output
is what each robot mounts and what the collector reads), the router is shapefleet's own and the
official image of the alternative is the binding's version, discovery is off, docker/certs.sh
writes the files the TLS commands name, and the image is multi-stage and runs as a non-root user.
"""

from __future__ import annotations

import importlib.metadata
import json
import re
import tomllib
from pathlib import Path

import pytest

from tests.conftest import skip_evidence  # noqa: E402

EVIDENCE = True  # with SHAPEFLEET_REQUIRE_EVIDENCE set a skip here fails (tests/conftest.py)
try:
    import yaml
except ImportError:
    skip_evidence("PyYAML (test extra) parses docker/compose.yaml", allow_module_level=True)

from launcher import config  # noqa: E402
from launcher.cli import build_parser, main  # noqa: E402
from protocol.zenoh_config import flatten, parse_endpoint, robot_config_dict, router_config_dict  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
DOCKER = ROOT / "docker"


class _ComposeLoader(yaml.SafeLoader):
    """YAML with compose's merge tags: ``!reset`` (drop what the files before set) and ``!override``."""


_ComposeLoader.add_constructor("!reset", lambda loader, node: None)
_ComposeLoader.add_constructor(
    "!override",
    lambda loader, node: loader.construct_sequence(node, deep=True) if isinstance(node, yaml.SequenceNode)
    else loader.construct_mapping(node, deep=True),
)


def _load(name: str) -> dict:
    return yaml.load((DOCKER / name).read_text(), Loader=_ComposeLoader)


COMPOSE = _load("compose.yaml")
SERVICES = COMPOSE["services"]
OURS = {name: s for name, s in SERVICES.items() if str(s.get("image", "")).startswith("shapefleet")}
ROBOTS = {name: s for name, s in OURS.items() if s["command"][0] == "robot"}


def _mounts(service: dict) -> list[dict]:
    """The service's volumes in the long form (source, target, read_only, volume.subpath)."""
    out = []
    for v in service.get("volumes", []):
        if isinstance(v, str):
            source, target, *mode = v.split(":")
            v = {"source": source, "target": target, "read_only": mode == ["ro"]}
        out.append(v)
    return out


def _volume(service: dict, target: str) -> dict:
    """The service's volume mounted at ``target``."""
    for v in _mounts(service):
        if v["target"] == target:
            return v
    raise AssertionError(f"no volume at {target} in {service}")


def _router_port() -> int:
    """The port of the compose router (shapefleet's own: `router --port N`)."""
    args = build_parser().parse_args(SERVICES["router"]["command"])
    return args.port


def _binding_version() -> str:
    return importlib.metadata.version("eclipse-zenoh")


def _merged(*overrides: str) -> dict:
    """compose.yaml with override files over it: commands replaced, volumes merged by target (as compose)."""
    services = {name: dict(svc) for name, svc in SERVICES.items()}
    for name in overrides:
        for svc_name, svc in _load(name)["services"].items():
            merged = services[svc_name]
            for key, value in svc.items():
                if key == "volumes":
                    by_target = {m["target"]: m for m in _mounts(merged)}
                    by_target.update({m["target"]: m for m in _mounts(svc)})
                    merged["volumes"] = list(by_target.values())
                else:
                    merged[key] = value
    return services


# -- the router ------------------------------------------------------------------------------------------
def test_the_router_is_shapefleets_own_with_scouting_off():
    router = SERVICES["router"]
    assert router["image"] == OURS["prepare"]["image"]  # the project's image, not a pulled one
    args = build_parser().parse_args(router["command"])
    assert args.command == "router" and args.host == "0.0.0.0" and args.allow_remote and args.tls_cert is None
    conf = router_config_dict(args.port, args.host, loopback_only=False)  # what `shapefleet router` opens
    assert conf["scouting"]["multicast"]["enabled"] is False and conf["scouting"]["gossip"]["enabled"] is False


def test_official_router_alternative_is_the_bindings_version():
    alt = _load("compose.zenoh-router.yaml")["services"]["router"]
    image = alt["image"]
    assert image.startswith("eclipse/zenoh:")
    tag = image.split(":", 1)[1]
    assert tag == _binding_version(), f"router {tag}, eclipse-zenoh binding {_binding_version()}"
    from packaging.specifiers import SpecifierSet

    deps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    (spec,) = [d for d in deps if d.startswith("eclipse-zenoh")]
    assert tag in SpecifierSet(spec.removeprefix("eclipse-zenoh").split("#")[0].strip()), spec
    assert "build" in alt and alt["build"] is None  # `!reset`: compose must not build our image under its name


def test_official_router_config_is_ours_with_scouting_off():
    import zenoh

    router = _load("compose.zenoh-router.yaml")["services"]["router"]
    path = router["command"][router["command"].index("-c") + 1]
    mount = _volume(router, path)
    source = (DOCKER / mount["source"]).resolve()
    assert source == DOCKER / "zenoh-router.json5" and mount["read_only"]
    conf = zenoh.Config.from_file(str(source))
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    assert json.loads(conf.get_json("scouting/gossip/enabled")) is False
    # exactly what protocol/zenoh_config builds for shapefleet's router in its container
    for key, value in flatten(router_config_dict(_router_port(), "0.0.0.0", loopback_only=False)):
        assert json.loads(conf.get_json(key)) == value, key


@pytest.mark.parametrize("name", ["compose.yaml", "compose.tls.yaml", "compose.zenoh-router.yaml"])
def test_nothing_is_exposed_on_the_host_and_nobody_uses_the_host_network(name):
    for service_name, service in _load(name)["services"].items():
        assert "ports" not in service, service_name
        assert service.get("network_mode") != "host", service_name
        assert "privileged" not in service, service_name


# -- every command through the CLI's own parser ------------------------------------------------------------
@pytest.mark.parametrize("name", sorted(OURS))
def test_every_command_is_accepted_by_the_cli(name, monkeypatch):
    service = OURS[name]
    for key, value in (service.get("environment") or {}).items():
        monkeypatch.setenv(key, str(value))
    args = build_parser().parse_args(service["command"])
    assert args.command == service["command"][0]
    if args.command == "robot":
        (endpoint,) = args.connect
        assert parse_endpoint(endpoint) == ("tcp", "router", _router_port())
        assert args.allow_remote
        robot_config_dict(args.connect, loopback_only=False)  # a valid client config
        assert "{id}" in args.result  # one file per robot in the shared results volume
    if args.command == "router":
        router_config_dict(args.port, args.host, loopback_only=not args.allow_remote)


def test_robots_each_mount_their_own_slice_and_say_who_they_are():
    ids = []
    for name, service in ROBOTS.items():
        rid = int(service["environment"]["SHAPEFLEET_ROBOT_ID"])
        assert name == f"robot-{rid}"
        fleet = _volume(service, "/fleet")
        assert fleet["source"] == "fleet" and fleet["read_only"]
        assert fleet["volume"]["subpath"] == f"robot-{rid}"  # its own data, nobody else's
        assert _volume(service, "/results")["source"] == "results"
        needs = service["depends_on"]
        assert needs["prepare"]["condition"] == "service_completed_successfully" and "router" in needs
        ids.append(rid)
    assert sorted(ids) == list(range(len(ids))) and len(ids) == 3
    scenario_robots = config.load_scenario(_scenario_path()).values["robots"]
    assert scenario_robots == len(ids)


def _scenario_path() -> Path:
    prepare = SERVICES["prepare"]
    target = prepare["command"][prepare["command"].index("--config") + 1]
    mount = _volume(prepare, target)
    assert mount["read_only"]
    return (DOCKER / mount["source"]).resolve()


def test_the_mounted_scenario_parses():
    path = _scenario_path()
    assert path == DOCKER / "scenario.toml"
    scenario = config.load_scenario(path)
    assert "fleet-id" not in scenario.values  # a new id per run: old results are never collected


def test_the_compose_flow_on_local_folders(tmp_path, monkeypatch):
    """Replay prepare -> robots' mounts -> collector's inputs with the volumes as folders."""
    from agents.spec import FleetSpec
    from launcher import deploy
    from launcher.cli import _robot_id

    volumes = {"fleet": tmp_path / "fleet", "results": tmp_path / "results", "run": tmp_path / "run"}

    def local(service: dict) -> list[str]:
        """The service's command with container paths turned into the folders standing in."""
        argv = []
        for arg in service["command"]:
            for m in _mounts(service):
                if arg == m["target"] or arg.startswith(m["target"] + "/"):
                    base = (DOCKER / m["source"]).resolve() if m["source"].startswith(".") else volumes[m["source"]]
                    arg = str(base / m.get("volume", {}).get("subpath", "")) + arg[len(m["target"]):]
                    break
            argv.append(arg)
        return argv

    assert main(local(SERVICES["prepare"])) == 0
    full = FleetSpec.load(volumes["fleet"] / "fleet.json")
    for service in ROBOTS.values():
        monkeypatch.setenv("SHAPEFLEET_ROBOT_ID", service["environment"]["SHAPEFLEET_ROBOT_ID"])
        args = build_parser().parse_args(local(service))
        spec = FleetSpec.load(args.fleet_file)
        rid = _robot_id(args, spec)
        assert spec.owner == rid and spec.config_tag == full.config_tag
        assert [i for i, r in spec.robots.items() if len(r.points)] == [rid]
    collector = SERVICES["collector"]
    args = build_parser().parse_args(local(collector))
    prepared = deploy.load_prepared(args.fleet_file)
    assert prepared.spec.fleet == full.fleet and prepared.world.shape is not None
    assert args.results == volumes["results"] and args.out == str(volumes["run"])
    assert _volume(collector, "/results")["read_only"]


# -- the Dockerfile ---------------------------------------------------------------------------------------
def _stages() -> list[list[str]]:
    """Instructions (continuation lines joined) grouped by FROM."""
    text = re.sub(r"\\\n", " ", (DOCKER / "Dockerfile").read_text())
    stages: list[list[str]] = []
    for line in text.splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        if line.upper().startswith("FROM "):
            stages.append([])
        if stages:
            stages[-1].append(line)
    return stages


def test_dockerfile_is_multi_stage_slim_and_non_root():
    stages = _stages()
    assert len(stages) >= 2
    args = dict(re.findall(r"^ARG (\w+)=(\S+)", (DOCKER / "Dockerfile").read_text(), re.M))
    for stage in stages:
        base = stage[0].split()[1]
        base = re.sub(r"\$\{(\w+)\}", lambda m: args[m.group(1)], base)
        assert re.fullmatch(r"python:3\.11-slim(-\w+)?", base), base
    final = stages[-1]
    users = [line.split()[1] for line in final if line.upper().startswith("USER ")]
    assert users and users[-1].split(":")[0] not in ("root", "0")
    assert any(line == 'ENTRYPOINT ["shapefleet"]' for line in final)
    cmd = next(line for line in final if line.startswith("CMD "))
    with pytest.raises(SystemExit) as exc:  # the default command is the robot's help
        build_parser().parse_args(json.loads(cmd[4:]))
    assert exc.value.code == 0
    body = " ".join(final)
    for tool in ("gcc", "build-essential", "g++", "make ", "apt-get install", "pip install"):
        assert tool not in body, tool  # nothing is built or fetched in the final stage
    # the final stage takes only the environment the build stage installed, nothing of the source tree
    copies = [line for line in final if line.upper().startswith("COPY ")]
    assert copies == ["COPY --from=build /opt/shapefleet /opt/shapefleet"]
    assert re.search(r"PATH=/opt/shapefleet/bin:", body)
    build = " ".join(stages[0])
    assert "python -m venv /opt/shapefleet" in build and "/opt/shapefleet/bin/python -m pip install ." in build


def test_dockerfile_builds_without_buildkit():
    """The classic builder (no BuildKit: e.g. Debian's docker.io without buildx) must build it."""
    text = "\n".join(line for line in (DOCKER / "Dockerfile").read_text().splitlines() if not line.startswith("#"))
    assert "--mount" not in text and "# syntax=" not in text and "<<" not in text  # no BuildKit-only syntax
    args = re.findall(r"^ARG (\w+)", text, re.M)
    assert "PYTHON_IMAGE" in args and "PIP_INDEX_URL" in args  # the base and the index can be given


def test_build_context_is_limited():
    ignore = [line.strip() for line in (DOCKER / "Dockerfile.dockerignore").read_text().splitlines()
              if line.strip() and not line.startswith("#")]
    assert ignore[0] == "*"  # nothing but what is named after it
    for needed in ("!pyproject.toml", "!agents/", "!protocol/", "!launcher/"):
        assert needed in ignore


# -- mutual TLS (compose.tls.yaml over compose.yaml, certificates by docker/certs.sh) -----------------------
TLS = _merged("compose.tls.yaml")


def test_tls_commands_are_accepted_and_mutual(monkeypatch):
    router = build_parser().parse_args(TLS["router"]["command"])
    assert router.command == "router" and router.port == _router_port()
    assert (router.tls_cert, router.tls_key, router.tls_ca) == (
        Path("/certs/router.pem"), Path("/certs/router.key"), Path("/certs/ca.pem"))  # --tls-ca: mutual TLS
    robots = [name for name, svc in TLS.items() if svc["command"][0] == "robot"]
    assert sorted(robots) == sorted(ROBOTS)  # every robot of compose.yaml is switched to TLS
    for name in robots:
        monkeypatch.setenv("SHAPEFLEET_ROBOT_ID", TLS[name]["environment"]["SHAPEFLEET_ROBOT_ID"])
        args = build_parser().parse_args(TLS[name]["command"])
        assert args.connect == [f"tls/router:{_router_port()}"]
        assert (args.tls_ca, args.tls_cert, args.tls_key) == (
            Path("/certs/ca.pem"), Path("/certs/robot.pem"), Path("/certs/robot.key"))
        # everything else as in the plain file: only the endpoint and the --tls-* flags differ
        plain = [a for a in SERVICES[name]["command"] if a != "tcp/router:7447"]
        tls = [a for a in TLS[name]["command"] if a != "tls/router:7447"]
        i = tls.index("--tls-ca")
        assert tls[:i] + tls[i + 6:] == plain


def test_tls_each_container_mounts_only_its_own_certificates():
    sources = {}
    for name in ["router", *ROBOTS]:
        mount = _volume(TLS[name], "/certs")
        assert mount["type"] == "bind" and mount["read_only"], name
        folder = mount["source"].replace("${SHAPEFLEET_CERTS:-./certs}", "")
        assert folder == f"/{name}", name
        sources[name] = folder
    assert len(set(sources.values())) == len(sources)  # nobody shares a folder; the CA's is mounted nowhere


def test_certs_script_writes_what_the_tls_commands_name(tmp_path):
    import shutil
    import subprocess

    from protocol.zenoh_config import TLSFiles, robot_common_name

    if shutil.which("openssl") is None:
        skip_evidence("openssl makes the certificates (docker/certs.sh)")
    out = tmp_path / "certs"
    proc = subprocess.run(["sh", str(DOCKER / "certs.sh"), str(out), "DNS:router", str(len(ROBOTS))],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert sorted(p.name for p in out.iterdir()) == sorted(["ca", "router", *ROBOTS])
    assert not any((out / name / "ca.key").exists() for name in ["router", *ROBOTS])

    def in_folder(name: str, path: Path) -> str:
        assert path.parent == Path("/certs")
        assert (out / name / path.name).is_file(), (name, path)
        return str(out / name / path.name)

    router = build_parser().parse_args(TLS["router"]["command"])
    files = TLSFiles(ca=in_folder("router", router.tls_ca), cert=in_folder("router", router.tls_cert),
                     key=in_folder("router", router.tls_key))
    router_config_dict(router.port, router.host, loopback_only=False, tls=files)
    san = subprocess.run(["openssl", "x509", "-in", files.cert, "-noout", "-ext", "subjectAltName"],
                         capture_output=True, text=True, timeout=30).stdout
    assert "DNS:router" in san  # the name robots connect to (tls/router:7447)
    for name in ROBOTS:
        rid = int(TLS[name]["environment"]["SHAPEFLEET_ROBOT_ID"])
        args = build_parser().parse_args(TLS[name]["command"])
        cert = in_folder(name, args.tls_cert)
        in_folder(name, args.tls_key)
        verify = subprocess.run(["openssl", "verify", "-CAfile", in_folder(name, args.tls_ca), cert],
                                capture_output=True, text=True, timeout=30)
        assert verify.returncode == 0, verify.stdout + verify.stderr
        subject = subprocess.run(["openssl", "x509", "-in", cert, "-noout", "-subject", "-nameopt", "multiline"],
                                 capture_output=True, text=True, timeout=30).stdout
        # the common name the router's access control knows robot rid by (protocol/zenoh_config.py)
        assert f"commonName                = {robot_common_name(rid)}" in subject


# -- docker/e2e.py's override: only the network and the volumes change -----------------------------------
def test_e2e_override_keeps_the_fleet_and_moves_it_to_loopback(tmp_path):
    import importlib.util

    spec = importlib.util.spec_from_file_location("docker_e2e", DOCKER / "e2e.py")
    e2e = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(e2e)
    folders = {v: tmp_path / v for v in ("fleet", "results", "run")}
    merged = {"services": {n: {**s, "volumes": [m for m in _mounts(s)]} for n, s in TLS.items()}}
    for svc in merged["services"].values():  # compose config's form: every mount has a type
        for m in svc["volumes"]:
            m.setdefault("type", "bind" if m["source"].startswith((".", "/", "$")) else "volume")
    over = e2e.override(merged, folders, 17447)["services"]
    assert set(over) == set(SERVICES)
    for name, svc in over.items():
        text = json.dumps(svc)
        assert "0.0.0.0" not in text and "router:7447" not in text, name
        assert svc["network_mode"] == ("host" if name == "router" or name in ROBOTS else "none"), name
        args = build_parser().parse_args(svc["command"])
        if name == "router":
            assert (args.host, args.port) == ("127.0.0.1", 17447)
        if name in ROBOTS:
            assert args.connect == ["tls/127.0.0.1:17447"]
            rid = TLS[name]["environment"]["SHAPEFLEET_ROBOT_ID"]
            fleet = _volume(svc, "/fleet")
            assert fleet["type"] == "bind" and fleet["read_only"] and fleet["source"] == str(folders["fleet"] / f"robot-{rid}")
        assert [m["target"] for m in svc["volumes"]] == [m["target"] for m in merged["services"][name]["volumes"]]
    yaml_text = e2e.to_yaml({"services": over})
    assert yaml.load(yaml_text, Loader=_ComposeLoader)["services"]["router"]["networks"] is None
