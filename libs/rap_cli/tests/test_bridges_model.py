"""Bridges from the model: ``bridge:`` on a port, checked by ``rap check``, run by
``rap up`` in a ``bridges`` process per compute node, and allowed by the access control
exactly what they carry. End to end: the lidar loop's spin plans reach an MQTT broker of
the test's own (seen by ``mosquitto_sub``), and a pose published with ``mosquitto_pub``
reaches the fabric (seen by ``rap topic echo``)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import anyio
import pytest
import yaml
from rap_cli.acl import process_grants
from rap_cli.bridges import bridges_on, port_bridges
from rap_cli.deploy import Paths, node_processes
from rap_cli.model_io import check_model_text
from rap_cli.testing import model_copy, rap_command, rap_up
from rap_schemas import keys, parse_plan
from rap_sdk.fabric import free_port
from rap_sdk.testing import require_binary

from libs.rap_bridges.tests.contract import MosquittoServer
from libs.rap_cli.tests.test_check import GOOD

ROOT = Path(__file__).resolve().parents[3]
LIDAR_MODEL = ROOT / "examples" / "lidar_occlusion" / "model.yaml"

BRIDGED = GOOD.replace(
    "      spin: {direction: in, kind: data, type: rap.SpinPlan/1, topic: tb1/spin_config}\n"
    "  monitor:",
    "      spin: {direction: in, kind: data, type: rap.SpinPlan/1, topic: tb1/spin_config,\n"
    "             bridge: {protocol: mqtt, url: 'mqtt://127.0.0.1:1883', address: robot/spin,\n"
    "                      format: json}}\n"
    "  monitor:",
    1,
).replace(
    "      anomaly: {direction: out, type: Mask}\n",
    "      anomaly: {direction: out, type: Mask,\n"
    "                bridge: {protocol: tcp, url: 'tcp://127.0.0.1:9000', format: envelope}}\n",
    1,
)


def _lines(text: str) -> list[str]:
    return [str(d) for d in check_model_text(text, "m.yaml").diagnostics]


def _at(text: str, part: str) -> str:
    """``m.yaml:LINE:COL`` of the first ``part`` of ``text`` (``marker|part``: of
    ``part`` on the first line that holds ``marker``)."""
    marker, _, part = part.rpartition("|")
    for n, line in enumerate(text.splitlines(), 1):
        if marker in line and part in line:
            return f"m.yaml:{n}:{line.index(part) + 1}"
    raise AssertionError(f"{part!r} is not in the model")


def test_a_model_with_bridges_checks_clean_and_each_bridge_goes_its_way() -> None:
    assert BRIDGED != GOOD
    assert _lines(BRIDGED) == []
    plan = parse_plan(BRIDGED).plan
    got = {b.name: (b.direction, b.key, b.node) for b in port_bridges(plan)}
    assert got == {
        # the robot is external and not started by RAP: it lives on MQTT, so what the
        # fabric sends its in port goes out
        "robot.spin": ("out", keys.data("demo", "tb1/spin_config"), "laptop"),
        # a stage's output is mirrored out
        "analysis.anomaly": ("out", keys.event("demo", "anomaly"), "laptop"),
    }


@pytest.mark.parametrize(
    ("old", "new", "at", "expected"),
    [
        (  # another protocol's URL, at the bridge
            "url: 'mqtt://127.0.0.1:1883'",
            "url: 'http://127.0.0.1:1883'",
            "{protocol: mqtt",
            "error: url 'http://127.0.0.1:1883'",
        ),
        (  # an MQTT bridge without a topic
            "address: robot/spin,",
            "",
            "{protocol: mqtt",
            "error: a bridge of protocol mqtt needs an address: the topic, e.g. address:",
        ),
        (  # an unknown protocol, at the protocol
            "protocol: mqtt",
            "protocol: mqtt5",
            "mqtt5",
            "error: $.components.robot.ports.spin.bridge.protocol: 'mqtt5' is not one of "
            "'amqp', 'dds', 'kafka', 'mqtt', 'nats', 'redis', 'redis-stream', 'tcp', 'websocket'",
        ),
        (  # Redis pub/sub bringing messages in at QoS 1: it cannot
            "anomaly: {direction: in, type: Mask}",
            "anomaly: {direction: in, type: Mask,\n"
            "                bridge: {protocol: redis, url: 'redis://127.0.0.1:6379',\n"
            "                         address: anomaly, qos: 1}}",
            "qos: 1}}|1}}",
            "error: port planner.anomaly: Redis pub/sub brings messages in at most once",
        ),
        (  # an outgoing MQTT bridge on a wildcard
            "address: robot/spin,",
            "address: 'robot/#',",
            "'robot/#'",
            "error: port robot.spin: its messages are published on one MQTT topic",
        ),
        (  # a format that needs a type on an untyped port
            "new_data: {direction: out, kind: event}",
            "new_data: {direction: out, kind: event,\n"
            "                 bridge: {protocol: tcp, url: 'tcp://127.0.0.1:9001', format: json}}",
            "9001|json}}",
            "error: port monitor.new_data: format json needs the message the port carries",
        ),
    ],
)
def test_rap_check_finds_a_bad_bridge_at_its_line(
    old: str, new: str, at: str, expected: str
) -> None:
    assert old in BRIDGED, old
    text = BRIDGED.replace(old, new, 1)
    found = _lines(text)
    assert any(line.startswith(f"{_at(text, at)}: {expected}") for line in found), found


def test_an_in_out_port_takes_no_bridge() -> None:
    text = BRIDGED.replace(
        "spin: {direction: in, kind: data, type: rap.SpinPlan/1",
        "spin: {direction: in-out, kind: data, type: rap.SpinPlan/1",
        1,
    )
    found = _lines(text)
    assert any(
        line.startswith(
            f"{_at(text, 'bridge: {protocol: mqtt')}: error: port robot.spin is "
            "in-out, and a bridge carries one direction"
        )
        for line in found
    ), found
    # and no bridge is run for it
    assert [b.name for b in port_bridges(parse_plan(text).plan)] == ["analysis.anomaly"]


def test_the_node_runs_a_bridges_process_allowed_only_what_it_carries(tmp_path: Path) -> None:
    doc = parse_plan(BRIDGED)
    paths = Paths.local(tmp_path / "m.yaml", tmp_path / "run", "laptop")
    procs = {p.name: p for p in node_processes(doc, "laptop", paths=paths)}
    argv = procs["bridges"].argv
    assert argv[1:4] == ("-m", "rap_cli.bridges", paths.model)
    assert argv[argv.index("--node") + 1] == "laptop"
    grant = process_grants(doc.plan)["laptop.bridges"]
    spin = keys.data("demo", "tb1/spin_config")
    anomaly = keys.event("demo", "anomaly")
    assert sorted(grant.may["declare_subscriber"]) == sorted([spin, anomaly])
    assert grant.may["put"] == [keys.log("demo", "bridges-laptop")]  # nothing comes in
    plain = parse_plan(GOOD)
    assert "bridges" not in {p.name for p in node_processes(plain, "laptop", paths=paths)}
    assert bridges_on(plain.plan, "laptop") == []


def _bridged_lidar(tmp_path: Path, broker: int) -> Path:
    """The lidar model with a dashboard outside RAP, on MQTT: it is sent the spin plans
    the robot gets, and publishes goals onto the fabric."""
    model = model_copy(LIDAR_MODEL, tmp_path)
    data: dict[str, Any] = yaml.safe_load(model.read_text())
    url = f"mqtt://127.0.0.1:{broker}"
    data["components"]["dashboard"] = {
        "external": True,
        "node": "robot",
        "doc": "an operator's dashboard on MQTT",
        "ports": {
            "spin_config": {
                "direction": "in",
                "kind": "data",
                "type": "rap.SpinPlan/1",
                "topic": "tb1/spin_config",
                "bridge": {
                    "protocol": "mqtt",
                    "url": url,
                    "address": "robot/spin_config",
                    "format": "json",
                    "qos": 1,
                },
            },
            "goal": {
                "direction": "out",
                "kind": "data",
                "type": "rap.Pose2D/1",
                "topic": "dashboard/goal",
                "bridge": {
                    "protocol": "mqtt",
                    "url": url,
                    "address": "dashboard/goal",
                    "format": "json",
                    "qos": 1,
                },
            },
        },
    }
    model.write_text(yaml.safe_dump(data, sort_keys=False))
    return model


@pytest.mark.zenoh
@pytest.mark.slow
@pytest.mark.anyio
@pytest.mark.timeout(120)
async def test_rap_up_runs_the_models_bridges_end_to_end(tmp_path: Path) -> None:
    sub_bin = require_binary("mosquitto_sub", hint="apt-get install mosquitto-clients")
    pub_bin = require_binary("mosquitto_pub", hint="apt-get install mosquitto-clients")
    (tmp_path / "broker").mkdir()
    broker = MosquittoServer(tmp_path / "broker", free_port())
    await broker.start()
    try:
        model = _bridged_lidar(tmp_path, broker.port)
        checked = check_model_text(model.read_text(), str(model))
        assert checked.ok, [str(d) for d in checked.diagnostics]
        run = tmp_path / "run"
        async with rap_up(model, run, timeout=60) as out:
            await out.line("bridges")  # rap up started the robot's bridges process
            # a spin plan the executor sends the robot reaches the broker as JSON
            got = await anyio.run_process(
                [
                    sub_bin,
                    "-h",
                    "127.0.0.1",
                    "-p",
                    str(broker.port),
                    "-t",
                    "robot/spin_config",
                    "-C",
                    "1",
                    "-W",
                    "60",
                    "-V",
                    "mqttv5",
                    "-F",
                    "%p",
                ],
                check=False,
            )
            assert got.returncode == 0, got.stderr.decode()
            plan = json.loads(got.stdout)
            assert set(plan) == {"commands", "period"}, plan
            assert plan["commands"], plan  # the occluded robot is told to spin
            # a goal published on MQTT reaches the fabric, sealed by the bridge
            echo = await anyio.open_process(
                [
                    rap_command(),
                    "topic",
                    "echo",
                    "data/dashboard/goal",
                    "-n",
                    "1",
                    "--json",
                    "-m",
                    str(model),
                    "--run-dir",
                    str(run),
                ],
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
            )
            async with echo:
                for _ in range(30):  # until its subscription is matched and one arrives
                    await anyio.run_process(
                        [
                            pub_bin,
                            "-h",
                            "127.0.0.1",
                            "-p",
                            str(broker.port),
                            "-q",
                            "1",
                            "-t",
                            "dashboard/goal",
                            "-m",
                            '{"x": 1.5, "y": -2.0, "theta": 0.5}',
                        ],
                    )
                    with anyio.move_on_after(1.0):
                        await echo.wait()
                    if echo.returncode is not None:
                        break
                else:
                    echo.terminate()  # nothing came: what it said tells why
                    await echo.wait()
                assert echo.stdout is not None
                assert echo.stderr is not None
                text = b"".join([chunk async for chunk in echo.stdout]).decode()
                err = b"".join([chunk async for chunk in echo.stderr]).decode()
            assert echo.returncode == 0, err
            sample = json.loads(text.splitlines()[0])
            assert sample["type"] == "rap.Pose2D/1"
            assert sample["source"] == "dashboard.goal"
            assert sample["body"] == {"x": 1.5, "y": -2.0, "theta": 0.5}
    finally:
        await broker.stop()


def _run_bridges(model: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "rap_cli.bridges", str(model), *args],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )


def test_the_bridges_process_refuses_what_it_cannot_run_with_the_place_and_the_fix(
    tmp_path: Path,
) -> None:
    model = tmp_path / "m.yaml"
    # a model message that no generated package defines cannot be carried as JSON
    model.write_text(BRIDGED.replace("format: envelope}}", "format: json}}", 1))
    done = _run_bridges(model, "--node", "laptop")
    assert done.returncode == 2, done.stderr
    where = _at(model.read_text(), "9000|json}}").replace("m.yaml", str(model))
    assert f"{where}: format json needs the port's message type" in done.stderr
    assert "use format: envelope" in done.stderr
    # a node without bridges, and one that is not in the model
    model.write_text(GOOD)
    done = _run_bridges(model, "--node", "laptop")
    assert done.returncode == 2
    assert "no port of a component on 'laptop' has a bridge" in done.stderr
    done = _run_bridges(model, "--node", "moon")
    assert done.returncode == 2
    assert "compute node 'moon' is not in the model" in done.stderr
    # what only the link knows, before anything starts: a wss server needs its certificate
    text = BRIDGED.replace(
        "bridge: {protocol: tcp, url: 'tcp://127.0.0.1:9000', format: envelope}",
        "bridge: {protocol: websocket, url: 'wss://127.0.0.1:9000', serve: true,\n"
        "                         format: envelope}",
        1,
    )
    model.write_text(text)
    assert check_model_text(text, "m.yaml").ok  # the spec alone is fine
    done = _run_bridges(model, "--node", "laptop")
    assert done.returncode == 2, done.stderr
    where = _at(text, "{protocol: websocket").replace("m.yaml", str(model))
    assert f"{where}: bridge analysis.anomaly (out): a serving wss:// bridge needs" in done.stderr
    assert "Traceback" not in done.stderr
