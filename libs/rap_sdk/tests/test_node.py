from __future__ import annotations

import logging
import math
from typing import Any

import anyio
import anyio.lowlevel
import msgspec
import pytest
from rap_schemas import (
    Empty,
    Envelope,
    LaserScan,
    LidarMask,
    Rejection,
    SpinPlan,
    Stage,
    StageTrace,
    Twist,
    keys,
    pack_flags,
    pack_ranges,
)
from rap_sdk import (
    ConfigError,
    Context,
    HandlerError,
    MemoryFabric,
    Node,
    NodeRuntime,
    Sealer,
    run_nodes,
)
from rap_sdk.fabric import Sample
from rap_sdk.rejections import Rejections
from rap_sdk.testing import Harness

pytestmark = pytest.mark.anyio

SETUPS = [
    pytest.param({"fabric": "memory"}, id="memory"),
    pytest.param({"fabric": "memory", "isolate": True}, id="memory-isolated"),
    pytest.param({"fabric": "zenoh"}, id="zenoh", marks=pytest.mark.zenoh),
    pytest.param(
        {"fabric": "zenoh", "isolate": True}, id="zenoh-isolated", marks=pytest.mark.zenoh
    ),
]


def scan(n: int = 4, *, stamp: int = 1) -> LaserScan:
    return LaserScan(
        stamp=stamp,
        frame_id="base_link",
        angle_min=-math.pi,
        angle_increment=2 * math.pi / n,
        range_min=0.1,
        range_max=12.0,
        ranges=pack_ranges([1.0] * (n - 1) + [math.inf]),
    )


def two_stage_loop() -> tuple[Node, Node, list[Any]]:
    seen: list[Any] = []
    monitor = Node("monitor", stage="monitor")
    analyse = Node("analyse", stage=Stage.ANALYSE)

    @monitor.on_data("scan")
    async def on_scan(ctx: Context, s: LaserScan) -> None:
        seen.append(("monitor", s.stamp))
        await ctx.emit("new-data")

    @analyse.on_event("new-data")
    async def detect(ctx: Context) -> None:
        seen.append(("analyse", ctx.envelope.source))
        mask = LidarMask(
            angle_min=-math.pi, angle_increment=1.0, occluded=pack_flags([False, True])
        )
        await ctx.emit("anomaly", mask)

    return monitor, analyse, seen


@pytest.mark.parametrize("setup", SETUPS)
async def test_a_cycle_flows_with_cycle_and_cause(setup: dict[str, Any]) -> None:
    monitor, analyse, seen = two_stage_loop()
    async with Harness(system="t", **setup) as h:
        await h.start(monitor, analyse)
        sent = await h.publish("scan", scan(stamp=42))
        anomaly = await h.expect_event("anomaly")
        new_data = (await h.expect_event("new-data")).envelope
        assert anomaly.envelope is not None
        assert new_data is not None
        # cycle = uid of the sample that started it; cause = the envelope reacted to
        assert new_data.cycle == sent.uid
        assert new_data.cause == sent.uid
        assert anomaly.envelope.cycle == sent.uid
        assert anomaly.envelope.cause == new_data.uid
        assert list(anomaly.decode(LidarMask).flags()) == [False, True]
        assert seen == [("monitor", 42), ("analyse", "monitor")]
        # one record per handler call, published before what its handler emitted
        for node in ("monitor", "analyse"):
            await h.wait_for(
                lambda r, node=node: (
                    r.kind is keys.Kind.TRACE  # type: ignore[misc]
                    and r.name == node
                    and r.decode(StageTrace).ended
                )
            )
        mon, ana = h.traces("monitor"), h.traces("analyse")
        # per node in order; across nodes the order is causal (trigger uids), since
        # records from two senders may reach the harness in either order
        assert [t.phase for t in mon] == ["call"]
        assert [t.phase for t in ana] == ["call"]
        assert {t.cycle for t in mon + ana} == {sent.uid}
        assert {t.stage for t in mon} == {Stage.MONITOR}
        assert {t.stage for t in ana} == {Stage.ANALYSE}
        assert mon[0].trigger == sent.uid
        assert ana[0].trigger == new_data.uid
        assert mon[0].ts <= new_data.ts <= mon[0].ts + mon[0].duration_ns
        assert all(t.ok for t in mon + ana)


