"""The checker on Redis pub/sub, end to end through a redis-server each test starts on a
free port. Inputs are published with ``redis-cli PUBLISH`` (a client none of us wrote);
what the checker publishes is read back with redis.asyncio. The server is killed and
started again under a running checker; it asks for a password, an ACL user, a client
certificate; and a spec update that no operator signed is refused."""

from __future__ import annotations

import json
import logging
import os
import signal
import ssl
import subprocess
import sys
from collections.abc import AsyncIterator, Sequence
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import anyio
import msgspec
import pytest
from anyio.streams.text import TextReceiveStream
from rap_schemas.admin import AuditRecord
from rap_sdk.errors import ConfigError
from rap_sdk.identity import load_signer, load_verifier
from rap_sdk.testing import require_binary
from redis.asyncio import Redis
from redis.asyncio.client import PubSub
from trust_checker.config import ChannelMap, RedisConfig, ServiceConfig
from trust_checker.io.auth import signed_update
from trust_checker.io.codec import MAX_PAYLOAD
from trust_checker.io.redis import RedisTransport, redis_credentials
from trust_checker.io.specs import load_text
from trust_checker.service import TrustService, open_service

from libs.rap_sdk.tests.certs_support import make_certs
from services.trust_checker.tests.io_support import (
    BrokerTls,
    FakeRunner,
    FakeSpec,
    RedisServer,
    fake_loader,
    redis_server,
)

pytestmark = [pytest.mark.anyio, pytest.mark.redis]

LOGGER = "trust_checker.io.redis"
CHECKER_COMMANDS = "+subscribe +psubscribe +unsubscribe +punsubscribe +publish +ping"


@pytest.fixture(autouse=True)
def _no_identities_from_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    """Whether a checker has identities is each test's choice, not the shell's."""
    monkeypatch.delenv("RAP_CERTS", raising=False)


@dataclass
class Pki:
    """RAP's identities (an operator, a process), and a TLS CA with a server's and a
    client's certificates."""

    rap: Path
    tls: Path

    def server_tls(self) -> BrokerTls:
        return BrokerTls(self.tls / "ca.pem", self.tls / "server.pem", self.tls / "server.key")


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Pki:
    base = tmp_path_factory.mktemp("pki")
    rap = make_certs(base / "rap", {"alice": "operator", "robot.trust-lidar": "process"})
    tls = make_certs(
        base / "tls",
        {"server": "", "checker": ""},
        system="redis",
        hosts={"server": ["127.0.0.1"]},
    )
    return Pki(rap, tls)


# -- the other side: redis-cli publishes, redis.asyncio listens ----------------------------


async def cli(
    server: RedisServer, *args: str, user: str = "", password: str = "", tls: Pki | None = None
) -> str:
    """What ``redis-cli ARGS`` against ``server`` prints (stdout, then stderr), stripped.
    The password goes in ``REDISCLI_AUTH``, never on the command line."""
    binary = require_binary("redis-cli", hint="apt-get install redis-tools")
    command = [binary, "-h", "127.0.0.1", "-p", str(server.port), "--no-auth-warning"]
    if user:
        command += ["--user", user]
    if tls is not None:
        command += ["--tls", "--cacert", str(tls.tls / "ca.pem")]
        command += ["--cert", str(tls.tls / "checker.pem"), "--key", str(tls.tls / "checker.key")]
    env = {k: v for k, v in os.environ.items() if k != "REDISCLI_AUTH"}
    if password:
        env["REDISCLI_AUTH"] = password
    res = await anyio.run_process([*command, *args], check=False, env=env)
    return (res.stdout + res.stderr).decode("utf-8", "replace").strip()


