"""The Redis bridges with the client no one here wrote: redis-cli (SUBSCRIBE, PUBLISH,
XADD, XRANGE, XREADGROUP, XPENDING), on redis-servers of the tests' own, with ACL users,
a bare requirepass, TLS with client certificates, and no blocking call on the event
loop."""

from __future__ import annotations

import json
import os
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import anyio
import msgspec
import pytest
from anyio.abc import Process
from blockbuster import blockbuster_ctx
from rap_bridges import Bridge, BridgeSpec, Frame, LinkContext, LinkDown
from rap_bridges.redis import BadMessage, RedisLink, RedisStreamLink, unwrap, wrap
from rap_schemas import Envelope, keys
from rap_sdk import InboxPolicy, MemoryFabric, Overflow
from rap_sdk.fabric import Fabric
from rap_sdk.testing import require_binary

from libs.rap_bridges.tests.contract import (
    KEY,
    SYSTEM,
    FabricSide,
    Reading,
    fast_backoff,
    until,
)
from libs.rap_bridges.tests.outside_redis import RedisServer
from libs.rap_bridges.tests.outside_redis import require_server as require_redis_server
from libs.rap_sdk.tests.certs_support import make_certs

pytestmark = [pytest.mark.anyio]

CYCLE = bytes(range(16))
CAUSE = bytes(range(16, 32))
CHANNEL = "robot.reading"
STREAM = "robot.readings"
BACK = keys.data(SYSTEM, "back")


@pytest.fixture
def cli() -> str:
    require_redis_server()
    return require_binary("redis-cli", hint="apt-get install redis-tools")


@asynccontextmanager
async def running(server: RedisServer) -> AsyncIterator[RedisServer]:
    await server.start()
    try:
        yield server
    finally:
        await server.stop()


async def run_cli(cli: str, port: int, *args: str, env: dict[str, str] | None = None) -> str:
    """redis-cli's answer to one command (its text output, stripped)."""
    with anyio.fail_after(10):
        done = await anyio.run_process(
            [cli, "-h", "127.0.0.1", "-p", str(port), *args],
            env={**os.environ, **(env or {})},
        )
    return done.stdout.decode().strip()


def make_bridge(
    fabric: Fabric, name: str, spec: BridgeSpec, direction: str, key: str = KEY
) -> Bridge:
    return Bridge(
        name,
        spec,
        fabric,
        key,
        direction=direction,  # type: ignore[arg-type]
        message=Reading,
        backoff=fast_backoff(),
    )


async def pending(cli: str, port: int, group: str) -> int:
    """How many entries ``group`` was given and has not acknowledged (XPENDING)."""
    return int((await run_cli(cli, port, "XPENDING", STREAM, group)).split()[0])


async def all_acknowledged(cli: str, port: int, group: str) -> None:
    """Wait until ``group`` has acknowledged everything it was given (polled: the last
    XACK may be on its way, and Redis tells no one)."""
    with anyio.fail_after(10):
        for _ in range(1000):
            if await pending(cli, port, group) == 0:
                return
            await anyio.sleep(0.01)
    raise AssertionError(f"group {group} still has entries it did not acknowledge")


class Lines:
    """The lines a process writes, as they come."""

    def __init__(self, proc: Process) -> None:
        assert proc.stdout is not None
        self._stdout = proc.stdout
        self._buffer = b""

    async def next(self) -> str:
        while b"\n" not in self._buffer:
            self._buffer += await self._stdout.receive()
        line, self._buffer = self._buffer.split(b"\n", 1)
        return line.decode()

    async def take(self, n: int) -> list[str]:
        return [await self.next() for _ in range(n)]


def link(cls: Any, name: str, direction: str, **kw: Any) -> Any:
    ctx = LinkContext(name=name, direction=direction, reject=lambda _r: None)  # type: ignore[arg-type]
    return cls(BridgeSpec(**kw), ctx)


# -- pub/sub ---------------------------------------------------------------------------


