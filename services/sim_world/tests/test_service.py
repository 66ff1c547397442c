from __future__ import annotations

import math

import anyio
import pytest
from rap_schemas import LaserScan, Odometry, SimTime, SpinCommand, SpinPlan, keys
from rap_sdk.testing import Harness
from sim_world.service import SimService
from sim_world.sim import Simulation
from sim_world.world import default_world_path, load_world

pytestmark = pytest.mark.anyio


@pytest.mark.parametrize("fabric", ["memory", pytest.param("zenoh", marks=pytest.mark.zenoh)])
async def test_scans_go_out_and_plans_come_in(fabric: str) -> None:
    sim = Simulation(load_world(default_world_path("default")))
    truth: list[object] = []
    async with Harness(system="s", fabric=fabric) as h:  # type: ignore[arg-type]
        service = SimService(
            sim, fabric=h.fabric, system="s", on_scan=lambda ev, env: truth.append(ev)
        )
        async with anyio.create_task_group() as tg:
            await tg.start(service.run, 2.0)
            plan = SpinPlan(commands=[SpinCommand(omega=1.0, duration=1.0)], period=8.0)
            await h.publish("tb1/spin_config", plan)
            scan = await h.expect_data("tb1/scan")
            odom = await h.expect_data("tb1/odom")
            clock = await h.expect_data("clock")
        assert len(scan.decode(LaserScan).values()) == 360
        assert odom.decode(Odometry).frame_id == "tb1/odom"
        assert clock.decode(SimTime).t > 0
        assert sim.robots["tb1"].executor.plan == plan  # the plan reached the executor
        assert len(truth) == 10  # 2 s at 5 Hz; ground truth only through on_scan
        assert not h.of(keys.Kind.DATA, "tb1/occlusion")


async def test_a_bad_plan_is_refused_and_the_simulator_carries_on() -> None:
    sim = Simulation(load_world(default_world_path("default")))
    async with Harness(system="s") as h:
        service = SimService(sim, fabric=h.fabric, system="s")
        async with anyio.create_task_group() as tg:
            await tg.start(service.run, 1.0)
            await h.publish_raw(keys.data("s", "tb1/spin_config"), b"\xc1")
            bad = SpinPlan(commands=[SpinCommand(omega=math.nan, duration=1.0)], period=8.0)
            await h.publish("tb1/spin_config", bad)
            await h.expect_data("tb1/scan")
        assert sim.robots["tb1"].executor.plan is None
        assert service.runtime is not None
        assert service.runtime.stats.rejected == 2  # undecodable; NaN refused by the schema
        assert sim.t == pytest.approx(1.0)


async def test_real_time_runs_at_the_requested_speed() -> None:
    sim = Simulation(load_world(default_world_path("default")))
    async with Harness(system="s") as h:
        service = SimService(sim, fabric=h.fabric, system="s", realtime_factor=10.0)
        t0 = anyio.current_time()
        await service.run(2.0)
        elapsed = anyio.current_time() - t0
    assert elapsed >= 0.19  # 2 s of sim time at x10: never faster than asked (about 0.2 s)
    assert elapsed < 5.0  # and it does finish