@dataclass
class Peer:
    """Collects what the checker publishes on the channels it listens to."""

    client: Redis
    pubsub: PubSub
    got: list[tuple[str, Any]] = field(default_factory=list)
    changed: anyio.Event = field(default_factory=anyio.Event)
    taken: dict[str, int] = field(default_factory=dict)

    async def collect(self) -> None:
        while True:
            message = await self.pubsub.get_message(ignore_subscribe_messages=True, timeout=None)
            if message is None or message["type"] != "message":
                continue
            self.got.append((message["channel"].decode(), json.loads(message["data"])))
            self.changed.set()

    async def wait(self, n: int, timeout: float = 5.0) -> list[tuple[str, Any]]:
        with anyio.fail_after(timeout):
            while len(self.got) < n:
                self.changed = anyio.Event()
                await self.changed.wait()
        return self.got

    async def next_on(self, channel: str, timeout: float = 5.0) -> Any:
        """The first message on ``channel`` that no call of this returned yet (one that
        came before the call included: redis-cli may end after the answer came)."""
        seen = self.taken.get(channel, 0)
        with anyio.fail_after(timeout):
            while len(self.on(channel)) <= seen:
                self.changed = anyio.Event()
                await self.changed.wait()
        self.taken[channel] = seen + 1
        return self.on(channel)[seen]

    def on(self, channel: str) -> list[Any]:
        return [p for c, p in self.got if c == channel]


@asynccontextmanager
async def peer(url: str, listen: Sequence[str], **kw: Any) -> AsyncIterator[Peer]:
    """A redis.asyncio client subscribed to ``listen`` (in place on entry)."""
    client = Redis.from_url(url, socket_timeout=5.0, **kw)
    pubsub = client.pubsub()
    try:
        if listen:
            await pubsub.subscribe(*listen)
            confirmed = 0
            with anyio.fail_after(5):
                while confirmed < len(listen):
                    message = await pubsub.get_message(timeout=5.0)
                    confirmed += message is not None and message["type"] == "subscribe"
        p = Peer(client, pubsub)
        async with anyio.create_task_group() as tg:
            tg.start_soon(p.collect)
            try:
                yield p
            finally:
                tg.cancel_scope.cancel()
    finally:
        await pubsub.aclose()
        await client.aclose()


@asynccontextmanager
async def checker(
    tmp_path: Path,
    runner: Any,
    *,
    config: dict[str, Any] | None = None,
    listen: Sequence[str] = (),
    verifier: Any = None,
    loader: Any = fake_loader,
) -> AsyncIterator[tuple[TrustService, RedisTransport, Peer, RedisServer]]:
    async with redis_server(tmp_path) as server:
        cfg = RedisConfig(url=server.url, timeout=5.0, **(config or {}))
        async with (
            open_service(
                ServiceConfig(redis=cfg), runner, loader=loader, verifier=verifier
            ) as service,
            peer(server.url, listen) as p,
        ):
            assert service.redis is not None
            yield service, service.redis, p, server


def audits(caplog: pytest.LogCaptureFixture) -> list[AuditRecord]:
    return [
        msgspec.json.decode(r.getMessage(), type=AuditRecord)
        for r in caplog.records
        if r.name == "rap.audit"
    ]


# -- inputs and outputs ----------------------------------------------------------------------


async def test_redis_cli_inputs_give_outputs_and_verdicts_on_channels_and_a_stream(
    tmp_path: Path,
) -> None:
    spec = load_text("in latency: Float\nout ok: Bool\nok = latency < 2.0\n", "lat.dsrv")
    cfg = {"verdict_stream": "trust:verdicts"}
    listen = ("ok", "trust/verdicts")
    async with checker(tmp_path, spec, config=cfg, listen=listen, loader=load_text) as (
        service,
        transport,
        peer,
        server,
    ):
        assert await cli(server, "PUBLISH", "latency", "1.5") == "1"  # the checker reads it
        assert await cli(server, "PUBLISH", "latency", '{"Float": 2.7}') == "1"
        await peer.wait(3)
        entries = await peer.client.xrange("trust:verdicts")
        assert await cli(server, "XLEN", "trust:verdicts") == "1"
    assert peer.on("ok") == [{"value": True}, {"value": False}]
    (verdict,) = peer.on("trust/verdicts")
    assert (verdict["stream"], verdict["tick"], verdict["value"]) == ("ok", 1, False)
    assert verdict["expr"] == "latency < 2.0"
    ((_id, fields),) = entries
    assert json.loads(fields[b"verdict"]) == verdict
    assert (transport.stats.published, transport.stats.streamed) == (3, 1)
    assert transport.stats.dropped == 0
    assert service.session.stats.ticks == 2


