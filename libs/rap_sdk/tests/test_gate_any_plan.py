"""One Legitimate gate for any plan type: a tiny "return to dock" plan goes through
propose -> legitimate -> execute with the freshness, future, replay, type and trust-veto
checks, on MemoryFabric and on real Zenoh sessions (one per node)."""

from __future__ import annotations

import time
from typing import Any

import msgspec
import pytest
from rap_schemas import (
    PLAN_REJECTED,
    Message,
    PlanProposal,
    SpinPlan,
    TrustOutput,
    Verdict,
    keys,
)
from rap_sdk import Context, HandlerError, Node, Sealer
from rap_sdk.gate import ApprovalGate, TrustGuard, legitimate, propose
from rap_sdk.testing import Harness

pytestmark = pytest.mark.anyio

S = "dock"


class Dock(Message, frozen=True):
    """Drive back to a charging station."""

    TYPE = "app.Dock/1"

    station: str
    speed: float = 0.2


class Battery(Message, frozen=True):
    TYPE = "app.Battery/1"

    level: float


def build() -> tuple[list[Node], ApprovalGate, list[Dock]]:
    planner = Node("planner", stage="plan")
    judge = Node("legitimate", stage="legitimate")
    executor = Node("executor", stage="execute")
    guard = TrustGuard(streams={"safe"}, checkers={"trust_checker"})
    gate = ApprovalGate(legitimators={"legitimate"}, max_age=5.0, guard=guard)
    docked: list[Dock] = []

    @planner.on_event("battery")
    async def plan(ctx: Context, battery: Battery) -> None:
        if battery.level < 0.2:
            await propose(ctx, Dock(station="A", speed=0.1 if battery.level < 0.1 else 0.3))

    @legitimate(judge)
    async def check(ctx: Context, proposal: PlanProposal[Dock]) -> str | None:
        return None if proposal.plan.speed <= 0.2 else "too fast with a weak battery"

    @gate.on_approved(executor)
    async def act(ctx: Context, proposal: PlanProposal[Dock]) -> None:
        docked.append(proposal.plan)
        await ctx.publish("base/cmd", proposal.plan)

    return [planner, judge, executor], gate, docked


SETUPS = [
    pytest.param({"fabric": "memory"}, id="memory"),
    pytest.param({"fabric": "zenoh", "isolate": True}, id="zenoh", marks=pytest.mark.zenoh),
]


def approval(plan: Message, *, created: int, uid: bytes) -> Verdict[Any]:
    proposal = PlanProposal(
        plan_uid=uid, plan_type=plan.TYPE, plan=plan, proposer="planner", created=created
    )
    return Verdict(
        plan_uid=uid, approved=True, legitimator="legitimate", ts=created, proposal=proposal
    )


