"""Knowledge on the fabric (docs/architecture.md, "Knowledge").

Writes travel as :class:`KbRecord` envelopes on ``rap/<system>/kb/<key>`` (the write
stream that replicas follow). Everything that needs an answer is a query on the same key
with a :class:`KbRequest` as payload and a :class:`KbReply` back (plain msgpack, no
envelope): a durable write, compare-and-set, get, history, key listing, and the model
store on ``rap/<system>/kb/_models/<name>``.

Versions are 64-bit hybrid-logical-clock stamps, totally ordered across writers:
``ms since 2024-01-01 (44 bits) | logical counter (12 bits) | writer tag (8 bits)``.
"""

from __future__ import annotations

from typing import Final

import msgspec

from .message import Message

__all__ = [
    "EPOCH_MS",
    "MAX_DRIFT_MS",
    "MAX_VALUE_BYTES",
    "MODELS_PREFIX",
    "KbDelete",
    "KbGet",
    "KbHistory",
    "KbList",
    "KbPut",
    "KbRecord",
    "KbReply",
    "KbRequest",
    "ModelGet",
    "ModelList",
    "ModelMeta",
    "ModelPin",
    "ModelPut",
    "RecordError",
    "check_record",
]

MODELS_PREFIX = "_models"
"""Knowledge keys under ``_models/`` belong to the model store."""
EPOCH_MS: Final = 1_704_067_200_000
"""2024-01-01T00:00:00Z: the zero of a version's time part."""
MAX_DRIFT_MS: Final = 5_000
"""How far ahead of the reader's clock a version's time may be (the clock skew allowed
between machines, as for envelopes). A version from further ahead would win every later
write, freeze the key at that value until the clocks caught up, and push every writer's
clock past it: the service and every replica refuse it. (make fuzz showed versions
accepted up to a 60 s limit shadowing genuine writes for ~58 s.)"""
MAX_VALUE_BYTES: Final = 1 << 20
"""A value's size limit (the service's default ``max_value_bytes``)."""


class KbRecord(Message, frozen=True, omit_defaults=True):
    """One version of one key."""

    TYPE = "rap.KbRecord/1"

    key: str
    version: int
    ts: int
    """UTC ns when written."""
    writer: str
    value: msgspec.Raw
    """The value, msgpack (a Struct or plain data); nil for a deletion."""
    deleted: bool = False


class _Req(msgspec.Struct, frozen=True, kw_only=True, tag_field="op"):
    pass


class KbPut(_Req, frozen=True, tag="put"):
    """A write that the service acknowledges once stored (durable), optionally only if
    the key's current version is ``expect`` (compare-and-set; 0 = the key must not
    exist)."""

    record: KbRecord
    expect: int | None = None
    budget_ms: int | None = None
    """Milliseconds, from the service's receipt of the request, within which the write
    must be stored, or never: past it the service refuses to store it, so a writer that
    gave up waiting is never contradicted by a write stored later. None: no limit."""


class KbDelete(_Req, frozen=True, tag="delete"):
    key: str
    writer: str
    version: int
    expect: int | None = None
    budget_ms: int | None = None
    """As for :class:`KbPut`."""


class KbGet(_Req, frozen=True, tag="get"):
    key: str
    min_version: int = 0


class KbHistory(_Req, frozen=True, tag="history"):
    key: str
    since: int | None = None
    """UTC ns, inclusive."""
    until: int | None = None
    """UTC ns, exclusive."""
    limit: int = 1000


class KbList(_Req, frozen=True, tag="list"):
    pattern: str = "**"
    """Key pattern with ``*`` / ``**`` chunks, relative to ``rap/<system>/kb/``."""


class ModelMeta(msgspec.Struct, frozen=True, kw_only=True, omit_defaults=True):
    name: str
    version: int
    """1, 2, ... per name."""
    sha256: str
    size: int
    created: int
    tags: dict[str, str] = {}


class ModelPut(_Req, frozen=True, tag="model-put"):
    name: str
    data: bytes
    sha256: str
    """Of ``data``, checked by the service before storing."""
    tags: dict[str, str] = {}


class ModelGet(_Req, frozen=True, tag="model-get"):
    name: str
    version: int | None = None
    """None: the pinned version if any, else the latest."""
    with_data: bool = True


class ModelList(_Req, frozen=True, tag="model-list"):
    name: str


class ModelPin(_Req, frozen=True, tag="model-pin"):
    """Pin ``version`` (None: unpin, latest wins again). ``rollback=True`` pins the
    version before the one currently in force."""

    name: str
    version: int | None = None
    rollback: bool = False


KbRequest = (
    KbPut | KbDelete | KbGet | KbHistory | KbList | ModelPut | ModelGet | ModelList | ModelPin
)


class KbReply(msgspec.Struct, frozen=True, kw_only=True, omit_defaults=True):
    ok: bool = True
    error: str = ""
    """What went wrong and how to fix it, when ``ok`` is false."""
    code: str = ""
    """Machine-readable error kind: bad-request, conflict, not-found, too-large,
    integrity, unavailable (not stored), unknown (a durable write whose outcome the
    service could not learn before its budget ran out: it may have been stored), denied
    (a model store request from an identity the system model does not grant it)."""
    version: int = 0
    record: KbRecord | None = None
    records: list[KbRecord] = []
    keys: list[str] = []
    model: ModelMeta | None = None
    models: list[ModelMeta] = []
    data: bytes = b""
    pinned: int | None = None


class RecordError(ValueError):
    """A record outside the bounds every holder of knowledge applies; ``code`` is the
    service's error kind (``bad-request`` or ``too-large``)."""

    def __init__(self, message: str, code: str = "bad-request") -> None:
        super().__init__(message)
        self.code = code


def check_record(rec: KbRecord, *, now_ms: int, max_value_bytes: int = MAX_VALUE_BYTES) -> None:
    """The bounds of a record, the same for the service and every replica: a version
    in 1 .. 2**63-1 whose time is at most ``MAX_DRIFT_MS`` ahead of ``now_ms`` (UTC
    ms), a ``ts`` in 0 .. 2**63-1, a value of at most ``max_value_bytes``. Raises
    :class:`RecordError`. (The key's syntax is checked where it is used.)"""
    if not 0 < rec.version < 2**63:
        raise RecordError(
            f"record for {rec.key!r} has version {rec.version}; versions are in "
            "1 .. 2**63-1 (hybrid-logical-clock stamps)"
        )
    if rec.version >> 20 > now_ms - EPOCH_MS + MAX_DRIFT_MS:
        raise RecordError(
            f"record for {rec.key!r} has a version {rec.version} more than "
            f"{MAX_DRIFT_MS // 1000} s ahead of this clock; check the writer's clock"
        )
    if not 0 <= rec.ts < 2**63:
        raise RecordError(
            f"record for {rec.key!r}: ts must be UTC nanoseconds in 0 .. 2**63-1, got {rec.ts}"
        )
    if len(rec.value) > max_value_bytes:
        raise RecordError(
            f"value for {rec.key!r} is {len(rec.value)} bytes, over the limit of "
            f"{max_value_bytes}; store large artefacts in the model store",
            "too-large",
        )
