"""RAP's side of the race: the robot (this process) against a deployed chain.

The robot publishes a 360-beam scan (42 beams at ``inf``, as the peer's) at a fixed rate
on absolute deadlines and receives spin plans; a cycle's latency is the time from
publishing its scan to receiving the plan whose envelope names that scan as its cycle,
on this process's monotonic clock. A cycle is lost when no plan arrives within
``LOST_AFTER`` s. The chain runs as a deployment plan: one runner process for all five
stages, or one per stage, each with the knowledge service in its own process.
"""

from __future__ import annotations

import math
import random
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import anyio
from knowledge.app import open_service
from knowledge.config import KnowledgeConfig
from lidar_occlusion.deploy import local_deployment
from rap_schemas import LaserScan, SpinPlan, keys, pack_ranges
from rap_sdk import Context, MemoryFabric, Node, NodeRuntime, ZenohConfig, ZenohFabric, run_nodes
from rap_sdk.fabric import free_port

from . import chain
from .chain import ROBOT, handlers
from .contract import contract_cycle

HERE = Path(__file__).resolve().parent
PLANS = {
    "rap-1proc": HERE / "plans" / "one.yaml",
    "rap-5proc": HERE / "plans" / "five.yaml",
    "rap-echo": HERE / "plans" / "echo.yaml",
    "rap-1proc-bare": HERE / "plans" / "one-bare.yaml",
    "rap-5proc-bare": HERE / "plans" / "five-bare.yaml",
}
SYSTEM = "race"
LOST_AFTER = 2.0
OCCLUDED = (*range(100, 130), *range(250, 262))


def make_scan(seed: int = 1) -> LaserScan:
    rnd = random.Random(seed)
    ranges = [round(rnd.uniform(0.3, 8.0), 7) for _ in range(360)]
    for i in OCCLUDED:
        ranges[i] = math.inf
    return LaserScan(
        stamp=0,
        frame_id=f"{ROBOT}/base_link",
        angle_min=-math.pi,
        angle_increment=2 * math.pi / 360,
        range_min=0.1,
        range_max=12.0,
        ranges=pack_ranges(ranges),
    )


class Robot:
    def __init__(self) -> None:
        self.node = Node("robot")
        self.sent: dict[bytes, int] = {}
        self.latencies: list[int] = []
        self.arrived: anyio.Event | None = None
        self.sending = False
        self.in_send: int | None = None
        """When the scan being sent now was sent: in one process its whole cycle may run
        inside the send (direct dispatch), before the send returns the scan's uid."""
        self.answered_in_send = False

        @self.node.on_data(f"{ROBOT}/spin_config")
        async def plan(ctx: Context, p: SpinPlan) -> None:
            t = time.perf_counter_ns()
            sent = self.sent.pop(ctx.envelope.cycle or b"", None)
            if sent is None and self.in_send is not None:
                sent, self.in_send, self.answered_in_send = self.in_send, None, True
            if sent is not None:
                self.latencies.append(t - sent)
                if not self.sent and not self.sending and self.arrived is not None:
                    self.arrived.set()


async def _round(rt: NodeRuntime, robot: Robot, rate: float, cycles: int) -> dict[str, Any]:
    key = keys.data(SYSTEM, f"{ROBOT}/scan")
    scan = make_scan()
    robot.latencies.clear()
    robot.sent.clear()
    robot.arrived = anyio.Event()
    robot.sending = True
    period = 1.0 / rate
    start = anyio.current_time()
    first = time.perf_counter()
    for i in range(cycles):
        due = start + i * period
        delay = due - anyio.current_time()
        if delay > 0:
            await anyio.sleep(delay)  # pacing on absolute deadlines
        t = time.perf_counter_ns()
        robot.in_send, robot.answered_in_send = t, False
        env = await rt.send(key, scan)
        robot.in_send = None
        if not robot.answered_in_send:
            robot.sent[env.uid] = t
    send_rate = (cycles - 1) / max(time.perf_counter() - first, 1e-9)
    robot.sending = False
    if not robot.sent:
        robot.arrived.set()
    with anyio.move_on_after(LOST_AFTER):
        await robot.arrived.wait()
    lost = len(robot.sent)
    return {
        "rate_hz": rate,
        "sent": cycles,
        "received": len(robot.latencies),
        "lost": lost,
        "send_rate_hz": round(send_rate, 1),
        "latencies_ns": list(robot.latencies),
    }


