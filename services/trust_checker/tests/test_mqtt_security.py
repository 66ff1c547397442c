"""The checker on a locked-down MQTT broker, and the attack on its MQTT hot swap.

A mosquitto of the test's own listens with TLS only (clients must present a certificate
of the broker's CA) and a password file (no anonymous client). The checker connects with
a user name, a password from a file or an environment variable, and its certificate.
Then a peer that may use the broker but holds no operator credentials publishes a spec
that says ``stage_order_ok = true`` whatever happens: the checker, which has identities,
refuses it (unsigned, signed by a process, by another CA, for another topic, replayed),
keeps its spec, says why on the status topic and audits it; an operator's update is
taken."""

from __future__ import annotations

import json
import logging
import ssl
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import aiomqtt
import anyio
import msgspec
import pytest
from rap_schemas.admin import AuditRecord
from rap_sdk.errors import ConfigError
from rap_sdk.identity import load_signer, load_verifier
from trust_checker.config import MqttConfig, ServiceConfig
from trust_checker.io.auth import signed_update, update_body
from trust_checker.io.mqtt import mqtt_credentials
from trust_checker.io.specs import load_text
from trust_checker.service import TrustService, open_service
from trust_checker.specs import maplek_specs

from libs.rap_sdk.tests.certs_support import make_certs
from services.trust_checker.tests.io_support import (
    BrokerTls,
    FakeRunner,
    FakeSpec,
    Mosquitto,
    mosquitto,
)

pytestmark = [pytest.mark.anyio]

NODE = "trust_stage_order"
EVIL = "in stage: Str\nout stage_order_ok: Bool\nstage_order_ok = true\n"
PASSWORDS = {"checker": "checker-pw-1", "peer": "peer-pw-2"}


@dataclass
class Pki:
    """The broker's CA and its clients' certificates; RAP's identities (another CA)."""

    mqtt: Path
    rap: Path
    foreign: Path

    def broker_tls(self) -> BrokerTls:
        return BrokerTls(self.mqtt / "ca.pem", self.mqtt / "broker.pem", self.mqtt / "broker.key")

    def client_context(self, name: str | None = "peer") -> ssl.SSLContext:
        ctx = ssl.create_default_context(cafile=str(self.mqtt / "ca.pem"))
        if name is not None:
            ctx.load_cert_chain(self.mqtt / f"{name}.pem", self.mqtt / f"{name}.key")
        return ctx


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Pki:
    base = tmp_path_factory.mktemp("pki")
    mqtt = make_certs(
        base / "mqtt",
        {"broker": "", "checker": "", "peer": ""},
        system="mqtt",
        hosts={"broker": ["127.0.0.1", "localhost"]},
    )
    rap = make_certs(base / "rap", {"alice": "operator", "robot.trust-lidar": "process"})
    foreign = make_certs(base / "foreign", {"alice": "operator"}, system="elsewhere")
    return Pki(mqtt, rap, foreign)


@dataclass
class Peer:
    client: aiomqtt.Client
    got: list[tuple[str, Any]] = field(default_factory=list)
    changed: anyio.Event = field(default_factory=anyio.Event)

    async def collect(self) -> None:
        async for message in self.client.messages:
            self.got.append((message.topic.value, json.loads(bytes(message.payload))))
            self.changed.set()

    async def next_on(self, topic: str, timeout: float = 5.0) -> Any:
        """The next message on ``topic`` from now on."""
        seen = len(self.on(topic))
        with anyio.fail_after(timeout):
            while len(self.on(topic)) <= seen:
                self.changed = anyio.Event()
                await self.changed.wait()
        return self.on(topic)[seen]

    def on(self, topic: str) -> list[Any]:
        return [p for t, p in self.got if t == topic]


