"""The lidar-occlusion loop with a ROS 2 robot, as a user declares it: the model's robot
is an external component whose ports are bound to ROS 2 topics over DDS (``bridge:``
with ``protocol: dds``, ``format: cdr``), ``rap up`` runs the robot node's bridges, and a
ROS 2 lidar node written with plain Cyclone DDS (its own types, ROS 2's QoS) publishes
``sensor_msgs/LaserScan`` with an occluded sector and gets the plan back as
``rap_msgs/SpinPlan``. Everything stays on the loopback interface."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import anyio
import pytest
import yaml
from anyio.streams.buffered import BufferedByteReceiveStream
from rap_cli.model_io import check_model_text
from rap_cli.testing import model_copy, rap_up
from rap_sdk.testing import stop_process

from libs.rap_bridges.tests.outside_dds import DOMAIN, LOOPBACK, require_server

ROOT = Path(__file__).resolve().parents[1]
LIDAR_MODEL = ROOT / "examples" / "lidar_occlusion" / "model.yaml"
NODE = ROOT / "libs" / "rap_bridges" / "tests" / "ros2_lidar_node.py"


def _ros2_model(tmp_path: Path, ns: str) -> Path:
    """The lidar model whose robot is a ROS 2 robot on DDS instead of the simulator."""
    model = model_copy(LIDAR_MODEL, tmp_path)
    data: dict[str, Any] = yaml.safe_load(model.read_text())
    robot = data["components"]["robot"]
    del robot["run"]  # nothing for rap up to start: the robot lives on DDS
    robot["doc"] = "a ROS 2 robot: its lidar and its spin controller, on DDS"
    url = f"dds://{DOMAIN}"
    ports = robot["ports"]
    # ROS 2 lidar drivers publish best effort (the sensor-data profile): qos 0
    ports["scan"]["bridge"] = {
        "protocol": "dds",
        "url": url,
        "address": f"{ns}/scan",
        "format": "cdr",
        "qos": 0,
    }
    # the plan is configuration the robot must get: reliable, transient-local
    ports["spin_config"]["bridge"] = {
        "protocol": "dds",
        "url": url,
        "address": f"{ns}/spin_config",
        "format": "cdr",
        "qos": 1,
    }
    model.write_text(yaml.safe_dump(data, sort_keys=False))
    return model


@pytest.mark.zenoh
@pytest.mark.slow
@pytest.mark.anyio
@pytest.mark.timeout(120)
async def test_a_ros2_robot_on_dds_closes_the_loop_rap_up_runs(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    require_server()
    monkeypatch.setenv("CYCLONEDDS_URI", LOOPBACK)  # rap up's processes inherit it
    ns = f"/model_{os.getpid()}/tb1"
    model = _ros2_model(tmp_path, ns)
    checked = check_model_text(model.read_text(), str(model))
    assert checked.ok, [str(d) for d in checked.diagnostics]
    async with rap_up(model, tmp_path / "run", timeout=60) as out:
        await out.line("bridge robot.scan")  # the robot node's bridges are up
        args = [sys.executable, str(NODE), "--domain", str(DOMAIN), "--ns", ns]
        node = await anyio.open_process(args, stdin=subprocess.PIPE, stdout=subprocess.PIPE)
        event: dict[str, Any] = {}
        try:
            assert node.stdout is not None
            lines = BufferedByteReceiveStream(node.stdout)
            with anyio.fail_after(60):
                while "plan" not in event:
                    event = json.loads(await lines.receive_until(b"\n", 1 << 20))
        finally:
            assert node.stdin is not None
            await node.stdin.aclose()  # the node's cue to stop
            with anyio.move_on_after(10):
                await node.wait()
            await stop_process(node, grace=5)
            await node.aclose()
    plan = event["plan"]
    # the executor's plan, as the ROS 2 node got it: a spin over the occluded sector and
    # back (three commands whose turns add up to nothing)
    assert len(plan["commands"]) == 3, plan
    turns = sum(c["omega"] * c["duration"] for c in plan["commands"])
    assert turns == pytest.approx(0, abs=1e-6)
    logs = (tmp_path / "run" / "robot" / "logs" / "bridges.log").read_text()
    assert f"bridge robot.scan: rap/demo/data/tb1/scan <- dds://{DOMAIN}{ns}/scan" in logs
