"""The Legitimate gate (DESIGN §5): execute only ever acts on approved, fresh, unreplayed plans.

    plan = Node("planner", stage="plan")

    @plan.on_event("anomaly")
    async def replan(ctx: Context) -> None:
        await propose(ctx, spin_plan)                     # emits "new-plan"

    legit = Node("legitimate", stage="legitimate")

    @legitimate(legit)
    async def check(ctx: Context, proposal: PlanProposal) -> str | None:
        return None if ok(proposal.plan) else "why not"   # None approves

    execute = Node("executor", stage="execute")
    gate = ApprovalGate(legitimators={"legitimate"}, max_age=0.2)

    @gate.on_approved(execute)
    async def act(ctx: Context, proposal: PlanProposal) -> None: ...

The legitimate side answers every proposal with a ``verdict`` event; an approving verdict
carries the proposal it approves, so execute acts on exactly that plan. A rejection also
emits ``plan-rejected`` (the planner's cue to replan within its budget). The execute side
calls its handler only for a verdict that approves, comes from a named legitimator, is
fresh (``max_age`` s from the plan's creation, on the runtime's clock) and whose plan
was neither executed before nor superseded by a newer executed plan; any other verdict
is refused, counted in :class:`GateStats`, logged, and answered with ``plan-rejected``
(except a replayed approval of a plan that did run: there is nothing to replan).
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from collections.abc import Awaitable, Callable, Collection
from dataclasses import dataclass
from typing import TypeVar

from rap_schemas import PlanProposal, SpinPlan, Verdict

from .envelope import new_uid
from .node import Node
from .runtime import Context

__all__ = [
    "NEW_PLAN",
    "PLAN_REJECTED",
    "VERDICT",
    "ApprovalGate",
    "GateStats",
    "legitimate",
    "propose",
]

log = logging.getLogger(__name__)

NEW_PLAN = "new-plan"
VERDICT = "verdict"
PLAN_REJECTED = "plan-rejected"

Check = Callable[[Context, PlanProposal], Awaitable[str | None]]
Act = Callable[[Context, PlanProposal], Awaitable[None]]
A = TypeVar("A", bound=Act)
C = TypeVar("C", bound=Check)


async def propose(ctx: Context, plan: SpinPlan) -> PlanProposal:
    """Put ``plan`` to the Legitimate stage (event ``new-plan``) in this cycle."""
    now = ctx.clock.time_ns()
    proposal = PlanProposal(plan_uid=new_uid(now), plan=plan, proposer=ctx.node.name, created=now)
    await ctx.emit(NEW_PLAN, proposal)
    return proposal


def legitimate(node: Node, *, event: str = NEW_PLAN) -> Callable[[C], C]:
    """Make ``fn(ctx, proposal) -> reason | None`` the node's legitimation of plans.

    None approves; a string rejects with that reason; an exception rejects too (with
    the exception as the reason): a check that fails never approves."""

    def register(fn: C) -> C:
        async def decide(ctx: Context, proposal: PlanProposal) -> None:
            try:
                reason = await fn(ctx, proposal)
            except Exception as exc:  # a failing check rejects, it never approves
                log.exception("node %s: legitimation of a plan failed", ctx.node.name)
                reason = f"legitimation failed: {type(exc).__name__}: {exc}"
            approved = reason is None
            verdict = Verdict(
                plan_uid=proposal.plan_uid,
                approved=approved,
                legitimator=ctx.node.name,
                ts=ctx.clock.time_ns(),
                reason=reason or "",
                proposal=proposal if approved else None,
            )
            await ctx.emit(VERDICT, verdict)
            if not approved:
                await ctx.emit(PLAN_REJECTED, verdict)

        decide.__qualname__ = getattr(fn, "__qualname__", decide.__qualname__)
        node.on_event(event)(decide)
        return fn

    return register


@dataclass(slots=True)
class GateStats:
    approved: int = 0
    """Plans handed to the execute handler."""
    not_approved: int = 0
    """Verdicts that rejected (the legitimator emitted ``plan-rejected``)."""
    unknown_legitimator: int = 0
    malformed: int = 0
    """Approvals without their proposal, or with a proposal of another uid."""
    stale: int = 0
    replayed: int = 0
    superseded: int = 0

    @property
    def refused(self) -> int:
        return (
            self.unknown_legitimator + self.malformed + self.stale + self.replayed + self.superseded
        )


class ApprovalGate:
    """The execute side of the gate; see the module docstring."""

    def __init__(
        self,
        *,
        legitimators: Collection[str] | None = None,
        max_age: float | None = 1.0,
        memory: int = 4096,
    ) -> None:
        """``legitimators``: node names whose verdicts count (None: any sender).
        ``max_age``: seconds a plan stays executable after its creation (None: no limit).
        ``memory``: how many executed plan uids are remembered against replay; older
        ones are still refused as superseded."""
        self.legitimators = frozenset(legitimators) if legitimators is not None else None
        self.max_age_ns = None if max_age is None else round(max_age * 1e9)
        self.memory = memory
        self.stats = GateStats()
        self._executed: OrderedDict[bytes, None] = OrderedDict()
        self._newest = -1
        """``created`` of the newest executed plan: anything older is superseded."""

    def check(self, verdict: Verdict, source: str, now_ns: int) -> str | None:
        """None when ``verdict`` (sent by node ``source``) may be executed now, else the
        reason it may not; counts either way and records an executable plan as executed."""
        st = self.stats
        if self.legitimators is not None and source not in self.legitimators:
            st.unknown_legitimator += 1
            return (
                f"verdict from {source!r}, which is not a legitimator "
                f"(allowed: {sorted(self.legitimators)})"
            )
        if not verdict.approved:
            st.not_approved += 1
            return f"rejected by {verdict.legitimator}: {verdict.reason}"
        proposal = verdict.proposal
        if proposal is None or proposal.plan_uid != verdict.plan_uid:
            st.malformed += 1
            return "approval without the proposal it approves"
        uid = proposal.plan_uid
        if uid in self._executed:
            st.replayed += 1
            return f"plan {uid.hex()} was executed already (replayed approval)"
        if self.max_age_ns is not None and now_ns - proposal.created > self.max_age_ns:
            st.stale += 1
            age = (now_ns - proposal.created) / 1e9
            return f"plan {uid.hex()} is stale: {age:.3f} s old, max_age {self.max_age_ns / 1e9} s"
        if proposal.created <= self._newest:
            st.superseded += 1
            return f"plan {uid.hex()} is older than the newest executed plan"
        self._executed[uid] = None
        if len(self._executed) > self.memory:
            self._executed.popitem(last=False)
        self._newest = proposal.created
        st.approved += 1
        return None

    def on_approved(self, node: Node, *, event: str = VERDICT) -> Callable[[A], A]:
        """Make ``fn(ctx, proposal)`` the node's execution of approved plans."""

        def register(fn: A) -> A:
            async def gated(ctx: Context, verdict: Verdict) -> None:
                reason = self.check(verdict, ctx.envelope.source, ctx.clock.time_ns())
                if reason is None:
                    assert verdict.proposal is not None  # check() guarantees it
                    await fn(ctx, verdict.proposal)
                    return
                if not verdict.approved and verdict.legitimator == ctx.envelope.source:
                    return  # an honest rejection: its legitimator emitted plan-rejected
                log.warning("node %s refused a plan: %s", ctx.node.name, reason)
                if verdict.plan_uid in self._executed:
                    return  # that plan ran: nothing to replan, only a replay to refuse
                await ctx.emit(
                    PLAN_REJECTED,
                    Verdict(
                        plan_uid=verdict.plan_uid,
                        approved=False,
                        legitimator=ctx.node.name,
                        ts=ctx.clock.time_ns(),
                        reason=reason,
                    ),
                )

            gated.__qualname__ = getattr(fn, "__qualname__", gated.__qualname__)
            node.on_event(event)(gated)
            return fn

        return register
