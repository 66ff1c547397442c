"""blockbuster turns a blocking call made on the event loop into an error: MQTT and TCP
bridges, both ways, make none while messages flow."""

from __future__ import annotations

from pathlib import Path
from typing import cast

import anyio
import pytest
from blockbuster import blockbuster_ctx
from rap_bridges import Bridge, BridgeSpec
from rap_bridges.tcp import TcpLink
from rap_schemas import keys
from rap_sdk import InboxPolicy, MemoryFabric, Overflow
from rap_sdk.fabric import free_port

from libs.rap_bridges.tests.contract import (
    KEY,
    SYSTEM,
    FabricSide,
    MosquittoServer,
    Reading,
    fast_backoff,
    until,
)

pytestmark = [pytest.mark.anyio]

VIA_MQTT = keys.data(SYSTEM, "via_mqtt")
VIA_TCP = keys.data(SYSTEM, "via_tcp")
N = 50


async def test_bridges_make_no_blocking_call(tmp_path: Path) -> None:
    server = MosquittoServer(tmp_path, free_port())
    await server.start()  # (the server's start is the test's, not a bridge's)
    mqtt = f"mqtt://127.0.0.1:{server.port}"
    policy = InboxPolicy(capacity=1000, overflow=Overflow.FIFO, block=False)
    try:
        with blockbuster_ctx():
            async with MemoryFabric() as fabric, anyio.create_task_group() as tg:
                via_mqtt = fabric.subscribe(VIA_MQTT, policy)
                via_tcp = fabric.subscribe(VIA_TCP, policy)

                def bridge(name: str, spec: BridgeSpec, key: str, direction: str) -> Bridge:
                    return Bridge(
                        name,
                        spec,
                        fabric,
                        key,
                        direction=direction,  # type: ignore[arg-type]
                        message=Reading,
                        backoff=fast_backoff(),
                    )

                mqtt_in = bridge(
                    "mqtt-in",
                    BridgeSpec(protocol="mqtt", url=mqtt, address="nb/r", format="raw"),
                    VIA_MQTT,
                    "in",
                )
                tcp_in = bridge(
                    "tcp-in",
                    BridgeSpec(protocol="tcp", url="tcp://127.0.0.1:0", serve=True),
                    VIA_TCP,
                    "in",
                )
                for b in (mqtt_in, tcp_in):
                    await tg.start(b.run)
                    with anyio.fail_after(10):
                        await b.wait_connected()
                port = cast(TcpLink, tcp_in.link).port
                outs = [
                    bridge(
                        "mqtt-out",
                        BridgeSpec(protocol="mqtt", url=mqtt, address="nb/r", format="raw"),
                        KEY,
                        "out",
                    ),
                    bridge(
                        "tcp-out",
                        BridgeSpec(protocol="tcp", url=f"tcp://127.0.0.1:{port}"),
                        KEY,
                        "out",
                    ),
                ]
                for b in outs:
                    await tg.start(b.run)
                    with anyio.fail_after(10):
                        await b.wait_connected()
                side = FabricSide(fabric)
                for n in range(N):
                    await side.publish(n)
                with anyio.fail_after(20):
                    for sub in (via_mqtt, via_tcp):
                        for _ in range(N):
                            await sub.get()
                await until(lambda: all(b.stats.sent == N for b in outs))
                tg.cancel_scope.cancel()
    finally:
        await server.stop()
    assert mqtt_in.stats.published == tcp_in.stats.published == N
