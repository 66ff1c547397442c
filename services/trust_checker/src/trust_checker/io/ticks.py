"""Tick policies: how arriving messages become the spec runner's ticks.

``message`` (the default, the reference checker's): every message that sets at least
one input of the spec is one tick. ``window:<duration>`` (e.g. ``window:10ms``): the
messages arriving within the window, counted from the first of a burst, are merged into
one atomic tick, the last value per stream winning; the tick's time is the first
message's. A message setting no input of the spec is never a tick.

Every tick carries a wall-clock timestamp (UTC ns, from the injected clock) that the
runner gets as ``ts_ns``. Periodic outputs (``out y @ 10Hz``) are driven by the session
(:mod:`trust_checker.io.session`), which asks the runner when it is next due.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Final, Literal

__all__ = ["MESSAGE", "Arrival", "TickPolicy", "merge", "parse_duration", "parse_tick_policy"]

_UNITS: Final = {"ns": 1, "us": 1_000, "ms": 1_000_000, "s": 1_000_000_000}
_DURATION = re.compile(r"\s*([0-9]+(?:\.[0-9]+)?)\s*(ns|us|ms|s)\s*")
MAX_WINDOW_NS: Final = 60 * 1_000_000_000


@dataclass(frozen=True, slots=True)
class TickPolicy:
    kind: Literal["message", "window"] = "message"
    window_ns: int = 0

    @property
    def window_s(self) -> float:
        return self.window_ns / 1e9

    def __str__(self) -> str:
        return "message" if self.kind == "message" else f"window:{self.window_ns}ns"


MESSAGE: Final = TickPolicy()


def parse_duration(text: str) -> int:
    """``10ms``, ``1.5s``, ``200us``, ``500ns`` to integer nanoseconds (> 0)."""
    m = _DURATION.fullmatch(text)
    if m is None:
        raise ValueError(
            f"{text!r} is not a duration - write a number and a unit, e.g. 10ms, 1.5s, 200us, 500ns"
        )
    ns = math.floor(float(m.group(1)) * _UNITS[m.group(2)])
    if ns <= 0 or ns > MAX_WINDOW_NS:
        raise ValueError(f"duration {text!r} is out of range - give one above 0 and at most 60s")
    return ns


def parse_tick_policy(text: str) -> TickPolicy:
    """``message`` or ``window:<duration>`` (``window:10ms``); ``ValueError`` saying how
    to write it otherwise."""
    text = text.strip()
    if text == "message":
        return MESSAGE
    kind, sep, rest = text.partition(":")
    if kind == "window" and sep:
        return TickPolicy("window", parse_duration(rest))
    raise ValueError(
        f"unknown tick policy {text!r} - use 'message' (one message, one tick) or "
        "'window:<duration>' (a burst within the window is one tick), e.g. window:10ms"
    )


@dataclass(slots=True)
class Arrival:
    """What one message set: stream -> value, at ``ts_ns`` (wall clock, UTC ns)."""

    values: dict[str, object]
    ts_ns: int
    origin: str = ""
    """Where it came from (topic or key), for log messages."""
    count: int = field(default=1)
    """How many messages it stands for (more than 1 after :func:`merge`)."""


def merge(arrivals: Iterable[Arrival]) -> Arrival:
    """One atomic tick from a burst: the last value per stream, the first message's time."""
    it = iter(arrivals)
    try:
        first = next(it)
    except StopIteration:
        raise ValueError("merge() needs at least one arrival") from None
    values = dict(first.values)
    count = first.count
    origins = [first.origin]
    for a in it:
        values.update(a.values)
        count += a.count
        if a.origin not in origins:
            origins.append(a.origin)
    return Arrival(values, first.ts_ns, ",".join(o for o in origins if o), count)