async def test_inputs_in_all_three_forms_and_plain_outputs(tmp_path: Path) -> None:
    mon = FakeRunner(FakeSpec(("a",), ("s",)))
    async with checker(tmp_path, mon, listen=("s",)) as (_service, transport, peer, server):
        for payload in ("1", '{"Int": 2}', '{"value": 3}', '"bottom"'):
            assert await cli(server, "PUBLISH", "a", payload) == "1"
        await peer.wait(4)
    assert peer.on("s") == [
        {"value": 1},
        {"value": 3},
        {"value": 6},
        {"value": None, "deferred": True},
    ]
    assert transport.stats.published == 4


async def test_bad_payloads_are_rejected_as_on_mqtt_and_the_checker_goes_on(
    tmp_path: Path,
) -> None:
    mon = FakeRunner(FakeSpec(("a",), ("s",)))
    cfg = {"tagged": True}
    async with checker(tmp_path, mon, config=cfg, listen=("s",)) as (
        service,
        transport,
        peer,
        server,
    ):
        for payload in ("{nope", '{"Int": "seven"}', ""):
            assert await cli(server, "PUBLISH", "a", payload) == "1"
        for junk in (b'"\xff"', b" " * (MAX_PAYLOAD + 1), b"[" * 100_000):
            await peer.client.publish("a", junk)
        assert await cli(server, "PUBLISH", "a", "7") == "1"
        assert await cli(server, "PUBLISH", "a", '"bottom"') == "1"
        await peer.wait(2)
        assert service.session.stats.ticks == 2
    assert peer.on("s") == [{"Int": 7}, "Unknown"]
    rejections = transport.stats.rejections
    assert rejections.total == 6
    # the reasons the MQTT transport gives for the same payloads (test_io_mqtt.py)
    assert {
        'empty payload - send one JSON value: N, {"Int": N} or {"value": N}',
        "payload: undecodable: JSON is malformed: object keys must be strings",
        "tagged value rejected: not a tagged value: {'Int': 'seven'} - write e.g. "
        '{"Int": N}, {"Str": "a"}, "Unit" or "Unknown"',
    } <= set(rejections.by_reason)
    assert any("larger than" in r for r in rejections.by_reason)


async def test_channel_map_and_patterns_for_inputs_and_outputs(tmp_path: Path) -> None:
    mon = FakeRunner(FakeSpec(("a", "b"), ("s",)))
    cfg = {
        "channels": {
            "a": ChannelMap("robot/*/speed"),
            "b": ChannelMap("robot/b"),
            "s": ChannelMap("verdicts/s"),
        }
    }
    listen = ("verdicts/s", "s")
    async with checker(tmp_path, mon, config=cfg, listen=listen) as (_s, _t, peer, server):
        assert await cli(server, "PUBLISH", "a", "100") == "0"  # not a's channel any more
        assert await cli(server, "PUBLISH", "robot/1/speed", "1") == "1"  # the pattern
        assert await cli(server, "PUBLISH", "robot/b", '{"value": 2}') == "1"
        await peer.wait(2)
        assert await cli(server, "PUBSUB", "NUMPAT") == "1"
    assert peer.got == [("verdicts/s", {"value": 1}), ("verdicts/s", {"value": 3})]


# -- the connection: lost, refused, accepted ------------------------------------------------