async def test_redis_cli_subscribe_reads_what_an_out_bridge_publishes(
    cli: str, tmp_path: Path
) -> None:
    async with running(RedisServer(tmp_path)) as server:
        sub = await anyio.open_process([cli, "-p", str(server.port), "SUBSCRIBE", CHANNEL])
        try:
            lines = Lines(sub)
            with anyio.fail_after(10):
                assert await lines.take(3) == ["subscribe", CHANNEL, "1"]
            async with MemoryFabric() as fabric, anyio.create_task_group() as tg:
                spec = BridgeSpec(
                    protocol="redis",
                    url=f"redis://127.0.0.1:{server.port}",
                    address=CHANNEL,
                    format="json",
                )
                b = make_bridge(fabric, "pub-out", spec, "out")
                await tg.start(b.run)
                side = FabricSide(fabric)
                await side.publish(1, cycle=CYCLE, cause=CAUSE)
                await side.publish(2)
                with anyio.fail_after(10):
                    got = await lines.take(6)
                tg.cancel_scope.cancel()
        finally:
            sub.kill()
            await sub.aclose()
    assert got[0::3] == ["message", "message"]
    assert got[1::3] == [CHANNEL, CHANNEL]
    first, second = (json.loads(m) for m in got[2::3])
    assert first["payload"] == {"n": 1, "note": ""}
    assert first["headers"]["rap-cycle"] == CYCLE.hex()
    assert first["headers"]["rap-cause"] == CAUSE.hex()
    assert first["headers"]["rap-type"] == "test.Reading/1"
    assert second["payload"] == {"n": 2, "note": ""}
    assert "rap-cycle" not in second["headers"]
    assert b.stats.sent == 2


async def test_redis_cli_publish_feeds_an_in_bridge_plain_or_wrapped(
    cli: str, tmp_path: Path
) -> None:
    async with (
        running(RedisServer(tmp_path)) as server,
        MemoryFabric() as fabric,
        anyio.create_task_group() as tg,
    ):
        side = FabricSide(fabric)
        await tg.start(side.record)
        url = f"redis://127.0.0.1:{server.port}"
        spec = BridgeSpec(protocol="redis", url=url, address=CHANNEL, format="json", qos=0)
        b = make_bridge(fabric, "pub-in", spec, "in")
        await tg.start(b.run)
        with anyio.fail_after(10):
            await b.wait_connected()
        wrapped = json.dumps({"headers": {"rap-cycle": CYCLE.hex()}, "payload": {"n": 2}})
        bad_headers = json.dumps({"headers": {"rap-cycle": 5}, "payload": {"n": 9}})
        # the answer is the number of subscribers that got it: the bridge is one
        assert await run_cli(cli, server.port, "PUBLISH", CHANNEL, '{"n": 1}') == "1"
        await run_cli(cli, server.port, "PUBLISH", CHANNEL, wrapped)
        await run_cli(cli, server.port, "PUBLISH", CHANNEL, "not json")
        await run_cli(cli, server.port, "PUBLISH", CHANNEL, bad_headers)
        await run_cli(cli, server.port, "PUBLISH", CHANNEL, '{"n": 3, "note": "x"}')
        await side.wait_for(3)
        tg.cancel_scope.cancel()
    assert side.readings() == [1, 2, 3]
    assert [e.cycle for e in side.got] == [None, CYCLE, None]
    assert side.got[0].source == "pub-in"
    assert b.stats.rejected == 2
    reasons = " | ".join(b.stats.rejections.by_reason)
    assert "test.Reading/N JSON" in reasons
    assert "headers must map strings to strings" in reasons


async def test_an_in_bridge_on_a_pattern_takes_every_matching_channel(
    cli: str, tmp_path: Path
) -> None:
    async with (
        running(RedisServer(tmp_path)) as server,
        MemoryFabric() as fabric,
        anyio.create_task_group() as tg,
    ):
        side = FabricSide(fabric)
        await tg.start(side.record)
        url = f"redis://127.0.0.1:{server.port}"
        spec = BridgeSpec(protocol="redis", url=url, address="robot.*", format="json", qos=0)
        b = make_bridge(fabric, "pattern-in", spec, "in")
        await tg.start(b.run)
        with anyio.fail_after(10):
            await b.wait_connected()
        await run_cli(cli, server.port, "PUBLISH", "robot.left", '{"n": 1}')
        await run_cli(cli, server.port, "PUBLISH", "other.left", '{"n": 2}')
        await run_cli(cli, server.port, "PUBLISH", "robot.right", '{"n": 3}')
        await side.wait_for(2)
        tg.cancel_scope.cancel()
    assert side.readings() == [1, 3]