@pytest.mark.parametrize("setup", SETUPS)
async def test_a_second_plan_type_goes_through_the_whole_gate(setup: dict[str, Any]) -> None:
    nodes, gate, docked = build()
    async with Harness(system=S, timeout=20, **setup) as h:
        await h.start(*nodes)
        # approved and executed: the executor gets a typed Dock
        await h.emit("battery", Battery(level=0.05))
        cmd = await h.expect_data("base/cmd")
        assert cmd.decode(Dock) == Dock(station="A", speed=0.1)
        assert docked == [Dock(station="A", speed=0.1)]
        # rejected by the legitimate stage: plan-rejected names the reason
        await h.emit("battery", Battery(level=0.15))
        rejected = await h.expect_event(PLAN_REJECTED)
        assert rejected.decode(Verdict).reason == "too fast with a weak battery"

        as_legit = Sealer("legitimate")
        key = keys.event(S, "verdict")
        now = time.time_ns()
        cases = [  # (verdict, the word in the refusal)
            (approval(Dock(station="B"), created=now - 60 * 10**9, uid=b"s" * 16), "stale"),
            (approval(Dock(station="F"), created=now + 3600 * 10**9, uid=b"f" * 16), "future"),
            (approval(SpinPlan(commands=[]), created=now, uid=b"t" * 16), "app.Dock/1"),
        ]
        for verdict, word in cases:
            n = len(h.of(keys.Kind.EVENT, PLAN_REJECTED))
            payload, _ = as_legit.seal_message(key, verdict)
            await h.publish_raw(key, payload)
            await h.wait_for(lambda r, n=n: len(h.of(keys.Kind.EVENT, PLAN_REJECTED)) > n)
            assert word in h.of(keys.Kind.EVENT, PLAN_REJECTED)[-1].decode(Verdict).reason
        # a replay of the approval that ran: refused, nothing executed again
        first = next(r for r in h.of(keys.Kind.EVENT, "verdict") if r.decode(Verdict).approved)
        assert first.envelope is not None
        replayed, _ = as_legit.seal(key, first.envelope.type, bytes(first.envelope.body))
        await h.publish_raw(key, replayed)
        await h.wait_for(lambda r: gate.stats.replayed == 1)
        # the trust checker says the situation is unsafe: approved plans are vetoed
        checker = Sealer("trust_checker")
        tkey = keys.trust(S, "safe")
        payload, _ = checker.seal_message(
            tkey, TrustOutput(stream="safe", tick=1, ts=now, value=False)
        )
        await h.publish_raw(tkey, payload)
        assert gate.guard is not None
        await gate.guard.wait_verdicts(1, timeout=20)
        n = len(h.of(keys.Kind.EVENT, PLAN_REJECTED))
        await h.emit("battery", Battery(level=0.05))
        await h.wait_for(lambda r: len(h.of(keys.Kind.EVENT, PLAN_REJECTED)) > n)
        assert (
            "trust guard 'safe' vetoes"
            in h.of(keys.Kind.EVENT, PLAN_REJECTED)[-1].decode(Verdict).reason
        )
        st = gate.stats
        assert (st.approved, st.stale, st.future, st.malformed, st.replayed, st.vetoed) == (
            1,
            1,
            1,
            1,
            1,
            1,
        )
        assert docked == [Dock(station="A", speed=0.1)]  # only the one approved plan ran


async def test_a_legitimate_stage_answers_a_plan_of_another_type_with_a_rejection() -> None:
    nodes, _, _ = build()
    async with Harness(system=S) as h:
        await h.start(*nodes)
        now = time.time_ns()
        spin = SpinPlan(commands=[])
        proposal = PlanProposal(
            plan_uid=b"x" * 16, plan_type=spin.TYPE, plan=spin, proposer="p", created=now
        )
        await h.emit("new-plan", proposal)
        rejected = (await h.expect_event(PLAN_REJECTED)).decode(Verdict)
        assert "rap.SpinPlan/1" in rejected.reason
        assert "app.Dock/1" in rejected.reason


def test_an_execute_stage_refuses_plans_outside_the_gate() -> None:
    executor = Node("executor", stage="execute")
    with pytest.raises(HandlerError, match=r"@gate\.on_approved\(node\)"):

        @executor.on_event("new-plan")
        async def sneaky(ctx: Context, proposal: PlanProposal[Dock]) -> None: ...

    with pytest.raises(HandlerError, match="execute stage"):

        @executor.on_event("verdict")
        async def careless(ctx: Context) -> None: ...

    plain = Node("logger")  # not an execute stage: it may watch plans

    @plain.on_event("verdict", type=Verdict)
    async def watch(ctx: Context) -> None: ...


def test_the_plan_type_must_be_known() -> None:
    node = Node("legitimate", stage="legitimate")
    with pytest.raises(HandlerError, match=r"PlanProposal\[YourPlan\]"):

        @legitimate(node)
        async def check(ctx: Context, proposal: PlanProposal) -> str | None:  # type: ignore[type-arg]
            return None


