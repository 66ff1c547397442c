"""The MQTT bridge on a locked-down broker: TLS only, client certificates of the broker's
CA, and passwords (no anonymous client)."""

from __future__ import annotations

from pathlib import Path

import anyio
import msgspec
import pytest
from rap_bridges import Bridge, BridgeSpec
from rap_schemas import Envelope, keys
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
from libs.rap_sdk.tests.certs_support import make_certs

pytestmark = [pytest.mark.anyio]

PASSWORDS = {"robot": "robot-pw-1"}
BACK = keys.data(SYSTEM, "reading_back")


def secure_spec(port: int, certs: Path, direction: str, **kw: object) -> BridgeSpec:
    return BridgeSpec(
        protocol="mqtt",
        url=f"mqtts://127.0.0.1:{port}",
        address="secure/reading",
        format="json",
        username="robot",
        ca=str(certs / "ca.pem"),
        cert=str(certs / "robot.pem"),
        key=str(certs / "robot.key"),
        client_id=f"secure-{direction}",
        **kw,  # type: ignore[arg-type]
    )


async def test_tls_and_a_password_carry_messages_and_a_wrong_password_is_retried(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    certs = make_certs(
        tmp_path / "certs",
        {"broker": "", "robot": ""},
        system="mqtt",
        hosts={"broker": ["127.0.0.1", "localhost"]},
    )
    server = MosquittoServer(
        tmp_path,
        free_port(),
        passwords=PASSWORDS,
        tls=(certs / "ca.pem", certs / "broker.pem", certs / "broker.key"),
    )
    monkeypatch.setenv("RAP_TEST_MQTT_PASSWORD", PASSWORDS["robot"])
    wrong = tmp_path / "wrong.pw"
    wrong.write_text("not-the-password\n", encoding="utf-8")
    await server.start()
    try:
        async with MemoryFabric() as fabric, anyio.create_task_group() as tg:
            back = fabric.subscribe(
                BACK, InboxPolicy(capacity=100, overflow=Overflow.FIFO, block=False)
            )
            out = Bridge(
                "secure-out",
                secure_spec(server.port, certs, "out", password_env="RAP_TEST_MQTT_PASSWORD"),
                fabric,
                KEY,
                direction="out",
                message=Reading,
                backoff=fast_backoff(),
            )
            inb = Bridge(
                "secure-in",
                secure_spec(server.port, certs, "in", password_file=str(wrong)),
                fabric,
                BACK,
                direction="in",
                message=Reading,
                backoff=fast_backoff(),
            )
            await tg.start(out.run)
            await tg.start(inb.run)
            with anyio.fail_after(10):
                await out.wait_connected()
            await until(lambda: inb.stats.connect_failures >= 2)
            assert not inb.connected  # refused, counted, tried again
            wrong.write_text(PASSWORDS["robot"] + "\n", encoding="utf-8")  # read at each try
            with anyio.fail_after(10):
                await inb.wait_connected()
            side = FabricSide(fabric)
            await side.publish(1)
            await side.publish(2)
            got = []
            with anyio.fail_after(10):
                while len(got) < 2:
                    sample = await back.get()
                    env = msgspec.msgpack.decode(sample.payload, type=Envelope)
                    got.append((env.source, msgspec.msgpack.decode(env.body, type=Reading).n))
            tg.cancel_scope.cancel()
    finally:
        await server.stop()
    assert got == [("secure-in", 1), ("secure-in", 2)]
    assert out.stats.sent == 2
    assert inb.stats.reconnects == 1
