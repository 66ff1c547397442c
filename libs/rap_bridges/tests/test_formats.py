"""The formats at the boundary, over TCP (the format does not depend on the protocol):
envelopes both ways (resent ones passed over), the message's msgpack bytes (raw); and
TCP frames that cannot be read."""

from __future__ import annotations

import struct
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import anyio
import msgspec
import pytest
from rap_bridges import Bridge, Frame
from rap_schemas import Envelope
from rap_sdk import Sealer

from libs.rap_bridges.tests.contract import (
    KEY,
    FabricSide,
    Reading,
    fabric_side,
    fast_backoff,
    json_frame,
    outside_of,
    until,
)

pytestmark = [pytest.mark.anyio]

CYCLE = bytes(range(16))


@asynccontextmanager
async def run_with(
    tmp_path: Path, direction: str, fmt: str, **kw: Any
) -> AsyncIterator[tuple[FabricSide, Any, Bridge]]:
    async with anyio.create_task_group() as outer:
        async with fabric_side(outer) as side, outside_of("tcp", tmp_path, outer) as out:
            await out.start()
            async with anyio.create_task_group() as tg:
                b = Bridge(
                    f"{fmt}-{direction}",
                    out.spec(direction, format=fmt, **kw),
                    side.fabric,
                    KEY,
                    direction=direction,  # type: ignore[arg-type]
                    message=Reading,
                    backoff=fast_backoff(),
                )
                await tg.start(b.run)
                with anyio.fail_after(10):
                    await b.wait_connected()
                yield side, out, b
                tg.cancel_scope.cancel()
        outer.cancel_scope.cancel()


async def test_envelopes_in_are_checked_resealed_and_resent_ones_passed_over(
    tmp_path: Path,
) -> None:
    async with run_with(tmp_path, "in", "envelope") as (side, out, b):
        far = Sealer("far-robot")
        one, _ = far.seal_message(KEY, Reading(n=1), cycle=CYCLE)
        pose, _ = far.seal(KEY, "rap.Pose2D/1", msgspec.msgpack.encode({"x": 1.0}))
        two, _ = far.seal_message(KEY, Reading(n=2))
        await out.send([Frame(one), Frame(one), Frame(b"\x00garbage"), Frame(pose), Frame(two)])
        await side.wait_for(2)
        await until(lambda: b.stats.rejected == 2)
        assert side.readings() == [1, 2]
        env = side.got[0]
        assert (env.source, env.cycle) == ("envelope-in", CYCLE)
        assert b.stats.duplicates == 1
        assert any("expected type test.Reading/N" in r for r in b.stats.rejections.by_reason)


async def test_envelope_and_raw_out(tmp_path: Path) -> None:
    async with run_with(tmp_path, "out", "envelope") as (side, out, b):
        await side.publish(5, cycle=CYCLE)
        await out.wait_received(1)
        env = msgspec.msgpack.decode(out.received[0].payload, type=Envelope)
        assert (env.source, env.cycle) == ("contract-test", CYCLE)
        assert msgspec.msgpack.decode(env.body, type=Reading) == Reading(n=5)
        await until(lambda: b.stats.sent == 1)  # the acknowledgement may be on its way
    async with run_with(tmp_path / "raw", "out", "raw") as (side, out, _b):
        await side.publish(6)
        await out.wait_received(1)
        assert msgspec.msgpack.decode(out.received[0].payload, type=Reading) == Reading(n=6)
        assert out.received[0].headers["rap-type"] == "test.Reading/1"


async def test_a_bad_frame_is_skipped_and_an_oversize_one_closes_the_connection(
    tmp_path: Path,
) -> None:
    """Headers that are not a JSON map: that frame is rejected, the next one read. A
    frame over the limit: rejected, the connection closed (the only way to find the next
    frame) and made again by the bridge."""
    async with run_with(tmp_path, "in", "json", max_frame=1024) as (side, out, b):
        bad_headers = struct.pack(">IH", 2 + 3 + 2, 3) + b"{x}" + b"{}"
        await until(lambda: bool(out.conns))  # the peer has taken the bridge's connection
        await out.conns[-1].send(bad_headers)
        await out.send([json_frame(1)])
        await side.wait_for(1)
        assert b.stats.connects == 1
        await out.conns[-1].send(struct.pack(">IH", 10_000_000, 0))
        await until(lambda: b.stats.connects == 2 and len(out.conns) == 1)
        await out.send([json_frame(2)])
        await side.wait_for(2)
        assert side.readings() == [1, 2]
        assert b.stats.rejected == 2
        assert b.stats.reconnects == 1
        reasons = " | ".join(b.stats.rejections.by_reason)
        assert "not a JSON map of strings" in reasons
        assert "over the limit" in reasons
