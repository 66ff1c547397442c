"""Trust-checker verdicts that veto plans: the TrustGuard alone, then on the execute
node of a gate, fed with sealed TrustOutput messages as a checker publishes them."""

from __future__ import annotations

import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

import pytest
from rap_schemas import PlanProposal, SpinCommand, SpinPlan, TrustOutput, Verdict, keys
from rap_sdk import Context, Node, Sealer
from rap_sdk.errors import HandlerError
from rap_sdk.gate import ApprovalGate, TrustGuard
from rap_sdk.testing import Harness

pytestmark = pytest.mark.anyio

S = "tg"
PLAN = SpinPlan(commands=[SpinCommand(omega=1.0, duration=0.5)])
STOP = SpinPlan(commands=[])


def out(stream: str, value: object, tick: int = 0, deferred: bool = False) -> TrustOutput:
    return TrustOutput(stream=stream, tick=tick, ts=1, value=value, deferred=deferred)


# -- the guard as a unit ----------------------------------------------------------------


def test_any_false_stream_vetoes_and_only_the_first_closes_it() -> None:
    g = TrustGuard(streams={"a", "b"})
    assert g.veto() is None  # no verdict yet: no veto by default
    assert g.take("a", out("a", True)) is False
    assert g.veto() is None
    assert g.take("a", out("a", False, tick=3)) is True  # closes: the safe action is due
    assert g.veto() == "trust guard 'a' vetoes: false at tick 3"
    assert g.take("b", out("b", False)) is False  # closed already
    assert g.take("a", out("a", False)) is False
    assert g.take("a", out("a", True)) is False
    assert g.veto() is not None  # b is still false
    assert "'b'" in (g.veto() or "")
    assert g.take("b", out("b", True)) is False
    assert g.veto() is None
    assert g.is_open
    assert (g.stats.closed, g.stats.reopened, g.stats.verdicts) == (1, 1, 6)
    assert g.take("c", out("c", False)) is False  # not a guard stream: ignored
    assert g.stats.verdicts == 6


def test_bottom_is_no_veto_and_a_value_that_is_not_a_bool_is_one() -> None:
    g = TrustGuard(streams={"a"})
    assert g.take("a", out("a", None, deferred=True)) is False
    assert g.veto() is None
    assert g.take("a", out("a", 1)) is True
    assert g.stats.not_bool == 1
    assert "is not a Bool" in (g.veto() or "")


def test_require_verdicts_refuses_until_every_stream_has_spoken() -> None:
    g = TrustGuard(streams={"a", "b"}, require_verdicts=True)
    assert g.veto() == "trust guard 'a' has no verdict yet (require_verdicts)"
    g.take("a", out("a", True))
    g.take("b", out("b", None, deferred=True))
    assert "'b' has no verdict yet" in (g.veto() or "")
    # a first false verdict closes it on a false verdict: the safe action is due
    assert g.take("b", out("b", False)) is True
    g.take("b", out("b", True))
    assert g.veto() is None


def test_verdicts_from_senders_that_are_not_checkers_are_ignored() -> None:
    g = TrustGuard(streams={"a"}, checkers={"trust_checker"})
    assert g.take("a", out("a", False), "intruder") is False
    assert g.veto() is None
    assert g.stats.unknown_checker == 1
    assert g.take("a", out("a", False), "trust_checker") is True


def test_stream_names_are_validated() -> None:
    with pytest.raises(ValueError, match="trust stream"):
        TrustGuard(streams={"a/*"})
    with pytest.raises(ValueError, match="trust stream"):
        Node("n").on_trust("")


def test_a_trust_handler_takes_a_trust_output() -> None:
    node = Node("n")

    @node.on_trust("ok")
    async def f(ctx: Context, o: TrustOutput) -> None: ...

    (route,) = node.routes
    assert (route.kind, route.key(S), route.traced) == ("trust", keys.trust(S, "ok"), False)
    with pytest.raises(HandlerError):
        node.on_trust("ok")(lambda ctx: None)  # type: ignore[type-var]  # not async


# -- on the execute node of a gate ------------------------------------------------------


class Loop:
    def __init__(self, guard: TrustGuard) -> None:
        self.guard = guard
        self.gate = ApprovalGate(legitimators={"legitimate"}, guard=guard)
        self.execute = Node("executor", stage="execute")
        self.reasons: list[str] = []
        self.executed: list[bytes] = []

        @self.gate.on_approved(self.execute)
        async def act(ctx: Context, proposal: PlanProposal[SpinPlan]) -> None:
            self.executed.append(proposal.plan_uid)
            await ctx.publish("spin_config", proposal.plan)


async def stop(ctx: Context, reason: str) -> None:
    await ctx.publish("spin_config", STOP)


@asynccontextmanager
async def running(guard: TrustGuard) -> AsyncIterator[tuple[Harness, Loop]]:
    loop = Loop(guard)
    async with Harness(system=S) as h:
        await h.start(loop.execute)
        yield h, loop


