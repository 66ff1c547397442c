"""The race's chain: the RPIO harness's five stages, as RAP nodes.

Like the peer (bench/loop/rpio_peer.py) every scan runs the whole loop: the monitor
stores the scan, the analysis stores the occlusion mask (beams with no finite return)
and always raises an anomaly, the planner stores a fixed plan and proposes it, the
legitimate stage checks it, and the executor sends it to the robot. Unlike the peer,
the approval gate is in force (execute acts only on an approved, fresh, unreplayed
plan) and every read is causal: that is RAP's contract, and it is measured with it.

``handlers()`` gives the same five steps as plain functions on a dict, for the floor.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from lidar_occlusion.planning import LegitimacyConfig, check_plan
from rap_schemas import (
    LaserScan,
    LidarMask,
    PlanProposal,
    SpinCommand,
    SpinPlan,
    Verdict,
    pack_flags,
)
from rap_sdk import Context, Node
from rap_sdk.gate import ApprovalGate, legitimate, propose

ROBOT = "tb1"
PLAN = SpinPlan(commands=[SpinCommand(omega=1.0, duration=0.5)], period=8.0)
LEGIT = LegitimacyConfig(max_age=1.0)

monitor = Node("monitor", stage="monitor")
analysis = Node("analysis", stage="analyse")
planner = Node("planner", stage="plan")
legitimator = Node("legitimate", stage="legitimate")
executor = Node("executor", stage="execute")
gate = ApprovalGate(legitimators={"legitimate"}, max_age=1.0)


def mask_of(scan: LaserScan) -> LidarMask:
    return LidarMask(
        angle_min=scan.angle_min,
        angle_increment=scan.angle_increment,
        occluded=pack_flags(~np.isfinite(np.asarray(scan.values()))),
        frame_id=scan.frame_id,
    )


@monitor.on_data(f"{ROBOT}/scan")
async def on_scan(ctx: Context, scan: LaserScan) -> None:
    await ctx.kb.write("laser_scan", scan)
    await ctx.emit("new-data")


@analysis.on_event("new-data")
async def detect(ctx: Context) -> None:
    scan = await ctx.kb.read("laser_scan", LaserScan)
    await ctx.kb.write("lidar_mask", mask_of(scan))
    await ctx.emit("anomaly")


@planner.on_event("anomaly")
async def make_plan(ctx: Context) -> None:
    await ctx.kb.read("lidar_mask", LidarMask)
    await ctx.kb.write("directions", PLAN)
    await propose(ctx, PLAN)


@legitimate(legitimator)
async def check(ctx: Context, proposal: PlanProposal[SpinPlan]) -> str | None:
    return check_plan(proposal, ctx.clock.time_ns(), LEGIT)


@gate.on_approved(executor)
async def act(ctx: Context, proposal: PlanProposal[SpinPlan]) -> None:
    await ctx.publish(f"{ROBOT}/spin_config", proposal.plan)


echo = Node("echo", stage="monitor")
"""The transport floor through RAP (plans/echo.yaml): each scan straight back as a plan."""


@echo.on_data(f"{ROBOT}/scan")
async def answer(ctx: Context, scan: LaserScan) -> None:
    await ctx.publish(f"{ROBOT}/spin_config", PLAN)


def handlers(now_ns: Callable[[], int]) -> Callable[[LaserScan], SpinPlan | None]:
    """The floor: the same five steps called directly, knowledge in a dict."""
    kb: dict[str, Any] = {}
    floor_gate = ApprovalGate(legitimators={"legitimate"}, max_age=1.0)
    uid = [0]

    def cycle(scan: LaserScan) -> SpinPlan | None:
        kb["laser_scan"] = scan  # monitor
        kb["lidar_mask"] = mask_of(kb["laser_scan"])  # analysis
        _ = kb["lidar_mask"]  # plan
        kb["directions"] = PLAN
        uid[0] += 1
        proposal = PlanProposal(
            plan_uid=uid[0].to_bytes(16, "big"),
            plan_type=PLAN.TYPE,
            plan=PLAN,
            proposer="planner",
            created=now_ns(),
        )
        reason = check_plan(proposal, now_ns(), LEGIT)  # legitimate
        verdict = Verdict(
            plan_uid=proposal.plan_uid,
            approved=reason is None,
            legitimator="legitimate",
            ts=now_ns(),
            proposal=proposal,
        )
        if floor_gate.check(verdict, "legitimate", now_ns()) is None:  # execute
            return proposal.plan
        return None

    return cycle
