"""Whole runs in lockstep, in this process: the loop closes, deterministically."""

from __future__ import annotations

import msgspec
import pytest
from lidar_occlusion.scenario import run_in_process
from sim_world.world import Occlusion, default_world_path, load_world

pytestmark = pytest.mark.anyio

WALL_CLOCK = {"loop_latency_ms", "anomaly_to_robot_ms"}


def world():  # type: ignore[no-untyped-def]
    w = load_world(default_world_path("default"))
    occ = Occlusion(robot="tb1", mode="sector", start_angle=-0.5, width=1.0, t_start=2.0, t_end=9.0)
    return msgspec.structs.replace(w, occlusions=[occ])


async def test_the_loop_closes_and_a_seeded_run_is_repeatable() -> None:
    a = await run_in_process(world(), duration=12.0)
    b = await run_in_process(world(), duration=12.0)
    assert a["occlusion_onsets"] == 1
    assert a["detection_rate"] == 1.0
    assert a["detection_latency_scans"]["max"] <= 1
    # onset, then the end of the occlusion (the plan goes back to nominal)
    assert a["anomalies"] == 2
    assert a["plans_executed"] == 2
    assert a["false_anomalies"] == 0
    assert a["lockstep_timeouts"] == 0
    same = {k: v for k, v in a.items() if k not in WALL_CLOCK}
    assert same == {k: v for k, v in b.items() if k not in WALL_CLOCK}


async def test_without_the_loop_nothing_is_detected() -> None:
    m = await run_in_process(world(), duration=12.0, loop=False)
    assert m["occlusion_onsets"] == 1
    assert m["anomalies"] == 0
    assert m["plans_executed"] == 0
