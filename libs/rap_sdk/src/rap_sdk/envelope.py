"""Sealing and opening envelopes (docs/architecture.md, "Envelope").

:class:`Sealer` stamps what a sender owes every message: a UUIDv7 ``uid``, ``ts``, a
per-key ``seq``, and the ``cycle``/``cause``/``ctx`` it is given. :class:`Opener` decodes
an envelope strictly (``RejectedSample`` with the ``$.path`` otherwise) and drops
duplicates while counting gaps and reordering per sender and key.
"""

from __future__ import annotations

import os
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Final, Generic, Protocol, TypeVar

import msgspec
from rap_schemas import Empty, Envelope, Message
from rap_schemas.limits import DECODE_ERRORS, decode_failure

from .errors import RejectedSample
from .fabric._types import Outgoing

__all__ = [
    "Clock",
    "Opener",
    "OutgoingEnvelope",
    "Sealer",
    "SenderStats",
    "SystemClock",
    "TypedEnvelope",
    "new_uid",
    "typed_decoder",
]

_VARIANT: Final = 0b10 << 62
_MASK62: Final = (1 << 62) - 1
_PACK = struct.Struct(">QQ").pack


class Clock(Protocol):
    def time_ns(self) -> int:
        """UTC wall clock, integer nanoseconds."""


class SystemClock:
    time_ns = staticmethod(time.time_ns)
    """UTC wall clock, integer nanoseconds (``time.time_ns`` itself: no Python frame)."""


class _UidSource:
    """UUIDv7 (RFC 9562): 48-bit ms timestamp, version 7, a 12-bit sub-ms counter in
    rand_a, the variant, and in rand_b 62 bits that start at a random value from the OS
    and count up per message: unique within the process by the counter, across
    processes by the random start (uniqueness, not secrecy, is what a message id needs).
    """

    __slots__ = ("_counter", "_hi", "_last_ms", "_low")

    def __init__(self) -> None:
        self._low = int.from_bytes(os.urandom(8)) & _MASK62
        self._last_ms = -1
        self._counter = 0
        self._hi = 0

    def __call__(self, ts_ns: int) -> bytes:
        ms = ts_ns // 1_000_000
        if ms == self._last_ms:
            self._counter = (self._counter + 1) & 0xFFF
        else:
            self._last_ms = ms
            self._counter = 0
            self._hi = (ms & 0xFFFF_FFFF_FFFF) << 16 | 0x7 << 12
        self._low = (self._low + 1) & _MASK62
        return _PACK(self._hi | self._counter, _VARIANT | self._low)

    at = __call__
    """The same as a method (cheaper to call than the instance itself)."""


new_uid = _UidSource()
_EMPTY: Final = Empty()


B = TypeVar("B")


class TypedEnvelope(msgspec.Struct, Generic[B], frozen=True, kw_only=True, omit_defaults=True):
    """An :class:`~rap_schemas.Envelope` decoded together with its body in one pass, by a
    decoder built once per handler (``body`` is the typed message, or ``msgspec.Raw``
    for a handler that takes no message)."""

    uid: bytes
    ts: int
    source: str
    seq: int
    type: str
    body: B
    cycle: bytes | None = None
    cause: bytes | None = None
    ctx: dict[str, int] = {}


def typed_decoder(msg_type: type[Any] | None) -> Callable[[bytes], TypedEnvelope[Any]]:
    """The one-pass decoder of envelopes whose body is ``msg_type`` (any body: None)."""
    body = msgspec.Raw if msg_type is None else msg_type
    return msgspec.msgpack.Decoder(TypedEnvelope[body]).decode  # type: ignore[valid-type]


_ANY_BODY = typed_decoder(None)


class OutgoingEnvelope(msgspec.Struct, frozen=True, kw_only=True, omit_defaults=True):
    """What a sender builds: the :class:`~rap_schemas.Envelope` fields in the same order,
    with ``body`` still the message object, so that envelope and body are encoded in one
    pass. On the wire it is an ``Envelope``."""

    uid: bytes
    ts: int
    source: str
    seq: int
    type: str
    body: Any
    cycle: bytes | None = None
    cause: bytes | None = None
    ctx: dict[str, int] = {}


_encode = msgspec.msgpack.Encoder().encode