@pytest.mark.parametrize("setup", SETUPS[:3])
async def test_bad_samples_are_rejected_and_the_node_carries_on(setup: dict[str, Any]) -> None:
    monitor, analyse, seen = two_stage_loop()
    async with Harness(system="t", **setup) as h:
        group = await h.start(monitor, analyse)
        data = keys.data("t", "scan")
        await h.publish_raw(data, b"\xc1")  # not msgpack
        await h.send(data, Twist(linear=1.0, angular=0.0))  # wrong type
        body = msgspec.msgpack.encode(
            {
                "stamp": 1,
                "frame_id": "x",
                "angle_min": 0.0,
                "angle_increment": "wide",
                "range_min": 0.1,
                "range_max": 1.0,
                "ranges": b"",
            }
        )
        p, _ = h.sealer.seal(data, LaserScan.TYPE, body)
        await h.publish_raw(data, p)
        await h.publish("scan", scan(stamp=7))
        await h.expect_event("anomaly")
        assert ("monitor", 7) in seen
        rt = group["monitor"]
        assert rt.stats.rejected == 3
        rejections = h.rejections("monitor")
        # rate limited: one record at once, the rest counted and flushed at shutdown
        assert len(rejections) == 1
        assert "undecodable envelope" in rejections[0].reason
    # the two held back were flushed when the node stopped, before the recorder closed
    later = h.rejections("monitor")
    assert len(later) == 2
    assert later[1].count == 2


async def test_rejection_reasons_name_the_path_and_type() -> None:
    node = Node("n")
    got: list[LaserScan] = []

    @node.on_data("scan")
    async def on_scan(ctx: Context, s: LaserScan) -> None:
        got.append(s)

    async with MemoryFabric() as fabric, run_nodes([node], fabric=fabric, system="t") as group:
        rt = group["n"]
        log = fabric.subscribe(keys.log("t", "n"))
        rt.rejections = Rejections("n", logging.getLogger("test"), interval_ns=0)  # no limit
        sealer = Sealer("src")
        key = keys.data("t", "scan")
        bad_body = msgspec.msgpack.encode({"stamp": "x"})
        for tname, body in ((LaserScan.TYPE, bad_body), (Twist.TYPE, b"\xc0")):
            payload, _ = sealer.seal(key, tname, body)
            await rt.handle(node.routes[0], _sample(key, payload))
        reasons = []
        for _ in range(2):
            with anyio.fail_after(2):
                s = await log.get()
            reasons.append(msgspec.msgpack.decode(_body(s.payload), type=Rejection).reason)
        assert "$.stamp" in reasons[0]
        assert "expected type rap.LaserScan/2, got 'rap.Twist/1'" in reasons[1]
        assert got == []


def _sample(key: str, payload: bytes) -> Sample:
    return Sample(key, payload)


def _body(payload: bytes) -> bytes:
    return bytes(msgspec.msgpack.decode(payload, type=Envelope).body)


async def test_handler_failure_is_traced_and_does_not_stop_the_node() -> None:
    node = Node("flaky", stage="plan")
    calls: list[int] = []

    @node.on_event("go")
    async def go(ctx: Context, s: LaserScan) -> None:
        calls.append(s.stamp)
        if s.stamp == 1:
            raise RuntimeError("planner bug")

    async with Harness(system="t") as h:
        group = await h.start(node)
        await h.emit("go", scan(stamp=1))
        await h.emit("go", scan(stamp=2))
        await h.wait_for(lambda r: r.kind is keys.Kind.TRACE and len(h.traces()) == 2)
        ends = [t for t in h.traces() if t.ended]
        assert [(t.ok, t.error) for t in ends] == [(False, "RuntimeError: planner bug"), (True, "")]
        assert calls == [1, 2]
        assert group["flaky"].stats.failed == 1
        assert group["flaky"].stats.handled == 1


async def test_duplicates_reach_the_handler_once() -> None:
    node = Node("n")
    calls = 0

    @node.on_event("e")
    async def e(ctx: Context) -> None:
        nonlocal calls
        calls += 1

    async with Harness(system="t") as h:
        group = await h.start(node)
        payload, _ = h.sealer.seal(keys.event("t", "e"), "rap.Empty/1", b"\x80")
        for _ in range(3):
            await h.publish_raw(keys.event("t", "e"), payload)
        await h.emit("e")
        await h.wait_for(lambda r: len([t for t in h.traces() if t.ended]) == 2)
        assert calls == 2
        assert group["n"].sender_stats.duplicates == 2


async def test_queued_samples_are_handled_on_graceful_stop() -> None:
    node = Node("n")
    handled: list[int] = []

    @node.on_event("e")
    async def e(ctx: Context, s: LaserScan) -> None:
        await anyio.lowlevel.checkpoint()
        handled.append(s.stamp)

    async with MemoryFabric() as fabric:
        async with run_nodes([node], fabric=fabric, system="t"):
            sealer = Sealer("src")
            for i in range(5):
                p, _ = sealer.seal(
                    keys.event("t", "e"), LaserScan.TYPE, msgspec.msgpack.encode(scan(stamp=i))
                )
                await fabric.publish(keys.event("t", "e"), p)
        assert handled == [0, 1, 2, 3, 4]


async def test_liveliness_token_while_running() -> None:
    async with MemoryFabric() as fabric:
        watch = fabric.watch_liveliness(keys.pattern("t", keys.Kind.ALIVE))
        async with run_nodes([Node("a"), Node("b")], fabric=fabric, system="t"):
            assert {(await watch.get()).key for _ in range(2)} == {
                keys.alive("t", "a"),
                keys.alive("t", "b"),
            }
        gone = {(await watch.get()) for _ in range(2)}
        assert {c.alive for c in gone} == {False}


