"""Co-located clients and nodes: written objects are handed over as they are (no
encoding, no decoding, no task woken up), with the checks the stream applies kept."""

from __future__ import annotations

import math
from collections.abc import Callable

import anyio
import msgspec
import pytest
from knowledge.app import open_service
from knowledge.config import KnowledgeConfig
from rap_schemas import LaserScan, LidarMask, keys, pack_ranges
from rap_sdk import (
    Context,
    KnowledgeClient,
    KnowledgeError,
    MemoryBus,
    MemoryFabric,
    Node,
    run_nodes,
)

pytestmark = pytest.mark.anyio
SYSTEM = "tb"


async def settled(done: Callable[[], bool]) -> None:
    """Poll ``done`` (another task's progress, not an event of ours) for up to 5 s."""
    with anyio.fail_after(5):
        while not done():  # noqa: ASYNC110
            await anyio.sleep(0.01)


def scan(stamp: int) -> LaserScan:
    return LaserScan(
        stamp=stamp,
        frame_id="base_link",
        angle_min=-math.pi,
        angle_increment=0.1,
        range_min=0.1,
        range_max=12.0,
        ranges=pack_ranges([1.0, math.inf]),
    )


async def test_a_colocated_reader_gets_the_written_object() -> None:
    async with (
        MemoryFabric() as fabric,
        open_service(KnowledgeConfig(system=SYSTEM), fabric=fabric) as svc,
        KnowledgeClient(fabric=fabric, system=SYSTEM, writer="w") as w,
        KnowledgeClient(fabric=fabric, system=SYSTEM, writer="r") as r,
    ):
        first = scan(1)
        await w.write("laser_scan", first)
        assert await r.read("laser_scan", LaserScan) == first  # replicated (a copy)
        second = scan(2)
        v = await w.write("laser_scan", second)
        got = await r.read("laser_scan", LaserScan, min_version=v, timeout=0)
        assert got is second  # the object itself: no decode, no wait
        assert r.waits == 0
        await settled(lambda: svc.stats.stream_applied >= 2)  # stored from the object too
        assert (await r.history("laser_scan", LaserScan))[-1].value == second


async def test_a_colocated_write_of_the_wrong_type_is_refused_by_the_reader() -> None:
    async with (
        MemoryFabric() as fabric,
        open_service(KnowledgeConfig(system=SYSTEM), fabric=fabric),
        KnowledgeClient(fabric=fabric, system=SYSTEM, writer="w") as w,
        KnowledgeClient(fabric=fabric, system=SYSTEM, writer="r") as r,
    ):
        await w.write("laser_scan", scan(1))
        assert (await r.read("laser_scan", LaserScan)).stamp == 1
        await w.write("laser_scan", LidarMask(angle_min=0, angle_increment=1, occluded=b""))
        assert (await r.read("laser_scan", LaserScan)).stamp == 1  # kept the good one
        assert r.rejections.total >= 1


async def test_another_process_still_gets_colocated_writes() -> None:
    bus = MemoryBus()
    async with (
        MemoryFabric(bus=bus) as here,
        MemoryFabric(bus=bus) as there,
        open_service(KnowledgeConfig(system=SYSTEM), fabric=here),
        KnowledgeClient(fabric=here, system=SYSTEM, writer="w") as w,
        KnowledgeClient(fabric=here, system=SYSTEM, writer="r") as near,
        KnowledgeClient(fabric=there, system=SYSTEM, writer="f") as far,
    ):
        await near.read("laser_scan", LaserScan, default=None)
        await far.read("laser_scan", LaserScan, default=None)
        v = await w.write("laser_scan", scan(7))
        await settled(lambda: far.known_version("laser_scan") >= v)  # a remote sample
        got = await far.read("laser_scan", LaserScan)
        assert got.stamp == 7
        assert got is not await near.read("laser_scan", LaserScan)  # decoded there


async def test_plain_data_nested_too_deep_is_refused_by_the_writer() -> None:
    async with (
        MemoryFabric() as fabric,
        KnowledgeClient(fabric=fabric, system=SYSTEM, writer="w") as w,
    ):
        deep: list[object] = []
        for _ in range(40):
            deep = [deep]
        with pytest.raises(KnowledgeError, match="nests"):
            await w.write("deep", deep)


async def test_nodes_in_one_process_hand_messages_over_as_objects() -> None:
    seen: list[object] = []
    sender, receiver = Node("sender"), Node("receiver")

    @receiver.on_data("scan")
    async def on_scan(ctx: Context, s: LaserScan) -> None:
        seen.append(s)

    sent = scan(3)
    async with (
        MemoryFabric() as fabric,
        run_nodes([sender, receiver], fabric=fabric, system=SYSTEM) as group,
    ):
        await group["sender"].send(keys.data(SYSTEM, "scan"), sent)
        await settled(lambda: bool(seen))
    assert seen[0] is sent


async def test_a_local_object_of_another_type_is_decoded_and_rejected() -> None:
    seen: list[object] = []
    sender, receiver = Node("sender"), Node("receiver")

    @receiver.on_data("scan")
    async def on_scan(ctx: Context, s: LaserScan) -> None:
        seen.append(s)

    async with (
        MemoryFabric() as fabric,
        run_nodes([sender, receiver], fabric=fabric, system=SYSTEM) as group,
    ):
        mask = LidarMask(angle_min=0, angle_increment=1, occluded=b"")
        await group["sender"].send(keys.data(SYSTEM, "scan"), mask)
        rt = group["receiver"]
        await settled(lambda: rt.stats.rejected == 1)
    assert seen == []


