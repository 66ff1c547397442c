"""The NATS bridge with clients no one here wrote (nats-py used directly) and with the
NATS text protocol spoken by hand over a raw socket, against nats-server instances of
the tests' own: core NATS, JetStream (stream made by the bridge, durable consumer),
passwords and TLS with client certificates."""

from __future__ import annotations

import json
import logging
import ssl
from collections.abc import AsyncIterator
from pathlib import Path

import anyio
import pytest
from anyio.streams.buffered import BufferedByteReceiveStream
from blockbuster import blockbuster_ctx
from nats.js.api import AckPolicy, ConsumerConfig, StorageType
from rap_bridges import Bridge, BridgeSpec
from rap_schemas import keys
from rap_sdk import InboxPolicy, MemoryFabric, Overflow
from rap_sdk.fabric import free_port

from libs.rap_bridges.tests.contract import (
    KEY,
    SYSTEM,
    FabricSide,
    Reading,
    fast_backoff,
    until,
)
from libs.rap_bridges.tests.outside_nats import NatsServer, require_server
from libs.rap_sdk.tests.certs_support import make_certs

pytestmark = [pytest.mark.anyio]

CYCLE = bytes(range(16))


@pytest.fixture
async def server(tmp_path: Path) -> AsyncIterator[NatsServer]:
    require_server()
    s = NatsServer(tmp_path, free_port())
    await s.start()
    try:
        yield s
    finally:
        await s.stop()


def spec(port: int, address: str, *, scheme: str = "nats", **kw: object) -> BridgeSpec:
    return BridgeSpec(
        protocol="nats",
        url=f"{scheme}://127.0.0.1:{port}",
        address=address,
        format="json",
        **kw,  # type: ignore[arg-type]
    )


async def test_a_nats_py_subscriber_reads_a_core_nats_out_bridge(server: NatsServer) -> None:
    nc = await server.client()
    sub = await nc.subscribe("robot.scan")
    await nc.flush()
    try:
        async with MemoryFabric() as fabric, anyio.create_task_group() as tg:
            b = Bridge(
                "core-out",
                spec(server.port, "robot.scan", qos=0),
                fabric,
                KEY,
                direction="out",
                message=Reading,
            )
            await tg.start(b.run)
            with anyio.fail_after(10):
                await b.wait_connected()
            side = FabricSide(fabric)
            for n in range(3):
                await side.publish(n, cycle=CYCLE if n == 0 else None)
            msgs = [await sub.next_msg(timeout=10) for _ in range(3)]
            tg.cancel_scope.cancel()
    finally:
        await nc.close()
    assert [json.loads(m.data) for m in msgs] == [{"n": n, "note": ""} for n in range(3)]
    assert msgs[0].headers is not None
    assert msgs[0].headers["rap-cycle"] == CYCLE.hex()
    assert msgs[0].headers["rap-type"] == "test.Reading/1"
    assert msgs[0].headers["rap-source"] == "contract-test"


async def test_a_jetstream_out_bridge_makes_a_file_stream_that_outlives_a_restart(
    server: NatsServer,
) -> None:
    async with MemoryFabric() as fabric, anyio.create_task_group() as tg:
        b = Bridge(
            "js-out", spec(server.port, "robot.scan"), fabric, KEY, direction="out", message=Reading
        )
        await tg.start(b.run)
        with anyio.fail_after(10):
            await b.wait_connected()
        side = FabricSide(fabric)
        for n in range(3):
            await side.publish(n)
        await until(lambda: b.stats.sent == 3)  # each acknowledged by the server
        tg.cancel_scope.cancel()
    await server.stop()
    await server.start()
    nc = await server.client()
    try:
        js = nc.jetstream()
        info = await js.stream_info("rap-robot_scan")
        pull = await js.pull_subscribe(
            "robot.scan", stream="rap-robot_scan", config=ConsumerConfig(ack_policy=AckPolicy.NONE)
        )
        msgs = await pull.fetch(3, timeout=5)
    finally:
        await nc.close()
    assert info.config.storage == StorageType.FILE
    assert info.config.subjects == ["robot.scan"]
    assert info.state.messages == 3
    assert [json.loads(m.data)["n"] for m in msgs] == [0, 1, 2]
    assert all(m.headers and m.headers["Nats-Msg-Id"] for m in msgs)


