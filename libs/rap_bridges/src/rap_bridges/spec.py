"""What a bridge is bound to: :class:`BridgeSpec`, one port's link to an outside protocol.

It will hang off a model port (``PortSpec.bridge``); until the model carries it, a
bridge is built from a spec given in code or decoded from YAML/JSON with
:func:`decode_spec`::

    BridgeSpec(protocol="mqtt", url="mqtt://broker:1883", address="robot/scan",
               format="json", qos=1, buffer=1000, overflow="drop-oldest")

Every check says what is wrong and what to write instead; decoding wraps them into a
``msgspec.ValidationError`` with the field's ``$.path``.
"""

from __future__ import annotations

from typing import Annotated, Final, Literal
from urllib.parse import SplitResult, urlsplit

import msgspec
from rap_schemas.limits import MAX_SAMPLE_BYTES

__all__ = [
    "DEFAULT_PORTS",
    "PROTOCOLS",
    "BridgeSpec",
    "Format",
    "OverflowPolicy",
    "ProtocolName",
    "decode_spec",
]

ProtocolName = Literal["mqtt", "tcp"]
"""The protocols with a bridge so far (to come: redis, redis-stream, amqp, websocket,
nats, dds)."""
PROTOCOLS: Final[tuple[str, ...]] = ("mqtt", "tcp")
Format = Literal["envelope", "json", "raw"]
"""``envelope``: the RAP envelope's msgpack bytes as they are on the fabric; ``json``:
the message (the envelope's body) as JSON; ``raw``: the message's msgpack bytes."""
OverflowPolicy = Literal["drop-oldest", "drop-newest", "block"]

SCHEMES: Final[dict[str, tuple[str, ...]]] = {
    "mqtt": ("mqtt", "mqtts"),
    "tcp": ("tcp", "tcps"),
}
"""The URL schemes of each protocol; the second one means TLS."""
DEFAULT_PORTS: Final[dict[str, int]] = {"mqtt": 1883, "mqtts": 8883}
"""Schemes whose port may be left out of the URL."""


class BridgeSpec(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """One port bound to an outside protocol. The direction is the port's: an ``out``
    port's messages leave the fabric, an ``in`` port's arrive on it."""

    protocol: ProtocolName
    """Which protocol: ``mqtt`` or ``tcp``."""
    url: str
    """Where: ``mqtt://host:port``, ``mqtts://host:port`` (TLS), ``tcp://host:port``;
    with ``serve`` the address a TCP bridge listens on."""
    address: str = ""
    """The protocol's name for the stream: the MQTT topic (an ``in`` bridge may use the
    ``+`` and ``#`` wildcards); unused by TCP (one connection is one stream)."""
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
    """TCP: listen at ``url`` and take any number of clients, instead of connecting."""
    max_frame: Annotated[int, msgspec.Meta(gt=0)] = MAX_SAMPLE_BYTES
    """The largest payload taken from outside (bytes); a bigger one is rejected."""
    username: str | None = None
    """MQTT: the user name to log in with."""
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

    def __post_init__(self) -> None:
        parts = _parse_url(self.protocol, self.url)
        if self.protocol == "mqtt":
            if not self.address:
                raise ValueError(
                    "an mqtt bridge needs an address: the topic, e.g. address: robot/scan"
                )
            if self.serve:
                raise ValueError("serve applies to tcp only: an mqtt bridge connects to a broker")
        if self.protocol == "tcp" and self.retain:
            raise ValueError("retain applies to mqtt only - remove it")
        if self.password_env and self.password_file:
            raise ValueError("give password_env or password_file, not both")
        if (self.password_env or self.password_file) and not self.username:
            raise ValueError("a password needs a username - add username: <name>")
        if (self.cert is None) != (self.key is None):
            raise ValueError("cert and key go together: give both or neither")
        if (self.ca or self.cert) and not self.tls:
            raise ValueError(
                f"ca/cert/key are TLS settings but {self.url} is not a TLS URL - write "
                f"{SCHEMES[self.protocol][1]}://{parts.netloc}"
            )
        if self.protocol == "tcp" and self.tls:
            raise ValueError("tcps:// (TCP with TLS) is not supported yet - use tcp://")

    @property
    def tls(self) -> bool:
        """Whether the URL asks for TLS (``mqtts://``)."""
        return self.url.split("://", 1)[0].lower() == SCHEMES[self.protocol][1]

    @property
    def host(self) -> str:
        return _parse_url(self.protocol, self.url).hostname or ""

    @property
    def port(self) -> int:
        parts = _parse_url(self.protocol, self.url)
        return parts.port if parts.port is not None else DEFAULT_PORTS[parts.scheme.lower()]

    @property
    def where(self) -> str:
        """The URL and address, for logs (a URL carries no credentials: they are refused)."""
        return f"{self.url}/{self.address}" if self.address else self.url


def _parse_url(protocol: str, url: str) -> SplitResult:
    schemes = SCHEMES[protocol]
    example = f"{schemes[0]}://127.0.0.1:{1883 if protocol == 'mqtt' else 9000}"
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
            f"url {url!r} has a path or query: put the topic/queue in address, not in the URL"
        )
    return parts


_decode_json = msgspec.json.Decoder(BridgeSpec).decode


def decode_spec(data: bytes | str) -> BridgeSpec:
    """A spec from JSON; ``msgspec.ValidationError`` naming the field otherwise."""
    return _decode_json(data)
