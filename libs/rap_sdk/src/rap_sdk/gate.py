"""The Legitimate gate: execute only ever acts on approved, fresh, unreplayed plans, of any
plan type the application declares.

    class Dock(Message, frozen=True):                     # the application's plan
        TYPE = "app.Dock/1"
        station: str

    plan = Node("planner", stage="plan")

    @plan.on_event("battery-low")
    async def replan(ctx: Context) -> None:
        await propose(ctx, Dock(station="A"))             # emits "new-plan"

    legit = Node("legitimate", stage="legitimate")

    @legitimate(legit)
    async def check(ctx: Context, proposal: PlanProposal[Dock]) -> str | None:
        return None if ok(proposal.plan) else "why not"   # None approves

    execute = Node("executor", stage="execute")
    gate = ApprovalGate(legitimators={"legitimate"}, max_age=0.2)

    @gate.on_approved(execute)
    async def act(ctx: Context, proposal: PlanProposal[Dock]) -> None: ...

The plan type comes from the annotation ``PlanProposal[Dock]`` (or ``plan=Dock``). The
legitimate side answers every proposal with a ``verdict`` event, a proposal of a plan
type it does not judge included (rejected, naming both types); an approving verdict
carries the proposal it approves, so execute acts on exactly that plan. A rejection also
emits ``plan-rejected`` (the planner's cue to replan within its budget). The execute side
calls its handler only for a verdict that approves a plan of its type, comes from a
named legitimator, is fresh (``max_age`` s from the plan's creation, on the runtime's
clock), is not dated in the future (beyond ``max_skew``), and whose plan was neither
executed before nor superseded by a newer executed plan; any other verdict is refused,
counted in :class:`GateStats`, logged, and answered with ``plan-rejected`` (except a
replayed approval of a plan that did run: there is nothing to replan). An execute-stage
Node refuses, when it is declared, any handler that would take proposals or verdicts
other than through :meth:`ApprovalGate.on_approved`.

One legitimate event judges one plan type; a system with two kinds of plan proposes
them on events of their own: ``propose(ctx, dock, event="new-dock-plan")``,
``@legitimate(node, event="new-dock-plan", verdict="dock-verdict",
rejected="dock-rejected")`` and a second gate with ``on_approved(node,
event="dock-verdict", rejected="dock-rejected")``. A node handles each key once, so two
gates on one execute node need their own verdict events.

Trust-checker verdicts can veto (DESIGN §5): a :class:`TrustGuard` names guard streams,
Bool outputs of trust specs published on ``rap/<system>/trust/<stream>``::

    async def stop(ctx: Context, reason: str) -> None:
        await ctx.publish("tb1/spin_config", SpinPlan(commands=[]))   # nominal behaviour

    guard = TrustGuard(streams={"anomaly_deadline_ok"}, safe_action=stop)
    gate = ApprovalGate(legitimators={"legitimate"}, guard=guard)

While any guard stream's latest verdict is false, the gate refuses approved plans
(``GateStats.vetoed``; ``plan-rejected`` with the reason naming the stream and tick);
when the guard closes (a first stream turns false) its safe action runs once. Without
a safe action the loop only stops adapting (keeps its nominal behaviour); a guard with
no streams never vetoes (continue). When every stream is true again plans flow again.
"""

from __future__ import annotations

import logging
import typing
from collections import OrderedDict
from collections.abc import Awaitable, Callable, Collection
from dataclasses import dataclass
from typing import Any, TypeVar

import anyio
import msgspec
from rap_schemas import (
    NEW_PLAN,
    PLAN_REJECTED,
    VERDICT,
    Message,
    PlanProposal,
    TrustOutput,
    Verdict,
    keys,
)
from rap_schemas.limits import DECODE_ERRORS, decode_failure

from .envelope import new_uid
from .errors import HandlerError
from .inbox import InboxPolicy
from .node import EVENT_POLICY, Node, message_class
from .runtime import Context

__all__ = [
    "NEW_PLAN",
    "PLAN_REJECTED",
    "VERDICT",
    "ApprovalGate",
    "GateStats",
    "GuardStats",
    "SafeAction",
    "TrustGuard",
    "legitimate",
    "propose",
]

log = logging.getLogger(__name__)