class Feed:
    """Sends as the legitimate stage and as the trust checker."""

    def __init__(self, h: Harness, guard: TrustGuard) -> None:
        self.h, self.guard = h, guard
        self.legit, self.checker = Sealer("legitimate"), Sealer("trust_checker")
        self.n = 0
        self.verdicts = 0

    async def verdict(self, stream: str, value: object) -> None:
        key = keys.trust(S, stream)
        payload, _ = self.checker.seal_message(key, out(stream, value, tick=self.verdicts))
        self.verdicts += 1
        await self.h.publish_raw(key, payload)
        await self.guard.wait_verdicts(self.verdicts, timeout=5.0)

    async def approve(self) -> bytes:
        self.n += 1
        now = time.time_ns()
        uid = self.n.to_bytes(16, "big")
        proposal = PlanProposal(
            plan_uid=uid, plan_type=PLAN.TYPE, plan=PLAN, proposer="planner", created=now
        )
        v = Verdict(
            plan_uid=uid, approved=True, legitimator="legitimate", ts=now, proposal=proposal
        )
        key = keys.event(S, "verdict")
        payload, _ = self.legit.seal_message(key, v)
        await self.h.publish_raw(key, payload)
        return uid


def spin_configs(h: Harness) -> list[SpinPlan]:
    return [r.decode(SpinPlan) for r in h.of(keys.Kind.DATA, "spin_config")]


async def test_a_false_verdict_takes_the_safe_action_once_and_refuses_plans_until_true() -> None:
    guard = TrustGuard(streams={"ok", "other"}, safe_action=stop, checkers={"trust_checker"})
    async with running(guard) as (h, loop):
        feed = Feed(h, guard)
        await feed.verdict("ok", True)
        await feed.approve()
        await h.wait_for(lambda r: len(spin_configs(h)) == 1)
        assert spin_configs(h) == [PLAN]
        # the guard turns false: the stop plan goes out once, however many false verdicts
        await feed.verdict("ok", False)
        await h.wait_for(lambda r: len(spin_configs(h)) == 2)
        await feed.verdict("ok", False)
        await feed.verdict("other", False)
        assert spin_configs(h)[1] == STOP
        assert (guard.stats.closed, guard.stats.safe_actions) == (1, 1)
        # approved plans are refused, counted, and answered with plan-rejected naming it
        uid = await feed.approve()
        rejected = await h.expect_event("plan-rejected")
        verdict = rejected.decode(Verdict)
        assert verdict.plan_uid == uid
        assert "trust guard 'ok' vetoes: false at tick 2" in verdict.reason
        assert loop.gate.stats.vetoed == 1
        # one stream true again is not enough; both are
        await feed.verdict("ok", True)
        await feed.approve()
        await h.wait_for(lambda r: len(h.of(keys.Kind.EVENT, "plan-rejected")) == 2)
        await feed.verdict("other", True)
        uid = await feed.approve()
        await h.wait_for(lambda r: len(spin_configs(h)) == 3)
        assert loop.executed[-1] == uid
        assert spin_configs(h) == [PLAN, STOP, PLAN]
        st = loop.gate.stats
        assert (st.approved, st.vetoed, st.refused) == (2, 2, 2)
        assert (guard.stats.closed, guard.stats.reopened, guard.stats.safe_actions) == (1, 1, 1)
        # verdict handlers run outside the cycle: no trace records for them
        assert {t.trigger_key for t in h.traces("executor")} == {keys.event(S, "verdict")}
        # a "true" from anyone but the checker does not reopen a closed guard
        await feed.verdict("ok", False)
        payload, _ = Sealer("intruder").seal_message(keys.trust(S, "ok"), out("ok", True))
        await h.publish_raw(keys.trust(S, "ok"), payload)
        await feed.verdict("ok", False)  # taken after the intruder's (one inbox, in order)
        assert guard.stats.unknown_checker == 1
        assert guard.veto() is not None
        assert guard.stats.closed == 2


async def test_a_failing_safe_action_is_counted_and_the_veto_holds() -> None:
    async def broken(ctx: Context, reason: str) -> None:
        raise RuntimeError("actuator offline")

    guard = TrustGuard(streams={"ok"}, safe_action=broken)
    async with running(guard) as (h, loop):
        feed = Feed(h, guard)
        await feed.verdict("ok", False)
        assert guard.stats.safe_action_failures == 1
        await feed.approve()
        await h.expect_event("plan-rejected")
        assert loop.gate.stats.vetoed == 1
        assert not spin_configs(h)


async def test_without_a_safe_action_plans_are_only_refused() -> None:
    guard = TrustGuard(streams={"ok"})
    async with running(guard) as (h, _loop):
        feed = Feed(h, guard)
        await feed.verdict("ok", False)
        await feed.approve()
        await h.expect_event("plan-rejected")
        assert not spin_configs(h)
        assert guard.stats.safe_actions == 0
