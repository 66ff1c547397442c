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

A process that has identities (``RAP_CERTS``: the folder ``rap certs`` wrote) takes only
signed requests: a :class:`SignedRequest` rides along with the query (its attachment),
made and checked by ``rap_sdk.identity``. ``status`` and ``config`` without values (the
reads) accept any identity of the system's CA; the other verbs need the role
``operator``. Every verb, refused ones included, leaves an :class:`AuditRecord` in the
process's log (logger ``rap.audit``).
"""

from __future__ import annotations

import enum
from typing import Any, Final

import msgspec

__all__ = [
    "ADMIN_VERBS",
    "AUDIT_LOGGER",
    "PAUSE_POLICY",
    "AdminReply",
    "AuditRecord",
    "ComponentSnapshot",
    "ComponentState",
    "ComponentStatus",
    "ComponentSwap",
    "ConfigRequest",
    "RestartRequest",
    "RestoreRequest",
    "SignedRequest",
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

AUDIT_LOGGER: Final = "rap.audit"
"""The logger of :class:`AuditRecord` lines (each line's message is one, as JSON)."""

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
    denied: bool = False
    """Refused for who asked: not authenticated, or not allowed (``message`` says why)."""
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


class SignedRequest(msgspec.Struct, kw_only=True, frozen=True):
    """Who sends a request, and the proof: the sender's certificate and its signature
    over what it asks. Made and checked by ``rap_sdk.identity``; it travels beside the
    request (a Zenoh query's attachment, msgpack; the ``auth`` field of an MQTT spec
    update, JSON), never inside the bytes it signs."""

    cert: str
    """The signer's certificate, PEM, issued by the system's CA (``rap certs``): its
    common name is the identity, its organizational unit the role (``operator``,
    ``router``, ``process``)."""
    ts: int
    """When it was signed, UTC ns (taken within a window of the receiver's clock)."""
    nonce: bytes
    """16 random bytes: a receiver takes one request with a nonce once."""
    sig: bytes
    """ECDSA P-256 with SHA-256 (DER) over the canonical encoding of the target (key or
    topic), the verb, the request's bytes, ``ts`` and ``nonce``."""


class AuditRecord(msgspec.Struct, kw_only=True, omit_defaults=True):
    """One admin action as the component that got it saw it: who, what, when, and what
    came of it. Logged on ``rap.audit`` (:data:`AUDIT_LOGGER`), one JSON object as the
    line's message, so it reaches the process's JSON lines file, the fabric's log stream
    and Redis like any line (``rap logs --audit`` shows them)."""

    ts: int
    """When the action ended, UTC ns."""
    who: str
    """The authenticated identity (the certificate's common name), or
    ``unauthenticated``."""
    role: str = ""
    """Its role (``operator``, ``router``, ``process``); empty when unauthenticated."""
    checked: bool = False
    """Whether the component checks identities (it has ``RAP_CERTS``); false: everyone
    is let in, as on a single machine without certificates."""
    verb: str
    component: str
    via: str = "fabric"
    """``fabric`` (an admin query) or ``mqtt`` (the trust checker's spec topic)."""
    key: str = ""
    """The key expression or MQTT topic the request came on."""
    request: str = ""
    """What was asked, in short (config values, the swap target, a spec's size and hash)."""
    result: str
    """``ok``, ``refused`` (not authenticated, or not allowed) or ``error`` (the verb
    failed or the request was bad)."""
    reason: str = ""
    """What was done, or why it was refused or failed."""
    repeated: int = 0
    """For a refusal: how many refusals like it (the same component, verb, caller and
    kind of reason) came since the last record of them and were not recorded one by one
    (refusals are recorded at most once a second each, so that a flood of bad requests
    cannot wash the record away)."""