Check = Callable[[Context, Any], Awaitable[str | None]]
Act = Callable[[Context, Any], Awaitable[None]]
SafeAction = Callable[[Context, str], Awaitable[None]]
"""``fn(ctx, reason)``: what the loop does when a trust guard closes (``ctx`` is that of
the verdict that closed it: ``ctx.publish`` reaches the managed system)."""
A = TypeVar("A", bound=Act)
C = TypeVar("C", bound=Check)


async def propose(ctx: Context, plan: Message, *, event: str = NEW_PLAN) -> PlanProposal[Any]:
    """Put ``plan`` (a message of the application's plan type) to the Legitimate stage,
    as event ``event`` in this cycle."""
    now = ctx.clock.time_ns()
    proposal = PlanProposal(
        plan_uid=new_uid(now),
        plan_type=plan.TYPE,
        plan=plan,
        proposer=ctx.node.name,
        created=now,
    )
    await ctx.emit(event, proposal)
    return proposal


def _plan_type(fn: Callable[..., Any], plan: type[Message] | None, where: str) -> type[Message]:
    """The plan type of a gate handler: ``plan=``, else the annotation
    ``PlanProposal[ThePlan]`` of its second parameter."""
    if plan is not None:
        if message_class(plan) is not plan:
            raise HandlerError(f"{where}: plan={plan!r} is not a rap_schemas.Message class")
        return plan
    params = list(typing.get_type_hints(fn).items())
    params = [(n, a) for n, a in params if n != "return"]
    ann = params[1][1] if len(params) >= 2 else None
    args = typing.get_args(ann)
    if typing.get_origin(ann) is PlanProposal and args and message_class(args[0]) is args[0]:
        return typing.cast("type[Message]", args[0])
    raise HandlerError(
        f"{where}: cannot tell the plan type of {getattr(fn, '__qualname__', fn)}: annotate "
        "its proposal as 'PlanProposal[YourPlan]' or pass plan=YourPlan"
    )


class _Plans:
    """Types the raw plan of a proposal as the declared plan type, or says why not."""

    __slots__ = ("cls", "decode")

    def __init__(self, cls: type[Message]) -> None:
        self.cls = cls
        self.decode = msgspec.msgpack.Decoder(cls).decode

    def plan_ok(self, plan: Any) -> bool:
        """A plan a local object may carry to a route that types it (else the sample
        goes through bytes, and a plan of another type is refused with the reason)."""
        return type(plan) is self.cls or type(plan) is msgspec.Raw

    def accepts_proposal(self, p: Any) -> bool:
        return type(p) is PlanProposal and self.plan_ok(p.plan)

    def accepts_verdict(self, v: Any) -> bool:
        return type(v) is Verdict and (v.proposal is None or self.accepts_proposal(v.proposal))

    def typed(self, proposal: PlanProposal[Any]) -> tuple[PlanProposal[Any] | None, str]:
        """The proposal with its plan typed: decoded from the raw plan that came over the
        wire, or as it is when a stage in this process sent it typed already."""
        if proposal.plan_type != self.cls.TYPE:
            return None, (
                f"a plan of type {proposal.plan_type!r}, but this stage handles "
                f"{self.cls.TYPE}; propose it on the event of a stage that handles it"
            )
        if type(proposal.plan) is self.cls:
            return proposal, ""
        try:
            plan = self.decode(proposal.plan)
        except DECODE_ERRORS as exc:
            return None, f"invalid {self.cls.TYPE} plan: {decode_failure(exc)}"
        return msgspec.structs.replace(proposal, plan=plan), ""