class Sealer:
    """Builds outgoing envelopes for one sender."""

    __slots__ = ("_now", "_seq", "source")

    def __init__(self, source: str, clock: Clock | None = None) -> None:
        self.source = source
        self._now = time.time_ns if clock is None or type(clock) is SystemClock else clock.time_ns
        self._seq: dict[str, int] = {}

    def seal_message(
        self,
        key: str,
        message: Message | None,
        *,
        cycle: bytes | None = None,
        cause: bytes | None = None,
        ctx: dict[str, int] | None = None,
    ) -> tuple[bytes, OutgoingEnvelope]:
        """Seal a typed message (None: an ``rap.Empty/1`` event): envelope and body are
        encoded in one pass."""
        out = self.seal_out(key, message, cycle=cycle, cause=cause, ctx=ctx)
        return out.data, out.obj

    def seal_out(
        self,
        key: str,
        message: Message | None,
        *,
        cycle: bytes | None = None,
        cause: bytes | None = None,
        ctx: dict[str, int] | None = None,
    ) -> Outgoing:
        """Seal a typed message for :meth:`Fabric.publish`: local subscribers may take
        the envelope object itself; the bytes are made once, when first needed."""
        if message is None:
            message = _EMPTY
        seqs = self._seq
        seq = seqs.get(key, 0)
        seqs[key] = seq + 1
        ts = self._now()
        env = OutgoingEnvelope(
            uid=new_uid.at(ts),
            ts=ts,
            source=self.source,
            seq=seq,
            type=message.TYPE,
            body=message,
            cycle=cycle,
            cause=cause,
            ctx=ctx or {},
        )
        return Outgoing(env, _encode)

    def seal(
        self,
        key: str,
        type_name: str,
        body: bytes,
        *,
        cycle: bytes | None = None,
        cause: bytes | None = None,
        ctx: dict[str, int] | None = None,
    ) -> tuple[bytes, OutgoingEnvelope]:
        """Seal a body already encoded as msgpack, under wire type ``type_name`` (for
        relays and tests that need a body of their own making)."""
        env = self._envelope(key, type_name, msgspec.Raw(body), cycle, cause, ctx)
        return _encode(env), env

    def _envelope(
        self,
        key: str,
        type_name: str,
        body: Any,
        cycle: bytes | None,
        cause: bytes | None,
        ctx: dict[str, int] | None,
    ) -> OutgoingEnvelope:
        seq = self._seq.get(key, 0)
        self._seq[key] = seq + 1
        ts = self._now()
        return OutgoingEnvelope(
            uid=new_uid(ts),
            ts=ts,
            source=self.source,
            seq=seq,
            type=type_name,
            body=body,
            cycle=cycle,
            cause=cause,
            ctx=ctx or {},
        )


@dataclass(slots=True)
class SenderStats:
    duplicates: int = 0
    missing: int = 0
    """Samples skipped in a sender's sequence and not (yet) seen late."""
    reordered: int = 0
    restarts: int = 0
    """A lower seq with a newer ts: the sender restarted and its seq began again."""
    stale: int = 0
    """Samples older than the 64-sample window (and not newer in ts): dropped, since
    they cannot be told from a replay."""
    future: int = 0
    """Samples dated further ahead of this clock than ``Opener.max_skew_ns``: rejected."""


_WINDOW: Final = 64
_FULL: Final = (1 << _WINDOW) - 1
MAX_SKEW_NS: Final = 5_000_000_000
"""How far ahead of the receiver's clock an envelope's ``ts`` may be (clocks of two
machines differ a little). A sample from further ahead is rejected: taken as the newest
of its sender, it would make the sender's real samples look stale."""


