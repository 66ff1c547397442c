"""The knowledge service and client together, on MemoryFabric and on real Zenoh."""

from __future__ import annotations

import hashlib
import os
from typing import Any

import anyio
import msgspec
import pytest
from knowledge.app import open_service
from knowledge.config import KnowledgeConfig
from rap_schemas import KbReply, LidarMask, SpinCommand, SpinPlan, keys
from rap_sdk import LifecycleError
from rap_sdk.knowledge import KnowledgeError, KnowledgeTypeError

from services.knowledge.tests.deployment import deployment

pytestmark = pytest.mark.anyio
KINDS = ["memory", pytest.param("zenoh", marks=pytest.mark.zenoh)]

PLAN = SpinPlan(commands=[SpinCommand(omega=1.0, duration=1.5)], period=8.0)


@pytest.mark.parametrize("kind", KINDS)
async def test_write_then_read_elsewhere(kind: str) -> None:
    async with deployment(kind) as d:
        planner, executor = await d.client("planner"), await d.client("executor")
        v1 = await planner.write("directions", PLAN, durable=True)
        assert await executor.read("directions", SpinPlan) == PLAN  # catch-up from service
        v2 = await planner.write("directions", SpinPlan(commands=[], period=8.0))
        assert v2 > v1
        got = await executor.read_record("directions", min_version=v2)  # via the stream
        assert got is not None
        assert got.version == v2
        assert (await executor.read("directions", SpinPlan)).commands == []
        assert await executor.read("nothing", default="d") == "d"
        with pytest.raises(KnowledgeError, match="has no value; pass default="):
            await executor.read("nothing")


@pytest.mark.parametrize("kind", KINDS)
async def test_compare_and_set_and_delete(kind: str) -> None:
    async with deployment(kind) as d:
        a, b = await d.client("a"), await d.client("b")
        v = await a.write("lock", "a", expect=0)
        with pytest.raises(KnowledgeError, match="expected version 0") as exc:
            await b.write("lock", "b", expect=0)
        assert exc.value.code == "conflict"
        v2 = await b.write("lock", "b", expect=v)
        assert v2 > v
        await a.delete("lock", durable=True)
        assert await b.read("lock", default=None) is None
        assert await b.keys() == []
        await a.write("lock", "again", expect=0)
        assert await b.keys("*") == ["lock"]


@pytest.mark.parametrize("kind", KINDS)
async def test_history_and_listing(kind: str) -> None:
    async with deployment(kind) as d:
        w = await d.client("w")
        versions = [
            await w.write(f"robot/tb1/{k}", i, durable=True)
            for i, k in enumerate(["pose", "pose", "pose", "scan"])
        ]
        hist = await w.history("robot/tb1/pose", int)
        assert [h.value for h in hist] == [0, 1, 2]
        assert [h.version for h in hist] == versions[:3]
        assert all(h.writer == "w" for h in hist)
        assert [h.value for h in await w.history("robot/tb1/pose", limit=2)] == [1, 2]
        since = hist[1].ts
        assert [h.value for h in await w.history("robot/tb1/pose", since=since)] == [1, 2]
        assert await w.keys("robot/*/pose") == ["robot/tb1/pose"]
        assert await w.keys("robot/**") == ["robot/tb1/pose", "robot/tb1/scan"]


@pytest.mark.parametrize("kind", KINDS)
async def test_a_value_of_the_wrong_type_names_the_path(kind: str) -> None:
    async with deployment(kind) as d:
        w = await d.client("w")
        await w.write(
            "mask", {"angle_min": 0.0, "angle_increment": "x", "occluded": b""}, durable=True
        )
        with pytest.raises(KnowledgeTypeError, match=r"\$\.angle_increment"):
            await w.read("mask", LidarMask)


@pytest.mark.parametrize("kind", KINDS)
async def test_bad_requests_get_a_reason_and_the_service_carries_on(kind: str) -> None:
    async with deployment(kind, KnowledgeConfig(system="t", max_value_bytes=1000)) as d:
        w = await d.client("w")
        fabric = w.fabric

        async def raw(key: str, payload: bytes) -> KbReply:
            (reply,) = await fabric.query(keys.kb("t", key), payload, timeout=5)
            return msgspec.msgpack.decode(reply.payload, type=KbReply)

        for payload, code, words in [
            (b"\xc1", "bad-request", "knowledge request: undecodable"),
            (msgspec.msgpack.encode({"op": "explode"}), "bad-request", "knowledge request: "),
            (  # an unknown field nested 5000 deep: skipped by the decoder, still bounded
                b"\x83\xa2op\xa3get\xa3key\xa1k\xa1x" + b"\x91" * 5000 + b"\xc0",
                "bad-request",
                "nested too deeply",
            ),
            (b"\xdd\xff\xff\xff\xff", "bad-request", "knowledge request: "),
            (msgspec.msgpack.encode({"op": "get", "key": "a//b"}), "bad-request", "chunk"),
            (
                msgspec.msgpack.encode({"op": "history", "key": "k", "limit": 0}),
                "bad-request",
                "history limit",
            ),
            (
                msgspec.msgpack.encode({"op": "get", "key": 123}),
                "bad-request",
                "Expected `str`, got `int` - at `$.key`",
            ),
        ]:
            reply = await raw("k", payload)
            assert (reply.ok, reply.code) == (False, code)
            assert words in reply.error
        assert d.service is not None
        assert d.service.rejections.total == 5  # the ones that did not decode, by reason
        assert await w.read("k", default=None) is None  # and the service still answers
        with pytest.raises(KnowledgeError, match="over the limit of 1000") as exc:
            await w.write("big", "x" * 2000, durable=True)
        assert exc.value.code == "too-large"
        with pytest.raises(ValueError, match="invalid knowledge key"):
            await w.write("bad key", 1)
        with pytest.raises(KnowledgeError, match="reserved"):
            await w.write("_models/x", 1)
        assert await w.write("fine", 1, durable=True) > 0  # still serving
        assert d.service is not None
        assert d.service.stats.query_errors == 8


