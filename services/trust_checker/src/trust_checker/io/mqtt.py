"""The checker on MQTT (aiomqtt).

Inputs: each input stream is read from the topic of its own name, or the topic that
``MqttConfig.topics`` maps it to (``{"x": {"topic": "robot/x"}}``; MQTT wildcards ``+``
and ``#`` allowed); payloads in any of the forms of :mod:`trust_checker.io.codec`. The
subscriptions follow the running spec's inputs across hot swaps.

Outputs: each output that ticks is published on its topic (same rule) as
``{"value": <plain JSON>}`` (⊥: ``{"value": null, "deferred": true}``), or tagged
(``{"Int": 42}``, ⊥: ``"Unknown"``) with ``tagged``; NoVal is never published.

Hot swap: ``{"spec": "<spec text>"}`` (optionally ``"path"``: a name for error messages;
at most :data:`MAX_SPEC_BYTES`) on ``spec_topic`` (default ``trust/spec``) replaces the
running spec between two ticks with the streams' history carried over. The outcome, a
``rap.TrustSpecStatus`` as JSON (``{"ok": false, "problems": ["<swap>:2:5: ..."], ...}``),
is published on ``status_topic`` (default ``trust/status``); a refused spec leaves the old
one running. A checker with identities takes an update only when its ``auth`` field holds
an operator's signature (:func:`trust_checker.io.auth.signed_update`); any other is
refused (``"problems": ["swap refused: ..."]``), counted, logged and audited.

The connection: a user name and a password (from an environment variable or a file,
never from the config or the command line) and TLS (the broker's CA, and a client
certificate and key for brokers that ask for one), as :class:`MqttConfig` says; the
password and the certificates are read again at each connection.

Verdicts (a session with ``explain=True``): each ``rap.TrustVerdict`` as JSON on
``verdict_topic`` (default ``trust/verdicts``; "" for none), e.g.
``{"stream": "ok", "tick": 41, "ts": ..., "value": false, "expr": "latency < 2.0 &&
approved", "because": [{"expr": "latency < 2.0", "value": false}, {"expr": "latency",
"value": 2.7, "depth": 1, "input": "latency", "input_tick": 41}]}``.

Bad input (a payload the codec refuses, a spec update that is not one) is rejected: counted
by reason in ``stats.rejections`` (a :class:`rap_sdk.rejections.Rejections`), logged
rate-limited, and the next message is taken; a refused spec update is also answered on
``status_topic``.

The connection is re-established after a loss (pauses doubling from 0.1 s up to
``reconnect_max``); the runner and its history live on in the session meanwhile, and
outputs of ticks that happen while disconnected are dropped and counted.
"""

from __future__ import annotations

import logging
import ssl
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import partial
from typing import Final

import aiomqtt
import anyio
import msgspec
from anyio.abc import TaskStatus
from rap_schemas import TrustSpecStatus, TrustVerdict
from rap_schemas.limits import MAX_SAMPLE_BYTES, DecodeRejected, SafeDecoder
from rap_sdk.admin import Gate, audit
from rap_sdk.errors import ConfigError
from rap_sdk.identity import AuthError, Caller
from rap_sdk.rejections import Rejections, Throttle

from ..config import MqttConfig
from .auth import SWAP_VERB, SignedSpecUpdate, outcome, spec_summary, update_body
from .codec import CodecError, decode_payload, encode_value
from .credentials import read_credentials
from .ports import OutputLike
from .session import Session, SwapRequest
from .ticks import Arrival

__all__ = [
    "MAX_SPEC_BYTES",
    "MqttCredentials",
    "MqttTransport",
    "MqttTransportStats",
    "mqtt_credentials",
]

log = logging.getLogger(__name__)

MAX_SPEC_BYTES: Final = MAX_SAMPLE_BYTES
"""Largest spec update taken on the spec topic (bytes of JSON)."""

_decode_update: Callable[[bytes], SignedSpecUpdate] = SafeDecoder(
    SignedSpecUpdate, protocol="json", max_bytes=MAX_SPEC_BYTES, what="spec update"
).decode
_encode = msgspec.json.Encoder().encode


@dataclass(frozen=True, slots=True)
class MqttCredentials:
    """What one connection presents: the password and the TLS context (None: none)."""

    password: str | None = field(default=None, repr=False)
    tls: ssl.SSLContext | None = None


def mqtt_credentials(config: MqttConfig, env: Mapping[str, str] | None = None) -> MqttCredentials:
    """The password and TLS context ``config`` names, read now (files: call it in a worker
    thread from an event loop); :class:`rap_sdk.ConfigError` saying what is missing."""
    return MqttCredentials(*read_credentials("MQTT", "--mqtt", config, env))


