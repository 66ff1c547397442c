"""One behaviour suite for every Fabric: MemoryFabric and ZenohFabric (real sessions on
loopback). ``pair`` gives two fabrics that see each other as separate processes would;
tests that need one fabric use ``a`` only."""

from __future__ import annotations

import asyncio
import logging
import threading
from collections.abc import AsyncIterator
from contextlib import AsyncExitStack
from typing import Any

import anyio
import pytest
from anyio import wait_all_tasks_blocked
from rap_sdk import (
    BackpressureTimeout,
    FabricError,
    InboxPolicy,
    LifecycleError,
    LivelinessChange,
    MemoryBus,
    MemoryFabric,
    Overflow,
    QueryError,
    QueryRequest,
    Reply,
    ZenohConfig,
    ZenohFabric,
)
from rap_sdk.fabric import Fabric, Outgoing
from rap_sdk.testing import free_port

pytestmark = pytest.mark.anyio

KINDS = ["memory", pytest.param("zenoh", marks=pytest.mark.zenoh)]


async def open_pair(kind: str, stack: AsyncExitStack) -> tuple[Any, Any]:
    if kind == "memory":
        bus = MemoryBus()
        a = await stack.enter_async_context(MemoryFabric(bus=bus))
        b = await stack.enter_async_context(MemoryFabric(bus=bus))
        return a, b
    port = free_port()
    a = await stack.enter_async_context(ZenohFabric(ZenohConfig(listen=[f"tcp/127.0.0.1:{port}"])))
    b = await stack.enter_async_context(
        ZenohFabric(ZenohConfig(listen=[], connect=[f"tcp/127.0.0.1:{port}"]))
    )
    return a, b


@pytest.fixture(params=KINDS)
async def pair(request: pytest.FixtureRequest) -> AsyncIterator[tuple[Any, Any]]:
    async with AsyncExitStack() as stack:
        yield await open_pair(request.param, stack)


async def get(sub: Any, timeout: float = 5.0) -> Any:
    with anyio.fail_after(timeout):
        return await sub.get()


async def test_both_implement_the_protocol(pair: tuple[Any, Any]) -> None:
    a, b = pair
    assert isinstance(a, Fabric)
    assert isinstance(b, Fabric)
    assert a.id
    assert a.id != b.id


async def test_local_delivery_is_not_remote(pair: tuple[Any, Any]) -> None:
    a, _ = pair
    sub = a.subscribe("rap/s/data/scan")
    await a.publish("rap/s/data/scan", b"x")
    s = await get(sub)
    assert (s.key, s.payload, s.remote) == ("rap/s/data/scan", b"x", False)


async def test_each_subscriber_gets_each_sample_once(pair: tuple[Any, Any]) -> None:
    a, b = pair
    local, remote = a.subscribe("rap/s/data/**"), b.subscribe("rap/s/data/**")
    await a.wait_matched("rap/s/data/n")
    for i in range(5):
        await a.publish("rap/s/data/n", bytes([i]))
    await a.publish("rap/s/data/end", b"")
    for sub, is_remote in ((local, False), (remote, True)):
        got = [await get(sub) for _ in range(6)]
        assert [s.payload for s in got] == [bytes([i]) for i in range(5)] + [b""]
        assert all(s.remote is is_remote for s in got)
    # nothing more was delivered: a duplicate would be queued behind 'end'
    assert len(local.inbox) == 0
    await a.publish("rap/s/data/probe", b"p")
    assert (await get(remote)).key == "rap/s/data/probe"


@pytest.mark.parametrize(
    ("expr", "hits"),
    [
        ("rap/s/data/*", ["rap/s/data/scan"]),
        ("rap/s/data/**", ["rap/s/data/scan", "rap/s/data/tb1/scan"]),
        ("rap/*/data/tb1/*", ["rap/s/data/tb1/scan"]),
        ("rap/**/scan", ["rap/s/data/scan", "rap/s/data/tb1/scan"]),
        ("rap/s/event/**", ["rap/s/event/new-data"]),
    ],
)
async def test_wildcards(pair: tuple[Any, Any], expr: str, hits: list[str]) -> None:
    a, b = pair
    keys = ["rap/s/data/scan", "rap/s/data/tb1/scan", "rap/s/event/new-data", "rap/t/x/y"]
    sub_local, sub_remote = a.subscribe(expr), b.subscribe(expr)
    sentinel = b.subscribe("rap/s/end")
    await a.wait_matched("rap/s/end")
    for k in keys:
        await a.wait_matched(k) if k in hits else None
        await a.publish(k, k.encode())
    await a.publish("rap/s/end", b"")
    await get(sentinel)
    for sub in (sub_local, sub_remote):
        got = [(await get(sub)).key for _ in hits]
        assert sorted(got) == sorted(hits)
        assert len(sub.inbox) == 0


