"""The MQTT link (aiomqtt, MQTT v5).

- ``out``: each message is published on ``address`` with the spec's QoS (0, 1, 2) and
  ``retain``; cycle, cause, wire type and sender go in MQTT v5 user properties
  (``rap-cycle``, ``rap-cause``: 32 hex digits; ``rap-type``, ``rap-source``). At QoS >= 1
  a message counts as sent once the broker confirmed it (PUBACK / PUBCOMP); a message
  whose confirmation was cut off by a lost connection is published again after the
  reconnect (at least once).
- ``in``: the bridge subscribes to ``address`` (wildcards allowed) at the spec's QoS;
  user properties ``rap-cycle``/``rap-cause``/``rap-type`` are read as headers. At QoS
  >= 1 it asks the broker for a session that outlives the connection (clean start off,
  one hour's session expiry, client id ``rap-bridge-<name>`` unless the spec names
  one), so that messages published while it reconnects are kept for it.
- Credentials: ``username`` with ``password_env`` or ``password_file`` (read at each
  connection, never from the spec); TLS with ``mqtts://`` and ``ca``/``cert``/``key``.
"""

from __future__ import annotations

import ssl
from typing import Final

import aiomqtt
import anyio
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties

from .core import Deliver, Frame, LinkContext, LinkDown
from .credentials import link_credentials
from .spec import BridgeSpec

__all__ = ["SESSION_EXPIRY_S", "MqttLink", "mqtt_credentials"]

SESSION_EXPIRY_S: Final = 3600
"""How long the broker keeps an ``in`` bridge's session (and its queued messages) while
the bridge is away."""
TIMEOUT_S: Final = 10.0
"""How long a connection, subscription or publication may take before the link counts
as lost."""


def mqtt_credentials(spec: BridgeSpec) -> tuple[str | None, ssl.SSLContext | None]:
    """The password and TLS context ``spec`` names, read now (it reads files: call it in
    a worker thread); :class:`LinkDown` saying what to fix otherwise."""
    return link_credentials(spec, "MQTT")


def _fix(exc: BaseException, spec: BridgeSpec) -> str:
    text = str(exc).lower()
    if "password" in text or "authori" in text:
        return "check username and password_env / password_file"
    if "certificate" in text or "ssl" in text or "tls" in text:
        return "check ca, cert and key, and that the broker's certificate names its host"
    if "refused" in text or "timed out" in text or "unreachable" in text:
        return f"is the broker running and reachable at {spec.host}:{spec.port}?"
    return ""


def _payload(value: object) -> bytes:
    if isinstance(value, bytes):
        return value
    if isinstance(value, bytearray):
        return bytes(value)
    if value is None:
        return b""
    return str(value).encode()


class MqttLink:
    """An MQTT v5 connection for one bridge (see the module's documentation)."""

    def __init__(self, spec: BridgeSpec, ctx: LinkContext) -> None:
        self.spec = spec
        self.ctx = ctx
        self.client_id = spec.client_id or f"rap-bridge-{ctx.name}"
        self._client: aiomqtt.Client | None = None
        self._persistent = ctx.direction == "in" and spec.qos > 0

    @property
    def where(self) -> str:
        return self.spec.where

    async def open(self) -> None:
        await self._drop()
        spec = self.spec
        password, tls = await anyio.to_thread.run_sync(mqtt_credentials, spec)
        props = Properties(PacketTypes.CONNECT)  # type: ignore[no-untyped-call]
        props.SessionExpiryInterval = SESSION_EXPIRY_S if self._persistent else 0
        client = aiomqtt.Client(
            spec.host,
            spec.port,
            username=spec.username,
            password=password,
            identifier=self.client_id,
            protocol=aiomqtt.ProtocolVersion.V5,
            clean_start=not self._persistent,
            properties=props,
            tls_context=tls,
            timeout=TIMEOUT_S,
        )
        try:
            await client.__aenter__()
        except aiomqtt.MqttError as exc:
            raise LinkDown(f"cannot connect: {exc}", _fix(exc, spec)) from None
        self._client = client
        if self.ctx.direction == "in":
            try:
                await client.subscribe(spec.address, qos=spec.qos)
            except aiomqtt.MqttError as exc:
                await self._drop()
                raise LinkDown(
                    f"cannot subscribe to {spec.address!r}: {exc}",
                    "check the topic and the broker's access control for this user",
                ) from None

    async def run(self, deliver: Deliver) -> None:
        client = self._client
        if client is None:
            raise LinkDown("not connected")
        try:
            async for message in client.messages:
                headers: dict[str, str] = {}
                props = message.properties
                for item in getattr(props, "UserProperty", None) or ():
                    if isinstance(item, tuple) and len(item) == 2:
                        headers[str(item[0])] = str(item[1])
                await deliver(Frame(_payload(message.payload), headers))
        except aiomqtt.MqttError as exc:
            raise LinkDown(f"connection lost: {exc}", _fix(exc, self.spec)) from None

    async def send(self, frame: Frame) -> None:
        client = self._client
        if client is None:
            raise LinkDown("not connected")
        props = Properties(PacketTypes.PUBLISH)  # type: ignore[no-untyped-call]
        if frame.headers:
            props.UserProperty = list(frame.headers.items())
        try:
            await client.publish(
                self.spec.address,
                frame.payload,
                qos=self.spec.qos,
                retain=self.spec.retain,
                properties=props,
            )
        except aiomqtt.MqttError as exc:
            raise LinkDown(f"publication failed: {exc}", _fix(exc, self.spec)) from None

    async def close(self) -> None:
        await self._drop()

    async def _drop(self) -> None:
        client, self._client = self._client, None
        if client is None:
            return
        with anyio.CancelScope(shield=True):
            try:
                await client.__aexit__(None, None, None)
            except aiomqtt.MqttError:
                pass  # already gone: nothing to say goodbye to
