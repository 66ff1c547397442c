"""The knowledge service: serves ``rap/<system>/kb/**`` (docs/architecture.md, "Knowledge").

- Follows the write stream (``KbRecord`` envelopes on ``rap/<system>/kb/<key>``) and
  stores every record (non-durable writes).
- Answers queries on the same keys (``KbRequest`` -> ``KbReply``): durable writes and
  compare-and-set (stored, then republished on the write stream for replicas), get,
  history, key listing, and the model store under ``_models/<name>``.
- A model store request is taken only on its model's own key (what the routers' access
  control grants), and, when the service has identities (``RAP_CERTS``), only signed by
  an operator or by an identity ``model_grants`` allows (read: get and list; write: also
  put, pin and roll back). Each is audited (``rap.audit``, as the admin verbs are): who,
  what, and what came of it; refusals with the identity that asked.
- Bad input (unknown operation, oversized value, wrong type, malformed key) gets an
  error reply with the reason; the service carries on.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Awaitable, Iterable
from functools import partial
from typing import Any

import anyio
import msgspec
from anyio.abc import TaskStatus
from rap_schemas import (
    MODELS_PREFIX,
    KbDelete,
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
from rap_schemas.limits import DecodeRejected, SafeDecoder
from rap_sdk import Fabric, InboxPolicy, Opener, QueryRequest, RapError, Reply, Sample, Sealer
from rap_sdk.admin import Gate, audit
from rap_sdk.envelope import typed_decoder
from rap_sdk.errors import LifecycleError, RejectedSample
from rap_sdk.identity import OPERATOR, AuthError, Caller, Verifier
from rap_sdk.inbox import Overflow
from rap_sdk.knowledge import SERVICE_NODE, join_colocated
from rap_sdk.rejections import Rejections, Throttle
from rap_sdk.runtime import refuse_running

from .config import KnowledgeConfig
from .core import admit_record, check_key, check_model, check_pattern, check_time, sha256
from .errors import (
    BadRequest,
    Conflict,
    IntegrityError,
    NotFound,
    ServiceError,
    StoreUnavailable,
    TooLarge,
)
from .ports import Store

__all__ = ["KnowledgeService", "ServiceStats"]

log = logging.getLogger(__name__)

NODE = SERVICE_NODE
_encode = msgspec.msgpack.Encoder().encode
_STREAM = typed_decoder(KbRecord)
PUT_RETRIES = 8
ModelRequest = ModelPut | ModelGet | ModelList | ModelPin
_MODEL_REQUESTS = (ModelPut, ModelGet, ModelList, ModelPin)
_MODEL_WHAT = {
    "model-put": "put a version of",
    "model-get": "get",
    "model-list": "list",
    "model-pin": "pin",
    "model-rollback": "roll back",
}
"""A model store verb (an audit record's), as a refusal says it."""


class ServiceStats(msgspec.Struct):
    stream_applied: int = 0
    stream_rejected: int = 0
    stream_failed: int = 0
    queries: int = 0
    query_errors: int = 0


class KnowledgeService:
    def __init__(
        self,
        config: KnowledgeConfig,
        *,
        fabric: Fabric,
        store: Store,
        verifier: Verifier | None = None,
    ) -> None:
        """``verifier``: who may use the model store is checked with it (default: the CA
        of ``RAP_CERTS`` when it is set; else everyone may)."""
        self.config = config
        self.fabric = fabric
        self.store = store
        self.stats = ServiceStats()
        self.sealer = Sealer(NODE)
        self.opener = Opener()
        self.rejections = Rejections(NODE, log)
        self._throttle = Throttle()
        """Write records and requests refused, by reason (logged rate-limited)."""
        self._request = SafeDecoder[KbRequest](
            KbRequest, max_bytes=config.max_model_bytes + (1 << 20), what="knowledge request"
        ).decode
        self._prefix = keys.kb(config.system, "x")[:-1]
        self._log_key = keys.log(config.system, NODE)
        self._model_locks: dict[str, anyio.Lock] = {}
        self._gate = Gate(verifier)
        """Who may use the model store (the admin verbs' gate: its verifier, its
        throttle of audited refusals)."""
        self._taking = 0
        """Records being stored now (a direct take waits for none: it goes to the inbox)."""

    async def run(self, *, task_status: TaskStatus[None] = anyio.TASK_STATUS_IGNORED) -> None:
        """Serve until cancelled; ready (subscribed and serving) when started. Raises
        :class:`~rap_sdk.LifecycleError` when a knowledge service of this system is
        alive already (clients would take whichever answer came first)."""
        await refuse_running(fabric=self.fabric, system=self.config.system, names=[NODE])
        pattern = keys.pattern(self.config.system, keys.Kind.KB)
        stream = self.fabric.subscribe(
            pattern,
            InboxPolicy(capacity=65536, overflow=Overflow.FIFO, block=True, max_bytes=256 << 20),
            prepare=_STREAM,
        )
        leave = None
        if getattr(self.store, "immediate", False):
            if hasattr(stream, "direct"):
                stream.direct = partial(self._direct, stream)
            if hasattr(self.store, "apply_now"):
                leave = join_colocated(self.fabric, self.config.system, _Intake(self, stream))
        queryable = self.fabric.serve(pattern, self._answer)
        token = self.fabric.declare_token(keys.alive(self.config.system, NODE))
        try:
            task_status.started()
            await self._follow(stream)
        finally:
            if leave is not None:
                leave()
            token.undeclare()
            queryable.undeclare()
            stream.close()

    # -- the write stream ------------------------------------------------------------------

    async def _follow(self, stream: Any) -> None:
        while True:
            try:
                sample = await stream.get()
            except LifecycleError:
                return
            await self._take(sample)

    def _direct(self, stream: Any, sample: Sample) -> Awaitable[None] | None:
        """A record written in this process, stored in the writer's task at once when the
        store applies without waiting (memory) and nothing is queued or being stored:
        no inbox, no task woken. None: it goes through the inbox."""
        if self._taking or len(stream.inbox):
            return None
        env = sample.obj
        if env is None or type(env.body) is not KbRecord:
            return None
        stream.inbox.stats.accepted += 1
        return self._take(sample)

    async def _take(self, sample: Sample) -> None:
        env = sample.obj  # a record written in this process: no decoding
        local = env is not None and type(env.body) is KbRecord
        if not local:
            try:
                env = self.opener.open_typed(
                    sample.key, sample.payload, _STREAM, KbRecord.TYPE, sample.prepared
                )
            except RejectedSample as exc:
                self.stats.stream_rejected += 1
                await self._rejected(
                    self.rejections.reject(sample.key, exc.reason, source=exc.source, type=exc.type)
                )
                return
        if env is None or env.source == NODE:
            return  # a duplicate, or our own republication of a durable write
        await self._store(env.body, local, sample.key)

    async def _store(self, rec: KbRecord, local: bool, key: str) -> None:
        """Store a record that came on stream key ``key``."""
        self._taking += 1
        try:
            if key != self._prefix + rec.key:
                raise BadRequest(f"record for {rec.key!r} arrived on {key!r}")
            await self.store.apply(admit_record(rec, self.config.max_value_bytes, local=local))
            self.stats.stream_applied += 1
        except (BadRequest, TooLarge) as exc:
            self.stats.stream_rejected += 1
            await self._rejected(self.rejections.reject(key, str(exc), source=rec.writer))
        except Exception as exc:  # the store failed: counted, logged, the stream goes on
            self.stats.stream_failed += 1
            if self._throttle.hit("store"):
                log.error("write stream: could not store a record on %s: %s", key, exc)
        finally:
            self._taking -= 1

    async def _rejected(self, rec: Rejection | None) -> None:
        """Publish a due rejection record on ``rap/<system>/log/knowledge``."""
        if rec is None:
            return
        payload, _ = self.sealer.seal_message(self._log_key, rec)
        try:
            await self.fabric.publish(self._log_key, payload, timeout=1.0)
        except RapError as exc:
            log.debug("a rejection record could not be published: %s", exc)

    # -- queries ---------------------------------------------------------------------------

    async def _answer(self, query: QueryRequest) -> Iterable[Reply]:
        self.stats.queries += 1
        try:  # the fabric bounds the whole query with its handler deadline
            req = self._request(query.payload)
            if isinstance(req, _MODEL_REQUESTS):
                reply = await self._model_request(req, query)
            else:
                reply = await self._dispatch(req, query.key, query.arrived or time.monotonic())
        except DecodeRejected as exc:
            await self._rejected(self.rejections.reject(query.key, exc.reason))
            reply = self._error(BadRequest(exc.reason), quiet=True)
        except (ServiceError, RapError) as exc:
            reply = self._error(exc)
        except Exception as exc:  # a store or a bug: an error reply, counted; serving goes on
            if self._throttle.hit("internal"):
                log.exception("knowledge request failed")
            reply = self._error(ServiceError(f"internal error: {type(exc).__name__}: {exc}"))
        key = query.key if "*" not in query.key else keys.kb(self.config.system, "_keys")
        return [Reply(key, _encode(reply))]

    def _error(self, exc: Exception, *, quiet: bool = False) -> KbReply:
        self.stats.query_errors += 1
        code = getattr(exc, "code", "error")
        count = 0 if quiet else self._throttle.hit(code)
        if count:
            log.info(
                "knowledge request failed (%s; %d such since the last line): %s", code, count, exc
            )
        return KbReply(ok=False, code=code, error=str(exc))

    async def _dispatch(self, req: Any, query_key: str, arrived: float) -> KbReply:
        store = self.store
        key = getattr(req, "key", None) or getattr(getattr(req, "record", None), "key", None)
        if key is not None and query_key != self._prefix + check_key(key):
            raise BadRequest(f"request for {key!r} was sent to {query_key!r}")
        if isinstance(req, (KbPut, KbDelete)) and req.budget_ms is not None:
            if not 0 < req.budget_ms <= 3_600_000:
                raise BadRequest(f"budget_ms must be 1 .. 3600000, got {req.budget_ms}")
            deadline: float | None = arrived + req.budget_ms / 1000
        else:
            deadline = None
        if isinstance(req, KbPut):
            return await self._put(
                admit_record(req.record, self.config.max_value_bytes), req.expect, deadline
            )
        if isinstance(req, KbDelete):
            rec = KbRecord(
                key=req.key,
                version=req.version,
                ts=time.time_ns(),
                writer=req.writer,
                value=msgspec.Raw(b"\xc0"),
                deleted=True,
            )
            return await self._put(
                admit_record(rec, self.config.max_value_bytes), req.expect, deadline
            )
        if isinstance(req, KbGet):
            latest = await store.get(check_key(req.key))
            return KbReply(record=latest, version=latest.version if latest else 0)
        if isinstance(req, KbHistory):
            if req.limit < 1 or req.limit > 100_000:
                raise BadRequest(f"history limit must be 1..100000, got {req.limit}")
            recs = await store.history(
                check_key(req.key),
                since=check_time("since", req.since),
                until=check_time("until", req.until),
                limit=req.limit,
            )
            return KbReply(records=recs)
        if isinstance(req, KbList):
            return KbReply(keys=await store.keys(check_pattern(req.pattern)))
        raise BadRequest(f"unknown knowledge operation {type(req).__name__}")

    async def _put(self, rec: KbRecord, expect: int | None, deadline: float | None) -> KbReply:
        """Store a durable write. The service orders durable writes: one that arrives at
        or below the key's current version is moved past it (keeping its own writer
        tag). If another write lands between reading the current version and storing,
        it is retried, so the reply's version is always this write's, as the latest.
        With a ``deadline`` (the request's budget) it is stored by then or not at all:
        a writer that stopped waiting is never contradicted by a later store."""
        for _ in range(PUT_RETRIES):
            current = await self._current(rec.key, deadline)
            if current is not None and (current.version, current.writer) == (
                rec.version,
                rec.writer,
            ):
                return KbReply(version=rec.version)  # a re-sent write: already the latest
            if current is not None and rec.version <= current.version:
                rec = msgspec.structs.replace(
                    rec, version=((current.version >> 8) + 1) << 8 | (rec.version & 0xFF)
                )
            applied = await self.store.apply(rec, expect=expect, deadline=deadline)
            if applied.latest:
                if not applied.duplicate:
                    await self._republish(rec)
                return KbReply(version=rec.version)
        raise Conflict(rec.key, None, applied.version)

    async def _current(self, key: str, deadline: float | None) -> KbRecord | None:
        """The stored latest record of ``key``, read within the write's deadline."""
        if deadline is None:
            return await self.store.get(key)
        try:
            with anyio.fail_after(max(0.0, deadline - time.monotonic())):
                return await self.store.get(key)
        except TimeoutError:
            raise StoreUnavailable(
                f"durable write of {key!r} not stored: the store did not answer within the "
                "write's budget; retry it"
            ) from None

    async def _republish(self, rec: KbRecord) -> None:
        """Replicas in other processes follow the stream (the service's own
        subscription is the service itself: it already stored the record)."""
        key = self._prefix + rec.key
        if self.fabric.has_subscribers(key, remote_only=True):
            payload, _ = self.sealer.seal_message(key, rec)
            await self.fabric.publish(key, payload, local=False)

    # -- model store -----------------------------------------------------------------------

    async def _model_request(self, req: ModelRequest, query: QueryRequest) -> KbReply:
        """A model store request: on its model's key, from whom may make it (refused
        with ``code="denied"``), then done; audited either way."""
        name = req.name
        try:
            expected = self._prefix + f"{MODELS_PREFIX}/{name}"
            keys.kb(self.config.system, f"{MODELS_PREFIX}/{name}")
        except keys.KeyError_ as exc:
            raise BadRequest(f"invalid model name: {exc}") from None
        if query.key != expected:
            raise BadRequest(
                f"a request for model {name!r} was sent to {query.key!r} - send it to "
                f"{expected} (KnowledgeClient does)"
            )
        verb = _verb(req)
        write = isinstance(req, ModelPut | ModelPin)
        asked = _asked(req)
        checked = self._gate.checks
        try:
            caller = await self._authorize(req, verb, write, query)
        except AuthError as exc:
            audit(
                verb=verb,
                component=NODE,
                result="refused",
                caller=exc.caller,
                checked=True,
                key=query.key,
                request=asked,
                reason=exc.reason,
                read=not write,
                kind=exc.kind,
                throttle=self._gate.refusals,
            )
            self.stats.query_errors += 1
            return KbReply(ok=False, code="denied", error=exc.reason)
        try:
            reply = await self._models(req)
        except (ServiceError, RapError) as exc:
            audit(
                verb=verb,
                component=NODE,
                result="error",
                caller=caller,
                checked=checked,
                key=query.key,
                request=asked,
                reason=str(exc),
                read=not write,
            )
            raise
        audit(
            verb=verb,
            component=NODE,
            result="ok",
            caller=caller,
            checked=checked,
            key=query.key,
            request=asked,
            reason=_done(req, reply),
            read=not write,
        )
        return reply

    async def _authorize(
        self, req: ModelRequest, verb: str, write: bool, query: QueryRequest
    ) -> Caller | None:
        """Who signed ``req`` when the service checks identities (None: it does not);
        :class:`~rap_sdk.identity.AuthError` unless an operator or an identity
        ``model_grants`` allows it."""
        gate = self._gate
        await gate.load()
        if gate.problem:
            raise AuthError(gate.problem, kind="identities not loadable")
        verifier = gate.verifier
        if verifier is None:
            return None
        signed = partial(
            verifier.verify,
            query.key,
            _tag(req),
            query.payload,
            query.attachment,
            scope=NODE,
        )
        caller = (
            signed() if len(query.payload) < 1 << 20 else await anyio.to_thread.run_sync(signed)
        )
        if caller.role == OPERATOR:
            return caller
        name = req.name
        granted = self.config.model_grants.get(caller.name, {}).get(name)
        if granted == "write" or (granted == "read" and not write):
            return caller
        need = "write" if write else "read"
        has = (
            f"grants it only read access (models: {{{name}: read}})"
            if granted
            else "grants it no access to it"
        )
        raise AuthError(
            f"{caller.name!r} may not {_MODEL_WHAT[verb]} model {name!r}: the system model "
            f"{has} - give its component 'models: {{{name}: {need}}}' in the model and "
            "restart it (rap up), or ask as one of the model's fabric.operators (rap models "
            "... --as NAME)",
            kind=f"model {need} not granted",
            caller=caller,
        )

    async def _models(self, req: Any) -> KbReply:
        store = self.store
        if isinstance(req, ModelPut):
            await anyio.to_thread.run_sync(
                check_model, req.name, req.data, req.sha256, self.config.max_model_bytes
            )
            async with self._model_lock(req.name):  # one version number per put
                return await self._put_model(req)
        if isinstance(req, ModelGet):
            version = (
                req.version if req.version is not None else await self._current_model(req.name)
            )
            got = await store.get_model(req.name, version)
            if got is None:
                raise NotFound(f"model {req.name!r} has no version {version}")
            meta, data = got
            if await anyio.to_thread.run_sync(sha256, data) != meta.sha256:
                raise IntegrityError(
                    f"model {req.name!r} version {version} is corrupted in "
                    "the store (sha256 mismatch); put it again"
                )
            return KbReply(model=meta, data=data if req.with_data else b"")
        if isinstance(req, ModelList):
            return KbReply(
                models=await store.list_models(req.name), pinned=await store.get_pin(req.name)
            )
        if isinstance(req, ModelPin):
            numbers = [m.version for m in await store.list_models(req.name)]
            if not numbers:
                raise NotFound(f"no model named {req.name!r}")
            target = req.version
            if req.rollback:
                current = await self._current_model(req.name)
                older = [v for v in numbers if v < current]
                if not older:
                    raise NotFound(
                        f"model {req.name!r}: nothing older than version {current} to roll back to"
                    )
                target = older[-1]
            if target is not None and target not in numbers:
                raise NotFound(f"model {req.name!r} has no version {target}; it has {numbers}")
            await store.set_pin(req.name, target)
            return KbReply(pinned=target)
        raise BadRequest(f"unknown knowledge operation {type(req).__name__}")

    def _model_lock(self, name: str) -> anyio.Lock:
        lock = self._model_locks.get(name)
        if lock is None:
            lock = self._model_locks[name] = anyio.Lock()
        return lock

    async def _put_model(self, req: ModelPut) -> KbReply:
        versions = await self.store.list_models(req.name)
        meta = ModelMeta(
            name=req.name,
            version=(versions[-1].version + 1) if versions else 1,
            sha256=req.sha256,
            size=len(req.data),
            created=time.time_ns(),
            tags=req.tags,
        )
        await self.store.put_model(meta, req.data)
        return KbReply(model=meta, pinned=await self.store.get_pin(req.name))

    async def _current_model(self, name: str) -> int:
        pinned = await self.store.get_pin(name)
        if pinned is not None:
            return pinned
        versions = await self.store.list_models(name)
        if not versions:
            raise NotFound(f"no model named {name!r} (under {MODELS_PREFIX}/)")
        return versions[-1].version


def _tag(req: ModelRequest) -> str:
    """A model store request's tag (``model-put``, ...): the verb it is signed for."""
    tag = type(req).__struct_config__.tag
    assert isinstance(tag, str)
    return tag


def _verb(req: ModelRequest) -> str:
    """The audit record's verb of a model store request."""
    if isinstance(req, ModelPin) and req.rollback:
        return "model-rollback"
    return _tag(req)


def _asked(req: ModelRequest) -> str:
    """A model store request as its audit record keeps it."""
    if isinstance(req, ModelPut):
        return f"{req.name}: {len(req.data)} bytes, sha256 {req.sha256[:12]}"
    if isinstance(req, ModelPin) and not req.rollback:
        return f"{req.name} version {req.version}" if req.version is not None else req.name
    if isinstance(req, ModelGet) and req.version is not None:
        return f"{req.name} version {req.version}"
    return req.name


def _done(req: ModelRequest, reply: KbReply) -> str:
    """What a model store request did, as its audit record says it."""
    if isinstance(req, ModelPut) and reply.model is not None:
        return f"stored version {reply.model.version}"
    if isinstance(req, ModelPin):
        if req.rollback:
            return f"rolled back to version {reply.pinned}"
        if reply.pinned is None:
            return "unpinned: the latest version is in force"
        return f"pinned version {reply.pinned}"
    if isinstance(req, ModelGet) and reply.model is not None:
        return f"version {reply.model.version}"
    return f"{len(reply.models)} version(s)"


class _Intake:
    """The service's intake of records written by co-located clients (same process,
    same fabric): stored in the writer's task, with no envelope, no sample and no task
    woken, when the store applies at once (memory's ``apply_now``) and nothing is
    queued or being stored; otherwise (and when the record is refused: the stream's
    way words and counts the reason) the writer sends it on the stream as usual."""

    __slots__ = ("_service", "stream")

    def __init__(self, service: KnowledgeService, stream: Any) -> None:
        self._service = service
        self.stream: Any = stream
        """The service's write-stream subscription (a local one: it has an inbox)."""

    def take(self, rec: KbRecord) -> bool:
        svc = self._service
        inbox = self.stream.inbox
        if svc._taking or inbox._items or inbox._closed:
            return False  # busy, or closing: the stream's way (it says the fabric closed)
        # the writer, a KnowledgeClient, checked the key (it refuses every key the
        # service does), the version and time (its own clock, as the co-located
        # replicas it hands the record to trust it) and the value's nesting; the size
        # is checked against this service's own limit
        if len(rec.value) > svc.config.max_value_bytes:
            return False  # refused: the stream's way words and counts it
        try:
            svc.store.apply_now(rec)  # type: ignore[attr-defined]
        except Exception:  # failed: the stream's way counts and logs it
            return False
        inbox.stats.accepted += 1
        svc.stats.stream_applied += 1
        return True