async def test_query_reply_local_remote_and_errors(pair: tuple[Any, Any]) -> None:
    a, b = pair

    async def value(req: QueryRequest) -> list[Reply]:
        if req.payload == b"boom":
            raise RuntimeError("handler exploded")
        return [Reply("rap/s/kb/x", b"x=" + req.payload)]

    async def listing(req: QueryRequest) -> list[Reply]:
        return [Reply("rap/s/kb/list/a", b"1"), Reply("rap/s/kb/list/b", b"2")]

    a.serve("rap/s/kb/x", value)
    a.serve("rap/s/kb/list/*", listing)
    await b.wait_matched("rap/s/kb/x", queryable=True)
    for asker in (a, b):
        assert await asker.query("rap/s/kb/x", b"1") == [Reply("rap/s/kb/x", b"x=1")]
        err = await asker.query("rap/s/kb/x", b"boom")
        assert [r.ok for r in err] == [False]
        assert b"handler exploded" in err[0].payload
        many = await asker.query("rap/s/kb/list/**")
        assert sorted(r.payload for r in many) == [b"1", b"2"]
        assert await asker.query("rap/s/kb/nobody", timeout=1.0) == []


async def test_a_query_attachment_reaches_the_queryable_beside_the_payload(
    pair: tuple[Any, Any],
) -> None:
    a, b = pair
    seen: list[tuple[bytes, bytes]] = []

    async def echo(req: QueryRequest) -> list[Reply]:
        seen.append((req.payload, req.attachment))
        return [Reply("rap/s/admin/x/status", req.attachment)]

    a.serve("rap/s/admin/x/*", echo)
    await b.wait_matched("rap/s/admin/x/status", queryable=True)
    for asker in (a, b):
        got = await asker.query("rap/s/admin/x/status", b"body", attachment=b"\x00signed")
        assert got == [Reply("rap/s/admin/x/status", b"\x00signed")]
        got = await asker.query("rap/s/admin/*/status", partial=True, attachment=b"w")
        assert got == [Reply("rap/s/admin/x/status", b"w")]
        assert await asker.query("rap/s/admin/x/status") == [Reply("rap/s/admin/x/status", b"")]
    assert seen == [(b"body", b"\x00signed"), (b"", b"w"), (b"", b"")] * 2


async def test_a_partial_query_keeps_the_replies_that_came_in_time(
    pair: tuple[Any, Any],
) -> None:
    a, b = pair

    async def quick(req: QueryRequest) -> list[Reply]:
        return [Reply("rap/s/admin/quick/status", b"here")]

    async def stuck(req: QueryRequest) -> list[Reply]:
        await anyio.sleep(30)
        return []

    a.serve("rap/s/admin/quick/*", quick)
    a.serve("rap/s/admin/stuck/*", stuck)
    await b.wait_matched("rap/s/admin/stuck/status", queryable=True)
    with pytest.raises(QueryError):
        await b.query("rap/s/admin/*/status", timeout=0.5)
    got = await b.query("rap/s/admin/*/status", timeout=0.5, partial=True)
    assert got == [Reply("rap/s/admin/quick/status", b"here")]


async def test_liveliness_appears_and_disappears(pair: tuple[Any, Any]) -> None:
    a, b = pair
    early = a.declare_token("rap/s/alive/early")
    watch = b.watch_liveliness("rap/s/alive/*")
    assert await get(watch) == LivelinessChange("rap/s/alive/early", True)
    late = a.declare_token("rap/s/alive/late")
    assert await get(watch) == LivelinessChange("rap/s/alive/late", True)
    late.undeclare()
    assert await get(watch) == LivelinessChange("rap/s/alive/late", False)
    early.undeclare()
    assert await get(watch) == LivelinessChange("rap/s/alive/early", False)
    own = b.declare_token("rap/s/alive/own")
    assert await get(watch) == LivelinessChange("rap/s/alive/own", True)
    own.undeclare()
    assert await get(watch) == LivelinessChange("rap/s/alive/own", False)


