"""The AMQP bridge seen by tools no one here wrote: ``rabbitmqctl`` (queues, consumers,
connections, users) and aio-pika's own client, on this test process's RabbitMQ node
(outside_amqp.py)."""

from __future__ import annotations

import secrets
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import aio_pika
import anyio
import msgspec
import pytest
from aio_pika.abc import AbstractConnection, AbstractIncomingMessage, HeadersType
from rap_bridges import Bridge, BridgeSpec, Direction, Frame, FrameRefused, LinkContext, LinkDown
from rap_bridges.amqp import AmqpLink
from rap_sdk import MemoryFabric

from libs.rap_bridges.tests.contract import KEY, FabricSide, Reading, fast_backoff, until
from libs.rap_bridges.tests.outside_amqp import RabbitNode, node, require_server
from libs.rap_sdk.tests.certs_support import make_certs

pytestmark = [pytest.mark.anyio]

CYCLE = bytes(range(16))


@pytest.fixture
async def rabbit() -> RabbitNode:
    require_server()
    n = node()
    await n.start()  # booted once per process; started again after a contract restart
    return n


@pytest.fixture
async def client(rabbit: RabbitNode) -> AsyncIterator[AbstractConnection]:
    """An aio-pika connection of the test's own (guest, on loopback)."""
    connection = await aio_pika.connect(host="127.0.0.1", port=rabbit.port, timeout=5)
    try:
        yield connection
    finally:
        with anyio.CancelScope(shield=True):
            await connection.close()


def unique(prefix: str) -> str:
    return f"{prefix}.{secrets.token_hex(4)}"


def spec(rabbit: RabbitNode, address: str, **kw: Any) -> BridgeSpec:
    kw.setdefault("format", "json")
    return BridgeSpec(protocol="amqp", url=f"amqp://127.0.0.1:{rabbit.port}", address=address, **kw)


def bridge(name: str, s: BridgeSpec, fabric: MemoryFabric, direction: Direction) -> Bridge:
    return Bridge(
        name, s, fabric, KEY, direction=direction, message=Reading, backoff=fast_backoff()
    )


def link(s: BridgeSpec, direction: Direction = "out") -> tuple[AmqpLink, list[str]]:
    rejected: list[str] = []
    ctx = LinkContext(name="probe", direction=direction, reject=rejected.append)
    return AmqpLink(s, ctx), rejected


async def refused(s: BridgeSpec, direction: Direction = "out") -> LinkDown:
    """The LinkDown opening a link for ``s`` gives."""
    probe, _ = link(s, direction)
    try:
        with pytest.raises(LinkDown) as caught:
            await probe.open()
    finally:
        await probe.close()
    return caught.value


async def test_rabbitmqctl_sees_the_durable_queue_and_its_count_across_a_restart(
    rabbit: RabbitNode,
) -> None:
    """An out bridge declares its queue durable and publishes persistent, confirmed
    messages: rabbitmqctl counts them, they outlive a broker restart, and an aio-pika
    client reads them with their headers."""
    queue_name = unique("robot.scan")
    async with MemoryFabric() as fabric, anyio.create_task_group() as tg:
        b = bridge("to-rabbit", spec(rabbit, queue_name), fabric, "out")
        await tg.start(b.run)
        with anyio.fail_after(10):
            await b.wait_connected()
        side = FabricSide(fabric)
        await side.publish(1, cycle=CYCLE)
        await side.publish(2)
        await side.publish(3)
        await until(lambda: b.stats.sent == 3)  # the broker confirmed all three
        tg.cancel_scope.cancel()
    queues = await rabbit.list_queues()
    assert queues[queue_name]["durable"] is True
    assert queues[queue_name]["messages"] == 3
    await rabbit.stop_app()
    await rabbit.start()
    assert (await rabbit.list_queues())[queue_name]["messages"] == 3  # on disk
    async with await aio_pika.connect(host="127.0.0.1", port=rabbit.port, timeout=5) as c:
        channel = await c.channel()
        queue = await channel.declare_queue(queue_name, passive=True)
        got = [await queue.get(no_ack=True, timeout=5) for _ in range(3)]
    assert [msgspec.json.decode(m.body) for m in got] == [
        {"n": 1, "note": ""},
        {"n": 2, "note": ""},
        {"n": 3, "note": ""},
    ]
    first = got[0]
    assert first.delivery_mode == aio_pika.DeliveryMode.PERSISTENT
    assert first.content_type == "application/json"
    assert first.headers["rap-cycle"] == CYCLE.hex()
    assert first.headers["rap-type"] == "test.Reading/1"
    assert first.headers["rap-source"] == "contract-test"