def checker_config(broker: Mosquitto, pki: Pki, password_file: Path, **kw: Any) -> MqttConfig:
    return MqttConfig(
        port=broker.port,
        timeout=5.0,
        username="checker",
        password_file=str(password_file),
        ca=str(pki.mqtt / "ca.pem"),
        cert=str(pki.mqtt / "checker.pem"),
        key=str(pki.mqtt / "checker.key"),
        **kw,
    )


def peer_client(broker: Mosquitto, pki: Pki, *, password: str = PASSWORDS["peer"]) -> Any:
    return aiomqtt.Client(
        "127.0.0.1",
        broker.port,
        username="peer",
        password=password,
        tls_context=pki.client_context(),
        timeout=5.0,
    )


def password_file(tmp_path: Path, text: str = PASSWORDS["checker"] + "\n") -> Path:
    path = tmp_path / "checker.pw"
    path.write_text(text, encoding="utf-8")
    path.chmod(0o600)
    return path


@asynccontextmanager
async def locked_down(
    tmp_path: Path, pki: Pki, runner: Any, *, verifier: Any = None, listen: tuple[str, ...] = ()
) -> AsyncIterator[tuple[TrustService, Peer]]:
    async with mosquitto(tmp_path, passwords=PASSWORDS, tls=pki.broker_tls()) as broker:
        cfg = checker_config(broker, pki, password_file(tmp_path))
        async with (
            open_service(
                ServiceConfig(node=NODE, verdicts=False, mqtt=cfg), runner, verifier=verifier
            ) as service,
            peer_client(broker, pki) as client,
            anyio.create_task_group() as tg,
        ):
            peer = Peer(client)
            for topic in listen:
                await client.subscribe(topic)
            tg.start_soon(peer.collect)
            try:
                yield service, peer
            finally:
                tg.cancel_scope.cancel()


# an MQTT 3.1.1 CONNECT: client id "t", user "peer" and its password, clean session
_CONNECT = (
    b"\x10"
    + bytes([10 + 3 + 6 + 2 + len(PASSWORDS["peer"])])
    + b"\x00\x04MQTT\x04\xc2\x00\x3c\x00\x01t\x00\x04peer"
    + len(PASSWORDS["peer"]).to_bytes(2, "big")
    + PASSWORDS["peer"].encode()
)


async def _connect_raw(port: int, context: ssl.SSLContext) -> str:
    """Open a TLS connection by hand (no MQTT library: its socket callbacks race with
    a connection the broker cuts), send CONNECT, and say what came back: the answer's
    first bytes in hex (``20020000``: CONNACK, accepted), or how the connection ended."""
    try:
        stream = await anyio.connect_tcp(
            "127.0.0.1", port, tls=True, ssl_context=context, tls_hostname="127.0.0.1"
        )
    except (OSError, anyio.BrokenResourceError) as exc:
        return f"{type(exc).__name__}: {exc}"
    try:
        with anyio.fail_after(5):
            await stream.send(_CONNECT)
            data = await stream.receive()
    except (OSError, anyio.BrokenResourceError, anyio.EndOfStream) as exc:
        return f"{type(exc).__name__}: {exc!r} {exc.__cause__!r}"
    finally:
        await anyio.aclose_forcefully(stream)  # no TLS close_notify on a cut connection
    return f"answered: {data[:4].hex()}"


def audits(caplog: pytest.LogCaptureFixture) -> list[AuditRecord]:
    return [
        msgspec.json.decode(r.getMessage(), type=AuditRecord)
        for r in caplog.records
        if r.name == "rap.audit"
    ]


# -- the connection ------------------------------------------------------------------------


async def test_the_checker_reads_and_publishes_over_tls_with_a_password(
    tmp_path: Path, pki: Pki
) -> None:
    runner = FakeRunner(FakeSpec(("a",), ("s",)))
    async with locked_down(tmp_path, pki, runner, listen=("s",)) as (service, peer):
        await peer.client.publish("a", "2")
        assert await peer.next_on("s") == {"value": 2}
        await peer.client.publish("a", "3")
        assert await peer.next_on("s") == {"value": 5}
        assert service.mqtt is not None
        assert service.mqtt.stats.connects == 1


