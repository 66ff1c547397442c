"""Inputs and outputs of the checker: payload codec, tick policies, the session that
owns the spec runner, and the MQTT, Redis and fabric transports (:mod:`.mqtt`,
:mod:`.redis`, :mod:`.fabric`) and inputs from ROS 2 topics (:mod:`.dds`); wired together
by :func:`trust_checker.service.open_service`."""

from .codec import CodecError, decode_json, decode_payload, encode_value, payload_form
from .ports import OutputLike, RunnerLike, RunningSink, Sink, SpecLoader, VerdictSink
from .session import Session, SessionStats, SwapRequest
from .ticks import MESSAGE, Arrival, TickPolicy, merge, parse_duration, parse_tick_policy

__all__ = [
    "MESSAGE",
    "Arrival",
    "CodecError",
    "OutputLike",
    "RunnerLike",
    "RunningSink",
    "Session",
    "SessionStats",
    "Sink",
    "SpecLoader",
    "SwapRequest",
    "TickPolicy",
    "VerdictSink",
    "decode_json",
    "decode_payload",
    "encode_value",
    "merge",
    "parse_duration",
    "parse_tick_policy",
    "payload_form",
]