class PlannerState(msgspec.Struct):
    plans: int
    last: SpinPlan | None = None


class PlannerConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    period: float = 8.0
    omega: float = 1.0


def test_snapshot_and_restore_round_trip() -> None:
    node = Node("planner", stage="plan", config=PlannerConfig())
    state = PlannerState(plans=0)

    @node.on_snapshot
    def snap() -> PlannerState:
        return state

    @node.on_restore
    def restore(s: PlannerState) -> None:
        nonlocal state
        state = s

    state = PlannerState(plans=3, last=SpinPlan(commands=[], period=4.0))
    blob = node.snapshot()
    state = PlannerState(plans=0)
    node.restore(blob)
    assert state == PlannerState(plans=3, last=SpinPlan(commands=[], period=4.0))
    with pytest.raises(ConfigError, match="does not match the restore hook's type"):
        node.restore(msgspec.msgpack.encode({"plans": "many"}))
    assert Node("x").snapshot() == msgspec.msgpack.encode(None)


def test_config_is_validated_with_the_path() -> None:
    node = Node("planner", config=PlannerConfig())
    assert node.configure({"period": 4.0}) == PlannerConfig(period=4.0)
    with pytest.raises(ConfigError, match=r"\$\.omega"):
        node.configure({"omega": "fast"})
    with pytest.raises(ConfigError, match="unknown field `speed`"):
        node.configure({"speed": 1.0})
    assert node.config == PlannerConfig(period=4.0)
    with pytest.raises(ConfigError, match="declares no config"):
        Node("bare").configure({})


def test_handler_declarations_are_checked() -> None:
    node = Node("n")
    with pytest.raises(HandlerError, match="must be an 'async def'"):
        node.on_event("e")(lambda ctx: None)

    async def too_many(ctx: Context, a: LaserScan, b: LaserScan) -> None: ...

    with pytest.raises(HandlerError, match=r"must take \(ctx\) or \(ctx, message\)"):
        node.on_event("e")(too_many)

    async def untyped(ctx: Context, msg: dict) -> None: ...  # type: ignore[type-arg]

    with pytest.raises(HandlerError, match=r"rap_schemas\.Message subclass"):
        node.on_event("e")(untyped)
    with pytest.raises(ConfigError, match="unknown stage 'optimise'"):
        Node("n", stage="optimise")
    with pytest.raises(ValueError, match="invalid node"):
        Node("a/b")


async def test_handlers_are_plain_functions_tests_can_call() -> None:
    monitor, _, seen = two_stage_loop()
    fn = monitor.routes[0].fn

    class FakeCtx:
        async def emit(self, name: str, message: Any = None) -> None:
            seen.append(("emit", name))

    await fn(FakeCtx(), scan(stamp=5))
    assert seen == [("monitor", 5), ("emit", "new-data")]


async def test_empty_event_body_decodes() -> None:
    node = Node("n")
    got: list[Empty] = []

    @node.on_event("ping")
    async def ping(ctx: Context, e: Empty) -> None:
        got.append(e)

    async with Harness(system="t") as h:
        await h.start(node)
        await h.emit("ping", Empty())
        await h.wait_for(lambda r: len(got) == 1 or r.kind is keys.Kind.LOG)
        await h.wait_for(lambda r: r.kind is keys.Kind.TRACE and r.decode(StageTrace).ended)
        assert got == [Empty()]


async def test_stop_before_run_returns() -> None:
    node = Node("n")

    @node.on_event("e")
    async def e(ctx: Context) -> None: ...

    async with MemoryFabric() as fabric:
        rt = NodeRuntime(node, fabric=fabric, system="t")
        rt.stop()
        with anyio.fail_after(2):
            await rt.run()


async def test_the_harness_records_keys_outside_the_key_space() -> None:
    async with Harness(system="t") as h:
        await h.publish_raw("rap/t/unknown-kind/x", b"\x01")
        await h.emit("after")
        rec = await h.wait_for(lambda r: r.kind is None)
        assert (rec.key, rec.name, rec.envelope) == ("rap/t/unknown-kind/x", "", None)
        await h.expect_event("after")


async def test_a_rejection_names_the_sender_and_type_when_it_can() -> None:
    node = Node("n")

    @node.on_data("scan")
    async def on_scan(ctx: Context, s: LaserScan) -> None: ...

    async with Harness(system="t") as h:
        await h.start(node)
        await h.send(keys.data("t", "scan"), Twist(linear=0.0, angular=1.0))
        rec = await h.expect(keys.Kind.LOG, "n")
        rejection = rec.decode(Rejection)
        assert (rejection.source, rejection.type) == ("harness", Twist.TYPE)
        assert "expected type rap.LaserScan/2" in rejection.reason
