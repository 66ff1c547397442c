"""The cycle tracker and the approval gate, as units."""

from __future__ import annotations

from functools import partial

import anyio
import pytest
from rap_schemas import Empty, PlanProposal, SpinPlan, StageTrace, Verdict, keys
from rap_sdk import Context, Node
from rap_sdk.cycles import CycleTracker, Topology
from rap_sdk.gate import ApprovalGate
from rap_sdk.testing import Harness

pytestmark = pytest.mark.anyio

S = "t"
SCAN, A, B = keys.data(S, "scan"), keys.event(S, "a"), keys.event(S, "b")


def chain() -> list[Node]:
    first, second, third = Node("first"), Node("second"), Node("third")

    @first.on_data("scan")
    async def f(ctx: Context) -> None:
        await ctx.emit("a")

    @second.on_event("a")
    async def g(ctx: Context) -> None:
        await ctx.emit("b")

    @third.on_event("a")
    async def h(ctx: Context) -> None: ...

    @third.on_event("b")
    async def k(ctx: Context) -> None: ...

    return [first, second, third]


def end(node: str, trigger_key: str, sent: list[str], cycle: bytes = b"c") -> StageTrace:
    return StageTrace(
        node=node, handler="h", phase="end", trigger=b"x", trigger_key=trigger_key,
        cycle=cycle, ts=0, sent=sent,
    )  # fmt: skip


def test_topology_counts_routes_per_key() -> None:
    topo = Topology.of(chain(), system=S)
    assert topo.subscribers == {SCAN: 1, A: 2, B: 1}


def test_a_cycle_is_over_only_when_every_promised_call_ended_in_any_arrival_order() -> None:
    tracker = CycleTracker(Topology.of(chain(), system=S))
    records = [
        end("third", B, []),  # downstream records first: nothing may balance early
        end("third", A, []),
        end("second", A, [B]),
        end("first", SCAN, [A]),
    ]
    tracker.expect(b"c", SCAN)
    for i, rec in enumerate(records):
        tracker.observe(rec)
        assert tracker.pending(b"c") != (0, 0)
        over = tracker._cycles[b"c"].done.is_set()
        assert over == (i == len(records) - 1), i


def test_records_of_nodes_outside_the_topology_do_not_count() -> None:
    tracker = CycleTracker(Topology.of(chain(), system=S))
    tracker.expect(b"c", SCAN)
    tracker.observe(end("stranger", SCAN, []))
    assert not tracker._cycles[b"c"].done.is_set()


async def test_wait_times_out_on_a_lost_cycle_and_counts_it() -> None:
    tracker = CycleTracker(Topology.of(chain(), system=S))
    tracker.expect(b"c", SCAN)
    tracker.observe(end("first", SCAN, [A]))  # "a" never handled
    assert not await tracker.wait(b"c", 0.01)
    assert tracker.timeouts == 1


async def test_the_tracker_follows_a_real_loop_on_the_fabric() -> None:
    nodes = chain()
    async with Harness(system=S) as h:
        tracker = CycleTracker(Topology.of(nodes, system=S))
        await h.start(*nodes)
        async with anyio.create_task_group() as tg:
            await tg.start(partial(tracker.follow, fabric=h.fabric))
            for _ in range(20):
                env = await h.send(SCAN, None)
                tracker.expect(env.uid, SCAN)
                assert await tracker.wait(env.uid, 5.0)
                # when it reports the cycle over, all four handler calls have ended
                ends = [t for t in h.traces() if t.ended and t.cycle == env.uid]
                assert len(ends) == 4
            tg.cancel_scope.cancel()
        assert tracker.completed == 20
        assert tracker.timeouts == 0


def proposal(uid: bytes, created: int) -> PlanProposal:
    plan = SpinPlan(commands=[])
    return PlanProposal(plan_uid=uid, plan_type=plan.TYPE, plan=plan, proposer="p", created=created)


def approve(p: PlanProposal, approved: bool = True) -> Verdict:
    return Verdict(plan_uid=p.plan_uid, approved=approved, legitimator="leg", ts=0, proposal=p)


def test_gate_checks_in_order() -> None:
    gate = ApprovalGate(legitimators={"leg"}, max_age=1.0)
    p1, p2, p0 = proposal(b"1", 10), proposal(b"2", 20), proposal(b"0", 5)
    assert gate.check(approve(p1), "leg", 11) is None
    assert "replayed" in (gate.check(approve(p1), "leg", 12) or "")
    assert "not a legitimator" in (gate.check(approve(p2), "eve", 21) or "")
    assert "rejected by leg" in (gate.check(approve(p2, approved=False), "leg", 21) or "")
    assert "stale" in (gate.check(approve(p2), "leg", 20 + 2_000_000_000) or "")
    assert "older than" in (gate.check(approve(p0), "leg", 21) or "")  # superseded by p1
    no_plan = Verdict(plan_uid=b"3", approved=True, legitimator="leg", ts=0)
    assert "without the proposal" in (gate.check(no_plan, "leg", 21) or "")
    assert gate.check(approve(p2), "leg", 21) is None
    st = gate.stats
    assert (st.approved, st.replayed, st.unknown_legitimator, st.not_approved) == (2, 1, 1, 1)
    assert (st.stale, st.superseded, st.malformed, st.refused) == (1, 1, 1, 5)


def test_gate_memory_is_bounded_and_old_plans_stay_refused() -> None:
    gate = ApprovalGate(max_age=None, memory=4)
    ps = [proposal(bytes([i]), i + 1) for i in range(10)]
    for p in ps:
        assert gate.check(approve(p), "any", 0) is None
    assert len(gate._executed) == 4
    assert gate.check(approve(ps[0]), "any", 0) is not None  # forgotten uid, still refused


async def test_a_write_caused_by_an_event_orders_after_the_writes_it_carries() -> None:
    a, b = Node("a"), Node("b")
    got: list[tuple[int, int]] = []

    @a.on_data("go")
    async def first(ctx: Context) -> None:
        # this writer's clock runs 50 ms ahead of b's (same host here; in a fleet, skew)
        ctx.kb.client.clock.observe(ctx.kb.client.clock.next() + (50 << 20))
        v = await ctx.kb.write("flag", True)
        await ctx.emit("e")
        got.append((v, 0))

    @b.on_event("e")
    async def second(ctx: Context) -> None:
        got.append((0, await ctx.kb.write("flag", False)))

    async with Harness(system=S) as h:
        await h.start(a, b)
        await h.publish("go", Empty())
        await h.wait_for(lambda r: len(got) == 2)
    (va, _), (_, vb) = got
    assert vb > va  # last writer in causal order wins, whatever the clocks say
