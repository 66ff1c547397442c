"""The five MAPLE-K stages of the lidar-occlusion loop as RAP nodes.

- monitor, on data ``<robot>/scan`` and ``<robot>/odom``: writes ``laser_scan`` and,
  when the robot sends odometry, with the pose of the scan's stamp, ``odometry`` and
  ``obstacle_map`` (what the robot has seen: :mod:`lidar_occlusion.belief`); emits
  ``new-data``.
- analyse, on ``new-data``: reads ``laser_scan``, ``planned_lidar_mask`` and
  ``handling_anomaly``; writes ``lidar_mask`` and, on an anomaly, ``handling_anomaly``;
  emits ``anomaly`` (with the mask), else ``scan-mask``.
- plan, on ``anomaly`` (and ``plan-rejected``; the lookahead planner on ``scan-mask``
  too): reads ``lidar_mask`` (and ``odometry``); writes ``planned_lidar_mask``,
  ``directions`` and ``planned_for``; proposes the plan (``new-plan``).
- legitimate, on ``new-plan``: emits ``verdict`` (and ``plan-rejected`` when it rejects);
  with ``LegitimacyConfig.twin`` it rolls the plan out on the twin from the robot's belief
  (:mod:`lidar_occlusion.twin`).
- execute, on an approving ``verdict`` that passes the gate: publishes the plan on data
  ``<robot>/spin_config``; writes ``handling_anomaly`` = false.

Stage order holds by causality alone: every event carries the knowledge versions written
before it, and a read waits for them. Execute acts only through the
:class:`~rap_sdk.gate.ApprovalGate`: on the approved proposal itself, never on what the
``directions`` key holds by then (RPIO's Execute read whatever was there).

``build(robot)`` makes a fresh set (one per robot, or per evaluation run); the module
attributes ``monitor`` ... ``execute`` are the set for robot ``tb1`` that the shipped
deployment plans name.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any

import msgspec
import numpy as np
from rap_schemas import LaserScan, LidarMask, Odometry, PlanProposal, SpinPlan, Verdict
from rap_sdk import Context, Node
from rap_sdk.gate import PLAN_REJECTED, ApprovalGate, legitimate, propose
from rap_sdk.twin import ask

from .analysis import AnalysisConfig, MaskWindow, analyse_scan, is_anomaly, to_message
from .belief import MapConfig, ObstacleMap, belief_of, update
from .lookahead import Lookahead
from .planning import LegitimacyConfig, PlanConfig, check_plan, plan_for
from .twin import LidarTwin, TwinConfig, pose_mismatch

__all__ = [
    "ANOMALY",
    "DIRECTIONS",
    "HANDLING",
    "LASER_SCAN",
    "LIDAR_MASK",
    "NEW_DATA",
    "PLANNED_MASK",
    "ExecuteConfig",
    "Loop",
    "MonitorConfig",
    "analyse",
    "build",
    "execute",
    "fresh_analysis",
    "legitimate_node",
    "monitor",
    "plan",
]

log = logging.getLogger(__name__)

NEW_DATA = "new-data"
ANOMALY = "anomaly"
PAIRING = 8
"""Scans (or odometry) the monitor keeps while it waits for their partner."""
SCAN_MASK = "scan-mask"
"""Analysis's mask of a scan that raised no anomaly (the lookahead planner decides on
every scan)."""

# knowledge keys (the reference's names)
LASER_SCAN = "laser_scan"
# what the twin-backed Legitimate stage needs besides (RAP's own keys)
ODOMETRY = "odometry"
OBSTACLE_MAP = "obstacle_map"
PLANNED_FOR = "planned_for"
LIDAR_MASK = "lidar_mask"
PLANNED_MASK = "planned_lidar_mask"
DIRECTIONS = "directions"
HANDLING = "handling_anomaly"


class MonitorConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    belief: bool = False
    """Keep the obstacle map (:mod:`lidar_occlusion.belief`) in knowledge, for the
    twin-backed Legitimate stage (``LegitimacyConfig.twin``): 15-60 kB a scan, so off
    unless a twin reads it."""


class ExecuteConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    max_age: float = 0.2
    """Seconds an approved plan stays executable after its creation."""


@dataclass
class Loop:
    robot: str
    monitor: Node
    analyse: Node
    plan: Node
    legitimate: Node
    execute: Node
    gate: ApprovalGate
    window: MaskWindow = field(default_factory=MaskWindow)

    @property
    def nodes(self) -> list[Node]:
        return [self.monitor, self.analyse, self.plan, self.legitimate, self.execute]


class _PlanState(msgspec.Struct):
    attempts: int = 0
    """Re-proposals of the current plan after rejections."""
    previous: LidarMask | None = None
    """The planned mask before the current proposal: restored when it is given up."""
    current: bytes = b""
    """uid of the plan proposed last: rejections of other plans are not this one's."""


