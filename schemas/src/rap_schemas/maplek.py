"""MAPLE-K vocabulary: stages, the plan/verdict messages of the Legitimate gate, and the
records the SDK publishes about stages and knowledge.

The gate's messages are generic over the plan: an application declares its own plan
message (a spin plan, a route to the dock, a model version to deploy) and proposes it in
a ``PlanProposal[ItsPlan]``; ``plan_type`` names the plan's wire type so that a stage
that judges one kind of plan refuses another with a clear reason. Decoded without a type
parameter (a recorder, the trust checker), ``plan`` is plain data.
"""

from __future__ import annotations

import enum
from typing import Annotated, Final, Generic, Literal, TypeVar

import msgspec

from .message import Message

__all__ = [
    "NEW_PLAN",
    "PLAN_REJECTED",
    "VERDICT",
    "Access",
    "Empty",
    "KnowledgeAccess",
    "PlanProposal",
    "Rejection",
    "Stage",
    "StageTrace",
    "Verdict",
]

P = TypeVar("P")

NEW_PLAN: Final = "new-plan"
"""The event a plan is proposed on (a ``PlanProposal``)."""
VERDICT: Final = "verdict"
"""The event the Legitimate stage answers every proposal on (a ``Verdict``)."""
PLAN_REJECTED: Final = "plan-rejected"
"""The event a rejected or refused plan is announced on (a ``Verdict``): the planner's
cue to replan within its budget."""

Uid = Annotated[bytes, msgspec.Meta(min_length=16, max_length=16)]
Nanos = Annotated[int, msgspec.Meta(ge=0)]
"""UTC wall clock, integer nanoseconds."""


class Empty(Message, frozen=True):
    """A body-less event (what ``ctx.emit(name)`` sends without a message)."""

    TYPE = "rap.Empty/1"


class PlanProposal(Message, Generic[P], frozen=True):
    """A plan put to the Legitimate stage (event ``new-plan``)."""

    TYPE = "rap.PlanProposal/1"

    plan_uid: Uid
    plan_type: str
    """The wire type of ``plan`` (its ``TYPE``, e.g. ``rap.SpinPlan/1``)."""
    plan: P
    proposer: str
    created: Nanos
    """When the plan was made; the gate refuses stale plans and plans from the future."""


class Verdict(Message, Generic[P], frozen=True, omit_defaults=True):
    """The Legitimate stage's decision on one plan.

    An approving verdict carries the proposal it approves: the execute side acts on
    exactly that plan, never on whatever a knowledge key holds by then."""

    TYPE = "rap.Verdict/1"

    plan_uid: Uid
    approved: bool
    legitimator: str
    ts: Nanos
    reason: str = ""
    proposal: PlanProposal[P] | None = None


class Stage(enum.StrEnum):
    MONITOR = "monitor"
    ANALYSE = "analyse"
    PLAN = "plan"
    LEGITIMATE = "legitimate"
    EXECUTE = "execute"


class Access(msgspec.Struct, frozen=True, array_like=True):
    """A knowledge read, write or delete of a handler call, in a :class:`StageTrace`."""

    op: Literal["read", "write", "delete"]
    key: str
    version: int
    """The version read (the newest known: 0 for none) or written."""
    ts: int
    """When, UTC ns."""


class StageTrace(Message, frozen=True, omit_defaults=True):
    """A handler call (``rap/<system>/trace/<node>``): one ``call`` record, published
    when the handler returns and before what it sent; or, for a call that sent before
    it returned (``ctx.flush()``), a ``start`` record before those sends and an ``end``
    record after the call."""

    TYPE = "rap.StageTrace/2"

    node: str
    handler: str
    phase: Literal["start", "end", "call"]
    trigger: bytes
    """uid of the envelope that triggered the handler."""
    trigger_key: str
    cycle: bytes
    ts: int
    """When the handler started (``call``, ``start``) or ended (``end``), UTC ns."""
    stage: Stage | None = None
    """None for a node that declares no MAPLE-K stage."""
    duration_ns: int = 0
    """Handler run time; set on ``call`` and ``end``."""
    ok: bool = True
    error: str = ""
    sent: list[str] = msgspec.field(default_factory=list)
    """On ``call`` and ``end``: the keys of what the handler emitted or published, in
    order (a cycle tracker expects one handler call per subscriber of each)."""
    access: list[Access] = msgspec.field(default_factory=list)
    """The handler's knowledge reads and writes, in order (on ``start``: those before
    the flush; on ``end``: those after)."""

    @property
    def started(self) -> bool:
        """The record tells that the handler started (``start`` or ``call``)."""
        return self.phase != "end"

    @property
    def ended(self) -> bool:
        """The record tells that the handler ended (``end`` or ``call``)."""
        return self.phase != "start"


class KnowledgeAccess(Message, frozen=True, omit_defaults=True):
    """A knowledge read or write by a handler, as a record of its own (the runtime now
    lists them in its :class:`StageTrace`; checkers still take these from other
    senders)."""

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