async def test_reconnects_after_its_server_is_killed_and_keeps_history(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger=LOGGER)
    mon = FakeRunner(FakeSpec(("a",), ("s",)))

    async def exchange(server: RedisServer, value: str) -> Any:
        async with peer(server.url, ["s"]) as p:
            assert await cli(server, "PUBLISH", "a", value) == "1"
            return await p.next_on("s")

    first = RedisServer(tmp_path)
    config = ServiceConfig(redis=RedisConfig(url=first.url, timeout=5.0, reconnect_max=0.5))
    async with anyio.create_task_group() as tg:
        await tg.start(first.run)
        try:
            async with open_service(config, mon, loader=fake_loader) as service:
                transport = service.redis
                assert transport is not None
                assert await exchange(first, "5") == {"value": 5}
                await first.kill()  # SIGKILL: no goodbye to the clients
                async with redis_server(tmp_path, first.port) as second:
                    with anyio.fail_after(10):
                        while transport.stats.reconnects < 1:
                            await transport.connected.wait()
                    assert await exchange(second, "2") == {"value": 7}  # the history lived on
                    assert transport.stats.connects == 2
                assert service.session.stats.ticks == 2
        finally:
            with anyio.CancelScope(shield=True):
                await first.stop()
    said = [r.getMessage() for r in caplog.records if r.name == LOGGER]
    assert any("lost or refused" in m for m in said), said
    assert any("reconnected to 127.0.0.1" in m and "(reconnection 1)" in m for m in said), said


async def _never_ready(config: RedisConfig, seconds: float = 2.0) -> bool:
    """Whether a checker with ``config`` got ready within ``seconds`` (it keeps trying)."""
    runner = FakeRunner(FakeSpec(("a",), ("s",)))
    with anyio.move_on_after(seconds):
        async with open_service(ServiceConfig(redis=config), runner):
            return False
    return True


