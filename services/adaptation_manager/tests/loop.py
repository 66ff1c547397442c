"""A small MAPLE-K loop for the manager's tests: five stages, a real Legitimate gate.

monitor (data ``scan``) -> ``new-data`` -> analysis -> ``anomaly`` -> planner -> ``new-plan``
-> legitimate -> ``verdict`` -> executor (through the gate) -> data ``spin_config``.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from typing import Any

import anyio
from rap_schemas import Empty, PlanProposal, SpinPlan
from rap_sdk import Context, Node
from rap_sdk.gate import ApprovalGate, legitimate, propose

__all__ = ["Waiter", "loop_nodes"]


def loop_nodes() -> list[Node]:
    monitor = Node("monitor", stage="monitor")
    analysis = Node("analysis", stage="analyse")
    planner = Node("planner", stage="plan")
    legit = Node("legitimate", stage="legitimate")
    executor = Node("executor", stage="execute")
    gate = ApprovalGate(legitimators={"legitimate"}, max_age=30.0)

    @monitor.on_data("scan")
    async def watch(ctx: Context) -> None:
        await ctx.emit("new-data")

    @analysis.on_event("new-data")
    async def find(ctx: Context) -> None:
        await ctx.emit("anomaly", Empty())

    @planner.on_event("anomaly")
    async def make(ctx: Context) -> None:
        await propose(ctx, SpinPlan(commands=[]))

    @legitimate(legit)
    async def judge(ctx: Context, proposal: PlanProposal[SpinPlan]) -> str | None:
        return None

    @gate.on_approved(executor)
    async def act(ctx: Context, proposal: PlanProposal[SpinPlan]) -> None:
        await ctx.publish("spin_config", proposal.plan)

    return [monitor, analysis, planner, legit, executor]


class Waiter:
    """Await a condition on the registry, woken by its change hook (no polling)."""

    def __init__(self) -> None:
        self._event = anyio.Event()
        self.inner: Callable[[str, Any], None] | None = None

    def hook(self, kind: str, view: Any) -> None:
        if self.inner is not None:
            self.inner(kind, view)
        self._event.set()

    def poke(self) -> None:
        self._event.set()

    async def until(self, pred: Callable[[], bool], timeout: float = 10.0, what: str = "") -> None:
        with anyio.fail_after(timeout):
            while not pred():
                await self._event.wait()
                self._event = anyio.Event()

    async def until_async(self, pred: Callable[[], Awaitable[bool]], timeout: float = 10.0) -> None:
        with anyio.fail_after(timeout):
            while not await pred():
                await self._event.wait()
                self._event = anyio.Event()
