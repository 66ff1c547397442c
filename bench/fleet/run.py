"""One fleet run: deploy the robots' loops, drive scans at them, time every cycle.

Processes, all on loopback Zenoh (each listens on a free port and connects to the ones
started before it, as ``lidar_occlusion.deploy.local_deployment`` meshes them):

- this process: the scan source, and the probe that times the cycles. The source is
  ``sim_world`` (:class:`sim_world.service.SimService` in real time, as ``make demo``
  hosts it) or a plain scan driver (one prepared scan per robot, sent on absolute
  deadlines);
- one knowledge service (``python -m knowledge``, memory backend);
- ``runners`` runner processes (``python -m maplek_runner PLAN --node fleetK``), robot
  ``i``'s five nodes on runner ``i % runners``.

A cycle's latency is the time from its scan's envelope stamp (sealed just before it is
published) to the moment this process's source receives the spin plan whose envelope
names that scan as its cycle; both on this process's wall clock. A scan whose plan has
not arrived within ``LOST_AFTER`` s is lost.
"""

from __future__ import annotations

import asyncio
import os
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import anyio
import msgspec
from anyio.abc import TaskStatus
from lidar_occlusion.deploy import local_deployment
from rap_schemas import SpinPlan, keys
from rap_sdk import (
    Context,
    InboxPolicy,
    Node,
    NodeRuntime,
    OutgoingEnvelope,
    Overflow,
    ZenohConfig,
    ZenohFabric,
)
from rap_sdk.envelope import TypedEnvelope
from rap_sdk.fabric import free_port
from sim_world.service import SimService
from sim_world.sim import ScanEvent, Simulation

from bench.loop.rap import make_scan
from bench.report import ROOT, pct

from .nodes import STAGES, node_name
from .procstat import Usage, machine_busy_s, usage
from .world import fleet_world, robot_names

SYSTEM = "fleet"
LOST_AFTER = 1.0
"""Seconds after its scan by which a cycle's plan must have arrived."""
SOURCES = ("sim", "driver")
SETTLE_MAX = 60.0
"""Seconds after the minimum warm-up to wait for the loops to settle before measuring
anyway (the run then says it did not settle)."""


class Interrupted(Exception):
    """SIGINT or SIGTERM during a run (the processes are stopped on the way out)."""


@dataclass(frozen=True)
class Options:
    robots: int = 50
    rate: float = 5.0
    seconds: float = 30.0
    warmup: float = 5.0
    runners: int = 2
    source: str = "sim"
    out: Path = ROOT / "out" / "bench-fleet"


@dataclass(slots=True)
class Cycle:
    robot: str
    ts: int
    """The scan envelope's stamp (wall clock, ns)."""
    tick: int
    pos: int
    """Place of the scan in its tick's burst (0: published first)."""
    latency: int | None = None


class Probe:
    """Every scan sent (by uid) and when its plan came back."""

    def __init__(self) -> None:
        self.cycles: dict[bytes, Cycle] = {}
        self.unmatched = 0
        """Plans whose cycle is no scan of this run."""
        self.duplicates = 0
        self.ticks: list[tuple[int, float, int]] = []
        """(tick, due time in s of the source's own clock, first scan's stamp)."""
        self._tick_t: float | None = None
        self._pos = 0

    def scan(self, robot: str, env: OutgoingEnvelope, t: float) -> None:
        """A scan published at source time ``t`` (scans of one tick share ``t``)."""
        if t != self._tick_t:
            self._tick_t, self._pos = t, 0
            self.ticks.append((len(self.ticks), t, env.ts))
        else:
            self._pos += 1
        self.cycles[env.uid] = Cycle(robot, env.ts, len(self.ticks) - 1, self._pos)

    def plan(self, cycle: bytes | None) -> None:
        now = time.time_ns()
        c = self.cycles.get(cycle or b"")
        if c is None:
            self.unmatched += 1
        elif c.latency is not None:
            self.duplicates += 1
        else:
            c.latency = now - c.ts


# -- sources -----------------------------------------------------------------------------