async def test_the_broker_refuses_a_wrong_password_or_no_certificate(
    tmp_path: Path, pki: Pki, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    caplog.set_level(logging.WARNING, logger="trust_checker.io.mqtt")
    async with mosquitto(tmp_path, passwords=PASSWORDS, tls=pki.broker_tls()) as broker:
        with pytest.raises(aiomqtt.MqttError):
            async with peer_client(broker, pki, password="guess"):
                pass
        # without a client certificate the TLS session is cut before any MQTT answer
        said = await _connect_raw(broker.port, pki.client_context(None))
        assert "CERTIFICATE_REQUIRED" in said or "Broken" in said or "EndOfStream" in said, said
        accepted = await _connect_raw(broker.port, pki.client_context("peer"))
        assert accepted == "answered: 20020000"  # CONNACK, accepted
        async with peer_client(broker, pki):  # the right ones get in
            pass
        # a checker given the wrong password (by environment) never gets ready, and says why
        monkeypatch.setenv("TC_MQTT_PASSWORD", "guess")
        cfg = MqttConfig(
            port=broker.port,
            timeout=5.0,
            username="checker",
            password_env="TC_MQTT_PASSWORD",
            ca=str(pki.mqtt / "ca.pem"),
            cert=str(pki.mqtt / "checker.pem"),
            key=str(pki.mqtt / "checker.key"),
            reconnect_max=0.2,
        )
        runner = FakeRunner(FakeSpec(("a",), ("s",)))
        ready = False
        with anyio.move_on_after(2):
            async with open_service(ServiceConfig(mqtt=cfg), runner):
                ready = True
        assert not ready
    warnings = [r.getMessage() for r in caplog.records if r.name == "trust_checker.io.mqtt"]
    assert warnings, "the refused connections are logged"
    assert "check the user name and the password" in warnings[0]
    assert "guess" not in "\n".join(warnings)  # the password is never logged


def test_the_password_comes_from_the_environment_or_a_file(tmp_path: Path, pki: Pki) -> None:
    env_cfg = MqttConfig(username="u", password_env="TC_PW")
    assert mqtt_credentials(env_cfg, env={"TC_PW": "from-env"}).password == "from-env"
    with pytest.raises(ConfigError, match=r"\$TC_PW is not set - export it"):
        mqtt_credentials(env_cfg, env={})
    file_cfg = MqttConfig(username="u", password_file=str(password_file(tmp_path, "pw\nx\n")))
    creds = mqtt_credentials(file_cfg)
    assert creds.password == "pw"  # the first line
    assert "pw" not in repr(creds)
    assert creds.tls is None
    empty = MqttConfig(username="u", password_file=str(password_file(tmp_path, "\n")))
    with pytest.raises(ConfigError, match="its first line is empty"):
        mqtt_credentials(empty)
    missing = MqttConfig(username="u", password_file=str(tmp_path / "nope"))
    with pytest.raises(ConfigError, match="cannot read it"):
        mqtt_credentials(missing)
    with pytest.raises(ValueError, match="not both"):
        MqttConfig(username="u", password_env="A", password_file="b")
    with pytest.raises(ValueError, match="needs a user name"):
        MqttConfig(password_env="A")
    with pytest.raises(ValueError, match="give both the certificate"):
        MqttConfig(cert="c.pem")
    tls = mqtt_credentials(MqttConfig(ca=str(pki.mqtt / "ca.pem")))
    assert tls.tls is not None
    assert tls.tls.verify_mode is ssl.CERT_REQUIRED
    with pytest.raises(ConfigError, match="MQTT TLS: cannot load"):
        mqtt_credentials(MqttConfig(ca=str(tmp_path / "missing.pem")))


# -- the hot swap --------------------------------------------------------------------------


async def test_an_mqtt_swap_without_operator_credentials_is_refused_and_the_spec_stays(
    tmp_path: Path, pki: Pki, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="rap.audit")
    spec = load_text(maplek_specs()["stage_order"], "stage_order.dsrv")
    verifier = load_verifier(pki.rap)
    topic = "trust/spec"
    async with locked_down(tmp_path, pki, spec, verifier=verifier, listen=("trust/status",)) as (
        service,
        peer,
    ):
        before = service.runner

        async def attempt(payload: bytes) -> Any:
            await peer.client.publish(topic, payload)
            return await peer.next_on("trust/status")

        unsigned = await attempt(update_body(EVIL))
        process = await attempt(
            signed_update(load_signer(pki.rap, "robot.trust-lidar"), topic, EVIL)
        )
        foreign = await attempt(signed_update(load_signer(pki.foreign, "alice"), topic, EVIL))
        # alice's signature for another checker's topic, sent to this one
        elsewhere = await attempt(
            signed_update(load_signer(pki.rap, "alice"), "trust/other/spec", EVIL)
        )
        for status in (unsigned, process, foreign, elsewhere):
            assert status["ok"] is False
            assert status["node"] == NODE
            assert status["outputs"] == ["stage_order_ok"]
        assert unsigned["problems"][0].startswith("swap refused: unsigned request")
        assert process["problems"][0].startswith(
            "swap refused: 'robot.trust-lidar' (role process) may not swap the spec of "
            "trust_stage_order: that needs the role operator"
        )
        assert "is not issued by this system's CA" in foreign["problems"][0]
        assert elsewhere["problems"][0].startswith("swap refused: bad signature: 'alice'")
        assert service.runner is before
        assert service.session.stats.swaps == 0
        assert service.mqtt is not None
        assert service.mqtt.stats.rejections.by_reason == {
            "swap refused: unsigned": 1,
            "swap refused: not an operator": 1,
            "swap refused: certificate refused": 1,
            "swap refused: bad signature": 1,
        }
    rows = [(a.verb, a.via, a.key, a.result, a.who, a.role) for a in audits(caplog)]
    assert rows == [
        ("swap", "mqtt", topic, "refused", "unauthenticated", ""),
        ("swap", "mqtt", topic, "refused", "robot.trust-lidar", "process"),
        ("swap", "mqtt", topic, "refused", "unauthenticated", ""),
        ("swap", "mqtt", topic, "refused", "unauthenticated", ""),
    ]


async def test_an_operators_mqtt_swap_is_taken_once_and_audited(
    tmp_path: Path, pki: Pki, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="rap.audit")
    spec = load_text(maplek_specs()["stage_order"], "stage_order.dsrv")
    topic = "trust/spec"
    async with locked_down(
        tmp_path, pki, spec, verifier=load_verifier(pki.rap), listen=("trust/status",)
    ) as (service, peer):
        before = service.runner
        update = signed_update(load_signer(pki.rap, "alice"), topic, EVIL, "decided.dsrv")
        await peer.client.publish(topic, update)
        status = await peer.next_on("trust/status")
        assert status["ok"] is True, status
        assert status["inputs"] == ["stage"]
        assert service.runner is not before
        assert service.session.stats.swaps == 1
        await peer.client.publish(topic, update)  # the same bytes again
        again = await peer.next_on("trust/status")
        assert again["ok"] is False
        assert again["problems"][0].startswith("swap refused: replayed request")
        assert service.session.stats.swaps == 1
    ok, replayed = audits(caplog)
    assert (ok.result, ok.who, ok.role, ok.via) == ("ok", "alice", "operator", "mqtt")
    assert ok.request.startswith(f"spec decided.dsrv: {len(EVIL)} characters")
    assert ok.reason.startswith("swapped at tick 0: inputs stage; outputs stage_order_ok")
    assert (replayed.result, replayed.who) == ("refused", "alice")
