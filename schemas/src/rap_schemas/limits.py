"""The limits of every decoder that reads input from outside the process.

No input, however shaped, ends a process: a payload over its size limit, nested deeper
than allowed, undecodable or of the wrong type is *rejected* with a reason, counted,
and the reader carries on. The limits are explicit:

======================  =====================================================  =========
what                    where                                                  limit
======================  =====================================================  =========
fabric sample           one envelope on a subscription (``MAX_SAMPLE_BYTES``;   4 MiB
                        a route or subscription may set its own)
fabric message          what a Zenoh link reassembles: the model's             257 MiB
                        ``fabric.max_sample_bytes`` (``MAX_MESSAGE_BYTES``
                        by default) plus ``MESSAGE_HEADROOM``; a link that
                        ``rap up`` configures drops a bigger message unread
knowledge value         one record's value (the service's ``max_value_bytes``)  1 MiB
untyped nesting         lists and maps inside a value decoded without a type   32 levels
                        (knowledge read without a type, ``Any`` fields, trust
                        stream values over MQTT or the fabric): ``MAX_DEPTH``
typed nesting           a typed message is as deep as its schema; unknown      (schema)
                        fields it skips are bounded by the decoder's own
                        recursion guard and rejected as "nested too deeply"
YAML file               plans, worlds, configs: ``MAX_YAML_BYTES`` and          4 MiB,
                        ``MAX_YAML_DEPTH`` nested collections                  64 levels
text file               trust specs and trace files: ``MAX_TEXT_BYTES``        64 MiB
======================  =====================================================  =========

:func:`decode_failure` words any exception a msgspec decoder raises (including the
``RecursionError`` of its nesting guard and the ``UnicodeDecodeError`` of a string that
is not UTF-8); :data:`DECODE_ERRORS` is the tuple to catch.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Final, Generic, TypeVar

import msgspec

__all__ = [
    "DECODE_ERRORS",
    "MAX_DEPTH",
    "MAX_MESSAGE_BYTES",
    "MAX_SAMPLE_BYTES",
    "MAX_TEXT_BYTES",
    "MAX_YAML_BYTES",
    "MAX_YAML_DEPTH",
    "MESSAGE_HEADROOM",
    "DecodeRejected",
    "SafeDecoder",
    "check_depth",
    "decode_failure",
]

T = TypeVar("T")

MAX_SAMPLE_BYTES: Final = 4 << 20
MAX_DEPTH: Final = 32
MAX_YAML_BYTES: Final = 4 << 20
MAX_YAML_DEPTH: Final = 64
MAX_TEXT_BYTES: Final = 64 << 20
MAX_MESSAGE_BYTES: Final = 257 << 20
"""The largest payload RAP's own services send in one fabric message: a model-store request
or reply (a model of the knowledge service's default ``max_model_bytes``, 256 MiB, and
1 MiB for the rest). The default of the model's ``fabric.max_sample_bytes``."""
MESSAGE_HEADROOM: Final = 64 << 10
"""What a fabric message carries beside its payload (key expression, attachment such as a
signed request with its certificate, Zenoh's headers): Zenoh's link limit
(``transport.link.rx.max_message_size``) is a payload limit plus this."""

DECODE_ERRORS: Final = (msgspec.MsgspecError, RecursionError, ValueError)
"""What a msgspec decoder may raise on bad input: its own errors, ``RecursionError``
from its nesting guard, ``UnicodeDecodeError`` (a ``ValueError``) for a string that is
not UTF-8."""


class DecodeRejected(ValueError):
    """Input that cannot be accepted; ``reason`` says why, fit for a rejection record."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


def decode_failure(exc: BaseException) -> str:
    """A reason for a decoder's exception (one of :data:`DECODE_ERRORS`)."""
    if isinstance(exc, RecursionError):
        return "nested too deeply (the decoder's nesting guard stopped it)"
    if isinstance(exc, UnicodeDecodeError):
        return f"a string is not valid UTF-8 (byte {exc.start})"
    if isinstance(exc, msgspec.ValidationError):
        return str(exc)
    if isinstance(exc, msgspec.DecodeError):
        return f"undecodable: {exc}"
    return f"{type(exc).__name__}: {exc}"


def check_depth(value: Any, max_depth: int = MAX_DEPTH, what: str = "value") -> Any:
    """``value`` if its lists, tuples and maps nest at most ``max_depth`` levels, else
    :class:`DecodeRejected`. Iterative: any depth is measured without recursion; a
    container of scalars only (a scan's ranges) is passed over at C speed."""
    stack: list[tuple[Any, int]] = [(value, 0)]
    pop, push = stack.pop, stack.append
    while stack:
        item, depth = pop()
        if isinstance(item, (list, tuple)):
            children: Any = item
        elif isinstance(item, dict):
            children = item.values()
        else:
            continue
        if depth >= max_depth:
            raise DecodeRejected(
                f"{what} nests lists or maps more than {max_depth} levels deep; flatten it"
            )
        if not any(_container_type(k) for k in set(map(type, children))):
            continue  # scalars only
        for child in children:
            if isinstance(child, (list, tuple, dict)):
                push((child, depth + 1))
    return value


_CONTAINER_TYPES: dict[type, bool] = {}


def _container_type(cls: type) -> bool:
    hit = _CONTAINER_TYPES.get(cls)
    if hit is None:
        hit = issubclass(cls, (list, tuple, dict))
        if len(_CONTAINER_TYPES) < 1024:
            _CONTAINER_TYPES[cls] = hit
    return hit


class SafeDecoder(Generic[T]):
    """A msgspec decoder (``msgpack`` or ``json``) with a size limit and, for values with
    untyped parts, a depth limit; every failure is one :class:`DecodeRejected`.

        decode = SafeDecoder(KbReply, max_bytes=1 << 20).decode
        reply = decode(payload)          # DecodeRejected("... over the limit ...")
    """

    __slots__ = ("_decode", "max_bytes", "max_depth", "what")

    def __init__(
        self,
        type: Any = Any,
        *,
        protocol: str = "msgpack",
        max_bytes: int = MAX_SAMPLE_BYTES,
        max_depth: int | None = None,
        what: str = "payload",
    ) -> None:
        """``max_depth``: also check the decoded value's nesting (for untyped values;
        None: the type bounds it)."""
        if protocol == "msgpack":
            self._decode: Callable[[bytes], T] = msgspec.msgpack.Decoder(type).decode
        elif protocol == "json":
            self._decode = msgspec.json.Decoder(type).decode
        else:
            raise ValueError(f"protocol must be 'msgpack' or 'json', got {protocol!r}")
        self.max_bytes = max_bytes
        self.max_depth = max_depth
        self.what = what

    def decode(self, data: bytes | bytearray | memoryview | str) -> T:
        if len(data) > self.max_bytes:
            raise DecodeRejected(
                f"{self.what} of {len(data)} bytes is over the limit of {self.max_bytes}"
            )
        try:
            value = self._decode(data)  # type: ignore[arg-type]
        except DECODE_ERRORS as exc:
            raise DecodeRejected(f"{self.what}: {decode_failure(exc)}") from None
        if self.max_depth is not None:
            check_depth(value, self.max_depth, self.what)
        return value