class SimSource:
    """sim_world in real time, in this process; its scans and the plans it applies go
    through the probe."""

    name = "sim_world"

    def __init__(self, opts: Options, probe: Probe, fabric: ZenohFabric) -> None:
        self.sim = Simulation(fleet_world(opts.robots, opts.rate))

        def on_scan(ev: ScanEvent, env: OutgoingEnvelope) -> None:
            probe.scan(ev.robot, env, ev.t)

        def on_plan(robot: str, plan: SpinPlan, env: TypedEnvelope[SpinPlan]) -> None:
            probe.plan(env.cycle)

        self.service = SimService(
            self.sim,
            fabric=fabric,
            system=SYSTEM,
            realtime_factor=1.0,
            on_scan=on_scan,
            on_plan=on_plan,
        )

    async def run(self, *, task_status: TaskStatus[None] = anyio.TASK_STATUS_IGNORED) -> None:
        await self.service.run(None, task_status=task_status)

    def dropped(self) -> int:
        """Plans sim_world's inboxes dropped, full (each robot's keeps the newest 4)."""
        rt = self.service.runtime
        return rt.stats.dropped if rt is not None else 0


class DriverSource:
    """A plain scan driver: every ``1 / rate`` s (absolute deadlines) one prepared
    360-beam scan per robot, all robots in one burst as sim_world sends them."""

    name = "driver"

    def __init__(self, opts: Options, probe: Probe, fabric: ZenohFabric) -> None:
        self.rate, self.probe, self.fabric = opts.rate, probe, fabric
        self.robots = robot_names(opts.robots)
        base = make_scan()
        self.scans = {
            r: msgspec.structs.replace(base, frame_id=f"{r}/base_link") for r in self.robots
        }
        self.node = Node("fleet_driver")
        self.runtime: NodeRuntime | None = None
        latest = InboxPolicy(capacity=4, overflow=Overflow.LATEST)  # as sim_world's inputs
        for r in self.robots:
            self.node.on_data(f"{r}/spin_config", policy=latest)(self._on_plan)

    def dropped(self) -> int:
        """Plans the driver's inboxes dropped, full (each robot's keeps the newest 4)."""
        return self.runtime.stats.dropped if self.runtime is not None else 0

    async def _on_plan(self, ctx: Context, plan: SpinPlan) -> None:
        self.probe.plan(ctx.envelope.cycle)

    async def run(self, *, task_status: TaskStatus[None] = anyio.TASK_STATUS_IGNORED) -> None:
        rt = self.runtime = NodeRuntime(self.node, fabric=self.fabric, system=SYSTEM)
        scan_keys = {r: keys.data(SYSTEM, f"{r}/scan") for r in self.robots}
        async with anyio.create_task_group() as tg:
            await tg.start(rt.run)
            task_status.started()
            period, start = 1.0 / self.rate, anyio.current_time()
            i = 0
            while True:
                i += 1
                t = i * period
                await anyio.sleep(max(0.0, start + t - anyio.current_time()))
                for r in self.robots:
                    env = await rt.send(scan_keys[r], self.scans[r])
                    self.probe.scan(r, env, t)


Source = SimSource | DriverSource


# -- the deployment ----------------------------------------------------------------------


def write_plan(path: Path, robots: list[str], runners: int) -> Path:
    """The deployment plan: robot ``i``'s five nodes on compute node ``fleet{i % runners}``."""
    lines = [
        f"# bench/fleet: {len(robots)} robots' five-stage loops on {runners} runner(s).",
        f"system: {SYSTEM}",
        "compute_nodes:",
        *(f"  fleet{k}: {{}}" for k in range(runners)),
        "knowledge: {backend: memory, node: fleet0}",
        "components:",
    ]
    for i, robot in enumerate(robots):
        for prefix, stage in STAGES.items():
            name = node_name(prefix, robot)
            lines.append(
                f'  {name}: {{module: "bench.fleet.nodes:{name}", stage: {stage}, '
                f"node: fleet{i % runners}}}"
            )
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