@pytest.mark.parametrize("kind", KINDS)
async def test_liveliness_ends_when_a_fabric_closes(kind: str) -> None:
    port = free_port()
    if kind == "memory":
        bus = MemoryBus()
        watcher: Any = MemoryFabric(bus=bus)
        leaver: Any = MemoryFabric(bus=bus)
    else:
        watcher = ZenohFabric(ZenohConfig(listen=[f"tcp/127.0.0.1:{port}"]))
        leaver = ZenohFabric(ZenohConfig(listen=[], connect=[f"tcp/127.0.0.1:{port}"]))
    async with watcher:
        watch = watcher.watch_liveliness("rap/s/alive/**")
        async with leaver:
            leaver.declare_token("rap/s/alive/n")
            assert await get(watch) == LivelinessChange("rap/s/alive/n", True)
        assert await get(watch) == LivelinessChange("rap/s/alive/n", False)


async def test_alive_lists_the_tokens_up_now(pair: tuple[Any, Any]) -> None:
    a, b = pair
    watch = b.watch_liveliness("rap/s/alive/*")
    tok = a.declare_token("rap/s/alive/x")
    own = b.declare_token("rap/s/alive/y")
    assert (await get(watch)).alive
    assert (await get(watch)).alive  # both have reached b
    assert await b.alive("rap/s/alive/*") == ["rap/s/alive/x", "rap/s/alive/y"]
    assert await a.alive("rap/s/alive/x") == ["rap/s/alive/x"]
    tok.undeclare()
    assert not (await get(watch)).alive
    assert await b.alive("rap/s/alive/*") == ["rap/s/alive/y"]
    own.undeclare()
    assert await b.alive("rap/other/alive/*") == []


@pytest.mark.zenoh
async def test_links_to_other_processes_are_counted_and_logged(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.INFO, logger="rap_sdk.fabric")
    port = free_port()
    async with ZenohFabric(ZenohConfig(listen=[f"tcp/127.0.0.1:{port}"])) as a:
        watch = a.watch_liveliness("rap/s/alive/*")
        async with ZenohFabric(ZenohConfig(connect=[f"tcp/127.0.0.1:{port}"])) as b:
            b.declare_token("rap/s/alive/b")
            assert (await get(watch)).alive
            assert a.stats.links_up == 1
        assert not (await get(watch)).alive
        with anyio.fail_after(5):
            while a.stats.links_down < 1:
                await wait_all_tasks_blocked()
    assert "link to peer" in caplog.text
    assert "lost" in caplog.text


@pytest.mark.zenoh
async def test_a_port_0_endpoint_becomes_the_port_it_listens_on() -> None:
    async with ZenohFabric(ZenohConfig(listen=["tcp/127.0.0.1:0"])) as a:
        (endpoint,) = a.endpoints
        assert endpoint.startswith("tcp/127.0.0.1:")
        assert int(endpoint.rsplit(":", 1)[1]) > 0
        watch = a.watch_liveliness("rap/s/alive/*")
        async with ZenohFabric(ZenohConfig(connect=[endpoint])) as b:  # it is reachable there
            b.declare_token("rap/s/alive/b")
            assert await get(watch) == LivelinessChange("rap/s/alive/b", True)


async def test_per_sender_order_is_kept(pair: tuple[Any, Any]) -> None:
    a, b = pair
    n = 2000
    sub = b.subscribe("rap/s/event/e", InboxPolicy(capacity=n + 1, overflow=Overflow.FIFO))
    await a.wait_matched("rap/s/event/e")
    for i in range(n):
        await a.publish("rap/s/event/e", i.to_bytes(4, "big"))
    got = [int.from_bytes((await get(sub)).payload, "big") for _ in range(n)]
    assert got == list(range(n))


async def test_latest_keeps_the_newest_locally(pair: tuple[Any, Any]) -> None:
    a, _ = pair
    sub = a.subscribe("rap/s/data/scan", InboxPolicy(capacity=3, overflow=Overflow.LATEST))
    for i in range(10):
        await a.publish("rap/s/data/scan", bytes([i]))
    assert [(await get(sub)).payload for _ in range(3)] == [b"\x07", b"\x08", b"\x09"]
    assert sub.stats.dropped == 7


