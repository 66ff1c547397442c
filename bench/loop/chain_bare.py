"""The race's chain with no knowledge: the same five nodes, messages and gate as
:mod:`bench.loop.chain`, with every knowledge read and write taken out.

The analysis computes its mask from the race's scan, held here, instead of reading it
from knowledge; the planner proposes without reading the mask or storing the plan; the
legitimate and execute stages, which use no knowledge, are the chain's own.
Deployed like the chain (plans/five-bare.yaml, plans/one-bare.yaml), it shows what the
loop costs without its knowledge: ``python -m bench.loop.split``.
"""

from __future__ import annotations

from rap_schemas import LaserScan
from rap_sdk import Context, Node
from rap_sdk.gate import propose

from .chain import PLAN, ROBOT, executor, legitimator, mask_of
from .rap import make_scan

SCAN = make_scan()

monitor = Node("monitor", stage="monitor")
analysis = Node("analysis", stage="analyse")
planner = Node("planner", stage="plan")


@monitor.on_data(f"{ROBOT}/scan")
async def on_scan(ctx: Context, scan: LaserScan) -> None:
    await ctx.emit("new-data")


@analysis.on_event("new-data")
async def detect(ctx: Context) -> None:
    mask_of(SCAN)
    await ctx.emit("anomaly")


@planner.on_event("anomaly")
async def make_plan(ctx: Context) -> None:
    await propose(ctx, PLAN)


__all__ = ["analysis", "executor", "legitimator", "monitor", "planner"]
