"""The simulator on the fabric.

Per robot ``R`` of system ``S``:

    rap/S/data/R/scan        LaserScan, every 1 / rate_hz s of sim time   (out)
    rap/S/data/R/odom        Odometry, with every scan                    (out)
    rap/S/data/R/spin_config SpinPlan: the spin-plan executor's input     (in)
    rap/S/data/R/cmd_vel     Twist: a plain velocity command, 0.5 s       (in)
    rap/S/data/clock         SimTime, with every scan                     (out)

Ground truth (occlusion masks, collisions, route progress) stays in the Simulation for
evaluation code; it is never published on the robot's topics.

Clocks: lockstep (``realtime_factor=None``) steps as fast as the host allows, yielding
to the event loop between steps so that inputs are applied at the sim time they
arrive; real time sleeps to keep sim time at ``realtime_factor`` x wall time.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable

import anyio
import anyio.lowlevel
from anyio.abc import TaskStatus
from rap_schemas import LaserScan, SimTime, SpinPlan, Twist, keys
from rap_sdk import Context, Fabric, InboxPolicy, Node, NodeRuntime, Overflow

from .sim import ScanEvent, Simulation
from .viz import RerunLog

__all__ = ["SimService"]

log = logging.getLogger(__name__)

NODE = "sim_world"
CMD_DURATION = 0.5
"""Seconds of sim time a velocity command stays in force."""


class SimService:
    def __init__(
        self,
        sim: Simulation,
        fabric: Fabric,
        *,
        system: str,
        realtime_factor: float | None = None,
        on_scan: Callable[[ScanEvent], None] | None = None,
        rerun: RerunLog | None = None,
    ) -> None:
        self.sim = sim
        self.fabric = fabric
        self.system = system
        self.realtime_factor = realtime_factor
        self.on_scan = on_scan
        self.rerun = rerun
        self.node = Node(NODE)
        for name in sim.robots:
            self._inputs(name)
        self.runtime: NodeRuntime | None = None

    def _inputs(self, robot: str) -> None:
        latest = InboxPolicy(capacity=4, overflow=Overflow.LATEST)

        @self.node.on_data(f"{robot}/spin_config", policy=latest)
        async def plan(ctx: Context, p: SpinPlan) -> None:
            if p.period <= 0 or any(
                not math.isfinite(c.omega) or c.duration < 0 for c in p.commands
            ):
                log.warning(
                    "robot %s: refused a plan %r (period > 0, finite omega and "
                    "durations >= 0 are required)",
                    robot,
                    p,
                )
                return
            self.sim.set_plan(robot, p)
            if self.rerun is not None:
                self.rerun.plan(robot, self.sim.t, p)

        @self.node.on_data(f"{robot}/cmd_vel", policy=latest)
        async def cmd_vel(ctx: Context, t: Twist) -> None:
            if math.isfinite(t.linear) and math.isfinite(t.angular):
                self.sim.set_velocity(robot, t, CMD_DURATION)

    async def run(
        self,
        duration: float | None = None,
        *,
        task_status: TaskStatus[None] = anyio.TASK_STATUS_IGNORED,
    ) -> None:
        """Simulate ``duration`` s of sim time (None: until cancelled)."""
        self.runtime = rt = NodeRuntime(self.node, self.fabric, system=self.system)
        async with anyio.create_task_group() as tg:
            await tg.start(rt.run)
            task_status.started()
            sim, start = self.sim, anyio.current_time()
            t_end = math.inf if duration is None else sim.t + duration
            t0 = sim.t
            clock_key = keys.data(self.system, "clock")
            while sim.t + 1e-9 < t_end:
                for ev in sim.step():
                    await self._publish(rt, ev)
                    await rt.send(
                        clock_key,
                        SimTime(t=round(sim.t * 1e9), realtime_factor=self.realtime_factor or 0.0),
                    )
                if self.realtime_factor is None:
                    await anyio.lowlevel.checkpoint()  # let inputs in: they apply at this sim time
                else:
                    due = start + (sim.t - t0) / self.realtime_factor
                    await anyio.sleep(max(0.0, due - anyio.current_time()))  # pacing
            rt.stop()

    async def _publish(self, rt: NodeRuntime, ev: ScanEvent) -> None:
        scan: LaserScan = ev.scan
        await rt.send(keys.data(self.system, f"{ev.robot}/scan"), scan)
        await rt.send(keys.data(self.system, f"{ev.robot}/odom"), self.sim.odometry(ev.robot))
        if self.on_scan is not None:
            self.on_scan(ev)
        if self.rerun is not None:
            self.rerun.scan(self.sim, ev)