@dataclass
class Sampler:
    """CPU seconds over the measurement window and resident memory of each process."""

    pids: dict[str, int]
    start: dict[str, Usage] = field(default_factory=dict)
    end: dict[str, Usage] = field(default_factory=dict)
    rss_max: dict[str, int] = field(default_factory=dict)
    machine: list[tuple[float, float]] = field(default_factory=list)
    t: list[float] = field(default_factory=list)

    def take(self) -> dict[str, Usage]:
        now = {name: usage(pid) for name, pid in self.pids.items()}
        for name, u in now.items():
            self.rss_max[name] = max(self.rss_max.get(name, 0), u.rss)
        return now

    def begin(self) -> None:
        self.start = self.take()
        self.machine.append(machine_busy_s())
        self.t.append(time.perf_counter())

    def finish(self) -> None:
        self.end = self.take()
        self.machine.append(machine_busy_s())
        self.t.append(time.perf_counter())

    def figures(self) -> dict[str, Any]:
        wall = self.t[1] - self.t[0]
        rows: list[dict[str, Any]] = []
        for name, pid in self.pids.items():
            cpu = self.end[name].cpu_s - self.start[name].cpu_s
            rows.append(
                {
                    "process": name,
                    "pid": pid,
                    "cpu_s": round(cpu, 2),
                    "cpu_pct": round(100 * cpu / wall, 1),
                    "rss_start_mib": round(self.start[name].rss / 2**20, 1),
                    "rss_mib": round(self.end[name].rss / 2**20, 1),
                    "rss_max_mib": round(self.rss_max[name] / 2**20, 1),
                    "rss_peak_mib": round(self.end[name].rss_peak / 2**20, 1),
                }
            )
        ours = sum(r["cpu_s"] for r in rows)
        busy = self.machine[1][0] - self.machine[0][0]
        cores = os.cpu_count() or 1
        return {
            "window_s": round(wall, 2),
            "processes": rows,
            "total": {
                "cpu_s": round(ours, 2),
                "cpu_pct": round(100 * ours / wall, 1),
                "cpu_pct_of_machine": round(100 * ours / (wall * cores), 1),
                "rss_mib": round(sum(r["rss_mib"] for r in rows), 1),
            },
            "machine": {
                "cores": cores,
                "busy_pct_of_machine": round(100 * busy / (wall * cores), 1),
                "others_pct": round(100 * max(0.0, busy - ours) / wall, 1),
                "note": "others: CPU the rest of the machine used in the window, % of one core",
            },
        }


async def _wait(seconds: float, stop: anyio.Event) -> None:
    with anyio.move_on_after(seconds):
        await stop.wait()
    if stop.is_set():
        raise Interrupted


async def _settle(probe: Probe, stop: anyio.Event) -> bool:
    """Wait until every scan of a whole second (the one that ended ``LOST_AFTER`` s ago)
    had its plan back within ``LOST_AFTER`` s: the loops have got through their start
    (first reads of each key, the backlog of the first scans). False after
    ``SETTLE_MAX`` s."""
    deadline = anyio.current_time() + SETTLE_MAX
    while anyio.current_time() < deadline:
        now = time.time_ns()
        hi = now - round(LOST_AFTER * 1e9)
        lo = hi - 1_000_000_000
        recent = [c for c in probe.cycles.values() if lo <= c.ts < hi]
        limit = LOST_AFTER * 1e9
        if recent and all(c.latency is not None and c.latency <= limit for c in recent):
            return True
        await _wait(0.25, stop)
    return False


async def measure(opts: Options, say: Callable[[str], None]) -> dict[str, Any]:
    """Deploy, warm up, measure ``opts.seconds``, stop; raw figures of the run.
    SIGINT/SIGTERM stop it early (raising :class:`Interrupted`, processes stopped)."""
    stop = anyio.Event()
    loop = asyncio.get_running_loop()
    for s in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(s, stop.set)
    try:
        return await _measure(opts, stop, say)
    finally:
        for s in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(s)