async def run_rap(
    variant: str, rates: list[float], cycles: int, warmup: int, logs: Path
) -> list[dict[str, Any]]:
    """Deploy ``variant``'s plan, then one round per rate (after a warm-up round)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    robot = Robot()
    out = []
    async with (
        ZenohFabric(ZenohConfig(listen=[endpoint])) as fabric,
        local_deployment(PLANS[variant], fabric=fabric, endpoint=endpoint, logs=logs / variant),
    ):
        rt = NodeRuntime(robot.node, fabric=fabric, system=SYSTEM, trace=False)
        async with anyio.create_task_group() as tg:
            await tg.start(rt.run)
            await fabric.wait_matched(keys.data(SYSTEM, f"{ROBOT}/scan"), timeout=10.0)
            await _round(rt, robot, 50.0, warmup)
            out.extend([await _round(rt, robot, rate, cycles) for rate in rates])
            rt.stop()
    return out


async def run_inproc(rates: list[float], cycles: int, warmup: int) -> list[dict[str, Any]]:
    """The chain without a transport: robot, the five nodes and the knowledge service in
    this process on the in-memory fabric (what the runtime itself costs per cycle)."""
    nodes = [chain.monitor, chain.analysis, chain.planner, chain.legitimator, chain.executor]
    robot = Robot()
    async with (
        MemoryFabric() as fabric,
        open_service(KnowledgeConfig(system=SYSTEM), fabric=fabric),
        run_nodes(nodes, fabric=fabric, system=SYSTEM, gc_idle=True),
        anyio.create_task_group() as tg,
    ):
        rt = NodeRuntime(robot.node, fabric=fabric, system=SYSTEM, trace=False)
        await tg.start(rt.run)
        await _round(rt, robot, 50.0, warmup)
        out = [await _round(rt, robot, rate, cycles) for rate in rates]
        rt.stop()
    return out


async def _paced(
    rate: float, cycles: int, warmup: int, once: Callable[[], Awaitable[int]]
) -> dict[str, Any]:
    """``once()`` (one cycle, returning its own duration in ns) on absolute deadlines at
    ``rate``, the event loop idle in between, as the loop rows are paced."""
    period = 1.0 / rate
    lat = []
    start = anyio.current_time()
    for i in range(warmup + cycles):
        delay = start + i * period - anyio.current_time()
        if delay > 0:
            await anyio.sleep(delay)
        dt = await once()
        if i >= warmup:
            lat.append(dt)
    return {"rate_hz": rate, "lost": 0, "send_rate_hz": rate, "latencies_ns": lat}


async def run_floor_paced(rate: float, cycles: int, warmup: int) -> dict[str, Any]:
    """The five handlers called directly, paced like the loop rows: one cycle per period
    on absolute deadlines, the event loop idle in between (caches as cold as the loop's
    own cycles find them)."""
    scan = make_scan()
    cycle = handlers(time.time_ns)

    async def once() -> int:
        t = time.perf_counter_ns()
        plan = cycle(scan)
        dt = time.perf_counter_ns() - t
        assert plan is not None
        return dt

    return await _paced(rate, cycles, warmup, once)


async def run_contract_paced(rate: float, cycles: int, warmup: int) -> dict[str, Any]:
    """The contract floor (bench/loop/contract.py), paced like ``floor-paced``: the five
    stages awaited one after another with the envelopes, knowledge versions and gate
    RAP's contract asks for, and no dispatch."""
    scan = make_scan()
    cycle = contract_cycle()

    async def once() -> int:
        t = time.perf_counter_ns()
        plan = await cycle(scan)
        dt = time.perf_counter_ns() - t
        assert plan is not None
        return dt

    return await _paced(rate, cycles, warmup, once)


def run_floor(cycles: int) -> list[int]:
    """The five handlers called directly, one cycle after another, in one task."""
    scan = make_scan()
    cycle = handlers(time.time_ns)
    for _ in range(min(cycles, 200)):
        cycle(scan)  # warm-up
    lat = []
    for _ in range(cycles):
        t = time.perf_counter_ns()
        plan = cycle(scan)
        lat.append(time.perf_counter_ns() - t)
        assert plan is not None
    return lat
