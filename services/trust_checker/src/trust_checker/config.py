"""Configuration of the checker's transports (frozen Structs; unknown fields refused).

The command line builds these from its flags; JSON maps (``--topics``,
``--fabric-inputs``) are decoded strictly with :func:`decode_map`, whose errors name the
``$.path`` of the bad part.
"""

from __future__ import annotations

from typing import Annotated, Any, TypeVar

import msgspec

__all__ = [
    "ConfigError",
    "FabricConfig",
    "FabricInput",
    "MqttConfig",
    "TopicMap",
    "decode_map",
]

T = TypeVar("T")


class ConfigError(ValueError):
    """A configuration value is invalid; the message names it and how to fix it."""


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

    def topic_of(self, stream: str) -> str:
        m = self.topics.get(stream)
        return m.topic if m is not None else stream


class FabricInput(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """An explicit input: the stream takes each message on ``key`` (a key expression):
    its body as plain data, or the one ``field`` of it."""

    key: Annotated[str, msgspec.Meta(min_length=1)]
    field: str | None = None


class FabricConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    system: str
    node: str = "trust_checker"
    """The checker's node id: the envelope source, and the admin key of hot swap
    (``rap/<system>/admin/<node>/swap``)."""
    inputs: dict[str, FabricInput] = {}
    """Explicit inputs; with ``default_inputs`` the trace records and events too."""
    default_inputs: bool = True
    """Read the system's trace records and events (see :mod:`trust_checker.io.fabric`)."""
    publish_timeout: Annotated[float, msgspec.Meta(gt=0)] = 2.0
    inbox: Annotated[int, msgspec.Meta(ge=1)] = 1 << 16
    """Input samples that may wait for the checker; past this many, new ones are dropped,
    counted (``FabricStats.lost``) and logged as an error."""


def decode_map(text: str, value_type: type[T], what: str) -> dict[str, T]:
    """A JSON object ``name -> value_type`` given on the command line."""
    try:
        out: dict[str, Any] = msgspec.json.decode(text, type=dict[str, value_type])  # type: ignore[valid-type]
    except msgspec.ValidationError as exc:
        raise ConfigError(f"{what}: {exc}") from None
    except msgspec.DecodeError as exc:
        raise ConfigError(f"{what} is not JSON: {exc}") from None
    return out
