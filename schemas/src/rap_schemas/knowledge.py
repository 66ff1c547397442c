"""Knowledge on the fabric (DESIGN.md section 4).

Writes travel as :class:`KbRecord` envelopes on ``rap/<system>/kb/<key>`` (the write
stream that replicas follow). Everything that needs an answer is a query on the same key
with a :class:`KbRequest` as payload and a :class:`KbReply` back (plain msgpack, no
envelope): a durable write, compare-and-set, get, history, key listing, and the model
store on ``rap/<system>/kb/_models/<name>``.

Versions are 64-bit hybrid-logical-clock stamps, totally ordered across writers:
``ms since 2024-01-01 (44 bits) | logical counter (12 bits) | writer tag (8 bits)``.
"""

from __future__ import annotations

import msgspec

from .message import Message

__all__ = [
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
]

MODELS_PREFIX = "_models"
"""Knowledge keys under ``_models/`` belong to the model store."""


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


class KbDelete(_Req, frozen=True, tag="delete"):
    key: str
    writer: str
    version: int
    expect: int | None = None


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
    integrity, unavailable."""
    version: int = 0
    record: KbRecord | None = None
    records: list[KbRecord] = []
    keys: list[str] = []
    model: ModelMeta | None = None
    models: list[ModelMeta] = []
    data: bytes = b""
    pinned: int | None = None
