"""The race's five-stage chain (bench/loop/chain.py), one per robot of the fleet.

``robot_nodes("r07")`` builds robot ``r07``'s five nodes, ``monitor_r07``,
``analysis_r07``, ``planner_r07``, ``legitimate_r07`` and ``executor_r07``, with the
chain's handlers on the robot's own topics (``r07/scan`` in, ``r07/spin_config`` out),
events (``r07/new-data``, ``r07/anomaly``, ``r07/new-plan``, ``r07/verdict``,
``r07/plan-rejected``) and knowledge keys (``r07/laser_scan``, ``r07/lidar_mask``,
``r07/directions``), and its own approval gate: execute acts only on a plan approved by
``legitimate_r07``, fresh and not replayed. Every scan runs the whole loop, as in the race.

A deployment plan names the nodes as attributes of this module
(``bench.fleet.nodes:monitor_r07``): the module builds a robot's five nodes the first
time one of them is asked for, so any fleet size works without a module per robot.
"""

from __future__ import annotations

import re

from lidar_occlusion.planning import check_plan
from rap_schemas import LaserScan, LidarMask, PlanProposal, SpinPlan
from rap_sdk import Context, Node
from rap_sdk.gate import ApprovalGate, legitimate, propose

from bench.loop.chain import LEGIT, PLAN, mask_of

STAGES = {
    "monitor": "monitor",
    "analysis": "analyse",
    "planner": "plan",
    "legitimate": "legitimate",
    "executor": "execute",
}
"""Node name prefix -> MAPLE-K stage."""

_NAME = re.compile(r"^(" + "|".join(STAGES) + r")_([A-Za-z0-9]+)$")
_built: dict[str, dict[str, Node]] = {}


def node_name(prefix: str, robot: str) -> str:
    return f"{prefix}_{robot}"


def robot_nodes(robot: str) -> dict[str, Node]:
    """Robot ``robot``'s five nodes by name (built once per process)."""
    if robot in _built:
        return _built[robot]
    monitor = Node(node_name("monitor", robot), stage="monitor")
    analysis = Node(node_name("analysis", robot), stage="analyse")
    planner = Node(node_name("planner", robot), stage="plan")
    legitimator = Node(node_name("legitimate", robot), stage="legitimate")
    executor = Node(node_name("executor", robot), stage="execute")
    gate = ApprovalGate(legitimators={legitimator.name}, max_age=1.0)
    scan_key, mask_key = f"{robot}/laser_scan", f"{robot}/lidar_mask"
    new_data, anomaly = f"{robot}/new-data", f"{robot}/anomaly"
    new_plan, verdict, rejected = f"{robot}/new-plan", f"{robot}/verdict", f"{robot}/plan-rejected"

    @monitor.on_data(f"{robot}/scan")
    async def on_scan(ctx: Context, scan: LaserScan) -> None:
        await ctx.kb.write(scan_key, scan)
        await ctx.emit(new_data)

    @analysis.on_event(new_data)
    async def detect(ctx: Context) -> None:
        scan = await ctx.kb.read(scan_key, LaserScan)
        await ctx.kb.write(mask_key, mask_of(scan))
        await ctx.emit(anomaly)

    @planner.on_event(anomaly)
    async def make_plan(ctx: Context) -> None:
        await ctx.kb.read(mask_key, LidarMask)
        await ctx.kb.write(f"{robot}/directions", PLAN)
        await propose(ctx, PLAN, event=new_plan)

    @legitimate(legitimator, event=new_plan, verdict=verdict, rejected=rejected)
    async def check(ctx: Context, proposal: PlanProposal[SpinPlan]) -> str | None:
        return check_plan(proposal, ctx.clock.time_ns(), LEGIT)

    @gate.on_approved(executor, event=verdict, rejected=rejected)
    async def act(ctx: Context, proposal: PlanProposal[SpinPlan]) -> None:
        await ctx.publish(f"{robot}/spin_config", proposal.plan)

    nodes = [monitor, analysis, planner, legitimator, executor]
    _built[robot] = {n.name: n for n in nodes}
    return _built[robot]


def __getattr__(name: str) -> Node:
    """``monitor_r07`` and the like: that robot's node (how a plan's ``module:`` finds it)."""
    m = _NAME.match(name)
    if m is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return robot_nodes(m.group(2))[name]