async def test_latest_keeps_the_newest_from_remote(pair: tuple[Any, Any]) -> None:
    a, b = pair
    capped = b.subscribe("rap/s/data/scan", InboxPolicy(capacity=3, overflow=Overflow.LATEST))
    observer = b.subscribe("rap/s/data/scan", InboxPolicy(capacity=100))
    await a.wait_matched("rap/s/data/scan")
    for i in range(11):
        await a.publish("rap/s/data/scan", bytes([i]))
    # the observer holding sample 10 means sample 9 reached the capped inbox before it
    assert [(await get(observer)).payload[0] for _ in range(11)] == list(range(11))
    got = [(await get(capped)).payload[0]]
    while got[-1] != 10:
        got.append((await get(capped)).payload[0])
    assert got in ([7, 8, 9, 10], [8, 9, 10])
    assert capped.stats.dropped == 11 - len(got)


async def test_fifo_block_applies_backpressure_to_local_publishers(pair: tuple[Any, Any]) -> None:
    a, _ = pair
    sub = a.subscribe("rap/s/event/e", InboxPolicy(capacity=2, overflow=Overflow.FIFO))
    await a.publish("rap/s/event/e", b"1")
    await a.publish("rap/s/event/e", b"2")
    done = anyio.Event()

    async def third() -> None:
        await a.publish("rap/s/event/e", b"3")
        done.set()

    async with anyio.create_task_group() as tg:
        tg.start_soon(third)
        await wait_all_tasks_blocked()
        assert not done.is_set(), "publish into a full FIFO inbox must wait"
        assert (await get(sub)).payload == b"1"
        with anyio.fail_after(5):
            await done.wait()
    assert [(await get(sub)).payload for _ in range(2)] == [b"2", b"3"]
    assert sub.stats.dropped == 0
    await a.publish("rap/s/event/e", b"4")
    await a.publish("rap/s/event/e", b"5")
    with pytest.raises(BackpressureTimeout, match="inbox full"):
        await a.publish("rap/s/event/e", b"6", timeout=0.01)


async def test_fifo_drop_counts_what_it_drops(pair: tuple[Any, Any]) -> None:
    a, b = pair
    local = a.subscribe("rap/s/event/e", InboxPolicy(capacity=2, block=False))
    remote = b.subscribe("rap/s/event/e", InboxPolicy(capacity=2, block=True))
    sentinel = b.subscribe("rap/s/event/end")
    await a.wait_matched("rap/s/event/e")
    await a.wait_matched("rap/s/event/end")
    for i in range(5):
        await a.publish("rap/s/event/e", bytes([i]))
    await a.publish("rap/s/event/end", b"")
    await get(sentinel)  # samples of one sender arrive in order: all five came before
    assert [(await get(local)).payload[0] for _ in range(2)] == [0, 1]
    assert local.stats.dropped == 3
    # a remote sender never waits: into a full FIFO inbox the sample is dropped, counted
    assert remote.stats.dropped == 3
    assert len(remote.inbox) == 2
    assert [(await get(remote)).payload[0] for _ in range(2)] == [0, 1]


@pytest.mark.parametrize("kind", KINDS)
async def test_misuse_is_refused_with_the_fix(kind: str) -> None:
    fabric: Any = MemoryFabric() if kind == "memory" else ZenohFabric()
    with pytest.raises(LifecycleError, match="not open: use 'async with"):
        await fabric.publish("rap/s/data/x", b"")
    async with fabric:
        with pytest.raises(ValueError, match="wildcards must be whole chunks"):
            fabric.subscribe("rap/s/da*ta")
        with pytest.raises(ValueError, match="empty chunk"):
            fabric.subscribe("rap//s")
        everything = fabric.subscribe("rap/**")
        with pytest.raises(FabricError, match="cannot publish on a wildcard expression"):
            await fabric.publish("rap/s/*/x", b"")
        with pytest.raises(ValueError, match="empty chunk"):
            await fabric.publish("rap/s//x", b"")
        assert len(everything.inbox) == 0, "a refused publish reached a local subscriber"
    with pytest.raises(LifecycleError, match="is closed"):
        await fabric.publish("rap/s/data/x", b"")


