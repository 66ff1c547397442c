"""The MQTT bridge with clients no one here wrote: mosquitto_sub and mosquitto_pub."""

from __future__ import annotations

import json
from pathlib import Path

import anyio
import pytest
from rap_bridges import Bridge, BridgeSpec
from rap_sdk import MemoryFabric
from rap_sdk.fabric import free_port
from rap_sdk.testing import require_binary

from libs.rap_bridges.tests.contract import (
    IN_TOPIC,
    KEY,
    OUT_TOPIC,
    FabricSide,
    MosquittoServer,
    Reading,
    fast_backoff,
    until,
)

pytestmark = [pytest.mark.anyio]

CYCLE = bytes(range(16))


async def test_mosquitto_sub_reads_what_an_out_bridge_publishes(tmp_path: Path) -> None:
    sub = require_binary("mosquitto_sub", hint="apt-get install mosquitto-clients")
    server = MosquittoServer(tmp_path, free_port())
    await server.start()
    base = [sub, "-h", "127.0.0.1", "-p", str(server.port), "-V", "mqttv5", "-q", "1"]
    session = ["-c", "-i", "outside-sub", "-x", "600", "-t", OUT_TOPIC]
    try:
        # a session of its own at the broker; the bridge's messages are queued for it
        await anyio.run_process([*base, *session, "-E"])
        async with MemoryFabric() as fabric, anyio.create_task_group() as tg:
            spec = BridgeSpec(
                protocol="mqtt",
                url=f"mqtt://127.0.0.1:{server.port}",
                address=OUT_TOPIC,
                format="json",
            )
            b = Bridge("out1", spec, fabric, KEY, direction="out", message=Reading)
            b.backoff = fast_backoff()
            await tg.start(b.run)
            side = FabricSide(fabric)
            await side.publish(1, cycle=CYCLE)
            await side.publish(2)
            await side.publish(3)
            await until(lambda: b.stats.sent >= 3)
            with anyio.fail_after(10):
                done = await anyio.run_process([*base, *session, "-C", "3", "-F", "%p|%P"])
            tg.cancel_scope.cancel()
    finally:
        await server.stop()
    lines = done.stdout.decode().splitlines()
    assert [json.loads(line.split("|")[0]) for line in lines] == [
        {"n": 1, "note": ""},
        {"n": 2, "note": ""},
        {"n": 3, "note": ""},
    ]
    assert f"rap-cycle:{CYCLE.hex()}" in lines[0]


async def test_mosquitto_pub_feeds_an_in_bridge(tmp_path: Path) -> None:
    pub = require_binary("mosquitto_pub", hint="apt-get install mosquitto-clients")
    server = MosquittoServer(tmp_path, free_port())
    await server.start()
    base = [pub, "-h", "127.0.0.1", "-p", str(server.port), "-V", "mqttv5", "-q", "1"]
    try:
        async with MemoryFabric() as fabric, anyio.create_task_group() as tg:
            side = FabricSide(fabric)
            await tg.start(side.record)
            spec = BridgeSpec(
                protocol="mqtt",
                url=f"mqtt://127.0.0.1:{server.port}",
                address=IN_TOPIC,
                format="json",
            )
            b = Bridge("in1", spec, fabric, KEY, direction="in", message=Reading)
            b.backoff = fast_backoff()
            await tg.start(b.run)
            with anyio.fail_after(10):
                await b.wait_connected()
            cycle = ["-D", "publish", "user-property", "rap-cycle", CYCLE.hex()]
            await anyio.run_process([*base, "-t", IN_TOPIC, "-m", '{"n": 5}', *cycle])
            await anyio.run_process([*base, "-t", IN_TOPIC, "-m", "not json"])
            await anyio.run_process([*base, "-t", IN_TOPIC, "-m", '{"n": 6, "note": "x"}'])
            await side.wait_for(2)
            tg.cancel_scope.cancel()
    finally:
        await server.stop()
    assert side.readings() == [5, 6]
    assert side.got[0].cycle == CYCLE
    assert side.got[0].source == "in1"
    assert b.stats.rejected == 1


async def test_a_retained_qos_2_message_reaches_a_late_mosquitto_sub(tmp_path: Path) -> None:
    sub = require_binary("mosquitto_sub", hint="apt-get install mosquitto-clients")
    server = MosquittoServer(tmp_path, free_port())
    await server.start()
    try:
        async with MemoryFabric() as fabric, anyio.create_task_group() as tg:
            spec = BridgeSpec(
                protocol="mqtt",
                url=f"mqtt://127.0.0.1:{server.port}",
                address="robot/last",
                format="json",
                qos=2,
                retain=True,
            )
            b = Bridge("retained", spec, fabric, KEY, direction="out", message=Reading)
            await tg.start(b.run)
            with anyio.fail_after(10):
                await b.wait_connected()
            await FabricSide(fabric).publish(7)
            await until(lambda: b.stats.sent == 1)  # PUBCOMP came back
            tg.cancel_scope.cancel()
        # subscribed after the bridge has gone: the broker kept the message
        cmd = [sub, "-h", "127.0.0.1", "-p", str(server.port), "-V", "mqttv5", "-q", "2"]
        with anyio.fail_after(10):
            done = await anyio.run_process([*cmd, "-t", "robot/last", "-C", "1", "-F", "%r %q %p"])
    finally:
        await server.stop()
    assert done.stdout.decode().strip() == '1 2 {"n":7,"note":""}'
