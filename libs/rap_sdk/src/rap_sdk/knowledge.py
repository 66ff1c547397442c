"""The knowledge client (docs/architecture.md, "Knowledge").

    async with KnowledgeClient(fabric=fabric, system="tb4", writer="planner") as kb:
        v = await kb.write("planned_lidar_mask", mask)          # no round trip
        v = await kb.write("plan", plan, durable=True)          # acknowledged by the service
        mask = await kb.read("lidar_mask", LidarMask, min_version=v_from_event_ctx)

Versions are hybrid-logical-clock stamps (``ms since 2024 | counter | writer tag``),
totally ordered across writers, so a write gets its version locally and goes out on the
write stream ``rap/<system>/kb/<key>`` without waiting. Each key the client reads is
replicated locally: subscribed to its write stream, caught up from the service once, and
then read without a round trip. A read that names a ``min_version`` (from the ``ctx`` of
the event being handled) waits for it, within a deadline, then asks the service, then
fails with :class:`KnowledgeError` naming key and versions.
"""

from __future__ import annotations

import hashlib
import logging
import time
import weakref
import zlib
from collections.abc import Awaitable, Callable
from types import TracebackType
from typing import TYPE_CHECKING, Any, Final, Protocol, TypeVar, overload

import anyio
import msgspec
from anyio.abc import TaskGroup
from rap_schemas import (
    MODELS_PREFIX,
    KbGet,
    KbHistory,
    KbList,
    KbPut,
    KbRecord,
    KbReply,
    KbRequest,
    ModelGet,
    ModelList,
    ModelMeta,
    ModelPin,
    ModelPut,
    Rejection,
    keys,
)
from rap_schemas.knowledge import (
    EPOCH_MS,
    MAX_DRIFT_MS,
    MAX_VALUE_BYTES,
    RecordError,
    check_record,
)
from rap_schemas.limits import (
    DECODE_ERRORS,
    MAX_DEPTH,
    DecodeRejected,
    SafeDecoder,
    check_depth,
    decode_failure,
)

from .envelope import Opener, Sealer, typed_decoder
from .errors import LifecycleError, QueryError, RapError, RejectedSample
from .fabric import Fabric, Subscription
from .inbox import InboxPolicy, Overflow
from .rejections import Rejections

if TYPE_CHECKING:
    from .identity import Signer

__all__ = [
    "DURABLE_BUDGET",
    "MAX_REPLY_BYTES",
    "OWN_WRITES",
    "SERVICE_NODE",
    "HybridClock",
    "Intake",
    "KnowledgeClient",
    "KnowledgeError",
    "KnowledgeTypeError",
    "Versioned",
    "join_colocated",
    "writer_tag",
]

log = logging.getLogger(__name__)

T = TypeVar("T")
_MISSING: Final = object()
_encode = msgspec.msgpack.Encoder().encode
MAX_REPLY_BYTES: Final = 512 << 20
"""A reply may carry a model (the service's ``max_model_bytes``, 256 MiB by default)."""
_reply = SafeDecoder[KbReply](KbReply, max_bytes=MAX_REPLY_BYTES, what="knowledge reply").decode
_NIL: Final = msgspec.Raw(b"\xc0")
OWN_WRITES: Final = 1024
"""Own writes remembered for keys not replicated yet (read-your-own-writes)."""
DURABLE_BUDGET: Final = 0.75
"""Share of the client's timeout the service may spend storing a durable write; the
rest is for the answer's way back."""
SERVICE_NODE: Final = "knowledge"
"""The node name the knowledge service declares its liveliness token under."""


class KnowledgeError(RapError):
    """A knowledge operation failed; ``code`` is the service's error kind when it
    answered (bad-request, conflict, not-found, too-large, integrity, unavailable,
    denied: a model store request the system model does not grant its signer), or
    ``bad-reply`` for an answer that could not be decoded."""

    def __init__(self, message: str, code: str = "") -> None:
        super().__init__(message)
        self.code = code


class KnowledgeTypeError(KnowledgeError):
    """A stored value does not match the type it was read as (with the ``$.path``)."""


def writer_tag(writer: str) -> int:
    """The 8-bit tag a writer stamps into the low bits of its versions."""
    return zlib.crc32(writer.encode()) & 0xFF


