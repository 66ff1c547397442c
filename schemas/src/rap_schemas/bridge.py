"""What a bridge is bound to: :class:`BridgeSpec`, one port's link to an outside protocol.

It hangs off a model port (``PortSpec.bridge``), where ``rap check`` checks it; a
bridge built in code takes one given there or decoded from JSON with
:func:`decode_spec`::

    BridgeSpec(protocol="mqtt", url="mqtt://broker:1883", address="robot/scan",
               format="json", qos=1, buffer=1000, overflow="drop-oldest")

Every check says what is wrong and what to write instead; decoding wraps them into a
``msgspec.ValidationError`` with the field's ``$.path``.
"""

from __future__ import annotations

import re
from typing import Annotated, Final, Literal
from urllib.parse import SplitResult, urlsplit

import msgspec

from .limits import MAX_SAMPLE_BYTES

__all__ = [
    "DEFAULT_PORTS",
    "PROTOCOLS",
    "SCHEMES",
    "BridgeSpec",
    "Format",
    "OverflowPolicy",
    "ProtocolName",
    "decode_spec",
]

ProtocolName = Literal[
    "mqtt", "tcp", "redis", "redis-stream", "amqp", "websocket", "nats", "dds", "kafka"
]
"""The protocols with a bridge: MQTT v5, length-prefixed TCP frames, Redis pub/sub,
Redis streams, AMQP 0-9-1, WebSocket, NATS (JetStream for QoS >= 1) and DDS with ROS 2's
naming and CDR (``dds``)."""
PROTOCOLS: Final[tuple[str, ...]] = (
    "mqtt",
    "tcp",
    "redis",
    "redis-stream",
    "amqp",
    "websocket",
    "nats",
    "dds",
    "kafka",
)
Format = Literal["envelope", "json", "raw", "cdr"]
"""``envelope``: the RAP envelope's msgpack bytes as they are on the fabric; ``json``:
the message (the envelope's body) as JSON; ``raw``: the message's msgpack bytes;
``cdr``: the ROS 2 message the port's type maps to, in CDR (DDS only; over DDS the
other formats travel in the generic ``rap_msgs/msg/Frame``)."""
OverflowPolicy = Literal["drop-oldest", "drop-newest", "block"]

SCHEMES: Final[dict[str, tuple[str, ...]]] = {
    "mqtt": ("mqtt", "mqtts"),
    "tcp": ("tcp", "tcps"),
    "redis": ("redis", "rediss"),
    "redis-stream": ("redis", "rediss"),
    "amqp": ("amqp", "amqps"),
    "websocket": ("ws", "wss"),
    "nats": ("nats", "tls"),
    "dds": ("dds",),
    "kafka": ("kafka",),
}
"""The URL schemes of each protocol; the second one means TLS."""
DEFAULT_PORTS: Final[dict[str, int]] = {
    "mqtt": 1883,
    "mqtts": 8883,
    "redis": 6379,
    "rediss": 6379,
    "amqp": 5672,
    "amqps": 5671,
    "ws": 80,
    "wss": 443,
    "nats": 4222,
    "tls": 4222,
    "kafka": 9092,
}
"""Schemes whose port may be left out of the URL."""
EXAMPLE_PORTS: Final[dict[str, int]] = {
    "mqtt": 1883,
    "tcp": 9000,
    "redis": 6379,
    "redis-stream": 6379,
    "amqp": 5672,
    "websocket": 8765,
    "nats": 4222,
    "kafka": 9092,
}
NEEDS_ADDRESS: Final = frozenset({"mqtt", "redis", "redis-stream", "amqp", "nats", "dds", "kafka"})
"""Protocols whose stream has a name (topic, channel, stream key, queue, subject)."""
SERVES: Final = frozenset({"tcp", "websocket"})
"""Protocols whose bridge may be the server (``serve: true``)."""
ADDRESS_EXAMPLES: Final[dict[str, str]] = {
    "mqtt": "the topic, e.g. address: robot/scan",
    "redis": "the channel, e.g. address: robot.scan",
    "redis-stream": "the stream's key, e.g. address: robot.scan",
    "amqp": "the queue (or routing key with exchange), e.g. address: robot.scan",
    "nats": "the subject, e.g. address: robot.scan",
    "dds": "the ROS 2 topic, e.g. address: /scan (on DDS: rt/scan)",
    "kafka": "the topic, e.g. address: robot.scan",
}
_ROS_TOPIC: Final = re.compile(r"(/[A-Za-z_][A-Za-z0-9_]*)+")
"""An absolute ROS 2 topic name (``/scan``, ``/tb1/scan``)."""

