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
from pathlib import Path
from typing import Any

import pytest
from rap_cli.testing import model_copy, rap_up
from rap_schemas import Verdict, keys
from rap_sdk.fabric import CONFIG_ENV
from rap_sdk.testing import Harness, Record

pytestmark = [pytest.mark.anyio, pytest.mark.zenoh, pytest.mark.slow, pytest.mark.timeout(120)]

REPO = Path(__file__).resolve().parents[1]
MODEL = REPO / "examples/lidar_occlusion/model.yaml"
SYSTEM = "demo"
PLAN_TOPIC = "tb1/spin_config"


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
    async with rap_up(model_copy(MODEL, tmp_path), run):
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
