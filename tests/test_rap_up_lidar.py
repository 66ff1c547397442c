"""``rap up examples/lidar_occlusion/model.yaml --all`` runs the whole case on this machine
(both compute nodes' routers, knowledge, the two runners and the simulator) and the loop
closes: the simulator's occlusion is found (an ``anomaly`` event), a plan is approved (a
``verdict``) and reaches the robot (data ``tb1/spin_config``). ``rap down`` stops it all.

The test watches as a Zenoh client of the robot's router (``rap_sdk.testing.Harness`` with
the node's client config), as any process of the node does.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import anyio
import pytest
from rap_schemas import Verdict, keys
from rap_sdk.fabric import CONFIG_ENV, free_port
from rap_sdk.testing import Harness, OutputLines, Record, stop_process

pytestmark = [pytest.mark.anyio, pytest.mark.zenoh, pytest.mark.slow, pytest.mark.timeout(120)]

REPO = Path(__file__).resolve().parents[1]
MODEL = REPO / "examples/lidar_occlusion/model.yaml"
SYSTEM = "demo"
PLAN_TOPIC = "tb1/spin_config"


def _rap() -> str:
    rap = Path(sys.executable).with_name("rap")
    assert rap.exists(), f"{rap}: the rap command is not installed next to {sys.executable}"
    return str(rap)


def _approved(r: Record) -> bool:
    """An approving verdict."""
    return r.kind is keys.Kind.EVENT and r.name == "verdict" and r.decode(Verdict[Any]).approved


def _gone(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    return False


async def test_rap_up_all_closes_the_loop_and_rap_down_stops_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    run = tmp_path / "run"
    # the shipped model with only the edge's port changed: 7447 may be taken on this
    # machine (another rap up of the case, a Zenoh router)
    text = MODEL.read_text()
    assert text.count("tcp/edge:7447") >= 2
    copy = tmp_path / "model.yaml"
    copy.write_text(text.replace("tcp/edge:7447", f"tcp/edge:{free_port()}"))
    model = str(copy)
    argv = [_rap(), "up", model, "--all", "--run-dir", str(run)]
    async with (
        await anyio.open_process(argv, stderr=subprocess.STDOUT) as up,
        anyio.create_task_group() as tg,
    ):
        out = OutputLines(up)
        tg.start_soon(out.pump)
        try:
            with anyio.fail_after(30):
                for node in ("robot", "edge"):
                    await out.line(f"compute node {node} is up")
            # a client of the robot's router, as the robot's own processes are
            monkeypatch.setenv(CONFIG_ENV, str(run / "robot" / "zenoh-client.json5"))
            async with Harness(system=SYSTEM, fabric="zenoh", timeout=30) as h:
                # the default world covers the lidar from 6 s of sim time on
                anomaly = await h.expect_event("anomaly")
                verdict = await h.wait_for(_approved, after=h.records.index(anomaly))
                plan = await h.expect_data(PLAN_TOPIC, after=h.records.index(verdict))
                assert plan.envelope is not None
                assert plan.envelope.source == "executor"
            states = {n: json.loads((run / n / "up.json").read_text()) for n in ("robot", "edge")}
            down = await anyio.run_process(
                [_rap(), "down", model, "--run-dir", str(run)], check=False
            )
            assert down.returncode == 0, down.stdout.decode() + down.stderr.decode()
            with anyio.fail_after(30):
                assert await up.wait() == 0, str(out)
        finally:
            await stop_process(up)  # a failure: it still stops what it started
    # what ran: each node's router, knowledge on the edge, the simulator on the robot
    names = {n: {c["name"] for c in s["children"]} for n, s in states.items()}
    assert names == {
        "robot": {"router", "runner", "robot"},
        "edge": {"router", "knowledge", "manager", "runner"},
    }
    # and all of it has stopped
    for node in ("robot", "edge"):
        after = json.loads((run / node / "up.json").read_text())
        assert after["state"] == "stopped", after
        for child in states[node]["children"]:
            assert child["pid"] is not None, child
            assert _gone(child["pid"]), child
