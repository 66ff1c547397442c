"""What the manager shows: the JSON the dashboard receives and ``rap trace`` asks for.

Every Struct here is encoded with ``msgspec.json``; strings in them come from the fabric
(component names, log text, reasons) and are shown by the page as text, never as HTML.
The ``rap trace`` messages (:class:`TraceRequest`, :class:`TraceReply`) travel on the
manager's queryable ``rap/<system>/admin/manager/trace``.
"""

from __future__ import annotations

from typing import Any, Final

import msgspec

__all__ = [
    "MANAGER",
    "TRACE_VERB",
    "AlertView",
    "CallView",
    "CauseView",
    "ComponentView",
    "CycleTrace",
    "CycleView",
    "LogView",
    "PlanView",
    "TraceReply",
    "TraceRequest",
    "TraceStep",
    "TrustOutputView",
    "TrustVerdictView",
]

MANAGER: Final = "manager"
"""The adaptation manager's node name: its liveliness token ``rap/<system>/alive/manager``
and its queryable ``rap/<system>/admin/manager/trace``."""
TRACE_VERB: Final = "trace"


class ComponentView(msgspec.Struct, kw_only=True):
    """One component as the manager knows it (liveliness, its status answers, its traces)."""

    name: str
    state: str
    """A ``ComponentState`` value (starting, idle, active, paused, failed, gone), or
    ``alive``: its liveliness token is up but it does not answer the admin verbs (a
    process that is not a component runtime: the knowledge service)."""
    alive: bool
    compute_node: str = ""
    stage: str = ""
    implementation: str = ""
    answers: bool = False
    """It answered the admin ``status`` query at least once."""
    last_cycle: str = ""
    last_call: int = 0
    p50_ms: float = 0.0
    p99_ms: float = 0.0
    inbox: int = 0
    received: int = 0
    handled: int = 0
    failed: int = 0
    rejected: int = 0
    dropped: int = 0
    restarts: int = 0
    swaps: int = 0
    paused_policy: str = ""
    updated: int = 0
    """When the manager last learned something of it (UTC ns)."""


class CallView(msgspec.Struct, kw_only=True):
    """One handler call of a cycle."""

    node: str
    handler: str
    stage: str
    trigger_key: str
    start: int
    """UTC ns."""
    duration_ns: int
    ended: bool
    ok: bool
    error: str = ""


class CycleView(msgspec.Struct, kw_only=True):
    """One loop cycle in the timeline."""

    cycle: str
    """The hex uid of the sample that started it."""
    state: str
    """``open`` (something outstanding), ``done``, ``executed`` (a plan reached the execute
    stage and nothing is outstanding) or ``stalled`` (outstanding past the deadline)."""
    start: int
    end: int
    stages: list[str]
    """The MAPLE-K stages that ran in it, in the order they first ran."""
    calls: list[CallView]
    plans: list[str]
    outstanding: list[str]


class PlanView(msgspec.Struct, kw_only=True):
    """A plan through the Legitimate gate."""

    plan: str
    """Hex plan uid."""
    cycle: str
    status: str
    """``proposed``, ``approved``, ``rejected``, ``executed`` or ``refused`` (approved, but
    the execute stage's gate refused it)."""
    proposer: str = ""
    plan_type: str = ""
    created: int = 0
    legitimator: str = ""
    reason: str = ""
    decided: int = 0
    executor: str = ""
    executed: int = 0


class TrustOutputView(msgspec.Struct, kw_only=True):
    """The latest value of one trust-checker output stream."""

    stream: str
    tick: int
    ts: int
    value: str
    """The value as JSON text (cut at a bound)."""
    deferred: bool = False
    false: bool = False
    """A Bool output that is false now."""


class CauseView(msgspec.Struct, kw_only=True):
    expr: str
    value: str
    depth: int = 0
    input: str = ""
    input_tick: int | None = None


class TrustVerdictView(msgspec.Struct, kw_only=True):
    """A trust verdict: a Bool output turned false, or a trigger fired, and why."""

    stream: str
    tick: int
    ts: int
    value: str
    kind: str
    expr: str = ""
    message: str = ""
    severity: str = ""
    because: list[CauseView] = msgspec.field(default_factory=list)
    truncated: bool = False


class LogView(msgspec.Struct, kw_only=True):
    """A line of the log tail."""

    ts: int
    level: str
    source: str
    text: str
    kind: str
    """``log`` (a LogRecord), ``rejection`` (a Rejection), ``other``."""


class AlertView(msgspec.Struct, kw_only=True):
    """What a watch found: a component gone or failing, a stalled cycle, a false verdict."""

    ts: int
    kind: str
    """``gone``, ``failed``, ``stalled`` or ``trust``."""
    subject: str
    message: str


# -- rap trace ------------------------------------------------------------------------------


class TraceRequest(msgspec.Struct, kw_only=True, omit_defaults=True, forbid_unknown_fields=True):
    """What ``rap trace`` asks the manager: one cycle by (a prefix of) its hex uid, or the
    latest complete one."""

    cycle: str = ""
    last: bool = False
    executed: bool = False
    """With ``last``: the latest complete cycle in which a plan reached the execute stage."""


class TraceStep(msgspec.Struct, kw_only=True):
    """One handler call in a cycle's causal chain."""

    depth: int
    """0 for a call on the cycle's first sample; a call on what another call sent is one
    deeper."""
    node: str
    handler: str
    stage: str
    trigger: str
    """Hex uid of the sample it handled."""
    trigger_key: str
    trigger_source: str
    """The sender of that sample, when the manager saw it ("" for data it does not follow)."""
    trigger_ts: int
    """When that sample was sent (UTC ns; 0: not known)."""
    start: int
    offset_ms: float
    """From the cycle's start to this call's start."""
    wait_ms: float | None
    """From its sample's sending to this call's start (transport and queue), when known."""
    duration_ms: float
    ended: bool
    ok: bool
    error: str
    sent: list[str]


class CycleTrace(msgspec.Struct, kw_only=True):
    """One cycle's causal chain, from its first sample to the last call."""

    system: str
    cycle: str
    state: str
    start: int
    """When its first sample was made (UTC ns, from the cycle uid's timestamp)."""
    end: int
    """When its last call ended (UTC ns)."""
    total_ms: float
    root_key: str
    executed: bool
    steps: list[TraceStep]
    plans: list[PlanView]
    outstanding: list[str]


class TraceReply(msgspec.Struct, kw_only=True, omit_defaults=True):
    ok: bool
    message: str = ""
    trace: CycleTrace | None = None
    matches: list[str] = msgspec.field(default_factory=list)
    """For an ambiguous prefix: the cycles it matches (at most a few)."""


def short_json(value: Any, limit: int = 240) -> str:
    """``value`` as JSON text, cut at ``limit`` characters."""
    try:
        text = msgspec.json.encode(value).decode()
    except (TypeError, msgspec.EncodeError):
        text = repr(value)
    return text if len(text) <= limit else text[: limit - 1] + "…"
