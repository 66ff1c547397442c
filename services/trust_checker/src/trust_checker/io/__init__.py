"""Inputs and outputs of the checker: payload codec, tick policies, the session that
owns the monitor, and the MQTT and fabric transports."""

from .codec import CodecError, decode_json, decode_payload, encode_value, payload_form
from .ports import Clock, MonitorLike, OutputLike, Sink, SpecLoader
from .session import Session, SessionStats, SwapRequest, SystemClock
from .ticks import MESSAGE, Arrival, TickPolicy, merge, parse_duration, parse_tick_policy

__all__ = [
    "MESSAGE",
    "Arrival",
    "Clock",
    "CodecError",
    "MonitorLike",
    "OutputLike",
    "Session",
    "SessionStats",
    "Sink",
    "SpecLoader",
    "SwapRequest",
    "SystemClock",
    "TickPolicy",
    "decode_json",
    "decode_payload",
    "encode_value",
    "merge",
    "parse_duration",
    "parse_tick_policy",
    "payload_form",
]