def legitimate(
    node: Node,
    *,
    plan: type[Message] | None = None,
    event: str = NEW_PLAN,
    verdict: str = VERDICT,
    rejected: str = PLAN_REJECTED,
    policy: InboxPolicy | None = None,
) -> Callable[[C], C]:
    """Make ``fn(ctx, proposal) -> reason | None`` the node's legitimation of plans of
    type ``plan`` (default: from the annotation ``PlanProposal[ThePlan]``), proposed on
    ``event`` and answered on ``verdict`` (and ``rejected`` when rejected): a second
    plan type uses events of its own.

    None approves; a string rejects with that reason; an exception rejects too (with
    the exception as the reason): a check that fails never approves. A proposal of
    another plan type is rejected without calling ``fn``."""

    verdict_event = verdict

    def register(fn: C) -> C:
        plans = _Plans(_plan_type(fn, plan, f"node {node.name!r}, legitimate"))

        async def decide(ctx: Context, proposal: PlanProposal[msgspec.Raw]) -> None:
            typed, reason_ = plans.typed(proposal)
            reason: str | None = reason_
            if typed is not None:
                try:
                    reason = await fn(ctx, typed)
                except Exception as exc:  # a failing check rejects, it never approves
                    log.exception("node %s: legitimation of a plan failed", ctx.node.name)
                    reason = f"legitimation failed: {type(exc).__name__}: {exc}"
            approved = reason is None
            answer = Verdict(
                plan_uid=proposal.plan_uid,
                approved=approved,
                legitimator=ctx.node.name,
                ts=ctx.clock.time_ns(),
                reason=reason or "",
                proposal=typed if approved else None,
            )
            await ctx.emit(verdict_event, answer)
            if not approved:
                await ctx.emit(rejected, answer)

        decide.__qualname__ = getattr(fn, "__qualname__", decide.__qualname__)
        node._route(
            "event",
            event,
            policy or EVENT_POLICY,
            PlanProposal[msgspec.Raw],
            accepts=plans.accepts_proposal,
        )(decide)
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
    """Approvals without their proposal, with a proposal of another uid, or of a plan
    that is not of the gate's plan type."""
    stale: int = 0
    future: int = 0
    """Plans dated further in the future than ``max_skew``."""
    replayed: int = 0
    superseded: int = 0
    vetoed: int = 0
    """Approved plans refused because a trust guard's verdict was false."""

    @property
    def refused(self) -> int:
        return (
            self.unknown_legitimator
            + self.malformed
            + self.stale
            + self.future
            + self.replayed
            + self.superseded
            + self.vetoed
        )


@dataclass(slots=True)
class GuardStats:
    verdicts: int = 0
    """Trust outputs taken on the guard streams."""
    unknown_checker: int = 0
    """Trust outputs from a sender not named in ``checkers`` (ignored)."""
    not_bool: int = 0
    """Verdicts whose value is not a Bool (taken as false: fix the guard's spec)."""
    closed: int = 0
    """Times the guard closed on a false verdict (a first stream turned false)."""
    reopened: int = 0
    safe_actions: int = 0
    safe_action_failures: int = 0