def test_settings_a_link_cannot_honour_are_refused() -> None:
    """An in bridge on pub/sub cannot be at least once, an out bridge needs one channel;
    maxlen is for the stream's writer, group for its reader."""
    url = "redis://127.0.0.1:6379"

    def refused(cls: Any, direction: str, match: str, **kw: Any) -> None:
        with pytest.raises(ValueError, match=match):
            link(cls, "b", direction, url=url, **kw)

    refused(RedisLink, "in", "use protocol: redis-stream", protocol="redis", address="cmd")
    refused(RedisLink, "out", "is a pattern", protocol="redis", address="robot.*")
    stream = {"protocol": "redis-stream", "address": "s"}
    refused(RedisStreamLink, "in", "remove maxlen", maxlen=10, **stream)
    refused(RedisStreamLink, "out", "remove group", group="g", **stream)
    assert link(RedisLink, "b", "in", url=url, protocol="redis", address="cmd", qos=0)


def test_the_wrapped_form_in_json_and_msgpack() -> None:
    """What docs/bridges/redis.md says a wrapped pub/sub message is, read with the
    standard library's json and msgspec's generic msgpack decoder; and plain messages,
    or maps that merely look alike, taken as they are."""
    headers = {"rap-type": "test.Reading/1", "rap-cycle": CYCLE.hex()}
    body = {"n": 4, "note": ""}
    as_json = wrap(Frame(json.dumps(body).encode(), headers), "json")
    assert json.loads(as_json) == {"headers": headers, "payload": body}
    as_msgpack = wrap(Frame(msgspec.msgpack.encode(body), headers), "raw")
    assert msgspec.msgpack.decode(as_msgpack) == {"headers": headers, "payload": body}
    for data, fmt in ((as_json, "json"), (as_msgpack, "raw")):
        frame = unwrap(data, fmt)
        assert frame.headers == headers
        assert (json.loads if fmt == "json" else msgspec.msgpack.decode)(frame.payload) == body
    for plain in (b'{"n": 1}', b'{"headers": {}, "payload": {}, "n": 1}', b"[" * 100_000):
        assert unwrap(plain, "json") == Frame(plain)
    with pytest.raises(BadMessage, match="headers must map strings to strings"):
        unwrap(b'{"headers": ["rap-cycle"], "payload": {"n": 1}}', "json")
    assert wrap(Frame(b"\x81", headers), "envelope") == b"\x81"


# -- streams ---------------------------------------------------------------------------


async def test_redis_cli_xrange_shows_what_an_out_stream_bridge_added(
    cli: str, tmp_path: Path
) -> None:
    async with (
        running(RedisServer(tmp_path)) as server,
        MemoryFabric() as fabric,
        anyio.create_task_group() as tg,
    ):
        url = f"redis://127.0.0.1:{server.port}"
        spec = BridgeSpec(protocol="redis-stream", url=url, address=STREAM, format="json")
        b = make_bridge(fabric, "stream-out", spec, "out")
        await tg.start(b.run)
        side = FabricSide(fabric)
        await side.publish(1, cycle=CYCLE)
        await side.publish(2)
        await until(lambda: b.stats.sent == 2)
        entries = json.loads(await run_cli(cli, server.port, "--json", "XRANGE", STREAM, "-", "+"))
        tg.cancel_scope.cancel()
    fields = [dict(zip(e[1][0::2], e[1][1::2], strict=True)) for e in entries]
    assert [json.loads(f["payload"]) for f in fields] == [
        {"n": 1, "note": ""},
        {"n": 2, "note": ""},
    ]
    assert fields[0]["rap-cycle"] == CYCLE.hex()
    assert fields[0]["rap-type"] == "test.Reading/1"
    assert fields[0]["rap-source"] == "contract-test"
    assert "rap-cycle" not in fields[1]


