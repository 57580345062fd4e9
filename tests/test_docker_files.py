"""docker/: the compose file, the router config and the Dockerfile, checked without a Docker engine.

Every command in compose.yaml goes through the CLI's own parser (with the service's environment),
the compose flow is replayed on local folders (prepare's output is what each robot mounts and what
the collector reads), the router image is the binding's version, discovery is off, and the image
is multi-stage and runs as a non-root user.
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
COMPOSE = yaml.safe_load((DOCKER / "compose.yaml").read_text())
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
    import zenoh

    conf = zenoh.Config.from_file(str(DOCKER / "zenoh-router.json5"))
    (endpoint,) = json.loads(conf.get_json("listen/endpoints"))
    return parse_endpoint(endpoint)[2]


def _binding_version() -> str:
    return importlib.metadata.version("eclipse-zenoh")


# -- the router ------------------------------------------------------------------------------------------
def test_router_image_is_the_bindings_version():
    image = SERVICES["router"]["image"]
    assert image.startswith("eclipse/zenoh:")
    tag = image.split(":", 1)[1]
    assert tag == _binding_version(), f"router {tag}, eclipse-zenoh binding {_binding_version()}"
    from packaging.specifiers import SpecifierSet

    deps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    (spec,) = [d for d in deps if d.startswith("eclipse-zenoh")]
    assert tag in SpecifierSet(spec.removeprefix("eclipse-zenoh").split("#")[0].strip()), spec


def test_router_config_is_ours_with_scouting_off():
    import zenoh

    router = SERVICES["router"]
    path = router["command"][router["command"].index("-c") + 1]
    mount = _volume(router, path)
    source = (DOCKER / mount["source"]).resolve()
    assert source == DOCKER / "zenoh-router.json5" and mount["read_only"]
    conf = zenoh.Config.from_file(str(source))
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    assert json.loads(conf.get_json("scouting/gossip/enabled")) is False
    # exactly what protocol/zenoh_config builds for a router on every interface of its container
    for key, value in flatten(router_config_dict(7447, "0.0.0.0", loopback_only=False)):
        assert json.loads(conf.get_json(key)) == value, key


def test_nothing_is_exposed_on_the_host_and_nobody_uses_the_host_network():
    for name, service in SERVICES.items():
        assert "ports" not in service, name
        assert service.get("network_mode") != "host", name
        assert "privileged" not in service, name


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
    for tool in ("gcc", "build-essential", "g++", "make ", "apt-get install"):
        assert tool not in body, tool
    installs = [line for line in final if "pip install" in line]
    assert installs and all("--no-index" in line for line in installs)  # only the wheels built before


def test_build_context_is_limited():
    ignore = [line.strip() for line in (DOCKER / "Dockerfile.dockerignore").read_text().splitlines()
              if line.strip() and not line.startswith("#")]
    assert ignore[0] == "*"  # nothing but what is named after it
    for needed in ("!pyproject.toml", "!agents/", "!protocol/", "!launcher/"):
        assert needed in ignore
