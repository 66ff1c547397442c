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

Lockstep with a loop: given ``sync`` (a :class:`~rap_sdk.cycles.CycleTracker` of the
loop's nodes and this service's own node), after each scan the simulation waits until
the cycle that scan started is over (every handler it caused has ended, including this
service's own handling of a plan), so that the loop's answers land at the sim time of
the scan that caused them, whatever the host's speed: a deterministic run.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable

import anyio
import anyio.lowlevel
from anyio.abc import TaskStatus
from rap_schemas import LaserScan, SimTime, SpinPlan, Twist, keys
from rap_sdk import Context, Fabric, InboxPolicy, Node, NodeRuntime, OutgoingEnvelope, Overflow
from rap_sdk.cycles import CycleTracker
from rap_sdk.envelope import TypedEnvelope

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
        on_scan: Callable[[ScanEvent, OutgoingEnvelope], None] | None = None,
        on_plan: Callable[[str, SpinPlan, TypedEnvelope[SpinPlan]], None] | None = None,
        rerun: RerunLog | None = None,
        sync: CycleTracker | None = None,
        sync_timeout: float = 2.0,
    ) -> None:
        """``on_scan(event, envelope)`` sees each scan published (with ground truth);
        ``on_plan(robot, plan, envelope)`` each plan applied. ``sync``: lockstep with a
        loop (see the module docstring); a cycle not over within ``sync_timeout`` s is
        counted in ``sync.timeouts`` and the simulation goes on."""
        self.sim = sim
        self.fabric = fabric
        self.system = system
        self.realtime_factor = realtime_factor
        self.on_scan = on_scan
        self.rerun = rerun
        self.on_plan = on_plan
        self.sync = sync
        self.sync_timeout = sync_timeout
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
            if self.on_plan is not None:
                self.on_plan(robot, p, ctx.envelope)
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
            sync = self.sync if self.realtime_factor is None else None
            while sim.t + 1e-9 < t_end:
                events = sim.step()
                cycles = [await self._publish(rt, ev) for ev in events]
                if events:
                    await rt.send(
                        clock_key,
                        SimTime(t=round(sim.t * 1e9), realtime_factor=self.realtime_factor or 0.0),
                    )
                if sync is not None:
                    for cycle in cycles:
                        await sync.wait(cycle, self.sync_timeout)
                if self.realtime_factor is None:
                    await anyio.lowlevel.checkpoint()  # let inputs in: they apply at this sim time
                else:
                    due = start + (sim.t - t0) / self.realtime_factor
                    await anyio.sleep(max(0.0, due - anyio.current_time()))  # pacing
            rt.stop()

    async def _publish(self, rt: NodeRuntime, ev: ScanEvent) -> bytes:
        """Publish one scan (and odometry); returns the cycle the scan starts."""
        scan: LaserScan = ev.scan
        key = keys.data(self.system, f"{ev.robot}/scan")
        env = await rt.send(key, scan)
        if self.sync is not None:
            self.sync.expect(env.uid, key)
        odom_key = keys.data(self.system, f"{ev.robot}/odom")
        await rt.send(odom_key, self.sim.odometry(ev.robot), cycle=env.uid, cause=env.uid)
        if self.on_scan is not None:
            self.on_scan(ev, env)
        if self.rerun is not None:
            self.rerun.scan(self.sim, ev)
        return env.uid
