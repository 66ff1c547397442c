"""Configuration of the checker as a service (frozen Structs; unknown fields refused).

:class:`ServiceConfig` is what :func:`trust_checker.service.open_service` runs: the
checker's node id, its tick policy, and the transports (:class:`MqttConfig`,
:class:`RedisConfig`, :class:`FabricConfig`, :class:`DdsConfig` for inputs from ROS 2
topics; any of them, or none for a checker fed in Python). The command line builds
these from its flags; JSON maps (``--topics``, ``--redis-channels``, ``--fabric-inputs``,
``--dds-topics``) are decoded strictly with :func:`decode_map`,
whose errors name the ``$.path`` of the bad part (:class:`rap_sdk.ConfigError`).
"""

from __future__ import annotations

import re
from typing import Annotated, Any, Final, Literal, TypeVar
from urllib.parse import urlsplit

import msgspec
from rap_schemas.limits import DECODE_ERRORS, decode_failure
from rap_sdk.errors import ConfigError

from .io.ticks import TickPolicy, parse_tick_policy

__all__ = [
    "ChannelMap",
    "DdsConfig",
    "DdsTopic",
    "FabricConfig",
    "FabricInput",
    "MqttConfig",
    "RedisConfig",
    "ServiceConfig",
    "TopicMap",
    "decode_map",
]

T = TypeVar("T")