_KAFKA_TOPIC: Final = re.compile(r"[A-Za-z0-9._-]{1,249}")
"""A Kafka topic name (the broker refuses any other)."""


class BridgeSpec(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """One port bound to an outside protocol. The direction is the port's: an ``out``
    port's messages leave the fabric, an ``in`` port's arrive on it."""

    protocol: ProtocolName
    """Which protocol: ``mqtt``, ``tcp``, ``redis`` (pub/sub), ``redis-stream``,
    ``amqp``, ``websocket`` or ``nats``."""
    url: str
    """Where: ``mqtt://host:port`` (``mqtts://``: TLS), ``tcp://host:port``,
    ``redis://host:port`` (``rediss://``), ``amqp://host:port`` (``amqps://``),
    ``ws://host:port`` (``wss://``), ``nats://host:port`` (``tls://``), ``dds://<domain
    id>`` (``dds://0``: ROS 2's default domain); with ``serve``
    the address a TCP or WebSocket bridge listens on. Never credentials, never a path:
    the topic, channel, queue or path goes in ``address``."""
    address: str = ""
    """The protocol's name for the stream: the MQTT topic (an ``in`` bridge may use the
    ``+`` and ``#`` wildcards), the Redis channel (``in``: a glob pattern with ``*``
    subscribes by pattern) or stream key, the AMQP queue (or routing key when
    ``exchange`` is set), the NATS subject, the WebSocket path (default ``/``), the
    ROS 2 topic name (``/scan``; ``rt/scan`` on DDS); unused by TCP (one connection is
    one stream)."""
    format: Format = "envelope"
    """How a message is written outside: ``envelope``, ``json`` or ``raw``."""
    qos: Annotated[int, msgspec.Meta(ge=0, le=2)] = 1
    """0: at most once; 1: at least once (a message is kept until the other side
    confirmed it, and sent again after a reconnect); 2: exactly once where the
    protocol has it (MQTT), else as 1."""
    retain: bool = False
    """MQTT: the broker keeps the last message for late subscribers."""
    buffer: Annotated[int, msgspec.Meta(gt=0)] = 1000
    """Messages held while the other side is away (or slower than the fabric)."""
    overflow: OverflowPolicy = "drop-oldest"
    """When the buffer is full: ``drop-oldest`` (make room for the newest),
    ``drop-newest`` (keep what is queued) or ``block`` (publishers wait; samples from
    other processes, which must never wait, are dropped as with ``drop-newest``)."""
    serve: bool = False
    """TCP and WebSocket: listen at ``url`` and take any number of clients, instead of
    connecting."""
    max_frame: Annotated[int, msgspec.Meta(gt=0)] = MAX_SAMPLE_BYTES
    """The largest payload taken from outside (bytes); a bigger one is rejected."""
    username: str | None = None
    """The user name to log in with (MQTT, Redis, AMQP, NATS)."""
    password_env: str | None = None
    """The environment variable holding the password (never the password itself)."""
    password_file: str | None = None
    """A file whose first line is the password."""
    ca: str | None = None
    """TLS: the CA certificates (PEM) that sign the server's certificate (None: the
    system's)."""
    cert: str | None = None
    """TLS: this client's certificate (PEM), for servers that ask for one."""
    key: str | None = None
    """TLS: the key of ``cert`` (PEM, unencrypted)."""
    client_id: str | None = None
    """MQTT: the client identifier (None: derived from the bridge's name); a session
    the broker keeps across reconnects is found by it."""
    exchange: str = ""
    """AMQP: the exchange to publish to or bind the queue to ("": the default
    exchange, where ``address`` is the queue)."""
    group: str | None = None
    """Redis streams: the consumer group of an ``in`` bridge (None: derived from the
    bridge's name); NATS: the durable consumer's name."""
    maxlen: Annotated[int, msgspec.Meta(gt=0)] | None = None
    """Redis streams: trim the stream to about this many entries (None: no trimming)."""
    stream: str | None = None
    """NATS at QoS >= 1: the JetStream stream that holds ``address`` (None: derived
    from the subject; created when missing)."""

    def __post_init__(self) -> None:
        parts = _parse_url(self.protocol, self.url)
        proto = self.protocol
        if proto in NEEDS_ADDRESS and not self.address:
            raise ValueError(
                f"a bridge of protocol {proto} needs an address: {ADDRESS_EXAMPLES[proto]}"
            )
        if self.format == "cdr" and proto != "dds":
            raise ValueError(
                f"format cdr (ROS 2 messages) applies to dds only - use envelope, json or raw "
                f"for {proto}"
            )
        if proto == "dds" and not _ROS_TOPIC.fullmatch(self.address):
            raise ValueError(
                f"address {self.address!r} is not a ROS 2 topic name: write it absolute, "
                "tokens of letters, digits and _ not starting with a digit, e.g. address: "
                "/scan or /tb1/scan"
            )
        if proto == "tcp" and self.address:
            raise ValueError(
                "a tcp bridge has no address (one connection is one stream) - remove it"
            )
        if proto == "websocket" and self.address and not self.address.startswith("/"):
            raise ValueError(
                f"a websocket address is the URL's path: write address: /{self.address}"
            )
        if self.serve and proto not in SERVES:
            raise ValueError(
                f"serve applies to tcp and websocket only: a bridge of protocol {proto} "
                "connects to a server - remove serve"
            )
        for name, value, owner in (
            ("retain", self.retain, "mqtt"),
            ("client_id", self.client_id, "mqtt"),
            ("exchange", self.exchange, "amqp"),
            ("maxlen", self.maxlen, "redis-stream"),
            ("stream", self.stream, "nats"),
        ):
            if value and proto != owner:
                raise ValueError(f"{name} applies to {owner} only - remove it")
        if self.group is not None and proto not in ("redis-stream", "nats", "kafka"):
            raise ValueError("group applies to redis-stream, nats and kafka only - remove it")
        if proto == "kafka" and (
            self.address in (".", "..") or not _KAFKA_TOPIC.fullmatch(self.address)
        ):
            raise ValueError(
                f"address {self.address!r} is not a Kafka topic name: 1 to 249 letters, "
                "digits, '.', '_' or '-', e.g. address: robot.scan"
            )
        if proto == "kafka" and (
            self.username or self.password_env or self.password_file or self.ca or self.cert
        ):
            raise ValueError(
                "a kafka bridge takes no credentials or TLS settings (SASL and TLS are not "
                "supported yet: it connects to a plaintext listener) - remove them"
            )
        if self.password_env and self.password_file:
            raise ValueError("give password_env or password_file, not both")
        if proto == "dds" and (
            self.username or self.password_env or self.password_file or self.ca or self.cert
        ):
            raise ValueError(
                "a dds bridge takes no credentials or TLS settings (DDS Security is not "
                "supported) - remove them"
            )
        if (self.password_env or self.password_file) and not self.username:
            raise ValueError("a password needs a username - add username: <name>")
        if (self.cert is None) != (self.key is None):
            raise ValueError("cert and key go together: give both or neither")
        if (self.ca or self.cert) and not self.tls:
            schemes = SCHEMES[self.protocol]
            raise ValueError(
                f"ca/cert/key are TLS settings but {self.url} is not a TLS URL - write "
                f"{schemes[1]}://{parts.netloc}"
                if len(schemes) > 1
                else f"ca/cert/key are TLS settings, and a {self.protocol} bridge has no TLS "
                "here - remove them"
            )
        if proto == "tcp" and self.tls:
            raise ValueError("tcps:// (TCP with TLS) is not supported yet - use tcp://")
        if proto == "websocket" and (self.username or self.password_env or self.password_file):
            raise ValueError(
                "a websocket bridge takes no username or password - use wss:// with a "
                "client certificate (cert and key)"
            )

    @property
    def tls(self) -> bool:
        """Whether the URL asks for TLS (``mqtts://``, ``rediss://``, ``amqps://``,
        ``wss://``, ``tls://``)."""
        schemes = SCHEMES[self.protocol]
        return len(schemes) > 1 and self.url.split("://", 1)[0].lower() == schemes[1]

    @property
    def domain(self) -> int:
        """DDS: the domain id of ``dds://<domain>``."""
        if self.protocol != "dds":
            raise ValueError(f"domain applies to dds only, not {self.protocol}")
        return int(_parse_dds_url(self.url).netloc)

    @property
    def host(self) -> str:
        return _parse_url(self.protocol, self.url).hostname or ""

    @property
    def port(self) -> int:
        if self.protocol == "dds":
            raise ValueError("a dds bridge has no port: its url names a domain")
        parts = _parse_url(self.protocol, self.url)
        return parts.port if parts.port is not None else DEFAULT_PORTS[parts.scheme.lower()]

    @property
    def where(self) -> str:
        """The URL and address, for logs (a URL carries no credentials: they are refused)."""
        if not self.address:
            return self.url
        return (
            f"{self.url}{self.address}"
            if self.address.startswith("/")
            else f"{self.url}/{self.address}"
        )


def _parse_url(protocol: str, url: str) -> SplitResult:
    if protocol == "dds":
        return _parse_dds_url(url)
    schemes = SCHEMES[protocol]
    example = f"{schemes[0]}://127.0.0.1:{EXAMPLE_PORTS[protocol]}"
    try:
        parts = urlsplit(url)
        port = parts.port
    except ValueError as exc:
        raise ValueError(f"url {url!r}: {exc} - write e.g. {example}") from None
    if parts.scheme.lower() not in schemes:
        raise ValueError(
            f"url {url!r} does not fit protocol {protocol}: its scheme must be "
            f"{' or '.join(s + '://' for s in schemes)} - write e.g. {example}"
        )
    if not parts.hostname:
        raise ValueError(f"url {url!r} has no host - write e.g. {example}")
    if parts.username or parts.password:
        raise ValueError(
            f"url {url!r} holds credentials: give username and password_env or "
            "password_file instead (a URL ends up in logs)"
        )
    if port is None and parts.scheme.lower() not in DEFAULT_PORTS:
        raise ValueError(f"url {url!r} has no port - write e.g. {example}")
    if parts.path not in ("", "/") or parts.query or parts.fragment:
        raise ValueError(
            f"url {url!r} has a path or query: put the topic, channel, queue or path in "
            "address, not in the URL"
        )
    return parts


def _parse_dds_url(url: str) -> SplitResult:
    parts = urlsplit(url)
    domain = parts.netloc
    if (
        parts.scheme.lower() != "dds"
        or not domain.isdigit()
        or not 0 <= int(domain) <= 232
        or parts.path not in ("", "/")
        or parts.query
        or parts.fragment
    ):
        raise ValueError(
            f"url {url!r} is not a DDS domain: write dds://<domain id, 0-232>, e.g. dds://0 "
            "(ROS 2's ROS_DOMAIN_ID)"
        )
    return parts


_decode_json = msgspec.json.Decoder(BridgeSpec).decode


def decode_spec(data: bytes | str) -> BridgeSpec:
    """A spec from JSON; ``msgspec.ValidationError`` naming the field otherwise."""
    return _decode_json(data)