class TrustGuard:
    """Trust-checker verdicts that veto plans; see the module docstring.

    ``streams``: the guard streams (Bool trust outputs). ``safe_action``: run once each
    time the guard closes on a false verdict (no stream was false, now one is); None:
    plans are only refused. ``require_verdicts``: also refuse while some stream has
    given no verdict yet (or only ⊥), for a loop that must not adapt unchecked; by
    default a stream without a verdict does not veto. ``checkers``: node ids of the
    checkers whose outputs count (None: any sender). ``policy``: the inbox of the
    verdict routes (default :data:`rap_sdk.node.TRUST_POLICY`).

    The guard sees verdicts through :meth:`attach` (``ApprovalGate.on_approved`` attaches
    it to the execute node), so its state and the gate's checks share the node's one
    handler at a time. Verdict handlers are not traced (they run outside the cycle)."""

    def __init__(
        self,
        *,
        streams: Collection[str],
        safe_action: SafeAction | None = None,
        require_verdicts: bool = False,
        checkers: Collection[str] | None = None,
        policy: InboxPolicy | None = None,
    ) -> None:
        for stream in streams:
            keys.trust("x", stream)  # validates the stream name
        self.streams = frozenset(streams)
        self.checkers = frozenset(checkers) if checkers is not None else None
        self.safe_action = safe_action
        self.require_verdicts = require_verdicts
        self.policy = policy
        self.stats = GuardStats()
        self.latest: dict[str, TrustOutput] = {}
        """Each stream's latest verdict."""
        self._false: dict[str, str] = {}
        """Streams whose latest verdict is false (or not a Bool) -> why."""
        self._attached: set[str] = set()
        self._taken: anyio.Event | None = None

    @property
    def is_open(self) -> bool:
        return self.veto() is None

    def veto(self) -> str | None:
        """None while plans may run; else why not (naming the guard stream)."""
        if self._false:
            stream = min(self._false)
            return f"trust guard {stream!r} vetoes: {self._false[stream]}"
        if self.require_verdicts:
            missing = sorted(
                s for s in self.streams if s not in self.latest or self.latest[s].deferred
            )
            if missing:
                return f"trust guard {missing[0]!r} has no verdict yet (require_verdicts)"
        return None

    async def wait_verdicts(self, count: int, *, timeout: float) -> None:
        """Wait until ``count`` verdicts have been taken in all (``stats.verdicts``): a
        node that must not act before the checker has spoken, or a test; raises
        ``TimeoutError`` after ``timeout`` s."""
        with anyio.fail_after(timeout):
            while self.stats.verdicts < count:
                if self._taken is None:
                    self._taken = anyio.Event()
                await self._taken.wait()

    def take(self, stream: str, out: TrustOutput, source: str | None = None) -> bool:
        """Record ``out``, a verdict on guard stream ``stream`` sent by node ``source``;
        True when it closed the guard (the safe action is due). Verdicts on other
        streams, or from a sender not in ``checkers``, are ignored."""
        st = self.stats
        if stream not in self.streams:
            return False
        if self.checkers is not None and source not in self.checkers:
            st.unknown_checker += 1
            if st.unknown_checker == 1 or st.unknown_checker % 1000 == 0:
                log.warning(
                    "trust guard: ignored %d verdict(s), the last on %s from %r, which is "
                    "not a checker (allowed: %s)",
                    st.unknown_checker,
                    stream,
                    source,
                    sorted(self.checkers),
                )
            return False
        st.verdicts += 1
        if self._taken is not None:
            self._taken.set()
            self._taken = None
        was_open, was_false = self.veto() is None, bool(self._false)
        self.latest[stream] = out
        if out.deferred or out.value is True:
            self._false.pop(stream, None)  # ⊥ (cannot be computed yet) is no veto either
        elif out.value is False:
            self._false[stream] = f"false at tick {out.tick}"
        else:
            st.not_bool += 1
            self._false[stream] = (
                f"value {out.value!r} at tick {out.tick} is not a Bool (a guard stream "
                "must be a Bool output of its spec)"
            )
        now_open = self.veto() is None
        if self._false and not was_false:
            st.closed += 1
            return True
        if now_open and not was_open:
            st.reopened += 1
            log.info("trust guard open again (%s is true): plans may run", stream)
        return False

    def attach(self, node: Node) -> None:
        """Subscribe ``node`` to the guard streams (once per node)."""
        if node.name in self._attached:
            return
        self._attached.add(node.name)

        async def on_verdict(ctx: Context, out: TrustOutput) -> None:
            # the stream is the key's (what was subscribed), whatever the body says
            if not self.take(keys.parse(ctx.key).name, out, ctx.envelope.source):
                return
            reason = self.veto() or ""
            log.warning("node %s: %s; plans are refused", ctx.node.name, reason)
            if self.safe_action is None:
                return
            try:
                await self.safe_action(ctx, reason)
            except Exception:  # a failing safe action must not stop the node
                self.stats.safe_action_failures += 1
                log.exception("node %s: the trust guard's safe action failed", ctx.node.name)
            else:
                self.stats.safe_actions += 1

        on_verdict.__qualname__ = "TrustGuard.on_verdict"
        for stream in sorted(self.streams):
            node.on_trust(stream, policy=self.policy)(on_verdict)