async def test_requirepass_refuses_a_wrong_password_and_takes_the_right_one(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    caplog.set_level(logging.WARNING, logger=LOGGER)
    async with redis_server(tmp_path, password="redis-pw-1") as server:
        assert "NOAUTH" in await cli(server, "PUBLISH", "a", "1")  # no password: refused
        assert "WRONGPASS" in await cli(server, "PING", password="guess")
        monkeypatch.setenv("TC_REDIS_PASSWORD", "guess")
        wrong = RedisConfig(
            url=server.url, timeout=5.0, password_env="TC_REDIS_PASSWORD", reconnect_max=0.2
        )
        assert await _never_ready(wrong)
        said = "\n".join(r.getMessage() for r in caplog.records if r.name == LOGGER)
        assert "check the user name and the password" in said
        assert "guess" not in said  # the password is never logged
        password_file = tmp_path / "redis.pw"
        password_file.write_text("redis-pw-1\n", encoding="utf-8")
        right = RedisConfig(url=server.url, timeout=5.0, password_file=str(password_file))
        runner = FakeRunner(FakeSpec(("a",), ("s",)))
        async with (
            open_service(ServiceConfig(redis=right), runner) as service,
            peer(server.url, ["s"], password="redis-pw-1") as p,
        ):
            assert await cli(server, "PUBLISH", "a", "4", password="redis-pw-1") == "1"
            assert await p.next_on("s") == {"value": 4}
            assert service.redis is not None
            assert service.redis.stats.connects == 1


async def test_an_acl_user_gets_in_and_others_do_not(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    caplog.set_level(logging.WARNING, logger=LOGGER)
    users = (
        "default off",
        # what the checker needs: pub/sub on its channels, PING; no keys, no other command
        f"checker on >checker-pw resetchannels &* -@all {CHECKER_COMMANDS}",
        f"narrow on >narrow-pw resetchannels &elsewhere/* -@all {CHECKER_COMMANDS}",
        "peer on >peer-pw ~* &* +@all",
    )
    monkeypatch.setenv("TC_CHECKER_PW", "checker-pw")
    monkeypatch.setenv("TC_NARROW_PW", "narrow-pw")
    async with redis_server(tmp_path, users=users) as server:
        assert "NOAUTH" in await cli(server, "PUBLISH", "a", "1")
        assert "WRONGPASS" in await cli(server, "PING", user="mallory", password="checker-pw")
        stranger = RedisConfig(
            url=server.url, username="mallory", password_env="TC_CHECKER_PW", reconnect_max=0.2
        )
        assert await _never_ready(stranger)
        narrow = RedisConfig(
            url=server.url, username="narrow", password_env="TC_NARROW_PW", reconnect_max=0.2
        )
        assert await _never_ready(narrow)
        said = "\n".join(r.getMessage() for r in caplog.records if r.name == LOGGER)
        assert "check the user name and the password" in said
        assert "the server's ACL does not let this user do that" in said
        cfg = RedisConfig(
            url=server.url, timeout=5.0, username="checker", password_env="TC_CHECKER_PW"
        )
        runner = FakeRunner(FakeSpec(("a",), ("s",)))
        auth = {"username": "peer", "password": "peer-pw"}
        async with (
            open_service(ServiceConfig(redis=cfg), runner) as service,
            peer(server.url, ["s"], **auth) as p,
        ):
            published = await cli(server, "PUBLISH", "a", "3", user="peer", password="peer-pw")
            assert published == "1"
            assert await p.next_on("s") == {"value": 3}
            clients = await p.client.client_list()
            assert {c["user"] for c in clients} == {"checker", "peer"}
            assert service.redis is not None
            assert service.redis.stats.dropped == 0


async def test_tls_with_a_client_certificate(tmp_path: Path, pki: Pki) -> None:
    async with redis_server(tmp_path, tls=pki.server_tls()) as server:
        url = f"rediss://127.0.0.1:{server.port}/0"
        ca = str(pki.tls / "ca.pem")
        # without a client certificate the server cuts the TLS session
        assert await _never_ready(RedisConfig(url=url, ca=ca, timeout=2.0, reconnect_max=0.2))
        cfg = RedisConfig(
            url=url,
            timeout=5.0,
            ca=ca,
            cert=str(pki.tls / "checker.pem"),
            key=str(pki.tls / "checker.key"),
        )
        runner = FakeRunner(FakeSpec(("a",), ("s",)))
        client_tls = {
            "ssl_ca_certs": ca,
            "ssl_certfile": str(pki.tls / "checker.pem"),
            "ssl_keyfile": str(pki.tls / "checker.key"),
        }
        async with (
            open_service(ServiceConfig(redis=cfg), runner) as service,
            peer(url, ["s"], **client_tls) as p,
        ):
            assert await cli(server, "PUBLISH", "a", "6", tls=pki) == "1"
            assert await p.next_on("s") == {"value": 6}  # out over TLS too
            assert service.redis is not None
            assert service.redis.stats.dropped == 0


def test_the_password_comes_from_the_environment_or_a_file(tmp_path: Path, pki: Pki) -> None:
    env_cfg = RedisConfig(password_env="TC_PW")
    assert redis_credentials(env_cfg, env={"TC_PW": "from-env"}).password == "from-env"
    with pytest.raises(ConfigError, match=r"\$TC_PW is not set - export it"):
        redis_credentials(env_cfg, env={})
    pw_file = tmp_path / "pw"
    pw_file.write_text("pw\nx\n", encoding="utf-8")
    creds = redis_credentials(RedisConfig(username="u", password_file=str(pw_file)))
    assert creds.password == "pw"  # the first line
    assert "pw" not in repr(creds)
    assert creds.tls is None
    with pytest.raises(ConfigError, match="cannot read it"):
        redis_credentials(RedisConfig(password_file=str(tmp_path / "nope")))
    with pytest.raises(ValueError, match="not both"):
        RedisConfig(password_env="A", password_file="b")
    with pytest.raises(ValueError, match="give both the certificate"):
        RedisConfig(cert="c.pem")
    tls = redis_credentials(RedisConfig(url="rediss://h:6380/1"))
    assert tls.tls is not None
    assert tls.tls.verify_mode is ssl.CERT_REQUIRED
    assert RedisConfig(url="rediss://h:6380/1").address == ("h", 6380, 1)
    assert RedisConfig(url="redis://h").address == ("h", 6379, 0)
    with pytest.raises(ConfigError, match="Redis TLS: cannot load"):
        redis_credentials(RedisConfig(ca=str(tmp_path / "missing.pem")))
    for url, message in [
        ("http://h:1", "is not a Redis URL"),
        ("redis://:secret@h:1", "holds a user name or a password"),
        ("redis://u:secret@h:1", "holds a user name or a password"),
        ("redis://h:1/zero", "is not a database number"),
        ("redis://h:99999", "Port out of range"),
        ("redis://h:1/0?password=x", "has a query or a fragment"),
    ]:
        with pytest.raises(ValueError, match=message) as caught:
            RedisConfig(url=url)
        assert "secret" not in str(caught.value)


# -- the hot swap ----------------------------------------------------------------------------

SWAP = "trust/spec"


async def test_without_identities_the_checker_takes_no_swap_over_redis(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger=LOGGER)
    mon = FakeRunner(FakeSpec(("a",), ("s",)))
    async with checker(tmp_path, mon, listen=("s",)) as (service, transport, _peer, server):
        assert transport.swaps is False
        assert await cli(server, "PUBSUB", "NUMSUB", SWAP) == f"{SWAP}\n0"
        update = json.dumps({"spec": "in c\nout t\n"})
        assert await cli(server, "PUBLISH", SWAP, update) == "0"  # no one reads it
        assert service.runner is mon
    said = [r.getMessage() for r in caplog.records if r.name == LOGGER]
    assert any("hot swap over Redis is off" in m for m in said)


async def test_only_an_operators_swap_is_taken_and_the_inputs_follow(
    tmp_path: Path, pki: Pki, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="rap.audit")
    mon = FakeRunner(FakeSpec(("a",), ("s",)))
    verifier = load_verifier(pki.rap)
    listen = ("s", "t", "trust/status")
    new = "in c\nout t\n"
    async with checker(tmp_path, mon, listen=listen, verifier=verifier) as (
        service,
        transport,
        peer,
        server,
    ):
        assert transport.swaps is True
        assert await cli(server, "PUBLISH", "a", "5") == "1"
        assert await peer.next_on("s") == {"value": 5}

        async def attempt(payload: bytes | str) -> Any:
            text = payload.decode() if isinstance(payload, bytes) else payload
            assert await cli(server, "PUBLISH", SWAP, text) == "1"
            return await peer.next_on("trust/status")

        unsigned = await attempt(json.dumps({"spec": new}))
        process = await attempt(signed_update(load_signer(pki.rap, "robot.trust-lidar"), SWAP, new))
        elsewhere = await attempt(signed_update(load_signer(pki.rap, "alice"), "trust/x", new))
        junk = await attempt("{not json")
        for status in (unsigned, process, elsewhere, junk):
            assert status["ok"] is False
            assert status["inputs"] == ["a"]
        assert unsigned["problems"][0].startswith("swap refused: unsigned request")
        assert process["problems"][0].startswith(
            "swap refused: 'robot.trust-lidar' (role process) may not swap the spec of "
            "trust_checker: that needs the role operator"
        )
        assert elsewhere["problems"][0].startswith("swap refused: bad signature: 'alice'")
        assert junk["problems"][0].startswith(f"spec update on '{SWAP}' refused: ")
        assert service.runner is mon

        update = signed_update(load_signer(pki.rap, "alice"), SWAP, new, "c.dsrv")
        ok = await attempt(update)
        assert ok["ok"] is True, ok
        assert ok["inputs"] == ["c"]
        assert await cli(server, "PUBLISH", "a", "1000") == "0"  # no longer read
        assert await cli(server, "PUBLISH", "c", "2") == "1"
        assert await peer.next_on("t") == {"value": 7}  # the total carried over
        again = await attempt(update)  # the same bytes again
        assert again["ok"] is False
        assert again["problems"][0].startswith("swap refused: replayed request")
        assert service.session.stats.swaps == 1
        by_reason = transport.stats.rejections.by_reason
        assert transport.stats.rejections.total == 5
        assert {k: n for k, n in by_reason.items() if k.startswith("swap refused")} == {
            "swap refused: unsigned": 1,
            "swap refused: not an operator": 1,
            "swap refused: bad signature": 1,
            "swap refused: replayed": 1,
        }
    rows = [(a.via, a.key, a.result, a.who) for a in audits(caplog)]
    assert rows == [
        ("redis", SWAP, "refused", "unauthenticated"),
        ("redis", SWAP, "refused", "robot.trust-lidar"),
        ("redis", SWAP, "refused", "unauthenticated"),
        ("redis", SWAP, "error", "unauthenticated"),
        ("redis", SWAP, "ok", "alice"),
        ("redis", SWAP, "refused", "alice"),
    ]


# -- the command line ------------------------------------------------------------------------

CLI_SPEC = "in x: Int\nout z: Int\nz = x + 1\n"
CLI_NEW = "in y: Int\nout w: Int\nw = y * 2\n"


def _env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("RAP_CERTS", "RAP_AS")}
    return {**env, **extra}


async def _read_until(stream: TextReceiveStream, text: str, seen: list[str]) -> None:
    async for chunk in stream:
        seen.append(chunk)
        if text in "".join(seen):
            return
    raise AssertionError(f"{text!r} never came:\n{''.join(seen)}")


async def test_the_command_line_on_an_acl_user_and_a_signed_swap(tmp_path: Path, pki: Pki) -> None:
    (tmp_path / "s.dsrv").write_text(CLI_SPEC)
    (tmp_path / "new.dsrv").write_text(CLI_NEW)
    users = ("default off", "checker on >checker-pw ~* &* +@all")
    env = _env(TC_REDIS_PW="checker-pw")
    async with redis_server(tmp_path, users=users) as server:
        creds = ["--redis-user", "checker", "--redis-password-env", "TC_REDIS_PW"]
        common = ["--redis", server.url, *creds, "--node", "trust_redis"]
        extra = ["--certs", str(pki.rap), "--tagged"]
        python = [sys.executable, "-m", "trust_checker"]
        proc = await anyio.open_process(
            [*python, str(tmp_path / "s.dsrv"), *common, *extra],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            env=env,
        )
        err: list[str] = []
        async with proc:
            assert proc.stderr is not None
            try:
                with anyio.fail_after(20):
                    await _read_until(TextReceiveStream(proc.stderr), "ready:", err)
                auth = {"username": "checker", "password": "checker-pw"}
                async with peer(server.url, ["z", "w"], **auth) as p:
                    said = await cli(
                        server, "PUBLISH", "x", "1", user="checker", password="checker-pw"
                    )
                    assert said == "1"
                    assert await p.next_on("z") == {"Int": 2}

                    def send(*args: str) -> subprocess.CompletedProcess[str]:
                        return subprocess.run(
                            [*python, str(tmp_path / "new.dsrv"), "--send-swap", *common, *args],
                            capture_output=True,
                            text=True,
                            timeout=60,
                            check=False,
                            env=env,
                        )

                    refused = await anyio.to_thread.run_sync(send)  # unsigned
                    assert refused.returncode == 1, refused.stderr
                    assert "swap refused: unsigned request" in refused.stderr
                    taken = await anyio.to_thread.run_sync(
                        send, "--as", "alice", "--certs", str(pki.rap)
                    )
                    assert taken.returncode == 0, taken.stderr
                    assert "trust_redis: swapped to new.dsrv at tick 1: inputs y" in taken.stdout
                    said = await cli(
                        server, "PUBLISH", "y", "4", user="checker", password="checker-pw"
                    )
                    assert said == "1"
                    assert await p.next_on("w") == {"Int": 8}
            finally:
                proc.send_signal(signal.SIGTERM)
                with anyio.fail_after(10):
                    err.extend([c async for c in TextReceiveStream(proc.stderr)])
                    code = await proc.wait()
        assert code == 0, "".join(err)
        assert "checker-pw" not in "".join(err)
