"""MAPLE-K vocabulary and the records the SDK publishes about stages and knowledge."""

from __future__ import annotations

import enum
from typing import Literal

import msgspec

from .message import Message

__all__ = ["KnowledgeAccess", "Rejection", "Stage", "StageTrace"]


class Stage(enum.StrEnum):
    MONITOR = "monitor"
    ANALYSE = "analyse"
    PLAN = "plan"
    LEGITIMATE = "legitimate"
    EXECUTE = "execute"


class StageTrace(Message, frozen=True, omit_defaults=True):
    """A handler started or ended (``rap/<system>/trace/<node>``)."""

    TYPE = "rap.StageTrace/1"

    node: str
    handler: str
    phase: Literal["start", "end"]
    trigger: bytes
    """uid of the envelope that triggered the handler."""
    trigger_key: str
    cycle: bytes
    ts: int
    stage: Stage | None = None
    """None for a node that declares no MAPLE-K stage."""
    duration_ns: int = 0
    """Handler run time; set on ``end``."""
    ok: bool = True
    error: str = ""
    sent: list[str] = msgspec.field(default_factory=list)
    """On ``end``: the keys of what the handler emitted or published, in order (a
    cycle tracker expects one handler call per subscriber of each)."""


class KnowledgeAccess(Message, frozen=True, omit_defaults=True):
    """A knowledge read or write by a handler (``rap/<system>/trace/<node>``)."""

    TYPE = "rap.KnowledgeAccess/1"

    node: str
    op: Literal["read", "write", "delete"]
    key: str
    version: int
    ts: int
    cycle: bytes | None = None


class Rejection(Message, frozen=True, omit_defaults=True):
    """A sample a node could not accept (``rap/<system>/log/<node>``)."""

    TYPE = "rap.Rejection/1"

    node: str
    key: str
    reason: str
    """What was wrong, with the ``$.path`` from msgspec where there is one."""
    ts: int
    source: str = ""
    type: str = ""
    count: int = 1
    """How many samples were rejected on this key since the last record (rate-limited)."""