async def test_two_plan_types_go_through_two_gates_on_events_of_their_own() -> None:
    spin_planner, dock_planner = Node("spin-planner", stage="plan"), Node("dock-planner")
    judge_spin, judge_dock = Node("legit-spin", stage="legitimate"), Node("legit-dock")
    exe = Node("executor", stage="execute")
    spin_gate = ApprovalGate(legitimators={"legit-spin"})
    dock_gate = ApprovalGate(legitimators={"legit-dock"})
    done: list[str] = []

    @spin_planner.on_event("go")
    async def p1(ctx: Context) -> None:
        await propose(ctx, SpinPlan(commands=[]))

    @dock_planner.on_event("go")
    async def p2(ctx: Context) -> None:
        await propose(ctx, Dock(station="B"), event="new-dock-plan")

    @legitimate(judge_spin)
    async def c1(ctx: Context, proposal: PlanProposal[SpinPlan]) -> str | None:
        return None

    @legitimate(judge_dock, event="new-dock-plan", verdict="dock-verdict", rejected="dock-no")
    async def c2(ctx: Context, proposal: PlanProposal[Dock]) -> str | None:
        return None

    @spin_gate.on_approved(exe)
    async def a1(ctx: Context, proposal: PlanProposal[SpinPlan]) -> None:
        done.append(proposal.plan.TYPE)

    @dock_gate.on_approved(exe, event="dock-verdict", rejected="dock-no")
    async def a2(ctx: Context, proposal: PlanProposal[Dock]) -> None:
        done.append(proposal.plan.TYPE)

    async with Harness(system=S) as h:
        await h.start(spin_planner, dock_planner, judge_spin, judge_dock, exe)
        await h.emit("go")
        await h.wait_for(lambda r: len(done) == 2)
        assert sorted(done) == ["app.Dock/1", "rap.SpinPlan/1"]
        assert not h.of(keys.Kind.EVENT, PLAN_REJECTED)
        assert not h.of(keys.Kind.EVENT, "dock-no")
        assert (spin_gate.stats.malformed, dock_gate.stats.malformed) == (0, 0)


class ExecuteConfig(msgspec.Struct, frozen=True, kw_only=True):
    plan_max_age: float | None = 1.0


async def test_the_gate_takes_max_age_from_the_node_as_configured() -> None:
    """``max_age_config``: the model's config (applied by the runner through
    ``Node.configure``) decides how old an approved plan may be, not the default."""
    executor = Node("executor", stage="execute", config=ExecuteConfig())
    gate = ApprovalGate(legitimators={"legitimate"}, max_age_config="plan_max_age")
    docked: list[Dock] = []

    @gate.on_approved(executor)
    async def act(ctx: Context, proposal: PlanProposal[Dock]) -> None:
        docked.append(proposal.plan)

    executor.configure({"plan_max_age": 60.0})
    as_legit, key = Sealer("legitimate"), keys.event(S, "verdict")
    async with Harness(system=S) as h:
        await h.start(executor)
        for n, (age, station) in enumerate([(30, "A"), (30, "B"), (0, "C")]):
            if n == 1:
                executor.configure({"plan_max_age": 10.0})  # rap admin config, say
            if n == 2:
                executor.configure({"plan_max_age": None})  # no limit
            created = time.time_ns() - age * 10**9 - (2 - n)  # each newer than the last
            verdict = approval(Dock(station=station), created=created, uid=bytes([n]) * 16)
            payload, _ = as_legit.seal_message(key, verdict)
            await h.publish_raw(key, payload)
            await h.wait_for(lambda r, n=n: gate.stats.approved + gate.stats.stale > n)
    assert [d.station for d in docked] == ["A", "C"]
    assert (gate.stats.approved, gate.stats.stale) == (2, 1)


def test_max_age_config_must_name_a_field_of_the_nodes_config() -> None:
    gate = ApprovalGate(max_age_config="plan_max_age")
    with pytest.raises(HandlerError, match="max_age_config='plan_max_age' names no field"):
        gate.on_approved(Node("executor", stage="execute"), plan=Dock)
