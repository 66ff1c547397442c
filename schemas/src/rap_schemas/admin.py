"""The management plane's messages: what the admin queryables
``rap/<system>/admin/<node>/<verb>`` take and answer.

Each runtime (one per component) serves the verbs below. A query's payload is the
verb's request as JSON (empty for the verbs that take nothing); every answer is one
:class:`AdminReply` as JSON, ``ok`` false with the reason when the verb was refused.
JSON rather than msgpack: an operator can read them with any Zenoh tool.

========= ===================== =====================================================
verb      request               answer (``AdminReply``)
========= ===================== =====================================================
status    -                     ``status``
config    ``ConfigRequest``     ``config`` (get when ``values`` is empty, else set)
pause     -                     ``status`` (paused)
resume    -                     ``status``
restart   ``RestartRequest``    ``status`` (a fresh instance, its state kept or restored)
swap      ``ComponentSwap``       ``status`` (the new implementation, state handed over)
snapshot  -                     ``snapshot`` (also kept in knowledge)
restore   ``RestoreRequest``    ``status``
========= ===================== =====================================================
"""

from __future__ import annotations

import enum
from typing import Any, Final

import msgspec

__all__ = [
    "ADMIN_VERBS",
    "PAUSE_POLICY",
    "AdminReply",
    "ComponentSnapshot",
    "ComponentState",
    "ComponentStatus",
    "ComponentSwap",
    "ConfigRequest",
    "RestartRequest",
    "RestoreRequest",
    "SnapshotInfo",
    "snapshot_key",
]


class ComponentState(enum.StrEnum):
    STARTING = "starting"
    IDLE = "idle"
    """Alive, no handler running."""
    ACTIVE = "active"
    """Alive, a handler running (in a cycle)."""
    PAUSED = "paused"
    FAILED = "failed"
    """Alive, its last handler call failed."""
    GONE = "gone"
    """Its liveliness token went away (set by the adaptation manager)."""


ADMIN_VERBS: Final = (
    "status",
    "config",
    "pause",
    "resume",
    "restart",
    "swap",
    "snapshot",
    "restore",
)

PAUSE_POLICY: Final = (
    "paused: no handler runs; what arrives waits in the component's inboxes under their "
    "own capacity and overflow policy (data keeps the newest, events queue and hold "
    "local senders back), counted as dropped when an inbox overflows; resume handles "
    "what waited, in order"
)


class ComponentStatus(msgspec.Struct, kw_only=True, omit_defaults=True):
    """One component as its runtime sees itself."""

    name: str
    state: ComponentState
    stage: str = ""
    compute_node: str = ""
    implementation: str = ""
    """``module:attr`` it runs (after a swap, the new one)."""
    since: int = 0
    """When it started (UTC ns)."""
    last_cycle: str = ""
    """Hex uid of the cycle of its last handler call."""
    last_call: int = 0
    """When its last handler call ended (UTC ns; 0: none yet)."""
    received: int = 0
    handled: int = 0
    failed: int = 0
    rejected: int = 0
    dropped: int = 0
    sent: int = 0
    inbox: int = 0
    """Samples waiting in its inboxes now."""
    p50_ms: float = 0.0
    """Handler latency over its recent calls (ms)."""
    p99_ms: float = 0.0
    restarts: int = 0
    swaps: int = 0
    paused_policy: str = ""
    """What happens to input while paused (set while paused)."""
    rejections: dict[str, int] = msgspec.field(default_factory=dict)
    """Rejected samples by reason (the first words of the reason)."""


class ConfigRequest(msgspec.Struct, kw_only=True, omit_defaults=True):
    values: dict[str, Any] = msgspec.field(default_factory=dict)
    """Fields to set (validated against the node's config Struct); empty: get."""


class ComponentSwap(msgspec.Struct, kw_only=True):
    target: str
    """``module:attr`` of the new implementation: a Node, or a function returning one."""


class RestartRequest(msgspec.Struct, kw_only=True, omit_defaults=True):
    from_snapshot: bool = False
    """Restore the latest snapshot kept in knowledge (else: the state it has)."""


class RestoreRequest(msgspec.Struct, kw_only=True, omit_defaults=True):
    version: int = 0
    """The knowledge version of the snapshot to restore (0: the latest)."""


class SnapshotInfo(msgspec.Struct, kw_only=True, omit_defaults=True):
    key: str
    """The knowledge key it is kept under."""
    version: int
    size: int
    """Bytes of state."""


class AdminReply(msgspec.Struct, kw_only=True, omit_defaults=True):
    ok: bool
    verb: str
    component: str
    message: str = ""
    """What was done, or why it was refused (with the fix)."""
    path: str = ""
    """For a refused config: the ``$.path`` of the bad value."""
    status: ComponentStatus | None = None
    config: dict[str, Any] | None = None
    snapshot: SnapshotInfo | None = None


class ComponentSnapshot(msgspec.Struct, kw_only=True, frozen=True):
    """A component's state as kept in knowledge (under :func:`snapshot_key`)."""

    component: str
    implementation: str
    """``module:attr`` that made it."""
    ts: int
    """When it was taken (UTC ns)."""
    state: bytes
    """The node's snapshot hook's value, msgpack."""


def snapshot_key(component: str) -> str:
    """The knowledge key a component's snapshots are kept under."""
    return f"admin/snapshot/{component}"