async def _measure(opts: Options, stop: anyio.Event, say: Callable[[str], None]) -> dict[str, Any]:
    robots = robot_names(opts.robots)
    for old in opts.out.glob("runner-fleet*.log"):  # a former run's, maybe more runners
        old.unlink()
    plan = write_plan(opts.out / "fleet.yaml", robots, opts.runners)
    # the runners import bench.fleet.nodes: the repository root on their path
    os.environ["PYTHONPATH"] = os.pathsep.join(
        p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p
    )
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    probe = Probe()
    t_start = time.perf_counter()
    async with ZenohFabric(ZenohConfig(listen=[endpoint])) as fabric:
        say(f"starting the knowledge service and {opts.runners} runner(s) for {len(robots)} robots")
        async with local_deployment(plan, fabric=fabric, endpoint=endpoint, logs=opts.out) as dep:
            say(f"{5 * len(robots)} nodes alive after {time.perf_counter() - t_start:.1f} s")
            source: Source = (
                SimSource(opts, probe, fabric)
                if opts.source == "sim"
                else DriverSource(opts, probe, fabric)
            )
            pids = {f"{source.name} + probe (this process)": os.getpid()}
            pids.update({name: p.pid for name, p in dep.processes.items()})
            sampler = Sampler(pids)
            async with anyio.create_task_group() as tg:
                await tg.start(source.run)
                say(f"{source.name}: {len(robots)} robots at {opts.rate:g} Hz")
                say(f"warm-up: {opts.warmup:g} s, then until a whole second's cycles came back")
                t_sent = time.perf_counter()
                await _wait(opts.warmup, stop)
                settled = await _settle(probe, stop)
                warmed = time.perf_counter() - t_sent
                say(
                    f"settled after {warmed:.1f} s"
                    if settled
                    else f"not settled after {warmed:.1f} s: measuring anyway"
                )
                sampler.begin()
                dropped0 = source.dropped()
                w0 = time.time_ns()
                say(f"measuring {opts.seconds:g} s")
                deadline = anyio.current_time() + opts.seconds
                while (left := deadline - anyio.current_time()) > 0:
                    await _wait(min(1.0, left), stop)
                    sampler.take()  # the largest resident set seen in the window
                w1 = time.time_ns()
                sampler.finish()
                sim_t = source.sim.t if isinstance(source, SimSource) else None
                await _wait(LOST_AFTER + 0.25, stop)  # the window's last plans
                dropped1 = source.dropped()
                tg.cancel_scope.cancel()
            say("stopping the processes")
    return {
        "window_ns": (w0, w1),
        "probe": probe,
        "resources": sampler.figures(),
        "source": source.name,
        "warmup_s": round(warmed, 1),
        "plans_dropped": {"warmup": dropped0, "window": dropped1 - dropped0},
        "settled": settled,
        "sim_seconds": sim_t,
        "plan": str(plan.relative_to(ROOT)) if plan.is_relative_to(ROOT) else str(plan),
        "wall_seconds": round(time.perf_counter() - t_start, 1),
    }


def cycles_in(probe: Probe, window: tuple[int, int]) -> list[Cycle]:
    w0, w1 = window
    return [c for c in probe.cycles.values() if w0 <= c.ts < w1]


def pacing(probe: Probe, window: tuple[int, int]) -> dict[str, float]:
    """How well the source kept its pace in the window: each tick's first scan stamp
    against its due time, relative to the tick that was least late (ms), and how long
    a tick's burst of scans took to publish (first to last stamp, ms)."""
    w0, w1 = window
    ticks = [(k, t, ts) for k, t, ts in probe.ticks if w0 <= ts < w1]
    if not ticks:
        return {}
    offsets = [ts - t * 1e9 for _, t, ts in ticks]
    base = min(offsets)
    lag = [(o - base) / 1e6 for o in offsets]
    last: dict[int, int] = {}
    for c in probe.cycles.values():
        last[c.tick] = max(last.get(c.tick, 0), c.ts)
    spread = [(last[k] - ts) / 1e6 for k, _, ts in ticks]
    return {
        "ticks": len(ticks),
        "lag_p99_ms": round(pct(lag, 0.99), 2),
        "lag_max_ms": round(max(lag), 2),
        "burst_p50_ms": round(pct(spread, 0.5), 2),
        "burst_max_ms": round(max(spread), 2),
    }