@pytest.mark.parametrize("kind", KINDS)
async def test_clean_shutdown_leaks_no_task_or_thread(kind: str) -> None:
    async def cycle() -> None:
        async with AsyncExitStack() as stack:
            a, b = await open_pair(kind, stack)
            sub = b.subscribe("rap/s/**")
            a.serve("rap/s/kb/x", lambda req: _reply())
            a.declare_token("rap/s/alive/x")
            b.watch_liveliness("rap/s/alive/*")
            await a.wait_matched("rap/s/data/x")
            await a.publish("rap/s/data/x", b"1")
            await get(sub)
            await b.query("rap/s/kb/x")

    before = set(asyncio.all_tasks())
    await cycle()  # the first session starts Zenoh's process-wide runtime threads
    threads_after_first = threading.active_count()
    await cycle()
    await cycle()
    assert set(asyncio.all_tasks()) == before
    assert threading.active_count() <= threads_after_first


async def _reply() -> list[Reply]:
    return [Reply("rap/s/kb/x", b"ok")]


@pytest.mark.zenoh
async def test_publishers_beyond_the_cap_evict_the_oldest(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from rap_sdk.fabric import zenoh_fabric

    monkeypatch.setattr(zenoh_fabric, "MAX_PUBLISHERS", 3)
    port = free_port()
    async with (
        ZenohFabric(ZenohConfig(listen=[f"tcp/127.0.0.1:{port}"])) as a,
        ZenohFabric(ZenohConfig(listen=[], connect=[f"tcp/127.0.0.1:{port}"])) as b,
    ):
        sub = b.subscribe("rap/s/data/**", InboxPolicy(capacity=100))
        for i in range(5):
            await a.wait_matched(f"rap/s/data/k{i}")
        assert list(a._pubs) == ["rap/s/data/k2", "rap/s/data/k3", "rap/s/data/k4"]
        for i in range(5):  # evicted keys are declared again on use, and still arrive
            await a.wait_matched(f"rap/s/data/k{i}")
            await a.publish(f"rap/s/data/k{i}", bytes([i]))
        assert sorted([(await get(sub)).payload[0] for _ in range(5)]) == list(range(5))


async def test_prepare_runs_before_the_consumer_or_leaves_none(pair: tuple[Any, Any]) -> None:
    import msgspec

    a, b = pair
    decode = msgspec.msgpack.Decoder(int).decode
    local = a.subscribe("rap/s/data/n", InboxPolicy(capacity=10), prepare=decode)
    remote = b.subscribe("rap/s/data/n", InboxPolicy(capacity=10), prepare=decode)
    await a.wait_matched("rap/s/data/n")
    payloads = [msgspec.msgpack.encode(7), b"\xc1", msgspec.msgpack.encode(9)]
    for p in payloads:
        await a.publish("rap/s/data/n", p)
    got_local = [await get(local) for _ in payloads]
    assert [s.prepared for s in got_local] == [7, None, 9]  # a failed prepare leaves None
    got_remote = [await get(remote) for _ in payloads]
    assert [s.payload for s in got_remote] == payloads
    # from another process it may not have finished when the loop takes the sample
    assert all(s.prepared in (None, w) for s, w in zip(got_remote, [7, None, 9], strict=True))


# -- local objects (Outgoing): handed over as they are, encoded once when needed ----------


class _Counted:
    """An encoder that counts its calls."""

    def __init__(self) -> None:
        self.calls = 0

    def __call__(self, obj: Any) -> bytes:
        self.calls += 1
        return repr(obj).encode()


async def test_a_local_object_is_handed_over_and_never_encoded_for_local_subscribers(
    pair: tuple[Any, Any],
) -> None:
    a, _ = pair
    s1, s2 = a.subscribe("rap/s/data/obj"), a.subscribe("rap/s/data/obj")
    enc, obj = _Counted(), ("frozen", 1)
    await a.publish("rap/s/data/obj", Outgoing(obj, enc))
    got1, got2 = await get(s1), await get(s2)
    assert got1.obj is obj
    assert got2.obj is obj
    assert got1.size == 0
    assert not got1.remote
    assert enc.calls == 0  # nobody needed the bytes
    assert got1.payload == got2.payload == b"('frozen', 1)"
    assert enc.calls == 1  # made once, for both


async def test_a_local_object_reaches_another_process_as_bytes_encoded_once(
    pair: tuple[Any, Any],
) -> None:
    a, b = pair
    remote1, remote2 = b.subscribe("rap/s/data/obj"), b.subscribe("rap/s/data/obj")
    await a.wait_matched("rap/s/data/obj")
    enc = _Counted()
    await a.publish("rap/s/data/obj", Outgoing(("x",), enc))
    r1, r2 = await get(remote1), await get(remote2)
    assert r1.obj is None
    assert r1.remote
    assert r1.payload == r2.payload == b"('x',)"
    assert enc.calls == 1


async def test_a_subscription_of_the_publishers_group_is_skipped(pair: tuple[Any, Any]) -> None:
    a, _ = pair
    group = object()
    fed = a.subscribe("rap/s/kb/k", group=group)
    other = a.subscribe("rap/s/kb/k")
    await a.publish("rap/s/kb/k", Outgoing(1, _Counted(), group))
    await a.publish("rap/s/kb/k", b"bytes")  # bytes always reach every subscriber
    assert (await get(other)).obj == 1
    assert (await get(other)).payload == b"bytes"
    assert (await get(fed)).payload == b"bytes"
    assert fed.get_nowait() is None


# -- direct dispatch hooks (the runtime sets them; see test_direct_dispatch.py) ---------


async def test_a_direct_hook_takes_a_local_object_after_every_other_subscriber(
    pair: tuple[Any, Any],
) -> None:
    a, _ = pair
    order: list[str] = []
    plain = a.subscribe("rap/s/data/d")
    hooked = a.subscribe("rap/s/data/d")

    def take(sample: Any) -> Any:
        async def run() -> None:
            order.append(f"direct {sample.obj}")
            assert len(plain.inbox) == 1  # the other subscriber has it already

        return run()

    hooked.direct = take
    await a.publish("rap/s/data/d", Outgoing("x", _Counted()))
    assert order == ["direct x"]
    assert hooked.get_nowait() is None  # handled, not queued
    assert (await get(plain)).obj == "x"


async def test_a_declining_hook_or_bytes_or_a_non_direct_send_goes_to_the_inbox(
    pair: tuple[Any, Any],
) -> None:
    a, _ = pair
    calls: list[object] = []
    sub = a.subscribe("rap/s/data/d", InboxPolicy(capacity=1, overflow=Overflow.LATEST))

    def decline(sample: Any) -> None:
        calls.append(sample.obj)
        return None

    sub.direct = decline
    await a.publish("rap/s/data/d", Outgoing(1, _Counted()))  # declined: queued
    await a.publish("rap/s/data/d", b"raw")  # bytes: never offered to the hook
    later = Outgoing(3, _Counted())
    later.direct = False  # not the last of a handler's sends
    await a.publish("rap/s/data/d", later)
    assert calls == [1]
    assert (await get(sub)).obj == 3  # the inbox's own policy: the newest kept
    assert sub.stats.dropped == 2


async def test_local_subscribers_and_the_epoch_follow_every_subscription(
    pair: tuple[Any, Any],
) -> None:
    """``local_subscribers`` lists this session's own matching subscriptions; ``epoch``
    moves with a subscription here or elsewhere, so what a caller concluded from them
    is redone when it may have changed."""
    a, b = pair
    key = "rap/s/kb/a"
    assert not a.has_subscribers(key)
    assert list(a.local_subscribers(key)) == []
    before = a.epoch
    mine = a.subscribe("rap/s/kb/**")
    assert a.epoch != before
    assert list(a.local_subscribers(key)) == [mine]
    assert list(a.local_subscribers("rap/s/data/x")) == []
    before = a.epoch
    theirs = b.subscribe(key)
    with anyio.fail_after(5):  # the remote declaration reaches a on its own time
        while not a.has_subscribers(key, remote_only=True):  # noqa: ASYNC110
            await anyio.sleep(0.01)
    assert a.epoch != before
    assert list(a.local_subscribers(key)) == [mine]  # the other session's is not local
    before = a.epoch
    theirs.close()
    with anyio.fail_after(5):
        while a.has_subscribers(key, remote_only=True):  # noqa: ASYNC110
            await anyio.sleep(0.01)
    assert a.epoch != before
    before = a.epoch
    mine.close()
    assert a.epoch != before
    assert list(a.local_subscribers(key)) == []