@pytest.mark.parametrize("kind", KINDS)
async def test_model_store(kind: str) -> None:
    async with deployment(kind) as d:
        w = await d.client("w")
        big = os.urandom(50 * 2**20)  # 50 MiB
        m1 = await w.put_model("detector", big, tags={"arch": "yolo"})
        m2 = await w.put_model("detector", b"second")
        assert (m1.version, m2.version, m1.size) == (1, 2, len(big))
        assert m1.sha256 == hashlib.sha256(big).hexdigest()
        meta, data = await w.get_model("detector")
        assert (meta.version, data) == (2, b"second")
        assert (await w.get_model("detector", 1))[1] == big
        assert await w.rollback_model("detector") == 1  # pin the one before
        assert (await w.get_model("detector"))[0].version == 1
        versions, pinned = await w.list_models("detector")
        assert ([m.version for m in versions], pinned) == ([1, 2], 1)
        assert await w.pin_model("detector", None) is None
        assert (await w.get_model("detector"))[0].version == 2
        with pytest.raises(KnowledgeError, match="has no version 9") as exc:
            await w.pin_model("detector", 9)
        assert exc.value.code == "not-found"


async def test_corrupted_models_are_refused(tmp_path: Any) -> None:
    async with deployment("memory") as d:
        w = await d.client("w")
        await w.put_model("m", b"good bytes")
        assert d.service is not None
        store = d.service.store
        meta, _ = await store.get_model("m", 1)  # type: ignore[misc]
        await store.put_model(meta, b"bad bytes!")  # bit rot in the store
        with pytest.raises(KnowledgeError, match="corrupted in the store") as exc:
            await w.get_model("m")
        assert exc.value.code == "integrity"


async def test_a_durable_write_wins_over_the_version_the_service_holds() -> None:
    async with deployment("memory") as d:
        fast, slow = await d.client("fast"), await d.client("slow")
        fast.clock.observe(fast.clock.next() + (1000 << 20))  # a clock 1 s ahead
        ahead = await fast.write("k", "fast", durable=True)
        behind = await slow.write("k", "slow", durable=True)  # later, with a lower clock
        assert behind > ahead
        assert await fast.read("k") == "slow"


@pytest.mark.parametrize("kind", KINDS)
async def test_garbage_on_the_write_stream_is_rejected_and_counted(kind: str) -> None:
    async with deployment(kind) as d:
        w = await d.client("w")
        key = keys.kb("t", "k")
        await w.fabric.publish(key, b"\xc1")  # not an envelope
        payload, _ = w.sealer.seal_message(key, SpinCommand(omega=1.0, duration=1.0))
        await w.fabric.publish(key, payload)  # an envelope of the wrong type
        await w.write("k", "fine")  # and the stream goes on
        assert await w.read("k") == "fine"
        assert d.service is not None
        with anyio.fail_after(5):
            while d.service.stats.stream_applied < 1:
                await anyio.wait_all_tasks_blocked() if kind == "memory" else anyio.sleep(0.01)
        assert d.service.stats.stream_rejected == 2
        hist = await w.history("k")
        assert [h.value for h in hist] == ["fine"]


async def test_a_second_service_for_the_same_system_refuses_to_start() -> None:
    """Two services of one system answered every query twice, and clients took whichever
    answer came first."""
    async with deployment("memory") as d:
        assert d.service is not None
        with pytest.raises(LifecycleError, match="'knowledge' is already running"):
            async with open_service(KnowledgeConfig(system="t"), fabric=d.service.fabric):
                pass


async def test_a_value_over_the_limit_fails_at_the_writer() -> None:
    async with deployment("memory") as d:
        w = await d.client("w", max_value_bytes=1000)
        with pytest.raises(KnowledgeError, match="over the limit of 1000") as exc:
            await w.write("big", "x" * 2000)  # not durable: it used to stay in w's replica
        assert exc.value.code == "too-large"
        assert await w.read("big", default=None) is None