async def test_an_in_bridge_consumes_with_the_buffer_as_prefetch_and_rejects_odd_headers(
    rabbit: RabbitNode, client: AbstractConnection
) -> None:
    """rabbitmqctl shows the bridge's consumer (manual acknowledgements, prefetch = the
    buffer); messages an aio-pika client publishes arrive on the fabric, and one whose
    rap-cycle header is an AMQP integer is rejected and counted, and the queue drains."""
    queue_name = unique("robot.cmd")
    async with MemoryFabric() as fabric, anyio.create_task_group() as tg:
        side = FabricSide(fabric)
        await tg.start(side.record)
        b = bridge("from-rabbit", spec(rabbit, queue_name, buffer=7), fabric, "in")
        await tg.start(b.run)
        with anyio.fail_after(10):
            await b.wait_connected()
        text = await rabbit.ctl(
            "list_consumers", "-q", "--formatter", "json", "queue_name", "ack_required",
            "prefetch_count",
        )  # fmt: skip
        consumers = [c for c in msgspec.json.decode(text) if c["queue_name"] == queue_name]
        assert consumers == [{"queue_name": queue_name, "ack_required": True, "prefetch_count": 7}]
        channel = await client.channel()
        publish = channel.default_exchange.publish
        await publish(aio_pika.Message(b'{"n": 1}', headers={"rap-cycle": CYCLE.hex()}), queue_name)
        await publish(aio_pika.Message(b'{"n": 2}', headers={"rap-cycle": 12345}), queue_name)
        nested: HeadersType = {"other": {"table": [1, 2]}, "flag": True}
        await publish(aio_pika.Message(b'{"n": 3}', headers=nested), queue_name)
        await side.wait_for(2)
        await until(lambda: b.stats.rejected == 1)
        await until(lambda: b.stats.received == 3)
        queues = await rabbit.list_queues()
        tg.cancel_scope.cancel()
    assert side.readings() == [1, 3]
    assert side.got[0].cycle == CYCLE
    assert "rap-cycle" in " | ".join(b.stats.rejections.by_reason)
    assert queues[queue_name]["durable"] is True
    assert queues[queue_name]["messages"] == 0  # all three acknowledged