class RawNats:
    """The NATS client protocol by hand: INFO, CONNECT, PUB/HPUB, PING/PONG."""

    def __init__(self, port: int) -> None:
        self.port = port

    async def __aenter__(self) -> RawNats:
        self.stream = await anyio.connect_tcp("127.0.0.1", self.port)
        self.reader = BufferedByteReceiveStream(self.stream)
        info = await self.reader.receive_until(b"\r\n", 65536)
        assert info.startswith(b"INFO ")
        assert json.loads(info[5:])["headers"] is True
        await self.stream.send(b'CONNECT {"verbose":false,"pedantic":false,"headers":true}\r\n')
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stream.aclose()

    async def pub(
        self, subject: str, payload: bytes, headers: dict[str, str] | None = None
    ) -> None:
        if headers is None:
            await self.stream.send(f"PUB {subject} {len(payload)}\r\n".encode() + payload + b"\r\n")
            return
        head = "NATS/1.0\r\n" + "".join(f"{k}: {v}\r\n" for k, v in headers.items()) + "\r\n"
        size = len(head) + len(payload)
        line = f"HPUB {subject} {len(head)} {size}\r\n{head}"
        await self.stream.send(line.encode() + payload + b"\r\n")

    async def ping(self) -> None:
        """PING, and wait for PONG: the server has read everything sent before."""
        await self.stream.send(b"PING\r\n")
        with anyio.fail_after(10):
            while (line := await self.reader.receive_until(b"\r\n", 65536)) != b"PONG":
                assert not line.startswith(b"-ERR"), line


async def wait_acknowledged(server: NatsServer, stream: str, consumer: str, seq: int) -> None:
    """Wait until nats-server says ``consumer`` has every message up to ``seq``
    acknowledged, and none waiting for an acknowledgement."""
    nc = await server.client()
    try:
        js = nc.jetstream()
        with anyio.fail_after(10):
            while True:
                info = await js.consumer_info(stream, consumer)
                assert info.ack_floor is not None
                if info.ack_floor.stream_seq >= seq and info.num_ack_pending == 0:
                    assert info.config.ack_policy == AckPolicy.EXPLICIT
                    return
                await anyio.sleep(0.02)
    finally:
        await nc.close()


async def test_the_text_protocol_over_a_raw_socket_feeds_a_durable_in_bridge(
    server: NatsServer,
) -> None:
    """QoS 1: what a plain ``PUB`` puts on a subject of the bridge's stream arrives; what
    is published while the bridge is away waits in its durable consumer, and only that
    arrives when it is back."""
    address = "robot.cmd"
    async with MemoryFabric() as fabric, anyio.create_task_group() as tg:
        side = FabricSide(fabric)
        await tg.start(side.record)

        def bridge() -> Bridge:
            s = spec(server.port, address)
            b = Bridge("raw-in", s, fabric, KEY, direction="in", message=Reading)
            b.backoff = fast_backoff()
            return b

        async with anyio.create_task_group() as first:
            b = bridge()
            await first.start(b.run)
            with anyio.fail_after(10):
                await b.wait_connected()
            async with RawNats(server.port) as raw:
                await raw.pub(address, b'{"n": 1}')
                await raw.pub(address, b'{"n": 2}', {"rap-cycle": CYCLE.hex()})
                await raw.pub(address, b"not json")
                await raw.ping()
            await side.wait_for(2)
            await until(lambda: b.stats.rejected == 1)
            first.cancel_scope.cancel()
        # every message taken is acknowledged (the rejected one too: it is the bridge's)
        await wait_acknowledged(server, "rap-robot_cmd", "rap-bridge-raw-in", 3)
        async with RawNats(server.port) as raw:  # the bridge is away
            await raw.pub(address, b'{"n": 3}')
            await raw.ping()
        async with anyio.create_task_group() as second:
            again = bridge()
            await second.start(again.run)
            await side.wait_for(3)
            await wait_acknowledged(server, "rap-robot_cmd", "rap-bridge-raw-in", 4)
            second.cancel_scope.cancel()
        tg.cancel_scope.cancel()
    assert side.readings() == [1, 2, 3]
    assert side.got[1].cycle == CYCLE
    assert "test.Reading/N JSON" in next(iter(b.stats.rejections.by_reason))
    assert again.stats.received == 1


