"""Rerun logging: a recording written to an .rrd file holds the world, the robot, its
scans with occluded beams marked, and the plans it received (read back with the rerun
CLI that ships with rerun-sdk)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest
from rap_schemas import SpinCommand, SpinPlan
from sim_world.sim import Simulation
from sim_world.viz import RerunLog
from sim_world.world import default_world_path, load_world

RERUN = Path(sys.executable).with_name("rerun")


def entities(rrd: Path) -> set[str]:
    out = subprocess.run(
        [str(RERUN), "rrd", "print", str(rrd)],
        capture_output=True,
        text=True,
        check=True,
        timeout=60,
        env={"RERUN_ANALYTICS": "0", "PATH": ""},
    ).stdout
    return set(re.findall(r"world/[A-Za-z0-9_/]+", out))


def test_a_recording_holds_world_robot_scans_occlusions_and_plans(tmp_path: Path) -> None:
    if not RERUN.exists():
        pytest.fail(f"the rerun CLI of rerun-sdk is missing beside {sys.executable}")
    world = load_world(default_world_path("default"))
    sim = Simulation(world)
    rrd = tmp_path / "sim.rrd"
    with RerunLog(world, path=str(rrd)) as viz:
        for ev in sim.run(10.0):  # the occlusion starts at 8 s
            viz.scan(sim, ev)
        viz.plan("tb1", sim.t, SpinPlan(commands=[SpinCommand(omega=1.0, duration=1.0)]))
    assert rrd.stat().st_size > 0
    assert {
        "world/room",
        "world/obstacles/circles",
        "world/obstacles/boxes",
        "world/tb1/pose",
        "world/tb1/heading",
        "world/tb1/path",
        "world/tb1/scan",
        "world/tb1/occluded",
        "world/tb1/plans",
    } <= entities(rrd)
