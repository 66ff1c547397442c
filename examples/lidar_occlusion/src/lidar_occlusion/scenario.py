"""One run of the case: the simulator in lockstep with the loop, observed, measured.

The :class:`Observer` lives beside the simulator: it sees ground truth through the
simulator's hooks (never on the robot's topics) and the loop through the fabric (its
events and trace records). :func:`metrics` turns what it saw into the figures of the
reference's "What working means". :func:`run_in_process` runs everything on one fabric
in this process (the knowledge service too); the demo runs the loop in other processes
and uses the same observer.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import partial
from typing import Any

import anyio
import msgspec
import numpy as np
from rap_schemas import LidarMask, PlanProposal, SpinPlan, StageTrace, Verdict, keys
from rap_sdk import Fabric, InboxPolicy, MemoryFabric, Node, OutgoingEnvelope, Overflow, run_nodes
from rap_sdk.cycles import CycleTracker, Topology
from rap_sdk.envelope import TypedEnvelope, typed_decoder
from rap_sdk.gate import NEW_PLAN, PLAN_REJECTED, VERDICT
from sim_world.service import SimService
from sim_world.sim import ScanEvent, Simulation
from sim_world.viz import RerunLog
from sim_world.world import WorldSpec

from .analysis import AnalysisConfig, ignore_band, signed_angles
from .nodes import ANOMALY, build

__all__ = ["Observer", "metrics", "rejection_codes", "run_in_process", "spin_seconds"]

_any = typed_decoder(None)
_OBSERVED = {
    ANOMALY: LidarMask,
    NEW_PLAN: PlanProposal,
    VERDICT: Verdict,
    PLAN_REJECTED: Verdict,
}


@dataclass
class _Scan:
    t: float
    sent_ns: int
    """When the scan was sent (its envelope's ts, UTC ns: one clock for every process of
    this host, as the anomaly's and the plan's times)."""
    visible: np.ndarray[Any, np.dtype[np.bool_]]
    """Ground truth: occluded beams outside the ignored band."""


@dataclass
class Observer:
    system: str
    robot: str = "tb1"
    cfg: AnalysisConfig = field(default_factory=AnalysisConfig)
    rerun: RerunLog | None = None
    scans: list[_Scan] = field(default_factory=list)
    by_cycle: dict[bytes, int] = field(default_factory=dict)
    anomalies: list[tuple[int, int, LidarMask]] = field(default_factory=list)
    """(scan index, emitted at (UTC ns, its envelope's ts), mask)."""
    proposed: int = 0
    approved: int = 0
    rejected: int = 0
    plans: list[tuple[int, int, SpinPlan]] = field(default_factory=list)
    """(scan index of the cycle, applied at (UTC ns), plan) for plans applied by the robot."""
    rejections: list[str] = field(default_factory=list)
    """The reason of each verdict of the legitimate stage that rejected a plan."""
    stages: dict[bytes, list[StageTrace]] = field(default_factory=dict)
    _band: np.ndarray[Any, np.dtype[np.bool_]] | None = None

    # -- simulator hooks ---------------------------------------------------------------
    def on_scan(self, ev: ScanEvent, env: OutgoingEnvelope) -> None:
        if ev.robot != self.robot:
            return
        s = ev.scan
        if self._band is None:
            angles = signed_angles(s.angle_min, s.angle_increment, s.beams)
            self._band = ignore_band(angles, self.cfg.ignore_from)
        self.by_cycle[env.uid] = len(self.scans)
        self.scans.append(_Scan(ev.t, env.ts, ev.occluded & ~self._band))

    def on_plan(self, robot: str, plan: SpinPlan, env: TypedEnvelope[SpinPlan]) -> None:
        idx = self.by_cycle.get(env.cycle or b"", -1)
        self.plans.append((idx, time.time_ns(), plan))
        if self.rerun is not None and idx >= 0:
            self.rerun.rec.log(
                f"maplek/{robot}/cycles",
                self.rerun.rr.TextLog(f"cycle of scan {idx}: plan at the robot"),
            )

    # -- the loop, seen on the fabric ---------------------------------------------------
    async def follow(
        self, *, fabric: Fabric, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        policy = InboxPolicy(capacity=65536, overflow=Overflow.FIFO)
        decoders = {
            keys.event(self.system, n): msgspec.msgpack.Decoder(t) for n, t in _OBSERVED.items()
        }
        trace = msgspec.msgpack.Decoder(StageTrace)
        with (
            fabric.subscribe(keys.pattern(self.system, keys.Kind.EVENT), policy) as events,
            fabric.subscribe(keys.pattern(self.system, keys.Kind.TRACE), policy) as traces,
        ):
            task_status.started()
            async with anyio.create_task_group() as tg:
                tg.start_soon(self._events, events, decoders)
                tg.start_soon(self._traces, traces, trace)

    async def _events(self, sub: Any, decoders: dict[str, msgspec.msgpack.Decoder[Any]]) -> None:
        async for sample in sub:
            dec = decoders.get(sample.key)
            if dec is None:
                continue
            env = _any(sample.payload)
            body = dec.decode(env.body)
            name = sample.key.rsplit("/", 1)[-1]
            if name == ANOMALY:
                idx = self.by_cycle.get(env.cycle or b"", -1)
                self.anomalies.append((idx, env.ts, body))
            elif name == NEW_PLAN:
                self.proposed += 1
            elif name == VERDICT and body.approved:
                self.approved += 1
            elif name == VERDICT:
                self.rejections.append(body.reason)
            elif name == PLAN_REJECTED:
                self.rejected += 1

    async def _traces(self, sub: Any, dec: msgspec.msgpack.Decoder[StageTrace]) -> None:
        async for sample in sub:
            env = _any(sample.payload)
            if env.type != StageTrace.TYPE:
                continue
            rec = dec.decode(env.body)
            if rec.ended and len(self.stages) < 100_000:
                self.stages.setdefault(rec.cycle, []).append(rec)
            if self.rerun is not None and rec.ended and rec.stage is not None:
                idx = self.by_cycle.get(rec.cycle, -1)
                if idx >= 0:
                    self.rerun.rec.set_time("sim", duration=self.scans[idx].t)
                    self.rerun.rec.log(
                        f"maplek/{rec.stage.value}",
                        self.rerun.rr.TextLog(
                            f"scan {idx}: {rec.node}.{rec.handler} "
                            f"{rec.duration_ns / 1000:.0f} us"
                            + (
                                f" sent {', '.join(k.rsplit('/', 1)[-1] for k in rec.sent)}"
                                if rec.sent
                                else ""
                            )
                        ),
                    )


def _pcts(values: Sequence[float]) -> dict[str, float | None]:
    if not values:
        return {"p50": None, "p99": None, "max": None}
    a = np.asarray(values, dtype=np.float64)
    return {
        "p50": float(np.percentile(a, 50, method="inverted_cdf")),
        "p99": float(np.percentile(a, 99, method="inverted_cdf")),
        "max": float(a.max()),
    }


def spin_seconds(applied: Sequence[tuple[float, SpinPlan]], end: float) -> float:
    """Seconds of turning that the plans ``applied`` ((sim time, plan), in order)
    commanded up to ``end``: each plan's commands once per period, from the time it
    was applied until the next plan replaced it (cut off there)."""
    total = 0.0
    for k, (t0, plan) in enumerate(applied):
        t1 = applied[k + 1][0] if k + 1 < len(applied) else end
        spin = sum(c.duration for c in plan.commands)
        if spin <= 0 or t1 <= t0:
            continue
        whole, rest = divmod(t1 - t0, plan.period)
        total += whole * spin + min(spin, rest)
    return total


def rejection_codes(reasons: Sequence[str]) -> dict[str, int]:
    """Rejections counted by the code their reason starts with (``"collision: ..."``
    -> ``collision``; a reason without such a code, e.g. the plan checks', -> ``check``)."""
    out: dict[str, int] = {}
    for r in reasons:
        head, sep, _ = r.partition(": ")
        code = head if sep and head and " " not in head else "check"
        out[code] = out.get(code, 0) + 1
    return out


def metrics(
    obs: Observer, sim: Simulation, *, tracker: CycleTracker | None = None
) -> dict[str, Any]:
    """The figures of one run (see docs/lidar_occlusion.md for each definition)."""
    cfg, scans = obs.cfg, obs.scans
    inc = 2 * math.pi / scans[0].visible.size if scans else 0.0
    occluded = [float(np.count_nonzero(s.visible)) * inc > cfg.min_arc for s in scans]
    onsets = [i for i, o in enumerate(occluded) if o and (i == 0 or not occluded[i - 1])]
    latencies: list[int] = []
    for i in onsets:
        end = next((j for j in range(i, len(scans)) if not occluded[j]), len(scans))
        hit = next((a for a, _, _ in obs.anomalies if i <= a < end), None)
        if hit is not None:
            latencies.append(hit - i)
    false = overreach = 0
    for idx, _, mask in obs.anomalies:
        flagged = np.asarray(mask.flags())
        if idx < 0 or flagged.size != scans[idx].visible.size:
            continue
        truth = np.zeros_like(flagged)
        for j in range(max(0, idx - cfg.window + 1), idx + 1):
            truth |= scans[j].visible
        if flagged.any() and not truth.any():
            false += 1  # occlusion claimed where there was none at all
        elif float(np.count_nonzero(flagged & ~truth)) * inc > cfg.min_arc:
            overreach += 1  # real occlusion, but the mask claims more than pi/48 too much
    loop_ms = [(ns - scans[i].sent_ns) / 1e6 for i, ns, _ in obs.plans if i >= 0]
    emitted = {idx: ns for idx, ns, _ in obs.anomalies}
    to_robot_ms = [(ns - emitted[i]) / 1e6 for i, ns, _ in obs.plans if i in emitted]
    applied = [(scans[i].t, plan) for i, _, plan in obs.plans if i >= 0]
    robot = sim.robots[obs.robot]
    route = robot.spec.route
    reached = robot.nav.index
    out: dict[str, Any] = {
        "sim_seconds": round(sim.t, 3),
        "scans": len(scans),
        "occlusion_onsets": len(onsets),
        "detected_onsets": len(latencies),
        "detection_rate": (len(latencies) / len(onsets)) if onsets else None,
        "anomalies": len(obs.anomalies),
        "false_anomalies": false,
        "overreaching_masks": overreach,
        "detection_latency_scans": {
            k: v for k, v in _pcts(latencies).items() if k in ("p50", "max")
        },
        "plans_proposed": obs.proposed,
        "plans_approved": obs.approved,
        "plans_rejected": obs.rejected,
        "plans_executed": len(obs.plans),
        "rejections": rejection_codes(obs.rejections),
        "spin_s": round(spin_seconds(applied, sim.t), 3),
        "loop_latency_ms": {k: v for k, v in _pcts(loop_ms).items() if k in ("p50", "p99")},
        "anomaly_to_robot_ms": {k: v for k, v in _pcts(to_robot_ms).items() if k in ("p50", "p99")},
        "collisions": robot.collisions,
        "waypoints_reached": reached,
        "route_completed": bool(route) and reached >= len(route),
        "distance_m": round(robot.distance, 2),
    }
    full = violations = 0
    order = ["monitor", "analyse", "plan", "legitimate", "execute"]
    for recs in obs.stages.values():
        start: dict[str, int] = {}
        for r in recs:  # a stage's first call in the cycle (the monitor handles the scan,
            if r.stage is None:  # then its odometry)
                continue
            # a call record is stamped at the start, an end record at the end
            at = r.ts if r.phase == "call" else r.ts - r.duration_ns
            start[r.stage.value] = min(at, start.get(r.stage.value, at))
        if all(st in start for st in order):
            full += 1  # one host, one clock: each stage started after the one before
            violations += [start[st] for st in order] != sorted(start[st] for st in order)
    out["full_cycles"] = full
    out["stage_order_violations"] = violations
    if tracker is not None:
        out["lockstep_timeouts"] = tracker.timeouts
    return out


async def run_in_process(
    world: WorldSpec,
    *,
    loop: bool = True,
    duration: float = 60.0,
    system: str = "demo",
    fabric: Fabric | None = None,
    rerun: RerunLog | None = None,
    nodes: Sequence[Node] | None = None,
) -> dict[str, Any]:
    """Run one scenario with everything in this process; returns :func:`metrics`."""
    from knowledge.app import open_service  # the service is wired only where it is run
    from knowledge.config import KnowledgeConfig

    if fabric is None:
        async with MemoryFabric() as own:
            return await run_in_process(
                world,
                loop=loop,
                duration=duration,
                system=system,
                fabric=own,
                rerun=rerun,
                nodes=nodes,
            )
    sim = Simulation(world)
    robot = world.robots[0].name
    obs = Observer(system, robot, rerun=rerun)
    loop_nodes = list(nodes) if nodes is not None else (build(robot).nodes if loop else [])
    async with anyio.create_task_group() as tg:
        service = SimService(
            sim, fabric=fabric, system=system, on_scan=obs.on_scan, on_plan=obs.on_plan, rerun=rerun
        )
        tracker = CycleTracker(Topology.of([*loop_nodes, service.node], system=system))
        service.sync = tracker
        await tg.start(partial(tracker.follow, fabric=fabric))
        await tg.start(partial(obs.follow, fabric=fabric))
        async with (
            open_service(KnowledgeConfig(system=system), fabric=fabric),
            run_nodes(loop_nodes, fabric=fabric, system=system),
        ):
            await service.run(duration)
        tg.cancel_scope.cancel()
    return metrics(obs, sim, tracker=tracker)