async def test_maxlen_trims_the_stream(cli: str, tmp_path: Path) -> None:
    """``maxlen`` 10: about ten entries stay (``MAXLEN ~`` trims whole nodes of up to
    100 entries, so at most 10 + 100), out of 300 added."""
    async with (
        running(RedisServer(tmp_path)) as server,
        MemoryFabric() as fabric,
        anyio.create_task_group() as tg,
    ):
        url = f"redis://127.0.0.1:{server.port}"
        spec = BridgeSpec(protocol="redis-stream", url=url, address=STREAM, maxlen=10)
        b = make_bridge(fabric, "trimmed", spec, "out")
        await tg.start(b.run)
        side = FabricSide(fabric)
        for n in range(300):
            await side.publish(n)
        await until(lambda: b.stats.sent == 300)
        length = int(await run_cli(cli, server.port, "XLEN", STREAM))
        tg.cancel_scope.cancel()
    assert 10 <= length <= 110


async def test_redis_cli_xadd_feeds_an_in_stream_bridge_which_acknowledges_each_entry(
    cli: str, tmp_path: Path
) -> None:
    async with (
        running(RedisServer(tmp_path)) as server,
        MemoryFabric() as fabric,
        anyio.create_task_group() as tg,
    ):
        side = FabricSide(fabric)
        await tg.start(side.record)
        url = f"redis://127.0.0.1:{server.port}"
        spec = BridgeSpec(
            protocol="redis-stream", url=url, address=STREAM, format="json", group="robots"
        )
        b = make_bridge(fabric, "stream-in", spec, "in")
        await tg.start(b.run)
        with anyio.fail_after(10):
            await b.wait_connected()  # the group exists (made with MKSTREAM)

        async def xadd(*fields: str) -> None:
            await run_cli(cli, server.port, "XADD", STREAM, "*", *fields)

        await xadd("payload", '{"n": 1}')
        await xadd("payload", '{"n": 2}', "rap-cycle", CYCLE.hex())
        await xadd("note", "no payload field")
        await xadd("payload", '{"n": "two"}')
        await xadd("payload", '{"n": 3}')
        await side.wait_for(3)
        await until(lambda: b.stats.rejected == 2)

        await all_acknowledged(cli, server.port, "robots")
        tg.cancel_scope.cancel()
    assert side.readings() == [1, 2, 3]
    assert side.got[1].cycle == CYCLE
    reasons = " | ".join(b.stats.rejections.by_reason)
    assert "no field 'payload'" in reasons
    assert "test.Reading/N JSON" in reasons


async def test_entries_read_but_not_acknowledged_are_read_again(cli: str, tmp_path: Path) -> None:
    """Two entries were given to the bridge's consumer (as by a bridge whose connection
    was lost before it acknowledged them): the bridge takes them first when it connects,
    then the new one, and acknowledges all."""
    async with running(RedisServer(tmp_path)) as server:
        port = server.port
        await run_cli(cli, port, "XGROUP", "CREATE", STREAM, "rap-bridge-again", "$", "MKSTREAM")
        for n in (1, 2, 3):
            await run_cli(cli, port, "XADD", STREAM, "*", "payload", json.dumps({"n": n}))
        read = ["XREADGROUP", "GROUP", "rap-bridge-again", "again", "COUNT", "2"]
        await run_cli(cli, port, *read, "STREAMS", STREAM, ">")
        assert await pending(cli, port, "rap-bridge-again") == 2
        async with MemoryFabric() as fabric, anyio.create_task_group() as tg:
            side = FabricSide(fabric)
            await tg.start(side.record)
            url = f"redis://127.0.0.1:{port}"
            spec = BridgeSpec(protocol="redis-stream", url=url, address=STREAM, format="json")
            b = make_bridge(fabric, "again", spec, "in")
            await tg.start(b.run)
            await side.wait_for(3)
            await all_acknowledged(cli, port, "rap-bridge-again")
            tg.cancel_scope.cancel()
    assert side.readings() == [1, 2, 3]


