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
:func:`open_service` builds that tracker from ``loop_nodes``.

    async with open_service(SimConfig(world="corridor", duration=30), fabric=fabric) as s:
        await s.finished.wait()
    report = s.summary().render()  # a text table of the run
"""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import AsyncIterator, Callable, Sequence
from contextlib import asynccontextmanager
from functools import partial

import anyio
import anyio.lowlevel
import anyio.to_thread
import msgspec
from anyio.abc import TaskStatus
from rap_schemas import LaserScan, SimTime, SpinPlan, Twist, keys
from rap_sdk import Context, Fabric, InboxPolicy, Node, NodeRuntime, OutgoingEnvelope, Overflow
from rap_sdk.cycles import CycleTracker, Topology
from rap_sdk.envelope import TypedEnvelope

from .config import MAX_REALTIME_FACTOR, SimConfig
from .sim import ScanEvent, Simulation
from .viz import RerunLog
from .world import WorldSpec, find_world, load_world

__all__ = ["NODE", "RobotSummary", "RunSummary", "SimService", "open_service"]

log = logging.getLogger(__name__)

NODE = "sim_world"
"""The service's node name (its trace records, its place in a loop's topology)."""
CMD_DURATION = 0.5
"""Seconds of sim time a velocity command stays in force."""


class RobotSummary(msgspec.Struct, frozen=True, kw_only=True):
    name: str
    collisions: int
    """Contacts that began with a wall, an obstacle or another robot."""
    waypoints_reached: int
    """Counting every lap of a looped route."""
    route_points: int
    route_completed: bool
    """Every point of the route reached (once, for a looped route)."""
    laps: int
    distance_m: float


class RunSummary(msgspec.Struct, frozen=True, kw_only=True):
    sim_seconds: float
    clock: str
    """``lockstep`` or ``real time x<factor>``."""
    finished: bool
    """The duration ran out (False: stopped before)."""
    scans_published: int
    robots: list[RobotSummary]

    def render(self) -> str:
        """A few lines for a person."""
        end = "finished" if self.finished else "stopped"
        lines = [
            f"sim_world {end} at {self.sim_seconds:g} s of sim time ({self.clock}): "
            f"{self.scans_published} scans published"
        ]
        for r in self.robots:
            route = (
                "no route"
                if not r.route_points
                else f"{r.waypoints_reached} of {r.route_points} waypoints reached"
                + (f" ({r.laps} laps)" if r.laps else "")
                + f", route {'completed' if r.route_completed else 'not completed'}"
            )
            lines.append(
                f"  {r.name}: {r.collisions} collisions, {route}, {r.distance_m:g} m driven"
            )
        return "\n".join(lines)


class SimService:
    def __init__(
        self,
        sim: Simulation,
        *,
        fabric: Fabric,
        system: str,
        realtime_factor: float | None = None,
        on_scan: Callable[[ScanEvent, OutgoingEnvelope], None] | None = None,
        on_plan: Callable[[str, SpinPlan, TypedEnvelope[SpinPlan]], None] | None = None,
        rerun: RerunLog | None = None,
        sync: CycleTracker | None = None,
        sync_timeout: float = 2.0,
        name: str = NODE,
    ) -> None:
        """``name``: its node name on the fabric. ``on_scan(event, envelope)`` sees each
        scan published (with ground truth);
        ``on_plan(robot, plan, envelope)`` each plan applied. ``sync``: lockstep with a
        loop (see the module docstring); a cycle not over within ``sync_timeout`` s is
        counted in ``sync.timeouts`` and the simulation goes on.

        ``finished`` is set when a run's duration is over; ``scans_published`` counts
        the scans sent."""
        if realtime_factor is not None and not (
            math.isfinite(realtime_factor) and 0 < realtime_factor <= MAX_REALTIME_FACTOR
        ):
            raise ValueError(
                f"realtime_factor {realtime_factor!r}: give a number > 0 and at most "
                f"{MAX_REALTIME_FACTOR:g}, or None for lockstep"
            )
        self.sim = sim
        self.fabric = fabric
        self.system = system
        self.realtime_factor = realtime_factor
        self.on_scan = on_scan
        self.rerun = rerun
        self.on_plan = on_plan
        self.sync = sync
        self.sync_timeout = sync_timeout
        self.node = Node(name)
        for name in sim.robots:
            self._inputs(name)
        self.runtime: NodeRuntime | None = None
        self.scans_published = 0
        self.finished = anyio.Event()

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
        self.runtime = rt = NodeRuntime(self.node, fabric=self.fabric, system=self.system)
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
        if duration is not None:
            self.finished.set()

    async def _publish(self, rt: NodeRuntime, ev: ScanEvent) -> bytes:
        """Publish one scan (and odometry); returns the cycle the scan starts."""
        scan: LaserScan = ev.scan
        key = keys.data(self.system, f"{ev.robot}/scan")
        env = await rt.send(key, scan)
        self.scans_published += 1
        if self.sync is not None:
            self.sync.expect(env.uid, key)
        if self.on_scan is not None:  # seen before the loop can answer it (its odometry)
            self.on_scan(ev, env)
        odom_key = keys.data(self.system, f"{ev.robot}/odom")
        if self.sync is not None:  # the odometry is of the scan's cycle: its handlers too
            self.sync.expect(env.uid, odom_key)
        await rt.send(odom_key, self.sim.odometry(ev.robot), cycle=env.uid, cause=env.uid)
        if self.rerun is not None:
            self.rerun.scan(self.sim, ev)
        return env.uid

    def summary(self) -> RunSummary:
        """Scans published and, per robot, collisions and route progress so far."""
        robots = []
        for name, r in self.sim.robots.items():
            route = len(r.spec.route)
            robots.append(
                RobotSummary(
                    name=name,
                    collisions=r.collisions,
                    waypoints_reached=r.nav.index,
                    route_points=route,
                    route_completed=route > 0 and r.nav.index >= route,
                    laps=r.nav.laps,
                    distance_m=round(r.distance, 2),
                )
            )
        factor = self.realtime_factor
        return RunSummary(
            sim_seconds=round(self.sim.t, 6),
            clock="lockstep" if factor is None else f"real time x{factor:g}",
            finished=self.finished.is_set(),
            scans_published=self.scans_published,
            robots=robots,
        )


@asynccontextmanager
async def open_service(
    config: SimConfig,
    *,
    fabric: Fabric,
    world: WorldSpec | None = None,
    loop_nodes: Sequence[Node] | None = None,
    on_scan: Callable[[ScanEvent, OutgoingEnvelope], None] | None = None,
    on_plan: Callable[[str, SpinPlan, TypedEnvelope[SpinPlan]], None] | None = None,
) -> AsyncIterator[SimService]:
    """Simulate ``config.duration`` s of sim time (None: until the block ends) on
    ``fabric`` during the block; on entry the service is subscribed to its inputs.
    ``await service.finished.wait()`` waits for the end of the duration.

    ``world``: simulate this world instead of loading ``config.world`` (a name or a
    path; loaded off the event loop). ``config.rerun``: write a Rerun recording, closed
    on exit. ``loop_nodes`` (lockstep only): after each scan wait until the cycle it
    started in these nodes is over (see the module docstring); ``service.sync`` is the
    tracker. Raises :class:`~sim_world.world.WorldError` for a world that cannot be
    used and :class:`~sim_world.viz.RerunFileError` for a recording that cannot be
    written, before anything runs."""
    if loop_nodes is not None and not config.lockstep:
        raise ValueError("loop_nodes needs config.lockstep: only a lockstep run waits for them")
    if world is None:
        world = await anyio.to_thread.run_sync(_load, config.world)
    sim = Simulation(world)
    rerun = None
    if config.rerun is not None:
        rerun = await anyio.to_thread.run_sync(
            functools.partial(RerunLog, world, path=config.rerun)
        )
    try:
        service = SimService(
            sim,
            fabric=fabric,
            system=config.system,
            realtime_factor=config.realtime_factor,
            on_scan=on_scan,
            on_plan=on_plan,
            rerun=rerun,
            sync_timeout=config.sync_timeout,
            name=config.name,
        )
        async with anyio.create_task_group() as tg:
            if loop_nodes is not None:
                tracker = CycleTracker(
                    Topology.of([*loop_nodes, service.node], system=config.system)
                )
                service.sync = tracker
                await tg.start(partial(tracker.follow, fabric=fabric))
            await tg.start(service.run, config.duration)
            try:
                yield service
            finally:
                tg.cancel_scope.cancel()
    finally:
        if rerun is not None:
            with anyio.CancelScope(shield=True):
                await anyio.to_thread.run_sync(rerun.close)


def _load(ref: str) -> WorldSpec:
    return load_world(find_world(ref))