async def test_a_user_and_its_password_and_what_a_wrong_one_says(
    rabbit: RabbitNode, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    user, locked = unique("robot"), unique("nobody")
    await rabbit.ctl("add_user", user, "robot-pw-1")
    await rabbit.ctl("set_permissions", "-p", "/", user, ".*", ".*", ".*")
    await rabbit.ctl("add_user", locked, "nobody-pw-1")  # no permissions on any vhost
    password = tmp_path / "robot.pw"
    password.write_text("robot-pw-1\n", encoding="utf-8")
    queue_name = unique("robot.auth")
    good = spec(rabbit, queue_name, username=user, password_file=str(password))
    async with MemoryFabric() as fabric, anyio.create_task_group() as tg:
        b = bridge("with-user", good, fabric, "out")
        await tg.start(b.run)
        with anyio.fail_after(10):
            await b.wait_connected()
        await FabricSide(fabric).publish(1)
        await until(lambda: b.stats.sent == 1)
        text = await rabbit.ctl(
            "list_connections", "-q", "--formatter", "json", "user", "client_properties"
        )
        tg.cancel_scope.cancel()
    assert (await rabbit.list_queues())[queue_name]["messages"] == 1
    users = [c["user"] for c in msgspec.json.decode(text)]
    assert user in users

    monkeypatch.setenv("RAP_TEST_AMQP_PW", "not-the-password")
    wrong = await refused(spec(rabbit, queue_name, username=user, password_env="RAP_TEST_AMQP_PW"))
    assert "cannot connect" in wrong.reason
    assert "password_env / password_file" in wrong.fix
    assert f"rabbitmqctl authenticate_user {user}" in wrong.fix

    monkeypatch.setenv("RAP_TEST_AMQP_PW", "nobody-pw-1")
    no_vhost = await refused(
        spec(rabbit, queue_name, username=locked, password_env="RAP_TEST_AMQP_PW")
    )
    assert "refused access to virtual host /" in no_vhost.reason
    assert no_vhost.fix == (
        f"give the user access to the virtual host: rabbitmqctl set_permissions -p / {locked} "
        "'.*' '.*' '.*'"
    )

    await rabbit.ctl("set_permissions", "-p", "/", locked, "^$", ".*", ".*")  # configure none
    no_configure = await refused(
        spec(rabbit, unique("robot.new"), username=locked, password_env="RAP_TEST_AMQP_PW")
    )
    assert "ACCESS_REFUSED" in no_configure.reason
    assert no_configure.fix.startswith("the user may not configure, write or read")

    monkeypatch.delenv("RAP_TEST_AMQP_PW")
    unset = await refused(spec(rabbit, queue_name, username=user, password_env="RAP_TEST_AMQP_PW"))
    assert unset.reason == "AMQP password: $RAP_TEST_AMQP_PW is not set"
    assert unset.fix == "export RAP_TEST_AMQP_PW before starting the bridge"


async def test_tls_with_a_client_certificate_and_what_a_wrong_ca_says(
    rabbit: RabbitNode, client: AbstractConnection, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    certs = rabbit.certs
    queue_name = unique("robot.tls")
    monkeypatch.setenv("RAP_TEST_AMQP_GUEST", "guest")
    tls = BridgeSpec(
        protocol="amqp",
        url=f"amqps://127.0.0.1:{rabbit.tls_port}",
        address=queue_name,
        format="json",
        username="guest",
        password_env="RAP_TEST_AMQP_GUEST",
        ca=str(certs / "ca.pem"),
        cert=str(certs / "client.pem"),
        key=str(certs / "client.key"),
    )
    async with MemoryFabric() as fabric, anyio.create_task_group() as tg:
        b = bridge("over-tls", tls, fabric, "out")
        await tg.start(b.run)
        with anyio.fail_after(10):
            await b.wait_connected()
        await FabricSide(fabric).publish(5)
        await until(lambda: b.stats.sent == 1)
        tg.cancel_scope.cancel()
    channel = await client.channel()  # a plain client on the plain port reads it
    queue = await channel.declare_queue(queue_name, passive=True)
    message = await queue.get(no_ack=True, timeout=5)
    assert msgspec.json.decode(message.body) == {"n": 5, "note": ""}

    other = make_certs(tmp_path / "other", {"client": ""}, system="other")
    wrong = await refused(msgspec.structs.replace(tls, ca=str(other / "ca.pem")))
    assert "certificate" in wrong.reason.lower()
    assert wrong.fix == "check ca, cert and key, and that the broker's certificate names its host"


async def test_exchanges_bind_route_and_refuse_what_no_queue_takes(
    rabbit: RabbitNode, client: AbstractConnection
) -> None:
    """in: the bridge binds its queue to the exchange, and what an aio-pika client
    publishes there arrives; out: a queue the client bound gets the bridge's messages,
    a routing key no queue is bound for is rejected and counted, and a missing exchange
    is refused with what to do."""
    routed, bound = unique("robot.in"), unique("robot.out")
    channel = await client.channel()
    exchange = await channel.get_exchange("amq.direct")
    theirs = await channel.declare_queue(bound, durable=True)
    await theirs.bind(exchange, routing_key=bound)
    async with (
        MemoryFabric() as fabric_in,
        MemoryFabric() as fabric_out,
        anyio.create_task_group() as tg,
    ):
        side = FabricSide(fabric_in)
        await tg.start(side.record)
        inb = bridge("in-x", spec(rabbit, routed, exchange="amq.direct"), fabric_in, "in")
        out = bridge("out-x", spec(rabbit, bound, exchange="amq.direct"), fabric_out, "out")
        await tg.start(inb.run)
        await tg.start(out.run)
        with anyio.fail_after(10):
            await inb.wait_connected()
            await out.wait_connected()
        await exchange.publish(aio_pika.Message(b'{"n": 9}'), routing_key=routed)
        await side.wait_for(1)
        await FabricSide(fabric_out).publish(10)
        await until(lambda: out.stats.sent == 1)
        tg.cancel_scope.cancel()
    assert side.readings() == [9]
    message = await theirs.get(no_ack=True, timeout=5)
    assert msgspec.json.decode(message.body) == {"n": 10, "note": ""}

    probe, _ = link(spec(rabbit, unique("nobody.listens"), exchange="amq.direct"))
    await probe.open()
    try:  # refused: the bridge counts it as rejected, not as sent
        with pytest.raises(FrameRefused, match=r"no queue is bound to exchange 'amq\.direct'"):
            await probe.send(Frame(msgspec.json.encode(Reading(n=1))))
    finally:
        await probe.close()

    missing = await refused(spec(rabbit, routed, exchange="no-such-exchange"))
    assert missing.reason == "exchange 'no-such-exchange' does not exist"
    assert "rabbitmqadmin declare exchange name=no-such-exchange" in missing.fix


async def test_qos_0_is_transient_and_unconfirmed_out_and_acknowledged_on_arrival_in(
    rabbit: RabbitNode, client: AbstractConnection
) -> None:
    first, second = unique("robot.q0"), unique("robot.q0")
    channel = await client.channel()
    queue = await channel.declare_queue(first, durable=True)
    got: list[AbstractIncomingMessage] = []
    arrived = anyio.Event()

    async def on_message(message: AbstractIncomingMessage) -> None:
        got.append(message)
        arrived.set()

    await queue.consume(on_message, no_ack=True)
    async with (
        MemoryFabric() as fabric_out,
        MemoryFabric() as fabric_in,
        anyio.create_task_group() as tg,
    ):
        side = FabricSide(fabric_in)
        await tg.start(side.record)
        out = bridge("q0-out", spec(rabbit, first, qos=0), fabric_out, "out")
        inb = bridge("q0-in", spec(rabbit, second, qos=0), fabric_in, "in")
        await tg.start(out.run)
        await tg.start(inb.run)
        with anyio.fail_after(10):
            await out.wait_connected()
            await inb.wait_connected()
        await FabricSide(fabric_out).publish(1)
        with anyio.fail_after(10):
            await arrived.wait()
        await channel.default_exchange.publish(aio_pika.Message(b'{"n": 2}'), second)
        await side.wait_for(1)
        tg.cancel_scope.cancel()
    assert got[0].delivery_mode == aio_pika.DeliveryMode.NOT_PERSISTENT
    assert msgspec.json.decode(got[0].body) == {"n": 1, "note": ""}
    assert side.readings() == [2]
    assert (await rabbit.list_queues())[second]["messages"] == 0


async def test_a_queue_deleted_under_a_bridge_is_declared_again(
    rabbit: RabbitNode, client: AbstractConnection
) -> None:
    """in: the broker cancels the consumer of a deleted queue; out: it returns what is
    published to it. Either way the bridge reconnects, declares the queue again, and
    nothing the fabric sent afterwards is lost."""
    inq, outq = unique("robot.gone-in"), unique("robot.gone-out")
    channel = await client.channel()
    async with (
        MemoryFabric() as fabric_in,
        MemoryFabric() as fabric_out,
        anyio.create_task_group() as tg,
    ):
        side = FabricSide(fabric_in)
        await tg.start(side.record)
        inb = bridge("gone-in", spec(rabbit, inq), fabric_in, "in")
        out = bridge("gone-out", spec(rabbit, outq), fabric_out, "out")
        await tg.start(inb.run)
        await tg.start(out.run)
        with anyio.fail_after(10):
            await inb.wait_connected()
            await out.wait_connected()
        await channel.queue_delete(inq)
        await channel.queue_delete(outq)
        with anyio.fail_after(10):
            await inb.wait_connects(2)
        await channel.default_exchange.publish(aio_pika.Message(b'{"n": 1}'), inq)
        await side.wait_for(1)
        await FabricSide(fabric_out).publish(2)  # returned: reconnect, declare, resend
        with anyio.fail_after(10):
            await out.wait_connects(2)
        await until(lambda: out.stats.sent == 1)
        tg.cancel_scope.cancel()
    assert side.readings() == [1]
    queue = await channel.declare_queue(outq, passive=True)
    message = await queue.get(no_ack=True, timeout=5)
    assert msgspec.json.decode(message.body) == {"n": 2, "note": ""}
    assert (inb.stats.disconnects, out.stats.disconnects) == (1, 1)


@pytest.mark.parametrize(
    ("kw", "direction", "says"),
    [
        ({"address": "x" * 256}, "out", "an amqp address is at most 255 bytes"),
        ({"address": "q", "exchange": "é" * 128}, "out", "an amqp exchange is at most 255"),
        ({"address": "amq.mine"}, "in", "queue names starting with 'amq.' are the broker's"),
    ],
)
def test_names_amqp_cannot_carry_are_refused_when_the_bridge_is_built(
    kw: dict[str, Any], direction: Direction, says: str
) -> None:
    s = BridgeSpec(protocol="amqp", url="amqp://127.0.0.1:5672", format="json", **kw)
    with pytest.raises(ValueError, match=says):
        link(s, direction)
    routing_key = BridgeSpec(
        protocol="amqp", url="amqp://127.0.0.1:5672", address="amq.ok", exchange="robots"
    )
    link(routing_key, "out")  # a routing key may start with amq.