def build(
    robot: str = "tb1",
    *,
    prefix: str = "",
    monitoring: MonitorConfig | None = None,
    analysis: AnalysisConfig | None = None,
    planning: PlanConfig | None = None,
    legitimacy: LegitimacyConfig | None = None,
    execution: ExecuteConfig | None = None,
) -> Loop:
    """A fresh set of the five nodes for ``robot`` (names start with ``prefix``)."""
    mon = Node(f"{prefix}monitor", stage="monitor", config=monitoring or MonitorConfig())
    ana = Node(f"{prefix}analysis", stage="analyse", config=analysis or AnalysisConfig())
    pla = Node(f"{prefix}planner", stage="plan", config=planning or PlanConfig())
    leg = Node(f"{prefix}legitimate", stage="legitimate", config=legitimacy or LegitimacyConfig())
    exe_cfg = execution or ExecuteConfig()
    exe = Node(f"{prefix}executor", stage="execute", config=exe_cfg)
    gate = ApprovalGate(legitimators={leg.name}, max_age=exe_cfg.max_age)
    loop = Loop(robot, mon, ana, pla, leg, exe, gate)
    spin_topic = f"{robot}/spin_config"

    # -- monitor ---------------------------------------------------------------------------
    scans: dict[int, LaserScan] = {}
    """Scans waiting for the odometry of their stamp."""
    poses: dict[int, Odometry] = {}
    """Odometry waiting for the scan of its stamp (the two come on separate routes)."""
    held: dict[str, Any] = {"map": None, "odometry": False}
    """The obstacle map, and whether this robot sends odometry at all."""
    map_cfg = MapConfig()

    def keep(waiting: dict[int, Any], stamp: int, value: Any) -> None:
        waiting[stamp] = value
        while len(waiting) > PAIRING:
            old = min(waiting)
            del waiting[old]
            log.debug("%s: %d had no partner (scan or odometry); dropped", mon.name, old)

    async def go_on(ctx: Context, scan: LaserScan, odom: Odometry | None) -> None:
        await ctx.kb.write(LASER_SCAN, scan)
        if odom is not None:
            await ctx.kb.write(ODOMETRY, odom)
            cfg: MonitorConfig = ctx.config
            if cfg.belief:
                pose, t = odom.pose, scan.stamp / 1e9
                seen: ObstacleMap = update(held["map"], scan, pose, t, map_cfg)
                held["map"] = seen
                await ctx.kb.write(OBSTACLE_MAP, seen)
        await ctx.emit(NEW_DATA)

    @mon.on_data(f"{robot}/scan")
    async def on_scan(ctx: Context, scan: LaserScan) -> None:
        """A robot without odometry: each scan goes on at once. With odometry, a scan
        goes on with the pose of its stamp (whichever of the two comes second), so that
        what follows carries both: the obstacle map and the planners need the pose."""
        odom = poses.pop(scan.stamp, None)
        if odom is not None or not held["odometry"]:
            await go_on(ctx, scan, odom)
        else:
            keep(scans, scan.stamp, scan)

    @mon.on_data(f"{robot}/odom")
    async def on_odom(ctx: Context, odom: Odometry) -> None:
        held["odometry"] = True
        scan = scans.pop(odom.stamp, None)
        if scan is not None:
            await go_on(ctx, scan, odom)
        else:
            keep(poses, odom.stamp, odom)

    # -- analyse ---------------------------------------------------------------------------
    raised_at: list[int | None] = [None]
    """Scan stamp (ns) of the last anomaly raised here (None: none since this node
    started, so an anomaly marked as handled before a restart is given up on at once)."""

    @ana.on_event(NEW_DATA)
    async def detect(ctx: Context) -> None:
        cfg: AnalysisConfig = ctx.config
        scan = await ctx.kb.read(LASER_SCAN, LaserScan)
        if loop.window.size != cfg.window:
            loop.window = MaskWindow(cfg.window)
        mask = analyse_scan(scan, loop.window, cfg)
        planned_msg = await ctx.kb.read(PLANNED_MASK, LidarMask, default=None)
        handling = await ctx.kb.read(HANDLING, bool, default=False)
        since = raised_at[0]
        # a scan older than the anomaly (a forged or replayed stamp raised it): lost too
        waited = math.inf if since is None or scan.stamp < since else (scan.stamp - since) / 1e9
        lost = handling and waited > cfg.handling_timeout
        if lost:
            log.warning(
                "%s: no plan came of the anomaly raised %s (a stage died mid-cycle, or its "
                "plan was lost); raising anew",
                ana.name,
                "before this node started" if since is None else f"{waited:.2f} s ago",
            )
            handling = False
        # the planned mask of a lost plan is not in force: judge against no plan at all
        planned = None if planned_msg is None or lost else np.asarray(planned_msg.flags())
        msg = to_message(mask, scan)
        await ctx.kb.write(LIDAR_MASK, msg)
        if is_anomaly(mask, planned, scan.angle_increment, handling, cfg):
            raised_at[0] = scan.stamp
            log.info("%s: anomaly: %d beams occluded; asking for a plan", ana.name, mask.sum())
            await ctx.kb.write(HANDLING, True)
            await ctx.emit(ANOMALY, msg)
        else:  # for planners that decide on every scan (the lookahead)
            await ctx.emit(SCAN_MASK, msg)

    @ana.on_snapshot
    def save_window() -> list[list[bool]]:
        return loop.window.state()

    @ana.on_restore
    def load_window(state: list[list[bool]]) -> None:
        loop.window.restore(state)

    # -- plan ------------------------------------------------------------------------------
    st = _PlanState()

    ahead = Lookahead()

    async def look_ahead(ctx: Context, mask: LidarMask, anomaly: bool) -> SpinPlan | None:
        """The lookahead planner's decision at this scan (None: nothing to propose)."""
        cfg: PlanConfig = ctx.config
        odom = await ctx.kb.read(ODOMETRY, Odometry, default=None)
        scan = await ctx.kb.read(LASER_SCAN, LaserScan, default=None)
        if odom is None or scan is None:  # no pose yet: the reference, on an anomaly only
            if not anomaly:
                return None
            return plan_for(np.asarray(mask.flags()), mask.angle_min, mask.angle_increment, cfg)
        flags = np.asarray(mask.flags())
        return ahead.step(
            flags,
            mask.angle_min,
            mask.angle_increment,
            odom.pose,
            cfg.route,
            scan.stamp / 1e9,
            cfg,
            anomaly=anomaly,
            loop=cfg.loop_route,
        )

    @pla.on_event(SCAN_MASK, type=LidarMask)
    async def every_scan(ctx: Context, mask: LidarMask) -> None:
        cfg: PlanConfig = ctx.config
        if cfg.planner != "lookahead":
            return
        spin = await look_ahead(ctx, mask, anomaly=False)
        if spin is not None:
            await offer(ctx, spin, mask)

    @pla.on_event(ANOMALY, type=LidarMask)
    async def make_plan(ctx: Context) -> None:
        cfg: PlanConfig = ctx.config
        mask = await ctx.kb.read(LIDAR_MASK, LidarMask)
        if cfg.planner == "lookahead":
            spin = await look_ahead(ctx, mask, anomaly=True)
            if spin is None:
                return
        else:
            spin = plan_for(np.asarray(mask.flags()), mask.angle_min, mask.angle_increment, cfg)
        await offer(ctx, spin, mask)

    async def offer(ctx: Context, spin: SpinPlan, mask: LidarMask) -> None:
        st.previous = await ctx.kb.read(PLANNED_MASK, LidarMask, default=None)
        st.attempts = 0
        odom = await ctx.kb.read(ODOMETRY, Odometry, default=None)
        if odom is not None:  # what the plan was made for: the twin checks it still holds
            await ctx.kb.write(PLANNED_FOR, odom)
        await ctx.kb.write(PLANNED_MASK, mask)
        await ctx.kb.write(DIRECTIONS, spin)
        st.current = (await propose(ctx, spin)).plan_uid

    @pla.on_event(PLAN_REJECTED)
    async def replan(ctx: Context, verdict: Verdict[Any]) -> None:
        cfg: PlanConfig = ctx.config
        if verdict.plan_uid != st.current:
            return  # not the plan in hand (a refused replay of an older one, say)
        st.attempts += 1
        if st.attempts <= cfg.replans:
            spin = await ctx.kb.read(DIRECTIONS, SpinPlan)
            log.info("%s: plan rejected (%s); proposing it again", pla.name, verdict.reason)
            st.current = (await propose(ctx, spin)).plan_uid
            return
        log.warning("%s: plan rejected (%s); giving up on it", pla.name, verdict.reason)
        if cfg.planner == "lookahead":
            odom = await ctx.kb.read(ODOMETRY, Odometry, default=None)
            ahead.withdrawn(odom.stamp / 1e9 if odom is not None else 0.0, cfg)
        if st.previous is None:
            await ctx.kb.delete(PLANNED_MASK)
        else:
            await ctx.kb.write(PLANNED_MASK, st.previous)
        await ctx.kb.write(HANDLING, False)

    @pla.on_snapshot
    def save_plan_state() -> _PlanState:
        return st

    @pla.on_restore
    def load_plan_state(state: _PlanState) -> None:
        st.attempts, st.previous, st.current = state.attempts, state.previous, state.current

    # -- legitimate ------------------------------------------------------------------------
    twins: dict[TwinConfig, LidarTwin] = {}

    async def on_twin(ctx: Context, plan: SpinPlan, cfg: LegitimacyConfig) -> str | None:
        """The plan rolled out on the twin from the robot's belief: None, or why not."""
        odom = await ctx.kb.read(ODOMETRY, Odometry, default=None)
        scan = await ctx.kb.read(LASER_SCAN, LaserScan, default=None)
        seen = await ctx.kb.read(OBSTACLE_MAP, ObstacleMap, default=None)
        if odom is None or scan is None or seen is None:
            return "belief: the twin has no pose, scan or obstacle map of the robot yet"
        planned = await ctx.kb.read(PLANNED_FOR, Odometry, default=None)
        if planned is not None:
            made_for = planned.frame_id.split("/")[0]
            off = pose_mismatch(planned.pose, odom.pose, robot, made_for, cfg.twin_config)
            if off is not None:
                return f"{off.code}: {off.message}"
        mask = await ctx.kb.read(LIDAR_MASK, LidarMask, default=None)
        b = belief_of(robot, odom, scan, seen, mask, cfg.route, loop_route=cfg.loop_route)
        twin = twins.get(cfg.twin_config) or twins.setdefault(
            cfg.twin_config, LidarTwin(cfg.twin_config)
        )
        report = await ask(twin, plan, b)
        log.debug(
            "%s: twin rolled the plan out over %.1f s in %.1f ms: %s",
            leg.name,
            report.horizon_s,
            report.elapsed_s * 1e3,
            report.metrics,
        )
        return report.verdict

    @legitimate(leg)
    async def check(ctx: Context, proposal: PlanProposal[SpinPlan]) -> str | None:
        cfg: LegitimacyConfig = ctx.config
        reason = check_plan(proposal, ctx.clock.time_ns(), cfg)
        if reason is None and cfg.twin:
            reason = await on_twin(ctx, proposal.plan, cfg)
        log.info("%s: plan %s", leg.name, "approved" if reason is None else f"rejected: {reason}")
        return reason

    # -- execute ---------------------------------------------------------------------------
    @gate.on_approved(exe)
    async def act(ctx: Context, proposal: PlanProposal[SpinPlan]) -> None:
        log.info(
            "%s: executing an approved plan (%d spin commands) on %s",
            exe.name,
            len(proposal.plan.commands),
            spin_topic,
        )
        await ctx.publish(spin_topic, proposal.plan)
        await ctx.kb.write(HANDLING, False)

    return loop


_default = build()
monitor = _default.monitor
analyse = _default.analyse
plan = _default.plan
legitimate_node = _default.legitimate
execute = _default.execute


def fresh_analysis() -> Node:
    """A new instance of the analysis stage: a swap target (``rap swap analysis
    lidar_occlusion.nodes:fresh_analysis``), e.g. after its code changed on disk; the
    running one's mask window and config are handed over."""
    return build().analyse
