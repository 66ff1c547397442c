"""Two OS processes over real Zenoh on loopback: discovery by liveliness, typed
round trips with cycle/cause, and a graceful stop on SIGTERM."""

from __future__ import annotations

import math
import signal
import subprocess
import sys
from pathlib import Path

import anyio
import pytest
from rap_schemas import LaserScan, keys, pack_ranges
from rap_sdk import LivelinessChange
from rap_sdk.testing import Harness

pytestmark = [pytest.mark.anyio, pytest.mark.zenoh]

PEER = Path(__file__).with_name("peer_echo.py")


async def test_a_node_in_another_process_round_trips_and_stops_on_sigterm() -> None:
    async with Harness(system="twoproc", fabric="zenoh", timeout=20) as h:
        watch = h.fabric.watch_liveliness(keys.alive("twoproc", "echo"))
        proc = await anyio.open_process(
            [sys.executable, str(PEER), h.endpoint, "twoproc"],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
        )
        try:
            with anyio.fail_after(20):
                assert await watch.get() == LivelinessChange(keys.alive("twoproc", "echo"), True)
            await h.fabric.wait_matched(keys.data("twoproc", "ping"), timeout=20)
            after = 0
            for i in range(50):  # ping-pong: data inboxes keep only the newest samples
                scan = LaserScan(
                    stamp=i,
                    frame_id="base_link",
                    angle_min=-math.pi,
                    angle_increment=0.1,
                    range_min=0.1,
                    range_max=12.0,
                    ranges=pack_ranges([1.0, math.inf]),
                )
                ping = await h.publish("ping", scan)
                rec = await h.expect_data("pong", after=after)
                after = h.records.index(rec) + 1
                assert rec.decode(LaserScan) == scan
                assert rec.envelope is not None
                assert rec.envelope.source == "echo"
                assert rec.envelope.seq == i
                assert rec.envelope.cycle == ping.uid
                assert rec.envelope.cause == ping.uid
            proc.send_signal(signal.SIGTERM)
            with anyio.fail_after(20):
                code = await proc.wait()
                assert await watch.get() == LivelinessChange(keys.alive("twoproc", "echo"), False)
        finally:
            if proc.returncode is None:
                proc.kill()
                await proc.wait()
            chunks = [chunk async for chunk in proc.stdout] if proc.stdout else []
            out = b"".join(chunks).decode()
            await proc.aclose()
        assert code == 0, out
        assert "received SIGTERM; stopping 1 node(s)" in out