def _hint(exc: aiomqtt.MqttError) -> str:
    """A fix for a refused connection, when the error says what it is."""
    text = str(exc).lower()
    if "password" in text or "authori" in text:
        return " - check the user name and the password (--mqtt-user, --mqtt-password-*)"
    if "certificate" in text or "ssl" in text or "tls" in text:
        return " - check --mqtt-ca, --mqtt-cert and --mqtt-key, and the broker's name"
    return ""


@dataclass(slots=True)
class MqttTransportStats:
    rejections: Rejections
    """Payloads refused (input values the codec cannot read, spec updates that are not
    one), counted by reason (``rejections.by_reason``, ``rejections.total``)."""
    connects: int = 0
    published: int = 0
    dropped: int = 0
    """Outputs or statuses that could not be published (no connection, broker error)."""


class MqttTransport:
    """Feeds ``session`` from MQTT and publishes its results there (it adds itself to
    the session's sinks). Run :meth:`run` in a task group, next to ``session.run``."""

    def __init__(self, session: Session, config: MqttConfig, *, gate: Gate | None = None) -> None:
        self.session = session
        self.config = config
        self.gate = gate if gate is not None else Gate()
        """Who may swap the spec (default: ``RAP_CERTS``'s CA when it is set)."""
        self.stats = MqttTransportStats(Rejections(f"{session.node} (mqtt)", log))
        self._throttle = Throttle()
        self._client: aiomqtt.Client | None = None
        self._subscribed: set[str] = set()
        self._routes: dict[str, list[str]] = {}
        """Input topic (or topic filter) -> the input streams it sets."""
        self.connected = anyio.Event()
        session.sinks.append(self)

    # -- routing ---------------------------------------------------------------------

    def _input_routes(self, inputs: Sequence[str]) -> dict[str, list[str]]:
        routes: dict[str, list[str]] = {}
        for stream in inputs:
            routes.setdefault(self.config.topic_of(stream), []).append(stream)
        return routes

    def _streams_for(self, topic: aiomqtt.Topic) -> list[str]:
        exact = self._routes.get(topic.value)
        if exact is not None:
            return exact
        out: list[str] = []
        for flt, streams in self._routes.items():
            if ("+" in flt or "#" in flt) and topic.matches(flt):
                out.extend(streams)
        return out

    async def _sync_subscriptions(self, client: aiomqtt.Client) -> None:
        """Subscribe to the running spec's input topics (and the spec topic); drop the
        topics no input needs any more."""
        self._routes = self._input_routes(self.session.runner.inputs)
        wanted = {*self._routes, self.config.spec_topic}
        timeout = self.config.timeout
        for topic in sorted(wanted - self._subscribed):
            await client.subscribe(topic, qos=self.config.qos, timeout=timeout)
            self._subscribed.add(topic)
        for topic in sorted(self._subscribed - wanted):
            await client.unsubscribe(topic, timeout=timeout)
            self._subscribed.discard(topic)
        log.debug("mqtt inputs: %s", self._routes)

    # -- the connection --------------------------------------------------------------

    async def run(self, *, task_status: TaskStatus[None] = anyio.TASK_STATUS_IGNORED) -> None:
        """Connect, subscribe, then take messages until cancelled; reconnect after a
        loss. ``task_status.started()`` once the first subscriptions are in place."""
        started = False
        pause = 0.1
        cfg = self.config
        while True:
            try:
                creds = await anyio.to_thread.run_sync(mqtt_credentials, cfg)
            except ConfigError as exc:
                if not started:
                    raise
                log.error("mqtt: %s; retrying in %.1f s", exc, pause)
                await anyio.sleep(pause)  # pacing: a file to be fixed, no event to wait on
                pause = min(pause * 2, cfg.reconnect_max)
                continue
            try:
                client = aiomqtt.Client(
                    cfg.host,
                    cfg.port,
                    identifier=cfg.client_id or None,
                    timeout=cfg.timeout,
                    username=cfg.username or None,
                    password=creds.password,
                    tls_context=creds.tls,
                )
                async with client:
                    self._subscribed = set()
                    await self._sync_subscriptions(client)
                    self._client = client
                    self.stats.connects += 1
                    pause = 0.1
                    log.info(
                        "mqtt: connected to %s:%d%s%s",
                        cfg.host,
                        cfg.port,
                        " over TLS" if creds.tls is not None else "",
                        f" as {cfg.username}" if cfg.username else "",
                    )
                    self.connected.set()
                    if not started:
                        started = True
                        task_status.started()
                    async for message in client.messages:
                        await self._on_message(message)
            except aiomqtt.MqttError as exc:
                log.warning(
                    "mqtt: connection to %s:%d lost or refused (%s%s); retrying in %.1f s",
                    cfg.host,
                    cfg.port,
                    exc,
                    _hint(exc),
                    pause,
                )
            finally:
                self._client = None
                self.connected = anyio.Event()
            # pacing reconnection attempts (not waiting for an event: there is none)
            await anyio.sleep(pause)
            pause = min(pause * 2, cfg.reconnect_max)

    async def _on_message(self, message: aiomqtt.Message) -> None:
        topic = message.topic.value
        payload = bytes(message.payload)
        if message.topic.matches(self.config.spec_topic):
            await self._on_spec(topic, payload)
            return
        streams = self._streams_for(message.topic)
        if not streams:
            return  # a topic no input of the running spec reads (any more)
        try:
            value = decode_payload(payload)
        except CodecError as exc:
            self.stats.rejections.reject(topic, exc.reason)
            return
        await self.session.submit(
            Arrival(dict.fromkeys(streams, value), self.session.clock.time_ns(), topic)
        )

    async def _on_spec(self, topic: str, payload: bytes) -> None:
        node = self.session.node
        try:
            update = _decode_update(payload)
        except DecodeRejected as exc:
            reason = (
                f"spec update on {topic!r} refused: {exc.reason} - send "
                '{"spec": "<spec text>"} as JSON'
            )
            self.stats.rejections.reject(topic, reason)
            audit(
                verb=SWAP_VERB,
                component=node,
                result="error",
                caller=None,
                checked=self.gate.checks,
                key=topic,
                via="mqtt",
                request=f"{len(payload)} bytes",
                reason=reason,
            )
            await self._refuse(reason)
            return
        path = update.path if update.path != "<swap>" else f"<mqtt:{topic}>"
        what = spec_summary(update.spec, path)
        checked = self.gate.checks
        try:
            caller = await self.gate.check(
                topic,
                SWAP_VERB,
                update_body(update.spec, update.path),
                update.auth,
                scope=f"{node}:mqtt",
                what=f"swap the spec of {node}",
            )
        except AuthError as exc:
            reason = f"swap refused: {exc.reason}"
            self.stats.rejections.reject(topic, f"swap refused: {exc.kind} ({exc.reason})")
            audit(
                verb=SWAP_VERB,
                component=node,
                result="refused",
                caller=exc.caller,
                checked=True,
                key=topic,
                via="mqtt",
                request=what,
                reason=exc.reason,
                kind=exc.kind,
                throttle=self.gate.refusals,
            )
            await self._refuse(reason)
            return
        done = partial(self._audit, caller, checked, topic, what)
        origin = f"{topic} from {caller}" if caller is not None else topic
        await self.session.submit(SwapRequest(update.spec, path, origin, on_done=done))

    def _audit(
        self, caller: Caller | None, checked: bool, topic: str, what: str, st: TrustSpecStatus
    ) -> None:
        result, reason = outcome(st)
        audit(
            verb=SWAP_VERB,
            component=self.session.node,
            result=result,
            caller=caller,
            checked=checked,
            key=topic,
            via="mqtt",
            request=what,
            reason=reason,
        )

    async def _refuse(self, reason: str) -> None:
        """Answer a spec update that was not taken on the status topic."""
        runner = self.session.runner
        await self.status(
            TrustSpecStatus(
                ok=False,
                node=self.session.node,
                ts=self.session.clock.time_ns(),
                tick=runner.tick,
                problems=[reason],
                inputs=list(runner.inputs),
                outputs=list(runner.outputs),
            )
        )

    # -- the sink --------------------------------------------------------------------

    async def _publish(self, topic: str, payload: bytes) -> None:
        client = self._client
        if client is None:
            self.stats.dropped += 1
            return
        try:
            await client.publish(topic, payload, qos=self.config.qos, timeout=self.config.timeout)
        except aiomqtt.MqttError as exc:
            self.stats.dropped += 1
            n = self._throttle.hit(topic)
            if n:
                log.warning("mqtt: %d publish(es) on %s failed: %s", n, topic, exc)
            return
        self.stats.published += 1

    async def outputs(self, outs: Sequence[OutputLike]) -> None:
        tagged = self.config.tagged
        for out in outs:
            await self._publish(
                self.config.topic_of(out.stream), encode_value(out.value, tagged=tagged)
            )

    async def verdicts(self, verdicts: Sequence[TrustVerdict]) -> None:
        topic = self.config.verdict_topic
        if topic:
            for verdict in verdicts:
                await self._publish(topic, _encode(verdict))

    async def status(self, status: TrustSpecStatus) -> None:
        await self._publish(self.config.status_topic, _encode(status))
        client = self._client
        if status.ok and client is not None:
            try:
                await self._sync_subscriptions(client)
            except aiomqtt.MqttError as exc:  # the reconnect resubscribes from scratch
                log.warning("mqtt: could not follow the new spec's inputs yet: %s", exc)
