"""Key expressions of the RAP key space (docs/architecture.md, "Key space").

Every key that crosses a service boundary is built here; code elsewhere never
writes a key as a string literal.

    rap/<system>/data/<topic>            managed-system streams
    rap/<system>/event/<name>            MAPLE-K events
    rap/<system>/kb/<key>                knowledge
    rap/<system>/trace/<node>            stage and knowledge trace records
    rap/<system>/trust/<stream>          trust-checker outputs
    rap/<system>/log/<node>              structured logs and rejections
    rap/<system>/alive/<node>            liveliness tokens
    rap/<system>/admin/<node>/<verb>     admin queryables

``system``, ``node`` and ``verb`` are single chunks; ``topic``, event ``name``, knowledge
``key`` and trust ``stream`` may span several chunks (``tb1/scan``). No chunk may be
empty or contain the Zenoh wildcard and reserved characters ``* $ # ?``. Patterns with
wildcards are built only by :func:`pattern`.
"""

from __future__ import annotations

import enum
import re
from typing import Final, NamedTuple

__all__ = [
    "ROOT",
    "KeyError_",
    "Kind",
    "ParsedKey",
    "admin",
    "alive",
    "data",
    "event",
    "kb",
    "log",
    "parse",
    "pattern",
    "system_pattern",
    "trace",
    "trust",
]

ROOT: Final = "rap"

_CHUNK = re.compile(r"[A-Za-z0-9_.\-~+:@=%,]+")


class Kind(enum.StrEnum):
    """The second-level families of the key space."""

    DATA = "data"
    EVENT = "event"
    KB = "kb"
    TRACE = "trace"
    TRUST = "trust"
    LOG = "log"
    ALIVE = "alive"
    ADMIN = "admin"


#: kinds whose name is one chunk (a node id); the others take a multi-chunk path
_SINGLE_CHUNK: Final = frozenset({Kind.TRACE, Kind.LOG, Kind.ALIVE})


class KeyError_(ValueError):
    """A key or one of its parts is malformed; the message names the part and the fix."""


class ParsedKey(NamedTuple):
    system: str
    kind: Kind
    name: str
    verb: str | None = None


def _chunk(what: str, value: str) -> str:
    if not isinstance(value, str) or not _CHUNK.fullmatch(value):
        raise KeyError_(
            f"invalid {what} {value!r}: use one non-empty chunk of letters, digits and "
            "'_.-~+:@=%,' (no '/', no wildcards '*', '$', '#', '?')"
        )
    return value


def _path(what: str, value: str) -> str:
    if not isinstance(value, str) or not value:
        raise KeyError_(f"invalid {what} {value!r}: must be a non-empty string")
    for part in value.split("/"):
        if not _CHUNK.fullmatch(part):
            raise KeyError_(
                f"invalid {what} {value!r}: chunk {part!r} is empty or has a forbidden "
                "character; chunks are separated by single '/' and may not use '*', '$', "
                "'#', '?'"
            )
    return value


def _build(system: str, kind: Kind, name: str) -> str:
    return f"{ROOT}/{_chunk('system', system)}/{kind.value}/{name}"


def data(system: str, topic: str) -> str:
    """``rap/<system>/data/<topic>``"""
    return _build(system, Kind.DATA, _path("topic", topic))


def event(system: str, name: str) -> str:
    """``rap/<system>/event/<name>``"""
    return _build(system, Kind.EVENT, _path("event name", name))


def kb(system: str, key: str) -> str:
    """``rap/<system>/kb/<key>``"""
    return _build(system, Kind.KB, _path("knowledge key", key))


def trace(system: str, node: str) -> str:
    """``rap/<system>/trace/<node>``"""
    return _build(system, Kind.TRACE, _chunk("node", node))


def trust(system: str, stream: str) -> str:
    """``rap/<system>/trust/<stream>``"""
    return _build(system, Kind.TRUST, _path("trust stream", stream))


def log(system: str, node: str) -> str:
    """``rap/<system>/log/<node>``"""
    return _build(system, Kind.LOG, _chunk("node", node))


def alive(system: str, node: str) -> str:
    """``rap/<system>/alive/<node>``"""
    return _build(system, Kind.ALIVE, _chunk("node", node))


def admin(system: str, node: str, verb: str) -> str:
    """``rap/<system>/admin/<node>/<verb>``"""
    return _build(system, Kind.ADMIN, f"{_chunk('node', node)}/{_chunk('admin verb', verb)}")


def pattern(system: str, kind: Kind, name: str = "**") -> str:
    """A wildcard expression over one family: ``pattern("s", Kind.EVENT)`` is
    ``rap/s/event/**``. ``name`` may use the Zenoh wildcards ``*`` and ``**`` as whole
    chunks."""
    for part in name.split("/"):
        if part not in ("*", "**"):
            _chunk("pattern chunk", part)
    return f"{ROOT}/{_chunk('system', system)}/{Kind(kind).value}/{name}"


def system_pattern(system: str) -> str:
    """Every key of one system: ``rap/<system>/**``."""
    return f"{ROOT}/{_chunk('system', system)}/**"


def parse(key: str) -> ParsedKey:
    """Split a concrete key into (system, kind, name[, verb]); the inverse of the
    builders. Raises :class:`KeyError_` naming what is wrong."""
    parts = key.split("/")
    if len(parts) < 4 or parts[0] != ROOT:
        raise KeyError_(
            f"not a RAP key: {key!r}; expected 'rap/<system>/<kind>/<name>' "
            f"with <kind> one of {', '.join(k.value for k in Kind)}"
        )
    system = _chunk("system", parts[1])
    try:
        kind = Kind(parts[2])
    except ValueError:
        raise KeyError_(
            f"unknown kind {parts[2]!r} in {key!r}; use one of {', '.join(k.value for k in Kind)}"
        ) from None
    rest = parts[3:]
    if kind is Kind.ADMIN:
        if len(rest) != 2:
            raise KeyError_(f"admin key {key!r} must be 'rap/<system>/admin/<node>/<verb>'")
        return ParsedKey(system, kind, _chunk("node", rest[0]), _chunk("admin verb", rest[1]))
    name = "/".join(rest)
    if kind in _SINGLE_CHUNK:
        _chunk("node", name)
    else:
        _path("name", name)
    return ParsedKey(system, kind, name)