class TopicMap(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """Where one stream lives on MQTT (an input's topic, or an output's)."""

    topic: Annotated[str, msgspec.Meta(min_length=1)]


class MqttConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    host: str = "127.0.0.1"
    port: Annotated[int, msgspec.Meta(ge=1, le=65535)] = 1883
    topics: dict[str, TopicMap] = {}
    """stream -> topic; a stream not named here uses its own name as the topic."""
    tagged: bool = False
    """Publish outputs in D5.2's tagged form (``{"Int": 42}``) instead of ``{"value": 42}``."""
    spec_topic: str = "trust/spec"
    """Hot swap: ``{"spec": "<spec text>"}`` here replaces the running spec."""
    status_topic: str = "trust/status"
    """The outcome of every spec update (``rap.TrustSpecStatus`` as JSON)."""
    verdict_topic: str = "trust/verdicts"
    """Verdicts (``rap.TrustVerdict`` as JSON: a Bool output turned false, a trigger
    fired), when the session explains; "" publishes none."""
    client_id: str = ""
    qos: Annotated[int, msgspec.Meta(ge=0, le=2)] = 0
    timeout: Annotated[float, msgspec.Meta(gt=0)] = 10.0
    """Seconds for connecting, subscribing and each publish."""
    reconnect_max: Annotated[float, msgspec.Meta(gt=0)] = 5.0
    """Longest pause between reconnection attempts (doubling from 0.1 s)."""
    username: str = ""
    """The user name given to the broker ("" for none)."""
    password_env: str = ""
    """The environment variable holding the password (never the password itself: a
    config and a command line are seen by others)."""
    password_file: str = ""
    """A file holding the password (its first line); read at each connection."""
    tls: bool = False
    """Connect over TLS, checking the broker's certificate (against ``ca``, else the
    system's CAs) and its name. Implied by ``ca``, ``cert`` and ``key``."""
    ca: str = ""
    """The CA certificate (PEM) the broker's certificate must be signed by."""
    cert: str = ""
    """A client certificate (PEM) to present, for brokers that require one."""
    key: str = ""
    """Its private key (PEM, unencrypted)."""

    def __post_init__(self) -> None:
        if self.password_env and self.password_file:
            raise ValueError(
                "give the MQTT password either in an environment variable (password_env) "
                "or in a file (password_file), not both"
            )
        if (self.password_env or self.password_file) and not self.username:
            raise ValueError("an MQTT password needs a user name (username) too")
        if bool(self.cert) != bool(self.key):
            raise ValueError(
                "an MQTT client certificate needs its key and the key its certificate - "
                "give both the certificate (cert) and its key (key), or neither"
            )

    @property
    def secure(self) -> bool:
        """Whether the connection is TLS."""
        return self.tls or bool(self.ca or self.cert)

    def topic_of(self, stream: str) -> str:
        m = self.topics.get(stream)
        return m.topic if m is not None else stream


class ChannelMap(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """Where one stream lives on Redis pub/sub (an input's channel or pattern, or an
    output's channel)."""

    channel: Annotated[str, msgspec.Meta(min_length=1)]


REDIS_PORT: Final = 6379
_REDIS_HOW: Final = (
    "write redis://HOST[:PORT][/DB], or rediss://... for TLS, e.g. redis://127.0.0.1:6379/0"
)
_DIGITS: Final = frozenset("0123456789")


def _split_redis_url(url: str) -> tuple[str, int, int, bool]:
    """``redis[s]://host[:port][/db]`` to (host, port, db, TLS); ``ValueError`` saying
    how to write it otherwise. A user name or password in the URL is refused: a URL
    goes on command lines and in configs, which others see."""
    try:
        parts = urlsplit(url)
    except ValueError as exc:  # not echoing the URL: it may hold a password
        raise ValueError(f"the Redis URL (url) is not one ({exc}) - {_REDIS_HOW}") from None
    if "@" in parts.netloc:
        raise ValueError(
            "the Redis URL (url) holds a user name or a password - drop it from the URL; "
            "give the user name as username and the password in password_env or "
            "password_file (a URL is seen by others)"
        )
    try:
        port = parts.port
    except ValueError as exc:
        raise ValueError(f"the Redis URL (url) {url!r}: {exc} - {_REDIS_HOW}") from None
    if parts.scheme not in ("redis", "rediss") or not parts.hostname:
        raise ValueError(f"{url!r} is not a Redis URL (url) - {_REDIS_HOW}")
    if parts.query or parts.fragment:
        raise ValueError(
            f"the Redis URL (url) {url!r} has a query or a fragment, which are not read "
            f"- {_REDIS_HOW}"
        )
    db = parts.path[1:] if parts.path.startswith("/") else parts.path
    if db and not (set(db) <= _DIGITS and len(db) <= 6):
        raise ValueError(
            f"the Redis URL (url) {url!r}: {db!r} is not a database number - {_REDIS_HOW}"
        )
    return parts.hostname, port or REDIS_PORT, int(db or 0), parts.scheme == "rediss"


class RedisConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """The checker on Redis pub/sub (see :mod:`trust_checker.io.redis`)."""

    url: str = "redis://127.0.0.1:6379/0"
    """``redis://HOST[:PORT][/DB]`` (``rediss://`` for TLS); no user name or password in
    it (``username``, ``password_env``, ``password_file``)."""
    channels: dict[str, ChannelMap] = {}
    """stream -> channel; a stream not named here uses its own name as the channel. An
    input's channel with ``*``, ``?`` or ``[`` is a pattern (``PSUBSCRIBE``)."""
    tagged: bool = False
    """Publish outputs in D5.2's tagged form (``{"Int": 42}``) instead of ``{"value": 42}``."""
    spec_channel: str = "trust/spec"
    """Hot swap, with identities only: a signed ``{"spec": ..., "auth": ...}`` here
    replaces the running spec ("" for none)."""
    status_channel: str = "trust/status"
    """The outcome of every spec update (``rap.TrustSpecStatus`` as JSON)."""
    verdict_channel: str = "trust/verdicts"
    """Verdicts (``rap.TrustVerdict`` as JSON), when the session explains; "" for none."""
    verdict_stream: str = ""
    """A Redis stream the verdicts are also added to (``XADD``, field ``verdict``), for
    readers that were not subscribed when they came; "" for none."""
    stream_maxlen: Annotated[int, msgspec.Meta(ge=1)] = 10_000
    """About how many verdicts the stream keeps (``MAXLEN ~``)."""
    client_name: str = ""
    """A name for the connections on the server (``CLIENT SETNAME``, seen in ``CLIENT
    LIST``); "" for none (an ACL user then needs no ``client`` command)."""
    timeout: Annotated[float, msgspec.Meta(gt=0)] = 10.0
    """Seconds for connecting and for each command (publish, subscribe)."""
    reconnect_max: Annotated[float, msgspec.Meta(gt=0)] = 5.0
    """Longest pause between reconnection attempts (doubling from 0.1 s)."""
    username: str = ""
    """An ACL user name ("" for none: a password alone is ``AUTH password``, the
    ``default`` user, as with ``requirepass``)."""
    password_env: str = ""
    """The environment variable holding the password (never the password itself)."""
    password_file: str = ""
    """A file holding the password (its first line); read at each connection."""
    tls: bool = False
    """Connect over TLS, checking the server's certificate (against ``ca``, else the
    system's CAs) and its name. Implied by ``rediss://``, ``ca``, ``cert`` and ``key``."""
    ca: str = ""
    """The CA certificate (PEM) the server's certificate must be signed by."""
    cert: str = ""
    """A client certificate (PEM) to present, for servers that require one."""
    key: str = ""
    """Its private key (PEM, unencrypted)."""

    def __post_init__(self) -> None:
        _split_redis_url(self.url)
        if self.password_env and self.password_file:
            raise ValueError(
                "give the Redis password either in an environment variable (password_env) "
                "or in a file (password_file), not both"
            )
        if bool(self.cert) != bool(self.key):
            raise ValueError(
                "a Redis client certificate needs its key and the key its certificate - "
                "give both the certificate (cert) and its key (key), or neither"
            )

    @property
    def address(self) -> tuple[str, int, int]:
        """(host, port, database number) of :attr:`url`."""
        host, port, db, _ = _split_redis_url(self.url)
        return host, port, db

    @property
    def secure(self) -> bool:
        """Whether the connection is TLS."""
        return self.tls or bool(self.ca or self.cert) or _split_redis_url(self.url)[3]

    def channel_of(self, stream: str) -> str:
        m = self.channels.get(stream)
        return m.channel if m is not None else stream


class FabricInput(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """An explicit input: the stream takes each message on ``key`` (a key expression):
    its body as plain data, or the one ``field`` of it."""

    key: Annotated[str, msgspec.Meta(min_length=1)]
    field: str | None = None


class FabricConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """The checker on the RAP fabric: which system it reads and publishes on. Its node
    id (envelope source, admin key of hot swap ``rap/<system>/admin/<node>/swap``) is
    :attr:`ServiceConfig.node`."""

    system: str
    inputs: dict[str, FabricInput] = {}
    """Explicit inputs; with ``default_inputs`` the trace records and events too."""
    default_inputs: bool = True
    """Read the system's trace records and events (see :mod:`trust_checker.io.fabric`)."""
    publish_timeout: Annotated[float, msgspec.Meta(gt=0)] = 2.0
    inbox: Annotated[int, msgspec.Meta(ge=1)] = 1 << 16
    """Input samples that may wait for the checker; past this many, new ones are dropped,
    counted (``FabricTransportStats.lost``) and logged as an error."""
    inbox_bytes: Annotated[int, msgspec.Meta(ge=1)] = 64 << 20
    """Bytes those samples may hold together (a count alone does not bound memory: a
    flood of large samples took a checker to 4 GiB); past it, new ones are dropped the
    same way."""


DdsType = Literal[
    "rap_msgs/msg/Frame",
    "std_msgs/msg/Bool",
    "std_msgs/msg/Int64",
    "std_msgs/msg/Float64",
    "std_msgs/msg/String",
]
"""The ROS 2 message types an input is read as (see :mod:`trust_checker.io.dds`)."""
_ROS_TOPIC: Final = re.compile(r"(/[A-Za-z_][A-Za-z0-9_]*)+")


class DdsTopic(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """Where one input stream lives on DDS: a ROS 2 topic and its message type."""

    topic: str
    """The ROS 2 topic, absolute (``/robot/latency``; on DDS ``rt/robot/latency``)."""
    type: DdsType = "rap_msgs/msg/Frame"
    """``rap_msgs/msg/Frame``: the payload is the value as on MQTT (any of the codec's
    forms); ``std_msgs/msg/Bool``, ``Int64``, ``Float64``, ``String``: ``data``."""

    def __post_init__(self) -> None:
        if not _ROS_TOPIC.fullmatch(self.topic):
            raise ValueError(
                f"{self.topic!r} is not a ROS 2 topic name - write it absolute, tokens of "
                "letters, digits and _ not starting with a digit, e.g. /robot/latency"
            )


class DdsConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """The checker's inputs from ROS 2 topics over DDS (see :mod:`trust_checker.io.dds`)."""

    domain: Annotated[int, msgspec.Meta(ge=0, le=232)] = 0
    """The DDS domain (ROS 2's ``ROS_DOMAIN_ID``)."""
    topics: dict[str, DdsTopic] = {}
    """input stream -> its topic and type; a stream not named here is read from the
    topic ``/<stream>`` as ``rap_msgs/msg/Frame``."""
    qos: Annotated[int, msgspec.Meta(ge=0, le=1)] = 0
    """0: best effort, volatile (takes every publisher); 1: reliable, transient-local
    (takes only publishers that offer it, and their history on joining)."""
    depth: Annotated[int, msgspec.Meta(ge=1, le=100_000)] = 100
    """Samples each reader keeps while the checker is busy (the newest win)."""

    def topic_of(self, stream: str) -> DdsTopic:
        found = self.topics.get(stream)
        if found is not None:
            return found
        try:
            return DdsTopic(f"/{stream}")
        except ValueError:
            raise ConfigError(
                f"input {stream!r} has no ROS 2 topic of its own name - map it in the DDS "
                'topics: {"' + stream + '": {"topic": "/robot/x"}}'
            ) from None


class ServiceConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """One checker: what :func:`trust_checker.service.open_service` wires and runs."""

    node: Annotated[str, msgspec.Meta(min_length=1)] = "trust_checker"
    """The checker's node id: the ``node`` of every spec status, and on the fabric the
    envelope source and the admin key of hot swap."""
    tick: str = "message"
    """Tick policy: ``message`` (one message, one tick) or ``window:<duration>``
    (``window:10ms``; see :mod:`trust_checker.io.ticks`). Checked when built."""
    verdicts: bool = True
    """Explain every tick and give the verdicts (a Bool output turned false, a trigger
    fired) to the sinks that take them (the transports publish them). Needs a
    :class:`~trust_checker.engine.SpecRunner`; a stand-in runner gives none."""
    capacity: Annotated[int, msgspec.Meta(ge=1)] = 1024
    """Messages (or batches, or spec updates) that may wait for the session."""
    mqtt: MqttConfig | None = None
    redis: RedisConfig | None = None
    fabric: FabricConfig | None = None
    dds: DdsConfig | None = None

    def __post_init__(self) -> None:
        parse_tick_policy(self.tick)  # ValueError saying how to write it

    @property
    def policy(self) -> TickPolicy:
        return parse_tick_policy(self.tick)


def decode_map(text: str, value_type: type[T], what: str) -> dict[str, T]:
    """A JSON object ``name -> value_type`` given on the command line;
    :class:`rap_sdk.ConfigError` saying what is wrong (with its ``$.path``) otherwise."""
    try:
        out: dict[str, Any] = msgspec.json.decode(text, type=dict[str, value_type])  # type: ignore[valid-type]
    except msgspec.ValidationError as exc:
        raise ConfigError(f"{what}: {exc}") from None
    except DECODE_ERRORS as exc:
        raise ConfigError(f"{what} is not a JSON object: {decode_failure(exc)}") from None
    return out