class Opener:
    """Strict envelope decoding plus per-(source, key) sequence tracking; envelopes
    dated more than ``max_skew_ns`` ahead of ``clock`` are rejected."""

    __slots__ = ("_decode", "_now", "_streams", "max_skew_ns", "stats")

    def __init__(self, clock: Clock | None = None, *, max_skew_ns: int = MAX_SKEW_NS) -> None:
        self._decode = msgspec.msgpack.Decoder(Envelope).decode
        self._now = time.time_ns if clock is None or type(clock) is SystemClock else clock.time_ns
        self._streams: dict[tuple[str, str], list[int]] = {}
        self.max_skew_ns = max_skew_ns
        self.stats = SenderStats()

    def open_typed(
        self,
        key: str,
        payload: bytes,
        decode: Callable[[bytes], TypedEnvelope[Any]],
        expected: str | None,
        prepared: TypedEnvelope[Any] | None = None,
    ) -> TypedEnvelope[Any] | None:
        """Decode envelope and body in one pass with ``decode`` (or take ``prepared``,
        the same decoding done already on the transport thread); check the wire type is
        ``expected`` (None: any). ``None`` for a duplicate; :class:`RejectedSample` with
        the reason otherwise (the slow path, taken only for bad samples, words it)."""
        try:
            env = prepared if prepared is not None else decode(payload)
        except DECODE_ERRORS as exc:
            raw = self._diagnose(payload)  # raises when the envelope itself is bad
            who = {"source": raw.source, "type": raw.type}
            if expected is not None and raw.type != expected:
                raise RejectedSample(f"expected type {expected}, got {raw.type!r}", **who) from None
            reason = decode_failure(exc).replace("`$.body", "`$")
            raise RejectedSample(f"invalid {raw.type} body: {reason}", **who) from None
        if expected is not None and env.type != expected:
            raise RejectedSample(
                f"expected type {expected}, got {env.type!r}", source=env.source, type=env.type
            )
        if len(env.uid) != 16 or env.seq < 0:
            raise RejectedSample(
                f"invalid envelope: uid must be 16 bytes and seq >= 0, got "
                f"{len(env.uid)} bytes and seq={env.seq}",
                source=env.source,
                type=env.type,
            )
        ahead = env.ts - self._now()
        if ahead > self.max_skew_ns:
            self.stats.future += 1
            raise RejectedSample(
                f"envelope dated {ahead / 1e9:.3f} s in the future (at most "
                f"{self.max_skew_ns / 1e9:g} s of clock skew is accepted): check the sender's "
                "clock",
                source=env.source,
                type=env.type,
            )
        return env if self._track(env.source, key, env.seq, env.ts) else None

    def _diagnose(self, payload: bytes) -> Envelope:
        try:
            return self._decode(payload)
        except msgspec.ValidationError as exc:
            raise RejectedSample(f"invalid envelope: {exc}") from None
        except DECODE_ERRORS as exc:
            raise RejectedSample(
                f"undecodable envelope ({len(payload)} bytes): {decode_failure(exc)}"
            ) from None

    def open(self, key: str, payload: bytes) -> TypedEnvelope[msgspec.Raw] | None:
        """The envelope with its body left raw, or ``None`` for a duplicate; raises
        :class:`RejectedSample`."""
        return self.open_typed(key, payload, _ANY_BODY, None)

    def _track(self, source: str, key: str, seq: int, ts: int) -> bool:
        """Within one sender instance seq and ts grow together. A lower seq with a
        *newer* ts than the highest seen means the sender restarted (its seq began
        again); a lower seq with an older ts is late (reordered) or a duplicate.

        State per stream: highest seq, a bitmap of the 64 seqs below it (1 = seen), the
        highest seq's ts, and the first seq seen (samples before it were never counted
        missing, so a late one does not reduce ``missing``)."""
        st = self._streams.get((source, key))
        if st is None:
            if len(self._streams) >= 65536:
                self._streams.clear()
            self._streams[(source, key)] = [seq, 1, ts, seq]
            return True
        hi, mask, hi_ts, base = st
        stats = self.stats
        if seq > hi:
            d = seq - hi
            if d > 1:
                stats.missing += d - 1
            st[0], st[2] = seq, ts
            st[1] = ((mask << d) | 1) & _FULL if d < _WINDOW else 1
            return True
        if ts > hi_ts:
            stats.restarts += 1
            st[0], st[1], st[2], st[3] = seq, 1, ts, seq
            return True
        back = hi - seq
        if back >= _WINDOW:
            stats.stale += 1  # too old to tell from a replay: dropped
            return False
        bit = 1 << back
        if mask & bit:
            stats.duplicates += 1
            return False
        st[1] = mask | bit
        stats.reordered += 1
        if seq > base:
            stats.missing -= 1
        return True