# -- credentials and TLS ---------------------------------------------------------------


async def test_acl_users_and_requirepass_and_what_is_said_when_credentials_are_wrong(
    cli: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An ACL user with only the commands and keys it needs (not even CLIENT SETNAME),
    the default user of a bare requirepass; and the fixes said when it goes wrong."""
    server = RedisServer(
        tmp_path,
        password="default-pw",
        users=["robot on >robot-pw ~robot.* &robot.* +ping +xadd +xlen +publish +subscribe"],
    )
    monkeypatch.setenv("RAP_TEST_REDIS_PASSWORD", "robot-pw")
    default_pw = tmp_path / "default.pw"
    default_pw.write_text("default-pw\n", encoding="utf-8")
    wrong_pw = tmp_path / "wrong.pw"
    wrong_pw.write_text("not-the-password\n", encoding="utf-8")
    url = f"redis://127.0.0.1:{server.port}"
    robot = {"username": "robot", "password_env": "RAP_TEST_REDIS_PASSWORD"}
    async with running(server):
        async with MemoryFabric() as fabric, anyio.create_task_group() as tg:
            out = make_bridge(
                fabric,
                "acl-out",
                BridgeSpec(protocol="redis-stream", url=url, address=STREAM, **robot),
                "out",
            )
            in_spec = BridgeSpec(
                protocol="redis",
                url=url,
                address=CHANNEL,
                format="json",
                qos=0,
                username="default",
                password_file=str(default_pw),
            )
            back = fabric.subscribe(BACK, InboxPolicy(capacity=10, overflow=Overflow.FIFO))
            inb = make_bridge(fabric, "requirepass-in", in_spec, "in", BACK)
            for b in (out, inb):
                await tg.start(b.run)
                with anyio.fail_after(10):
                    await b.wait_connected()
            await FabricSide(fabric).publish(5)
            await until(lambda: out.stats.sent == 1)
            auth = ["--user", "robot", "--no-auth-warning"]
            env = {"REDISCLI_AUTH": "robot-pw"}
            assert await run_cli(cli, server.port, *auth, "XLEN", STREAM, env=env) == "1"
            await run_cli(cli, server.port, *auth, "PUBLISH", CHANNEL, '{"n": 6}', env=env)
            with anyio.fail_after(10):
                sample = await back.get()
            tg.cancel_scope.cancel()

        wrong = link(
            RedisStreamLink,
            "wrong",
            "out",
            protocol="redis-stream",
            url=url,
            address=STREAM,
            username="robot",
            password_file=str(wrong_pw),
        )
        with pytest.raises(LinkDown) as refused:
            await wrong.open()
        anonymous = link(RedisLink, "anon", "out", protocol="redis", url=url, address=CHANNEL)
        with pytest.raises(LinkDown) as unknown:
            await anonymous.open()
        elsewhere = link(
            RedisLink,
            "elsewhere",
            "in",
            protocol="redis",
            url=url,
            address="other.channel",
            qos=0,
            **robot,
        )
        with pytest.raises(LinkDown) as noperm:
            await elsewhere.open()
    env_in = msgspec.msgpack.decode(sample.payload, type=Envelope)
    assert msgspec.msgpack.decode(env_in.body, type=Reading).n == 6
    assert env_in.source == "requirepass-in"
    assert "WRONGPASS" in refused.value.reason or "invalid" in refused.value.reason
    assert "password_file" in refused.value.fix
    assert "Authentication required" in unknown.value.reason
    assert "requirepass the user is default" in unknown.value.fix
    assert "no permissions to access one of the channels" in noperm.value.reason
    assert "give user robot the command and channel 'other.channel'" in noperm.value.fix


async def test_tls_with_client_certificates(cli: str, tmp_path: Path) -> None:
    certs = make_certs(
        tmp_path / "certs",
        {"redis": "", "robot": ""},
        system="redis",
        hosts={"redis": ["127.0.0.1", "localhost"]},
    )
    other = make_certs(tmp_path / "other", {"x": ""}, system="other")
    server = RedisServer(tmp_path, tls=(certs / "ca.pem", certs / "redis.pem", certs / "redis.key"))
    tls = {
        "ca": str(certs / "ca.pem"),
        "cert": str(certs / "robot.pem"),
        "key": str(certs / "robot.key"),
    }
    url = f"rediss://127.0.0.1:{server.port}"
    async with running(server):
        async with MemoryFabric() as fabric, anyio.create_task_group() as tg:
            spec = BridgeSpec(
                protocol="redis-stream", url=url, address=STREAM, format="json", **tls
            )
            b = make_bridge(fabric, "tls-out", spec, "out")
            await tg.start(b.run)
            await FabricSide(fabric).publish(7)
            await until(lambda: b.stats.sent == 1)
            tls_cli = ["--tls", "--cacert", tls["ca"], "--cert", tls["cert"], "--key", tls["key"]]
            got = await run_cli(cli, server.port, *tls_cli, "--json", "XRANGE", STREAM, "-", "+")
            tg.cancel_scope.cancel()
        # the server's certificate is checked: a CA that did not sign it is refused
        stranger = link(
            RedisStreamLink,
            "s",
            "out",
            protocol="redis-stream",
            url=url,
            address=STREAM,
            ca=str(other / "ca.pem"),
            cert=tls["cert"],
            key=tls["key"],
        )
        with pytest.raises(LinkDown) as refused:
            await stranger.open()
    fields = json.loads(got)[0][1]
    assert json.loads(fields[fields.index("payload") + 1]) == {"n": 7, "note": ""}
    assert "certificate verify failed" in refused.value.reason
    assert "check ca, cert and key" in refused.value.fix


# -- the event loop --------------------------------------------------------------------


async def test_redis_bridges_make_no_blocking_call(cli: str, tmp_path: Path) -> None:
    """blockbuster turns a blocking call made on the event loop into an error: pub/sub
    and streams, both ways, while messages flow (credentials read too)."""
    server = RedisServer(tmp_path, users=["robot on >robot-pw ~* &* +@all"])
    pw = tmp_path / "robot.pw"
    pw.write_text("robot-pw\n", encoding="utf-8")
    creds = {"username": "robot", "password_file": str(pw)}
    url = f"redis://127.0.0.1:{server.port}"
    via_pubsub = keys.data(SYSTEM, "via_pubsub")
    via_stream = keys.data(SYSTEM, "via_stream")
    policy = InboxPolicy(capacity=1000, overflow=Overflow.FIFO, block=False)
    n = 50
    async with running(server):
        with blockbuster_ctx():
            async with MemoryFabric() as fabric, anyio.create_task_group() as tg:
                subs = [fabric.subscribe(k, policy) for k in (via_pubsub, via_stream)]
                ins = [
                    make_bridge(
                        fabric,
                        "nb-pub-in",
                        BridgeSpec(protocol="redis", url=url, address="nb", qos=0, **creds),
                        "in",
                        via_pubsub,
                    ),
                    make_bridge(
                        fabric,
                        "nb-stream-in",
                        BridgeSpec(protocol="redis-stream", url=url, address="nb", **creds),
                        "in",
                        via_stream,
                    ),
                ]
                outs = [
                    make_bridge(
                        fabric,
                        "nb-pub-out",
                        BridgeSpec(protocol="redis", url=url, address="nb", **creds),
                        "out",
                    ),
                    make_bridge(
                        fabric,
                        "nb-stream-out",
                        BridgeSpec(protocol="redis-stream", url=url, address="nb", **creds),
                        "out",
                    ),
                ]
                for b in (*ins, *outs):
                    await tg.start(b.run)
                    with anyio.fail_after(10):
                        await b.wait_connected()
                side = FabricSide(fabric)
                for i in range(n):
                    await side.publish(i)
                with anyio.fail_after(20):
                    for sub in subs:
                        for _ in range(n):
                            await sub.get()
                tg.cancel_scope.cancel()
    assert [b.stats.published for b in ins] == [n, n]
    assert [b.stats.rejected for b in (*ins, *outs)] == [0, 0, 0, 0]
