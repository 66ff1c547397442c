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
one running.

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
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Final

import aiomqtt
import anyio
import msgspec
from anyio.abc import TaskStatus
from rap_schemas import TrustSpecStatus, TrustSpecUpdate, TrustVerdict
from rap_schemas.limits import MAX_SAMPLE_BYTES, DecodeRejected, SafeDecoder
from rap_sdk.rejections import Rejections, Throttle

from ..config import MqttConfig
from .codec import CodecError, decode_payload, encode_value
from .ports import OutputLike
from .session import Session, SwapRequest
from .ticks import Arrival

__all__ = ["MAX_SPEC_BYTES", "MqttTransport", "MqttTransportStats"]

log = logging.getLogger(__name__)

MAX_SPEC_BYTES: Final = MAX_SAMPLE_BYTES
"""Largest spec update taken on the spec topic (bytes of JSON)."""

_decode_update: Callable[[bytes], TrustSpecUpdate] = SafeDecoder(
    TrustSpecUpdate, protocol="json", max_bytes=MAX_SPEC_BYTES, what="spec update"
).decode
_encode = msgspec.json.Encoder().encode


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

    def __init__(self, session: Session, config: MqttConfig) -> None:
        self.session = session
        self.config = config
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
                client = aiomqtt.Client(
                    cfg.host, cfg.port, identifier=cfg.client_id or None, timeout=cfg.timeout
                )
                async with client:
                    self._subscribed = set()
                    await self._sync_subscriptions(client)
                    self._client = client
                    self.stats.connects += 1
                    pause = 0.1
                    log.info("mqtt: connected to %s:%d", cfg.host, cfg.port)
                    self.connected.set()
                    if not started:
                        started = True
                        task_status.started()
                    async for message in client.messages:
                        await self._on_message(message)
            except aiomqtt.MqttError as exc:
                log.warning(
                    "mqtt: connection to %s:%d lost or refused (%s); retrying in %.1f s",
                    cfg.host,
                    cfg.port,
                    exc,
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
        try:
            update = _decode_update(payload)
        except DecodeRejected as exc:
            reason = (
                f"spec update on {topic!r} refused: {exc.reason} - send "
                '{"spec": "<spec text>"} as JSON'
            )
            self.stats.rejections.reject(topic, reason)
            await self.status(
                TrustSpecStatus(
                    ok=False,
                    node=self.session.node,
                    ts=self.session.clock.time_ns(),
                    tick=self.session.runner.tick,
                    problems=[reason],
                    inputs=list(self.session.runner.inputs),
                    outputs=list(self.session.runner.outputs),
                )
            )
            return
        path = update.path if update.path != "<swap>" else f"<mqtt:{topic}>"
        await self.session.submit(SwapRequest(update.spec, path, topic))

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