async def test_a_password_is_required_and_a_wrong_one_is_retried(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    require_server()
    server = NatsServer(tmp_path, free_port(), user=("robot", "robot-pw-1"))
    monkeypatch.setenv("RAP_TEST_NATS_PASSWORD", "not-the-password")
    pw = tmp_path / "nats.pw"
    pw.write_text("robot-pw-1\n", encoding="utf-8")
    await server.start()
    caplog.set_level(logging.WARNING, logger="rap_bridges.core")
    try:
        async with MemoryFabric() as fabric, anyio.create_task_group() as tg:
            side = FabricSide(fabric)
            await tg.start(side.record)
            wrong = Bridge(
                "wrong-pw",
                spec(
                    server.port,
                    "robot.cmd",
                    qos=0,
                    username="robot",
                    password_env="RAP_TEST_NATS_PASSWORD",
                ),
                fabric,
                KEY,
                direction="in",
                message=Reading,
                backoff=fast_backoff(),
            )
            right = Bridge(
                "right-pw",
                spec(server.port, "robot.cmd", qos=0, username="robot", password_file=str(pw)),
                fabric,
                KEY,
                direction="in",
                message=Reading,
            )
            await tg.start(wrong.run)
            await tg.start(right.run)
            with anyio.fail_after(10):
                await right.wait_connected()
            await until(lambda: wrong.stats.connect_failures >= 2)
            assert not wrong.connected
            nc = await server.client(user="robot", password="robot-pw-1")
            try:
                await nc.publish("robot.cmd", b'{"n": 4}')
                await nc.flush()
            finally:
                await nc.close()
            await side.wait_for(1)
            tg.cancel_scope.cancel()
    finally:
        await server.stop()
    assert side.readings() == [4]
    assert side.got[0].source == "right-pw"
    assert "check username and password_env / password_file" in caplog.text


async def test_tls_with_client_certificates(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    require_server()
    certs = make_certs(
        tmp_path / "certs",
        {"server": "", "robot": ""},
        system="nats",
        hosts={"server": ["127.0.0.1"]},
    )
    server = NatsServer(
        tmp_path,
        free_port(),
        tls=(certs / "ca.pem", certs / "server.pem", certs / "server.key"),
    )
    await server.start()
    caplog.set_level(logging.WARNING, logger="rap_bridges.core")
    secure = {
        "ca": str(certs / "ca.pem"),
        "cert": str(certs / "robot.pem"),
        "key": str(certs / "robot.key"),
    }
    try:
        async with MemoryFabric() as fabric, anyio.create_task_group() as tg:
            plain = Bridge(
                "plain",
                spec(server.port, "robot.scan"),
                fabric,
                KEY,
                direction="out",
                message=Reading,
                backoff=fast_backoff(),
            )
            b = Bridge(
                "tls-out",
                spec(server.port, "robot.scan", scheme="tls", **secure),
                fabric,
                KEY,
                direction="out",
                message=Reading,
            )
            await tg.start(plain.run)
            await tg.start(b.run)
            with anyio.fail_after(10):
                await b.wait_connected()
            await FabricSide(fabric).publish(9)
            await until(lambda: b.stats.sent == 1)
            await until(lambda: plain.stats.connect_failures >= 1)
            assert not plain.connected
            tg.cancel_scope.cancel()
        context = ssl.create_default_context(cafile=secure["ca"])
        context.load_cert_chain(secure["cert"], secure["key"])
        nc = await server.client(tls=context)
        try:
            pull = await nc.jetstream().pull_subscribe(
                "robot.scan", config=ConsumerConfig(ack_policy=AckPolicy.NONE)
            )
            msgs = await pull.fetch(1, timeout=5)
        finally:
            await nc.close()
    finally:
        await server.stop()
    assert [json.loads(m.data)["n"] for m in msgs] == [9]
    assert f"write tls://127.0.0.1:{server.port}" in caplog.text


async def test_nats_bridges_make_no_blocking_call(tmp_path: Path) -> None:
    """blockbuster turns a blocking call on the event loop into an error: out bridges
    feeding in bridges through core NATS and JetStream, with a password read from a
    file, make none."""
    require_server()
    server = NatsServer(tmp_path, free_port(), user=("robot", "robot-pw-1"))
    pw = tmp_path / "nats.pw"
    pw.write_text("robot-pw-1\n", encoding="utf-8")
    await server.start()  # (the server's start is the test's, not a bridge's)
    login = {"username": "robot", "password_file": str(pw)}
    policy = InboxPolicy(capacity=1000, overflow=Overflow.FIFO, block=False)
    try:
        with blockbuster_ctx():
            async with MemoryFabric() as fabric, anyio.create_task_group() as tg:
                subs = {
                    qos: fabric.subscribe(keys.data(SYSTEM, f"back{qos}"), policy) for qos in (0, 1)
                }
                ins = [
                    Bridge(
                        f"nb-in{qos}",
                        spec(server.port, f"nb.q{qos}", qos=qos, **login),
                        fabric,
                        keys.data(SYSTEM, f"back{qos}"),
                        direction="in",
                        message=Reading,
                    )
                    for qos in (0, 1)
                ]
                outs = [
                    Bridge(
                        f"nb-out{qos}",
                        spec(server.port, f"nb.q{qos}", qos=qos, **login),
                        fabric,
                        KEY,
                        direction="out",
                        message=Reading,
                    )
                    for qos in (0, 1)
                ]
                for b in (*ins, *outs):
                    await tg.start(b.run)
                    with anyio.fail_after(10):
                        await b.wait_connected()
                side = FabricSide(fabric)
                for n in range(50):
                    await side.publish(n)
                with anyio.fail_after(20):
                    for sub in subs.values():
                        for _ in range(50):
                            await sub.get()
                await until(lambda: all(b.stats.sent == 50 for b in outs))
                tg.cancel_scope.cancel()
    finally:
        await server.stop()
    assert [b.stats.published for b in ins] == [50, 50]
