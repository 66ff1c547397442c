"""Stream values on the wire (MQTT payloads, JSON on any transport).

An input payload is one JSON document in one of three forms, told apart by its shape
alone, in this order:

=========  ==========================================  ==============================
form       shape                                       example
=========  ==========================================  ==============================
tagged     the bare strings ``"Unit"`` or              ``{"Int": 42}``, ``"Unknown"``
           ``"Unknown"``; or an object with exactly
           one key that is a D5.2 tag (``Int Float
           Bool Str List Tuple Map Struct``)
wrapped    an object with the key ``"value"`` and      ``{"value": 7}``,
           otherwise at most ``"deferred"`` (bool)     ``{"value": null, "deferred": true}``
plain      anything else                               ``7``, ``"a"``, ``[1, 2]``
=========  ==========================================  ==============================

A wrapped value is read as plain JSON (so ``{"value": {"Int": 1}}`` is the map
``{"Int": 1}``: wrap a plain value that would look tagged); ``"deferred": true`` makes it
⊥. Plain ``null`` is Unit. A tagged-looking document that is not a valid tagged value
(``{"Int": "x"}``) is rejected, never read as a plain map.

Outputs are written wrapped, ``{"value": <plain JSON>}`` (⊥ as
``{"value": null, "deferred": true}``), so one checker's outputs feed another's inputs;
or, on request, tagged (``{"Int": 42}``, ⊥ as ``"Unknown"``). NoVal is never written.

Limits: a payload is at most :data:`MAX_PAYLOAD` bytes, and its JSON document nests
lists and objects at most :data:`MAX_DEPTH` levels (``rap_schemas.limits.MAX_DEPTH``,
counted on the document as sent: in the tagged form each ``{"List": [...]}`` is two
levels). Anything else (too large, too deep, not JSON, not UTF-8, a tagged-looking
document that is not a valid tagged value) raises :class:`CodecError`, a
``DecodeRejected`` whose ``reason`` says why; nothing is decoded recursively before the
depth is checked.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, Final

import msgspec
from rap_schemas.limits import MAX_DEPTH, DecodeRejected, SafeDecoder, check_depth

from ..values import BOTTOM, NOVAL, ValueError_, from_plain, from_tagged, to_plain, to_tagged

__all__ = [
    "MAX_DEPTH",
    "MAX_PAYLOAD",
    "TAGS",
    "CodecError",
    "decode_json",
    "decode_payload",
    "encode_value",
    "payload_form",
]

MAX_PAYLOAD: Final = 1 << 20
"""Largest input payload taken (bytes); larger ones are rejected."""

TAGS: Final = frozenset({"Int", "Float", "Bool", "Str", "List", "Tuple", "Map", "Struct"})
_BARE_TAGS: Final = frozenset({"Unit", "Unknown"})
_WRAP_KEYS: Final = frozenset({"value", "deferred"})

_decode: Callable[[bytes | bytearray | str], Any] = SafeDecoder(
    Any, protocol="json", max_bytes=MAX_PAYLOAD, what="payload"
).decode
_encode = msgspec.json.Encoder().encode
_HOW: Final = 'send one JSON value: 42, {"Int": 42} or {"value": 42}'


class CodecError(DecodeRejected):
    """A payload that is not a stream value; ``reason`` (the message) says why and what
    would be."""


def payload_form(doc: Any) -> str:
    """``"tagged"``, ``"wrapped"`` or ``"plain"``: which form a decoded JSON document is."""
    if type(doc) is str:
        return "tagged" if doc in _BARE_TAGS else "plain"
    if type(doc) is dict:
        if len(doc) == 1 and next(iter(doc)) in TAGS:
            return "tagged"
        if "value" in doc and doc.keys() <= _WRAP_KEYS:
            return "wrapped"
    return "plain"


def decode_json(doc: Any) -> Any:
    """A decoded JSON document (any of the three forms) to a stream value;
    :class:`CodecError` for one nested deeper than :data:`MAX_DEPTH` or not a value."""
    try:
        check_depth(doc, MAX_DEPTH, "the value")
    except DecodeRejected as exc:
        raise CodecError(exc.reason) from None
    return _value(doc)


def _value(doc: Any) -> Any:
    """:func:`decode_json` on a document whose depth is checked."""
    form = payload_form(doc)
    try:
        if form == "tagged":
            return from_tagged(doc)
        if form == "wrapped":
            deferred = doc.get("deferred", False)
            if type(deferred) is not bool:
                raise CodecError(
                    f'"deferred" must be true or false, got {deferred!r} in wrapped value '
                    f"{_clip(doc)} - write true or false"
                )
            return BOTTOM if deferred else from_plain(doc["value"])
        return from_plain(doc)
    except ValueError_ as exc:
        raise CodecError(f"{form} value rejected: {exc}") from None


def _clip(doc: Any, n: int = 80) -> str:
    text = repr(doc)
    return text if len(text) <= n else text[: n - 3] + "..."


def decode_payload(payload: bytes | bytearray | str) -> Any:
    """A payload (UTF-8 JSON) to a stream value; :class:`CodecError` saying why not
    (never anything else, whatever the bytes)."""
    size = len(payload)
    if size > MAX_PAYLOAD:
        raise CodecError(
            f"payload of {size} bytes is larger than the {MAX_PAYLOAD} allowed - send a "
            "smaller value"
        )
    if not size or not (payload.strip() if isinstance(payload, str) else bytes(payload).strip()):
        raise CodecError(f"empty payload - {_HOW}")
    try:
        doc = _decode(payload)
    except DecodeRejected as exc:
        raise CodecError(f"{exc.reason} - {_HOW}") from None
    return decode_json(doc)


def _finite(v: Any) -> Any:
    """JSON has no NaN or infinity: they are written as null."""
    if type(v) is float and not math.isfinite(v):
        return None
    if type(v) is list:
        return [_finite(x) for x in v]
    if type(v) is dict:
        return {k: _finite(x) for k, x in v.items()}
    return v


def encode_value(value: object, *, tagged: bool = False) -> bytes:
    """An output value as a payload: ``{"value": ...}`` (default) or the tagged form.
    ``ValueError`` for NoVal, which is never written."""
    if value is NOVAL:
        raise ValueError("NoVal is never published")
    if tagged:
        return _encode(_finite(to_tagged(value)))
    if value is BOTTOM:
        return _encode({"value": None, "deferred": True})
    return _encode({"value": _finite(to_plain(value))})