class ApprovalGate:
    """The execute side of the gate; see the module docstring."""

    def __init__(
        self,
        *,
        legitimators: Collection[str] | None = None,
        max_age: float | None = 1.0,
        max_skew: float = 0.5,
        memory: int = 4096,
        guard: TrustGuard | None = None,
        max_age_config: str | None = None,
    ) -> None:
        """``legitimators``: node names whose verdicts count (None: any sender).
        ``max_age``: seconds a plan stays executable after its creation (None: no limit).
        ``max_skew``: seconds a plan may be dated ahead of this node's clock (clocks
        differ a little between machines; a plan from further ahead is refused, so that
        a forged date cannot make every later plan look superseded). ``memory``: how
        many executed plan uids are remembered against replay; older ones are still
        refused as superseded. ``guard``: trust-checker verdicts that veto
        (:class:`TrustGuard`). ``max_age_config``: the field of the execute node's config
        Struct that holds ``max_age`` (a number of seconds, or None): the gate then
        takes the value the node is configured with (the model's ``config:`` when the
        runner starts it, ``rap admin config`` while it runs) for each verdict."""
        self.guard = guard
        self.max_age_config = max_age_config
        self.legitimators = frozenset(legitimators) if legitimators is not None else None
        self.max_age_ns = None if max_age is None else round(max_age * 1e9)
        self.max_skew_ns = round(max_skew * 1e9)
        self.memory = memory
        self.stats = GateStats()
        self._executed: OrderedDict[bytes, None] = OrderedDict()
        self._newest = -1
        """``created`` of the newest executed plan: anything older is superseded."""

    def check(self, verdict: Verdict[Any], source: str, now_ns: int) -> str | None:
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
        if proposal.created > now_ns + self.max_skew_ns:
            st.future += 1
            ahead = (proposal.created - now_ns) / 1e9
            return (
                f"plan {uid.hex()} is dated {ahead:.3f} s in the future (max_skew "
                f"{self.max_skew_ns / 1e9} s): check the proposer's clock"
            )
        if self.max_age_ns is not None and now_ns - proposal.created > self.max_age_ns:
            st.stale += 1
            age = (now_ns - proposal.created) / 1e9
            return f"plan {uid.hex()} is stale: {age:.3f} s old, max_age {self.max_age_ns / 1e9} s"
        if proposal.created <= self._newest:
            st.superseded += 1
            return f"plan {uid.hex()} is older than the newest executed plan"
        veto = self.guard.veto() if self.guard is not None else None
        if veto is not None:
            st.vetoed += 1
            return f"plan {uid.hex()} refused: {veto}"
        self._executed[uid] = None
        if len(self._executed) > self.memory:
            self._executed.popitem(last=False)
        self._newest = proposal.created
        st.approved += 1
        return None

    def on_approved(
        self,
        node: Node,
        *,
        plan: type[Message] | None = None,
        event: str = VERDICT,
        rejected: str = PLAN_REJECTED,
        policy: InboxPolicy | None = None,
    ) -> Callable[[A], A]:
        """Make ``fn(ctx, proposal)`` the node's execution of approved plans of type
        ``plan`` (default: from the annotation ``PlanProposal[ThePlan]``), and subscribe
        ``node`` to the guard's streams, if the gate has a guard."""
        if self.guard is not None:
            self.guard.attach(node)
        field = self.max_age_config
        if field is not None and (
            node.config is None or field not in type(node.config).__struct_fields__
        ):
            raise HandlerError(
                f"node {node.name!r}, on_approved: max_age_config={field!r} names no field "
                "of the node's config Struct - add the field to it, or leave max_age_config out"
            )

        def register(fn: A) -> A:
            plans = _Plans(_plan_type(fn, plan, f"node {node.name!r}, on_approved"))

            async def gated(ctx: Context, verdict: Verdict[msgspec.Raw]) -> None:
                typed: PlanProposal[Any] | None = None
                if verdict.approved and verdict.proposal is not None:
                    typed, why = plans.typed(verdict.proposal)
                    if typed is None:
                        self.stats.malformed += 1
                        await self._refuse(ctx, verdict, why, rejected)
                        return
                self._configured(ctx.node)
                reason = self.check(verdict, ctx.envelope.source, ctx.clock.time_ns())
                if reason is None:
                    assert typed is not None  # check() guarantees an approved proposal
                    await fn(ctx, typed)
                    return
                if not verdict.approved and verdict.legitimator == ctx.envelope.source:
                    return  # an honest rejection: its legitimator emitted plan-rejected
                if verdict.plan_uid in self._executed:
                    log.warning("node %s refused a plan: %s", ctx.node.name, reason)
                    return  # that plan ran: nothing to replan, only a replay to refuse
                await self._refuse(ctx, verdict, reason, rejected)

            gated.__qualname__ = getattr(fn, "__qualname__", gated.__qualname__)
            node._route(
                "event",
                event,
                policy or EVENT_POLICY,
                Verdict[msgspec.Raw],
                gated=True,
                accepts=plans.accepts_verdict,
            )(gated)
            return fn

        return register

    def _configured(self, node: Node) -> None:
        """Take ``max_age`` from the node's config (``max_age_config``), as configured."""
        if self.max_age_config is None or node.config is None:
            return
        value = getattr(node.config, self.max_age_config, None)
        if value is None:
            self.max_age_ns = None
        elif isinstance(value, int | float) and not isinstance(value, bool):
            self.max_age_ns = round(value * 1e9)

    async def _refuse(
        self, ctx: Context, verdict: Verdict[Any], reason: str, rejected: str
    ) -> None:
        log.warning("node %s refused a plan: %s", ctx.node.name, reason)
        await ctx.emit(
            rejected,
            Verdict(
                plan_uid=verdict.plan_uid,
                approved=False,
                legitimator=ctx.node.name,
                ts=ctx.clock.time_ns(),
                reason=reason,
            ),
        )