def test_generic_messages_are_handed_over_only_with_the_declared_plan_type() -> None:
    from rap_schemas import Empty, PlanProposal, SpinCommand, SpinPlan, Verdict
    from rap_sdk.node import acceptor

    plan = SpinPlan(commands=[SpinCommand(omega=1.0, duration=0.5)])
    good = PlanProposal(plan_uid=b"u" * 16, plan_type=plan.TYPE, plan=plan, proposer="p", created=1)
    other = PlanProposal(plan_uid=b"u" * 16, plan_type="x", plan=Empty(), proposer="p", created=1)
    takes = acceptor(PlanProposal[SpinPlan])
    assert takes is not None
    assert takes(good)
    assert not takes(other)
    verdicts = acceptor(Verdict[SpinPlan])
    assert verdicts is not None
    assert verdicts(
        Verdict(plan_uid=b"u" * 16, approved=True, legitimator="l", ts=1, proposal=good)
    )
    assert verdicts(Verdict(plan_uid=b"u" * 16, approved=False, legitimator="l", ts=1))
    assert not verdicts(
        Verdict(plan_uid=b"u" * 16, approved=True, legitimator="l", ts=1, proposal=other)
    )
    assert not verdicts(good)


async def test_a_store_that_applies_at_once_stores_a_local_write_before_it_returns() -> None:
    async with (
        MemoryFabric() as fabric,
        open_service(KnowledgeConfig(system=SYSTEM), fabric=fabric) as svc,
        KnowledgeClient(fabric=fabric, system=SYSTEM, writer="w") as w,
    ):
        v = await w.write("laser_scan", scan(1))
        assert svc.stats.stream_applied == 1  # in the writer's task: no task woken
        assert (await svc.store.get("laser_scan")).version == v  # type: ignore[union-attr]


async def test_local_writes_keep_their_order_when_the_service_is_busy() -> None:
    """While a record waits in the service's inbox, later local writes queue behind it
    instead of being stored first."""
    async with (
        MemoryFabric() as fabric,
        open_service(KnowledgeConfig(system=SYSTEM), fabric=fabric) as svc,
        KnowledgeClient(fabric=fabric, system=SYSTEM, writer="w") as w,
    ):
        applied: list[int] = []
        store_apply = svc.store.apply_now  # type: ignore[attr-defined]

        def apply(rec, **kw):  # type: ignore[no-untyped-def]
            applied.append(rec.version)
            return store_apply(rec, **kw)

        svc.store.apply_now = apply  # type: ignore[attr-defined]  # both ways store through it
        svc._taking += 1  # as if a record were being stored: the next ones queue
        first = await w.write("a", 1)
        svc._taking -= 1
        second = await w.write("a", 2)  # one is queued: this one queues behind it
        assert applied == []
        await settled(lambda: len(applied) == 2)
        assert applied == [first, second]
        third = await w.write("a", 3)  # idle again: stored at once
        assert applied == [first, second, third]


def count_stream_publishes(fabric: MemoryFabric) -> list[str]:
    """The keys of knowledge stream records ``fabric`` publishes from now on."""
    sent: list[str] = []
    publish = fabric.publish

    async def counted(key, payload, **kw):  # type: ignore[no-untyped-def]
        if key.startswith(keys.kb(SYSTEM, "x")[:-1]):
            sent.append(key)
        return await publish(key, payload, **kw)

    fabric.publish = counted  # type: ignore[method-assign]
    return sent


async def test_a_stream_only_the_colocated_service_receives_is_not_published() -> None:
    """Co-located writer and service, nobody else on the stream: the record is stored in
    the writer's task with no envelope and no sample (and replicas still get it)."""
    async with (
        MemoryFabric() as fabric,
        open_service(KnowledgeConfig(system=SYSTEM), fabric=fabric) as svc,
        KnowledgeClient(fabric=fabric, system=SYSTEM, writer="w") as w,
        KnowledgeClient(fabric=fabric, system=SYSTEM, writer="r") as r,
    ):
        await r.read("a", default=None)  # a co-located replica of the key
        sent = count_stream_publishes(fabric)
        v = await w.write("a", 1)
        assert sent == []
        assert svc.stats.stream_applied == 1
        assert (await svc.store.get("a")).version == v  # type: ignore[union-attr]
        assert await r.read("a", min_version=v, timeout=0) == 1


async def test_every_other_receiver_of_the_stream_still_gets_each_record() -> None:
    """A subscriber in this process or in another one makes the writer publish again:
    it gets every record, the service stores each once; when it goes, the intake
    takes over again."""
    bus = MemoryBus()
    async with (
        MemoryFabric(bus=bus) as fabric,
        MemoryFabric(bus=bus) as elsewhere,
        open_service(KnowledgeConfig(system=SYSTEM), fabric=fabric) as svc,
        KnowledgeClient(fabric=fabric, system=SYSTEM, writer="w") as w,
    ):
        sent = count_stream_publishes(fabric)
        for where in (fabric, elsewhere):
            with where.subscribe(keys.kb(SYSTEM, "a")) as tap:
                want = svc.stats.stream_applied + 3
                for i in range(3):
                    await w.write("a", i)
                with anyio.fail_after(5):
                    got = [await tap.get() for _ in range(3)]
                assert [msgspec.msgpack.decode(s.payload)["body"]["key"] for s in got] == ["a"] * 3
                await settled(lambda: svc.stats.stream_applied >= want)  # noqa: B023
                assert svc.stats.stream_applied == want
        assert len(sent) == 6
        await w.write("a", 9)
        assert len(sent) == 6  # nobody else again: not published
        assert svc.stats.stream_applied == 7