class HybridClock:
    """Hybrid logical clock: ``(ms since 2024) << 20 | counter << 8 | writer tag``.
    Monotonic per writer, ahead of every version it has observed, and ordered across
    writers by time first."""

    def __init__(self, writer: str, now_ms: Callable[[], int] | None = None) -> None:
        self.tag = writer_tag(writer)
        self._now_ms = now_ms
        self._last = 0

    def next(self) -> int:
        now = self._now_ms
        wall = ((now() if now is not None else time.time_ns() // 1_000_000) - EPOCH_MS) << 20
        base = max(wall, (self._last >> 8 << 8) + (1 << 8))
        self._last = base | self.tag
        return self._last

    def observe(self, version: int) -> None:
        """Move ahead of ``version``, unless it claims a time more than ``MAX_DRIFT_MS``
        ahead of this clock (a broken writer must not drag every clock into the
        future; the service refuses such versions too)."""
        if version > self._last:
            now = self._now_ms
            ms = now() if now is not None else time.time_ns() // 1_000_000
            if (version >> 20) <= ms - EPOCH_MS + MAX_DRIFT_MS:
                self._last = version >> 8 << 8 | self.tag


class Versioned(msgspec.Struct, frozen=True):
    """A value with its version, time and writer (what :meth:`KnowledgeClient.history`
    returns)."""

    key: str
    version: int
    ts: int
    writer: str
    value: Any
    deleted: bool = False


class _Replica:
    __slots__ = (
        "_changed",
        "caught_up",
        "decoded",
        "key",
        "ready",
        "record",
        "seen_tags",
        "sub",
        "types",
        "version",
    )

    def __init__(self, key: str, seen_tags: set[int]) -> None:
        self.key = key
        self.seen_tags = seen_tags
        self.types: list[Any] = []
        """The types this client reads the key as: a record from elsewhere whose value is
        not one of them is refused (the replica keeps its last good value)."""
        self.record: KbRecord | None = None
        self.version = 0
        """``record.version`` (0: no record)."""
        self.decoded: dict[Any, Any] = {}
        self._changed: anyio.Event | None = None
        """Made when someone waits for a newer record (most offers have no waiter)."""
        self.ready = anyio.Event()
        """Set once the replica has caught up (concurrent first readers wait for it)."""
        self.caught_up = False
        """``ready`` is set (a flag: the read path checks it every time)."""
        self.sub: Subscription | None = None

    async def changed(self) -> None:
        """Wait for the next record adopted."""
        if self._changed is None:
            self._changed = anyio.Event()
        await self._changed.wait()

    def offer(self, rec: KbRecord, decoded: dict[Any, Any] | None = None) -> bool:
        if rec.version <= self.version:
            return False
        self.seen_tags.add(rec.version & 0xFF)
        self.record = rec
        self.version = rec.version
        self.decoded = decoded if decoded is not None else {}
        changed = self._changed
        if changed is not None:
            self._changed = None
            changed.set()
        return True


class _Colocated:
    """The knowledge clients of one system on one fabric (in one process). A write is
    handed to the others' replicas directly, value object and all: a co-located reader
    gets what was written with no decoding and no task woken up; the fabric then skips
    their replicas' subscriptions for it (``group``) and takes it to everyone else."""

    __slots__ = ("clients", "intake", "readers")

    def __init__(self) -> None:
        self.clients: list[KnowledgeClient] = []
        self.readers: dict[str, list[KnowledgeClient]] = {}
        """Key -> the clients that replicate it."""
        self.intake: Intake | None = None
        """The knowledge service of the system, when it runs in this process on the
        same fabric and can store a record in the writer's task."""


class Intake(Protocol):
    """A co-located knowledge service's direct intake of the write stream."""

    stream: Subscription
    """Its subscription to the write stream."""

    def take(self, rec: KbRecord) -> bool:
        """Store ``rec`` (written in this process) now, in the caller's frame, or
        return False when it cannot without waiting or overtaking what is queued:
        the record then goes out on the stream."""
        ...


def join_colocated(fabric: Fabric, system: str, intake: Intake) -> Callable[[], None]:
    """Make ``intake`` the co-located service of ``system`` on ``fabric``: writers
    there whose stream nobody else receives hand it their records directly. Returns
    the function that withdraws it."""
    group = _colocated(fabric, system)
    group.intake = intake

    def leave() -> None:
        if group.intake is intake:
            group.intake = None

    return leave


def _colocated(fabric: Fabric, system: str) -> _Colocated:
    by_system = _COLOCATED.get(fabric)
    if by_system is None:
        by_system = _COLOCATED[fabric] = {}
    group = by_system.get(system)
    if group is None:
        group = by_system[system] = _Colocated()
    return group


_COLOCATED: weakref.WeakKeyDictionary[Any, dict[str, _Colocated]] = weakref.WeakKeyDictionary()
_FROZEN: dict[type, bool] = {}


def _shareable(value: Any) -> bool:
    """Whether ``value`` may be handed to other readers as it is: a frozen Struct."""
    cls = type(value)
    frozen = _FROZEN.get(cls)
    if frozen is None:
        config = getattr(cls, "__struct_config__", None)
        frozen = _FROZEN[cls] = bool(config is not None and config.frozen)
    return frozen


class KnowledgeClient:
    def __init__(
        self,
        *,
        fabric: Fabric,
        system: str,
        writer: str,
        timeout: float = 2.0,
        replica_policy: InboxPolicy | None = None,
        max_value_bytes: int = MAX_VALUE_BYTES,
        signer: Signer | None = None,
    ) -> None:
        """``timeout``: seconds a read waits for a promised version, and each request to
        the service. ``max_value_bytes``: the largest value a replica adopts (the
        service's limit: records over it are refused here as they are there).
        ``signer``: the identity the model store's requests are signed as (default: the
        one ``RAP_AS`` names in ``RAP_CERTS`` when both are set, as under ``rap up``
        with TLS); a knowledge service with identities takes them only signed, from an
        operator or an identity the system model grants the model (``models:``)."""
        keys.system_pattern(system)
        self.fabric = fabric
        self.system = system
        self.writer = writer
        self.timeout = timeout
        self.clock = HybridClock(writer)
        self.sealer = Sealer(writer)
        self.opener = Opener()
        self.max_value_bytes = max_value_bytes
        self.signer = signer
        self._signer_loaded = signer is not None
        self.rejections = Rejections(writer, log)
        """Write records refused by the replicas (bounds, bad envelopes, wrong keys)."""
        self.on_rejection: Callable[[Rejection], Awaitable[None]] | None = None
        """Called with each rejection record that is due (rate-limited): a node's
        runtime publishes them on its log key."""
        self._replicas: dict[str, _Replica] = {}
        self._valid: set[str] = set()
        """Keys already checked (bounded)."""
        self._kb_keys: dict[str, str] = {}
        self._receivers: dict[str, tuple[int, Intake, bool]] = {}
        """Stream key -> the fabric's epoch and the intake when last looked at, and
        whether the intake and this group's replicas were its only receivers."""
        self._own: dict[str, KbRecord] = {}
        """This client's last write of each key it has not replicated (yet)."""
        self._policy = replica_policy or InboxPolicy(capacity=8, overflow=Overflow.LATEST)
        self._tg: TaskGroup | None = None
        self._tg_cm: Any = None
        self._decode_env = typed_decoder(KbRecord)
        self._group = _Colocated()
        """The clients of this system on this fabric (set when the client opens)."""
        self.waits = 0
        """Reads that had to wait for the version their trigger promised."""
        self.catch_ups = 0
        """Times every replica caught up because the knowledge service came back."""
        self._alive: dict[str, int] = {}
        """Alive node of the system -> its writer tag (from liveliness tokens)."""
        self._alive_tags: dict[int, int] = {}
        """Writer tag -> how many alive nodes have it."""
        self._seen_tags: set[int] = set()
        """Writer tags of records this client's replicas adopted (writers with a write
        stream, whether or not they declare liveliness: scripts, tools)."""
        self._gone_tags: set[int] = set()
        """Tags whose every node's liveliness token went away."""

    async def __aenter__(self) -> KnowledgeClient:
        group = _colocated(self.fabric, self.system)
        group.clients.append(self)
        self._group = group
        self._tg_cm = anyio.create_task_group()
        self._tg = await self._tg_cm.__aenter__()
        self._tg.start_soon(self._watch_service)
        return self

    async def _watch_service(self) -> None:
        """Follows which nodes of the system are alive (a promised version from a writer
        that is not alive is not waited for). When the knowledge service comes (back),
        every replica catches up from it: writes it stored while this client could not
        hear the stream are not missed."""
        service = keys.alive(self.system, SERVICE_NODE)
        with self.fabric.watch_liveliness(keys.pattern(self.system, keys.Kind.ALIVE, "*")) as watch:
            while True:
                try:
                    change = await watch.get()
                except LifecycleError:
                    return
                self._track_alive(change.key, change.alive)
                if change.key == service and change.alive and self._replicas:
                    # the service appeared (first time or back): replicas made without
                    # it, or while it was away, catch up from it
                    self.catch_ups += 1
                    for rep in list(self._replicas.values()):
                        await self._refresh_quietly(rep)

    def _track_alive(self, key: str, alive: bool) -> None:
        name = key.rsplit("/", 1)[-1]
        tags = self._alive_tags
        if alive and name not in self._alive:
            tag = self._alive[name] = writer_tag(name)
            tags[tag] = tags.get(tag, 0) + 1
            self._gone_tags.discard(tag)
        elif not alive and name in self._alive:
            tag = self._alive.pop(name)
            tags[tag] -= 1
            if not tags[tag]:
                del tags[tag]
                self._gone_tags.add(tag)

    def writer_alive(self, version: int) -> bool:
        """Whether the writer of ``version`` (by its tag) may still deliver it: this
        client, a node of the system whose liveliness token is up, or a writer whose
        records this client has adopted and whose token (if it had one) has not gone.
        A version promised by any other writer may never come: reads do not wait."""
        tag = version & 0xFF
        if tag == self.clock.tag or tag in self._alive_tags:
            return True
        return tag in self._seen_tags and tag not in self._gone_tags

    def has_versions(self, promised: dict[str, int]) -> bool:
        """Whether :meth:`await_versions` would return at once."""
        replicas = self._replicas
        for key, version in promised.items():
            rep = replicas.get(key)
            if rep is not None and rep.version < version and self.writer_alive(version):
                return False
        return True

    async def await_versions(self, promised: dict[str, int], deadline: float) -> None:
        """Wait until each replicated key in ``promised`` has reached its version, or the
        monotonic ``deadline``; never raises (the read that needs a version says so).
        Versions of keys not replicated here, or of writers that are not alive, are not
        waited for."""
        for key, version in promised.items():
            rep = self._replicas.get(key)
            if rep is None or rep.version >= version or not self.writer_alive(version):
                continue
            left = deadline - time.monotonic()
            if left <= 0:
                return
            self.waits += 1
            with anyio.move_on_after(left):
                while rep.version < version:
                    await rep.changed()

    async def __aexit__(
        self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None
    ) -> None:
        for rep in self._replicas.values():
            if rep.sub is not None:
                rep.sub.close()
        group = self._group
        if self in group.clients:
            group.clients.remove(self)
        for key in self._replicas:
            readers = group.readers.get(key)
            if readers is not None and self in readers:
                readers.remove(self)
                if not readers:
                    del group.readers[key]
        assert self._tg is not None
        self._tg.cancel_scope.cancel()
        await self._tg_cm.__aexit__(et, ev, tb)
        self._tg = None

    # -- writing ---------------------------------------------------------------------------

    async def write(
        self, key: str, value: Any, *, durable: bool = False, expect: int | None = None
    ) -> int:
        """Write ``value`` (a Struct or msgspec-encodable data); returns its version.

        Without ``durable`` the write goes out on the write stream and returns at once.
        ``durable=True`` waits for the service's acknowledgement; ``expect`` (0: the key
        must not exist) makes it a compare-and-set, always through the service. A value
        over ``max_value_bytes`` raises ``KnowledgeError`` (``too-large``), plain data
        nested more than ``MAX_DEPTH`` levels ``bad-request``: the service and every
        replica would refuse them (a Struct's own fields are typed: not walked)."""
        if not isinstance(value, msgspec.Struct):
            try:
                check_depth(value, MAX_DEPTH, f"the value for {key!r}")
            except DecodeRejected as exc:
                raise KnowledgeError(exc.reason, "bad-request") from None
        encoded = _encode(value)
        if len(encoded) > self.max_value_bytes:
            raise KnowledgeError(
                f"value for {key!r} is {len(encoded)} bytes, over the limit of "
                f"{self.max_value_bytes}; store large artefacts in the model store",
                "too-large",
            )
        rec = self._record(key, msgspec.Raw(encoded), False)
        if durable or expect is not None:
            return await self._submit(rec, expect, value)
        return await self._stream(rec, value)

    async def delete(self, key: str, *, durable: bool = False, expect: int | None = None) -> int:
        rec = self._record(key, _NIL, True)
        if durable or expect is not None:
            return await self._submit(rec, expect, None)
        return await self._stream(rec, None)

    def _record(self, key: str, value: msgspec.Raw, deleted: bool) -> KbRecord:
        if key not in self._valid:
            self._check_key(key)
        return KbRecord(
            key=key,
            version=self.clock.next(),
            ts=time.time_ns(),
            writer=self.writer,
            value=value,
            deleted=deleted,
        )

    async def _submit(self, rec: KbRecord, expect: int | None, value: Any) -> int:
        """Durable (or compare-and-set, ``expect`` given): through the service and
        acknowledged. Replicas here and in co-located clients then get the record (and
        ``value``, when it is a frozen Struct) directly."""
        # the service stores it within its budget or never, and answers before this
        # client stops waiting: a write reported failed is never stored later
        budget = max(1, int(self.timeout * DURABLE_BUDGET * 1000))
        reply = await self._ask(rec.key, KbPut(record=rec, expect=expect, budget_ms=budget))
        if reply.version != rec.version:  # the service moved it past the current one
            rec = msgspec.structs.replace(rec, version=reply.version)
        self.clock.observe(reply.version)
        refused = self._adopt(rec, value)
        if refused:
            await self._publish_refused(refused)
        return rec.version

    async def _stream(self, rec: KbRecord, value: Any) -> int:
        """Out on the write stream (encoded once, for the service and other processes);
        replicas here and in co-located clients get it directly, and so does a
        co-located service when nobody else receives the stream."""
        stream = self._kb_keys.get(rec.key) or self._kb_key(rec.key)
        intake = self._group.intake
        known = self._receivers.get(stream)
        if (
            intake is None
            or not (
                known[2]
                if known is not None and known[0] == self.fabric.epoch and known[1] is intake
                else self._only_intake(stream, intake)
            )
            or not intake.take(rec)
        ):
            out = self.sealer.seal_out(stream, rec)
            out.group = self._group
            await self.fabric.publish(stream, out)
        refused = self._adopt(rec, value)
        if refused:
            await self._publish_refused(refused)
        return rec.version

    def _only_intake(self, stream: str, intake: Intake) -> bool:
        """Whether the co-located service and this group's replicas are the only
        receivers of ``stream`` (no other process, no other local subscription),
        remembered under the fabric's epoch (``_stream`` reads it there first)."""
        fabric = self.fabric
        epoch = fabric.epoch
        group = self._group
        only = not fabric.has_subscribers(stream, remote_only=True) and all(
            s is intake.stream or s.group is group for s in fabric.local_subscribers(stream)
        )
        if len(self._receivers) < 4096:
            self._receivers[stream] = (epoch, intake, only)
        return only

    @staticmethod
    async def _publish_refused(refused: list[tuple[KnowledgeClient, Rejection]]) -> None:
        for other, rejection in refused:
            await other._rejected(rejection)

    def _adopt(self, rec: KbRecord, value: Any) -> list[tuple[KnowledgeClient, Rejection]] | None:
        """Hand a record this client wrote to the co-located clients' replicas and to its
        own; the rejections (due) of co-located clients that refused it are returned,
        for the writer to publish."""
        shared = value is not None and _shareable(value)
        refused: list[tuple[KnowledgeClient, Rejection]] | None = None
        for other in self._group.readers.get(rec.key, ()):
            if other is not self:
                rejection = other._handed(rec, value if shared else None)
                if rejection is not None:
                    refused = refused or []
                    refused.append((other, rejection))
        rep = self._replicas.get(rec.key)
        if rep is not None:
            rep.offer(rec, {type(value): value} if shared and type(value) in rep.types else None)
        else:  # read-your-own-writes: a replica made later starts from this record
            own = self._own
            own.pop(rec.key, None)
            own[rec.key] = rec
            if len(own) > OWN_WRITES:  # bounded: the oldest falls back to the service
                del own[next(iter(own))]
        return refused

    # -- reading ---------------------------------------------------------------------------

    @overload
    async def read(
        self,
        key: str,
        type: type[T],
        *,
        default: Any = ...,
        min_version: int = 0,
        timeout: float | None = None,
    ) -> T: ...

    @overload
    async def read(
        self,
        key: str,
        type: None = None,
        *,
        default: Any = ...,
        min_version: int = 0,
        timeout: float | None = None,
    ) -> Any: ...

    async def read(
        self,
        key: str,
        type: Any = None,
        *,
        default: Any = _MISSING,
        min_version: int = 0,
        timeout: float | None = None,
    ) -> Any:
        """The newest known value of ``key``, decoded as ``type`` (None: plain data).

        ``min_version``: wait (within ``timeout``, default the client's) until at least
        that version is known, then ask the service; a version whose writer is not
        alive is not waited for. A missing or deleted key returns ``default``, a
        version that does not come raises ``KnowledgeError``."""
        rep = self._replicas.get(key)
        if rep is not None and rep.version >= min_version and rep.caught_up:
            rec = rep.record  # here already: no wait, nothing to ask
            if rec is not None and not rec.deleted:
                hit = rep.decoded.get(type, _MISSING)
                if hit is not _MISSING:
                    return hit
        else:
            rec = await self.read_record(key, min_version=min_version, timeout=timeout)
        if rec is None or rec.deleted:
            if default is _MISSING:
                raise KnowledgeError(
                    f"knowledge key {key!r} has no value; pass default= "
                    "to read a key that may be absent",
                    "not-found",
                )
            return default
        rep = self._replicas[key]
        if type is not None and type not in rep.types:
            rep.types.append(type)
        hit = rep.decoded.get(type, _MISSING) if rep.record is rec else _MISSING
        if hit is _MISSING:
            hit = self._decode(rec, type)
            if rep.record is rec:
                rep.decoded[type] = hit
        return hit

    def value_here(self, key: str, type: Any, min_version: int = 0) -> Any:
        """The value of ``key`` read as ``type`` when this client has it at hand (at
        least ``min_version``, already read or handed over as that type): what
        :meth:`read` would return at once. Else ``_MISSING`` (then :meth:`read`)."""
        rep = self._replicas.get(key)
        if rep is not None and rep.caught_up:
            rec = rep.record
            if rec is not None and rec.version >= min_version and not rec.deleted:
                return rep.decoded.get(type, _MISSING)
        return _MISSING

    def known_version(self, key: str) -> int:
        """The version of ``key`` this client knows (0: none or not replicated)."""
        rep = self._replicas.get(key)
        return rep.version if rep is not None else 0

    async def read_record(
        self, key: str, *, min_version: int = 0, timeout: float | None = None
    ) -> KbRecord | None:
        """The newest known record of ``key`` (None when it never existed)."""
        rep = self._replicas.get(key)
        fresh = rep is None
        if rep is None:
            rep = await self._replicate(key)
        elif not rep.ready.is_set():
            await rep.ready.wait()
        if rep.version >= min_version:
            return rep.record
        alive = self.writer_alive(min_version)
        deadline = max(0.0, timeout if timeout is not None else self.timeout) if alive else 0.0
        if deadline > 0:
            self.waits += 1
            with anyio.move_on_after(deadline):
                if fresh:
                    await self._catch_up(rep, min_version)
                while rep.version < min_version:
                    await rep.changed()
        if rep.version < min_version:
            await self._refresh(rep, min_version)
        if rep.version < min_version:
            waited = f"waiting {deadline:.3g} s" if alive else "no wait: its writer is not alive"
            raise KnowledgeError(
                f"read of {key!r} needs version >= {min_version} (written before the event "
                f"that triggered this read) but the newest known is {rep.version} after "
                f"{waited} and asking the service: is the writer's write stream reaching "
                "this node?",
                "unavailable",
            )
        return rep.record

    @staticmethod
    def _decode(rec: KbRecord, type: Any) -> Any:
        """The value as ``type``; without a type as plain data nested at most
        ``MAX_DEPTH`` levels (see :mod:`rap_schemas.limits`)."""
        try:
            if type:
                return msgspec.msgpack.decode(rec.value, type=type)
            return check_depth(msgspec.msgpack.decode(rec.value), MAX_DEPTH, "the value")
        except (*DECODE_ERRORS, DecodeRejected) as exc:
            reason = exc.reason if isinstance(exc, DecodeRejected) else decode_failure(exc)
            raise KnowledgeTypeError(
                f"knowledge key {rec.key!r} (version {rec.version}) does not hold a "
                f"{getattr(type, '__name__', type) if type else 'plain value'}: {reason}"
            ) from None

    async def _replicate(self, key: str) -> _Replica:
        self._check_key(key)
        if self._tg is None:
            raise LifecycleError("KnowledgeClient is not open: use 'async with'")
        rep = self._replicas[key] = _Replica(key, self._seen_tags)
        self._group.readers.setdefault(key, []).append(self)
        rep.sub = self.fabric.subscribe(
            keys.kb(self.system, key), self._policy, prepare=self._decode_env, group=self._group
        )
        self._tg.start_soon(self._follow, rep)
        try:
            await self._refresh(rep, 0)  # catch up after subscribing: nothing falls between
        finally:
            own = self._own.pop(key, None)
            if own is not None:
                rep.offer(own)  # newer than what the service had stored yet, if it is
            for other in self._group.clients:  # co-located writes the service may not
                if other is not self:  # have stored yet
                    known = other._replicas.get(key)
                    rec = known.record if known is not None else other._own.get(key)
                    if rec is not None and rec.version > rep.version:
                        rep.offer(rec)
            rep.caught_up = True
            rep.ready.set()
        return rep

    async def _follow(self, rep: _Replica) -> None:
        assert rep.sub is not None
        key = keys.kb(self.system, rep.key)
        while True:
            try:
                sample = await rep.sub.get()
            except LifecycleError:
                return
            missing = self.opener.stats.missing
            try:
                env = self.opener.open_typed(
                    key, sample.payload, self._decode_env, KbRecord.TYPE, sample.prepared
                )
                if env is None:
                    continue  # a duplicate
                rec: KbRecord = env.body
                self._check(rec, rep.key)
                decoded = self._typed(rec, rep)
            except RejectedSample as exc:
                await self._rejected(
                    self.rejections.reject(key, exc.reason, source=exc.source, type=exc.type)
                )
                continue
            self.clock.observe(rec.version)
            rep.offer(rec, decoded)
            if self.opener.stats.missing > missing:  # a write went missing: catch up
                await self._refresh_quietly(rep)

    def _handed(self, rec: KbRecord, value: Any) -> Rejection | None:
        """A co-located client wrote ``rec`` (``value``: the written object, when it
        is a frozen Struct): adopted as a record from the stream would be, but read as
        the written object where this client reads the key as exactly its type. A
        record of another type is refused: the rejection record (when due) is
        returned for the writer to publish."""
        rep = self._replicas[rec.key]
        if rec.version <= rep.version:
            return None
        types = rep.types
        if value is not None and len(types) == 1 and types[0] is type(value):
            decoded: dict[Any, Any] | None = {types[0]: value}
        else:
            try:
                decoded = self._typed(rec, rep)
            except RejectedSample as exc:
                key = self._kb_key(rec.key)
                return self.rejections.reject(key, exc.reason, source=rec.writer, type=exc.type)
        self.clock.observe(rec.version)
        rep.offer(rec, decoded)
        return None

    def _check(self, rec: KbRecord, key: str) -> None:
        """The bounds the service applies (a replica must not adopt for good what the
        service refused), and the key the record was sent for."""
        if rec.key != key:
            raise RejectedSample(f"a record for {rec.key!r} arrived on the stream of {key!r}")
        try:
            check_record(
                rec, now_ms=time.time_ns() // 1_000_000, max_value_bytes=self.max_value_bytes
            )
        except RecordError as exc:
            raise RejectedSample(str(exc)) from None

    def _typed(self, rec: KbRecord, rep: _Replica) -> dict[Any, Any] | None:
        """The record's value decoded as each type this client reads the key as, or
        :class:`RejectedSample` when it is not one of them: a record of the wrong type
        (a bug or a hostile writer) would otherwise fail every read until a good one
        came, and stop a loop whose stages only write after they read."""
        if rec.version <= rep.version or not rep.types or rec.deleted:
            return None
        decoded: dict[Any, Any] = {}
        for t in rep.types:
            try:
                decoded[t] = self._decode(rec, t)
            except KnowledgeTypeError as exc:
                raise RejectedSample(
                    f"{exc}; the replica keeps version {rep.version}", type=KbRecord.TYPE
                ) from None
        return decoded

    async def _rejected(self, rec: Rejection | None) -> None:
        if rec is not None and self.on_rejection is not None:
            await self.on_rejection(rec)

    async def _refresh_quietly(self, rep: _Replica) -> None:
        """A background catch-up: a failure is logged, the replica keeps following."""
        try:
            await self._refresh(rep, 0)
        except (KnowledgeError, msgspec.MsgspecError) as exc:
            log.warning("replica of %r: catch-up from the service failed: %s", rep.key, exc)

    async def _catch_up(self, rep: _Replica, min_version: int) -> None:
        """A replica made for this read waits for a version written before it
        subscribed: the stream will not bring that record, the service will once it
        has stored it (it may not have when the replica first asked). Ask again, 10 ms
        after the first time and then twice as long each time (at most 0.25 s), until
        the version is here (from the service or the stream); the caller bounds it."""
        delay = 0.01
        while rep.version < min_version:
            with anyio.move_on_after(delay):
                while rep.version < min_version:
                    await rep.changed()
            if rep.version < min_version:
                await self._refresh(rep, min_version)
            delay = min(delay * 2, 0.25)

    async def _refresh(self, rep: _Replica, min_version: int) -> None:
        try:
            reply = await self._ask(rep.key, KbGet(key=rep.key, min_version=min_version))
        except KnowledgeError as exc:
            if exc.code != "unavailable":
                raise
            return  # no service: the replica follows the write stream alone
        if reply.record is not None:
            try:
                self._check(reply.record, rep.key)
                decoded = self._typed(reply.record, rep)
            except RejectedSample as exc:
                await self._rejected(
                    self.rejections.reject(keys.kb(self.system, rep.key), f"service reply: {exc}")
                )
                return
            self.clock.observe(reply.record.version)
            rep.offer(reply.record, decoded)

    # -- history, listing ------------------------------------------------------------------

    async def history(
        self,
        key: str,
        type: Any = None,
        *,
        since: int | None = None,
        until: int | None = None,
        limit: int = 1000,
    ) -> list[Versioned]:
        """Versions of ``key`` with ``since <= ts < until`` (UTC ns), oldest first."""
        self._check_key(key)
        reply = await self._ask(key, KbHistory(key=key, since=since, until=until, limit=limit))
        return [
            Versioned(
                r.key,
                r.version,
                r.ts,
                r.writer,
                None if r.deleted else self._decode(r, type),
                r.deleted,
            )
            for r in reply.records
        ]

    async def keys(self, pattern: str = "**") -> list[str]:
        reply = await self._ask("_keys", KbList(pattern=pattern))
        return reply.keys

    # -- model store -----------------------------------------------------------------------

    async def put_model(
        self, name: str, data: bytes, *, tags: dict[str, str] | None = None
    ) -> ModelMeta:
        digest = await _sha256(data)
        reply = await self._ask_model(
            ModelPut(name=name, data=data, sha256=digest, tags=tags or {}),
            timeout=max(self.timeout, 30.0),
        )
        assert reply.model is not None
        return reply.model

    async def get_model(self, name: str, version: int | None = None) -> tuple[ModelMeta, bytes]:
        """The pinned (else latest) version, or ``version``; integrity is checked."""
        reply = await self._ask_model(
            ModelGet(name=name, version=version), timeout=max(self.timeout, 30.0)
        )
        assert reply.model is not None
        if await _sha256(reply.data) != reply.model.sha256:
            raise KnowledgeError(
                f"model {name!r} version {reply.model.version} arrived "
                "corrupted (sha256 mismatch); fetch it again",
                "integrity",
            )
        return reply.model, reply.data

    async def list_models(self, name: str) -> tuple[list[ModelMeta], int | None]:
        """Versions of ``name`` and the pinned one (None: latest wins)."""
        reply = await self._ask_model(ModelList(name=name))
        return reply.models, reply.pinned

    async def pin_model(self, name: str, version: int | None) -> int | None:
        reply = await self._ask_model(ModelPin(name=name, version=version))
        return reply.pinned

    async def rollback_model(self, name: str) -> int | None:
        """Pin the version before the one in force; returns the pinned version."""
        reply = await self._ask_model(ModelPin(name=name, rollback=True))
        return reply.pinned

    async def _ask_model(
        self, request: ModelPut | ModelGet | ModelList | ModelPin, *, timeout: float | None = None
    ) -> KbReply:
        """A model store request, on the model's own key (``_models/<name>``: the key the
        access control grants), signed when the client has an identity."""
        return await self._ask(
            f"{MODELS_PREFIX}/{request.name}",
            request,
            timeout=timeout,
            sign=str(type(request).__struct_config__.tag),
        )

    async def _model_signer(self) -> Signer | None:
        """:attr:`signer`, else (looked up once, in a worker thread) the identity of
        ``RAP_AS`` and ``RAP_CERTS``."""
        if not self._signer_loaded:
            from .identity import IdentityError, signer_from_env

            try:
                self.signer = await anyio.to_thread.run_sync(signer_from_env)
            except IdentityError as exc:
                raise KnowledgeError(
                    f"cannot sign the model store request: {exc}", "denied"
                ) from None
            self._signer_loaded = True
        return self.signer

    # -- plumbing --------------------------------------------------------------------------

    def _check_key(self, key: str) -> None:
        if key in self._valid:
            return
        keys.kb("x", key)
        if key.split("/")[0].startswith("_"):
            raise KnowledgeError(
                f"knowledge key {key!r}: keys whose first chunk starts with '_' are reserved",
                "bad-request",
            )
        if len(self._valid) < 4096:
            self._valid.add(key)

    def _kb_key(self, key: str) -> str:
        full = self._kb_keys.get(key)
        if full is None:
            full = keys.kb(self.system, key)
            if len(self._kb_keys) < 4096:
                self._kb_keys[key] = full
        return full

    async def _ask(
        self, key: str, request: KbRequest, *, timeout: float | None = None, sign: str = ""
    ) -> KbReply:
        """``sign``: the verb to sign the request for (with :meth:`_model_signer`)."""
        selector = self._kb_key(key)
        payload = _encode(request)
        attachment = b""
        signer = await self._model_signer() if sign else None
        if signer is not None:
            if len(payload) < 1 << 20:
                attachment = signer.attachment(selector, sign, payload)
            else:  # a model: hashed off the event loop
                attachment = await anyio.to_thread.run_sync(
                    signer.attachment, selector, sign, payload
                )
        try:
            replies = await self.fabric.query(
                selector, payload, timeout=timeout or self.timeout, attachment=attachment
            )
        except QueryError as exc:
            raise KnowledgeError(
                f"knowledge service did not answer: {exc}", "unavailable"
            ) from None
        if not replies:
            raise KnowledgeError(
                f"no knowledge service answered for system {self.system!r} (is it "
                "running and connected?)",
                "unavailable",
            )
        first = replies[0]
        if not first.ok:
            raise KnowledgeError(first.payload.decode(errors="replace"), "unavailable")
        try:
            reply = _reply(first.payload)
        except DecodeRejected as exc:
            raise KnowledgeError(
                f"the knowledge service's reply is not valid: {exc}", "bad-reply"
            ) from None
        if not reply.ok:
            raise KnowledgeError(reply.error, reply.code)
        return reply


async def _sha256(data: bytes) -> str:
    """The sha256 of ``data``; large artefacts are hashed off the event loop."""
    if len(data) < 1 << 20:
        return hashlib.sha256(data).hexdigest()
    return await anyio.to_thread.run_sync(lambda: hashlib.sha256(data).hexdigest())
