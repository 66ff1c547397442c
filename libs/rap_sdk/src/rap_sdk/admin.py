"""The admin verbs of a running component, and the client that calls them.

Each :class:`~rap_sdk.runtime.NodeRuntime` answers queries on
``rap/<system>/admin/<component>/<verb>`` while it runs (``rap_schemas.admin`` lists the
verbs, their requests and the :class:`~rap_schemas.admin.AdminReply`). Verbs on one
component run one at a time.

    replies = await call(fabric, "demo", "monitor", "pause", signer=signer)
    replies = await call(fabric, "demo", "*", "status")   # every component

Who may call: a process with identities (``RAP_CERTS`` set, or a ``verifier`` given to
:func:`serve_admin`) takes only requests signed by a certificate of the system's CA
(:mod:`rap_sdk.identity`; :func:`call` signs with its ``signer``, the signature riding
as the query's attachment): the reads (``status``, ``config`` without values) from any
identity, the other verbs from an ``operator`` only. Anything else is refused with an
``AdminReply`` saying why. Without identities every request is taken, as before.

The audit trail: every verb, refused ones included, is one
:class:`~rap_schemas.admin.AuditRecord` logged on ``rap.audit`` (:func:`audit`): who
(the authenticated identity, or ``unauthenticated``), what, when, and the result;
changes at INFO, refusals and failures at WARNING, reads that succeed at DEBUG.
"""

from __future__ import annotations

import contextlib
import importlib
import logging
import os
import re
import time
from collections.abc import Iterable
from typing import TYPE_CHECKING, Any

import anyio
import msgspec
from rap_schemas import keys
from rap_schemas.admin import (
    ADMIN_VERBS,
    AUDIT_LOGGER,
    PAUSE_POLICY,
    AdminReply,
    AuditRecord,
    ComponentSnapshot,
    ComponentState,
    ComponentStatus,
    ComponentSwap,
    ConfigRequest,
    RestartRequest,
    RestoreRequest,
    SnapshotInfo,
    snapshot_key,
)

from .errors import ConfigError, LifecycleError, RapError
from .fabric import QueryRequest, Reply
from .identity import (
    CERTS_ENV,
    OPERATOR,
    UNAUTHENTICATED,
    AuthError,
    Caller,
    IdentityError,
    SignedRequest,
    Signer,
    Verifier,
    require_role,
    verifier_from_env,
)
from .knowledge import KnowledgeClient, KnowledgeError
from .node import Node
from .rejections import Throttle

if TYPE_CHECKING:
    from .fabric import Fabric, Queryable
    from .runtime import NodeRuntime

__all__ = [
    "AdminError",
    "Gate",
    "audit",
    "call",
    "is_read",
    "load_implementation",
    "resume_from_knowledge",
    "serve_admin",
    "summary",
]

log = logging.getLogger("rap.admin")
audit_log = logging.getLogger(AUDIT_LOGGER)

_encode = msgspec.json.encode
_reply_decoder = msgspec.json.Decoder(AdminReply)
_PATH = re.compile(r"`(\$[^`]*)`")
MAX_REQUEST = 64 * 1024
"""Bytes an admin request may have."""
SUMMARY_CHARS = 200
"""Characters of a request kept in its audit record."""
REASON_CHARS = 2000
"""Characters of a reason kept in an audit record."""


class AdminError(RapError):
    """An admin call that could not be made (nobody answered, a bad reply)."""


def load_implementation(target: str) -> Node:
    """The Node ``module:attr`` names: a Node, or a function of no argument returning a
    fresh one (each call: a new instance). Raises :class:`ConfigError` saying what to fix.
    Imports run the module's code: call it in a worker thread."""
    module_name, sep, attr = target.partition(":")
    if not sep or not module_name or not attr:
        raise ConfigError(f"{target!r} is not module:attr (e.g. my_robot.nodes:monitor)")
    try:
        mod = importlib.import_module(module_name)
    except Exception as exc:  # importing runs the module's code: anything can surface
        raise ConfigError(
            f"cannot import {module_name!r}: {type(exc).__name__}: {exc}; is it installed "
            "where the component runs?"
        ) from None
    obj = getattr(mod, attr, None)
    if obj is None:
        raise ConfigError(f"module {module_name!r} has no attribute {attr!r}")
    if not isinstance(obj, Node) and callable(obj):
        try:
            obj = obj()
        except Exception as exc:  # the user's factory
            raise ConfigError(f"{target}() failed: {type(exc).__name__}: {exc}") from None
    if not isinstance(obj, Node):
        raise ConfigError(
            f"{target} is a {type(obj).__name__}, not a rap_sdk.Node (or a function returning one)"
        )
    obj.implementation = target
    return obj


def status(rt: NodeRuntime) -> ComponentStatus:
    """What ``rt`` says of itself now."""
    node = rt.node
    if rt._state == "new":
        state = ComponentState.STARTING
    elif rt._state == "stopped":
        state = ComponentState.GONE
    elif rt.paused:
        state = ComponentState.PAUSED
    elif rt._calling:
        state = ComponentState.ACTIVE
    elif rt.last_failed:
        state = ComponentState.FAILED
    else:
        state = ComponentState.IDLE
    s = rt.stats
    return ComponentStatus(
        name=node.name,
        state=state,
        stage=node.stage.value if node.stage else "",
        compute_node=rt.compute_node,
        implementation=node.implementation,
        since=rt.started_at,
        last_cycle=rt.last_cycle.hex(),
        last_call=rt.last_call,
        received=s.received,
        handled=s.handled,
        failed=s.failed,
        rejected=s.rejected,
        dropped=s.dropped,
        sent=s.sent,
        inbox=rt.inbox_depth,
        p50_ms=round(rt.latency.percentile(0.5) * 1e3, 4),
        p99_ms=round(rt.latency.percentile(0.99) * 1e3, 4),
        restarts=rt.restarts,
        swaps=rt.swaps,
        paused_policy=PAUSE_POLICY if rt.paused else "",
        rejections=dict(rt.rejections.by_reason),
    )


def _config(rt: NodeRuntime) -> dict[str, Any] | None:
    conf = rt.node.config
    return None if conf is None else msgspec.to_builtins(conf)


async def _snapshot(rt: NodeRuntime) -> SnapshotInfo:
    kb = rt.knowledge
    async with rt.exclusive():
        state = rt.node.snapshot()
    snap = ComponentSnapshot(
        component=rt.node.name,
        implementation=rt.node.implementation,
        ts=time.time_ns(),
        state=state,
    )
    key = snapshot_key(rt.node.name)
    version = await kb.write(key, snap, durable=True)
    return SnapshotInfo(key=key, version=version, size=len(state))


async def _stored(kb: KnowledgeClient, component: str, version: int = 0) -> ComponentSnapshot:
    """The snapshot of ``version`` (0: the latest) kept for ``component``."""
    key = snapshot_key(component)
    if version == 0:
        snap: ComponentSnapshot | None = await kb.read(key, ComponentSnapshot, default=None)
        if snap is None:
            raise ConfigError(f"no snapshot of {component} in knowledge (take one: snapshot)")
        return snap
    for rec in await kb.history(key, ComponentSnapshot, limit=10_000):
        if rec.version == version and rec.value is not None:
            value: ComponentSnapshot = rec.value
            return value
    raise ConfigError(f"no snapshot of {component} with version {version} in knowledge")


async def resume_from_knowledge(rt: NodeRuntime, kb: KnowledgeClient) -> None:
    """Restore ``rt``'s node from its latest snapshot in knowledge, when it has a
    restore hook and a snapshot is kept (at start: a restarted component resumes)."""
    if rt.node._restore is None:
        return
    try:
        with anyio.fail_after(kb.timeout):
            snap: ComponentSnapshot | None = await kb.read(
                snapshot_key(rt.node.name), ComponentSnapshot, default=None
            )
    except (KnowledgeError, TimeoutError) as exc:
        log.warning(
            "node %s: could not read its snapshot from knowledge: %s; it starts with a fresh state",
            rt.node.name,
            exc,
        )
        return
    if snap is None:
        return
    try:
        rt.node.restore(snap.state)
    except ConfigError as exc:
        log.warning(
            "node %s: its snapshot in knowledge does not fit: %s; it starts with a fresh state",
            rt.node.name,
            exc,
        )
        return
    log.info(
        "node %s: resumed the state of its snapshot of %s",
        rt.node.name,
        _when(snap.ts),
    )


def _when(ts: int) -> str:
    return time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(ts / 1e9))


def _refused(verb: str, rt: NodeRuntime, message: str, path: str = "") -> AdminReply:
    return AdminReply(ok=False, verb=verb, component=rt.node.name, message=message, path=path)


def _request(payload: bytes, type_: type[Any]) -> Any:
    if len(payload) > MAX_REQUEST:
        raise ConfigError(f"request of {len(payload)} bytes is over {MAX_REQUEST}")
    try:
        return msgspec.json.decode(payload or b"{}", type=type_)
    except (msgspec.ValidationError, msgspec.DecodeError) as exc:
        raise ConfigError(f"bad request: {exc}") from None


async def _verb(rt: NodeRuntime, verb: str, payload: bytes) -> AdminReply:
    name = rt.node.name

    def done(**fields: Any) -> AdminReply:
        return AdminReply(ok=True, verb=verb, component=name, **fields)

    if verb == "status":
        return done(status=status(rt))
    if verb == "config":
        req: ConfigRequest = _request(payload, ConfigRequest)
        if not req.values:
            return done(config=_config(rt))
        if rt.node.config is None:
            return _refused(verb, rt, f"{name} declares no config Struct: nothing to set")
        unknown = sorted(set(req.values) - set(type(rt.node.config).__struct_fields__))
        if unknown:
            return _refused(
                verb,
                rt,
                f"{name} has no config field {unknown[0]!r}; its fields: "
                + ", ".join(type(rt.node.config).__struct_fields__),
                f"$.{unknown[0]}",
            )
        try:
            async with rt.exclusive():
                rt.node.configure(req.values)
        except ConfigError as exc:
            m = _PATH.search(str(exc))
            return _refused(verb, rt, f"{exc}; the config is unchanged", m.group(1) if m else "")
        return done(
            config=_config(rt),
            message=f"set {', '.join(sorted(req.values))}",
        )
    if verb == "pause":
        paused = await rt.pause()
        return done(
            status=status(rt),
            message="paused" if paused else "was paused already",
        )
    if verb == "resume":
        resumed = rt.resume()
        return done(
            status=status(rt),
            message="resumed" if resumed else "was not paused",
        )
    if verb == "swap":
        swap: ComponentSwap = _request(payload, ComponentSwap)
        new = await anyio.to_thread.run_sync(load_implementation, swap.target)
        old = rt.node.implementation
        await rt.swap(new)
        return done(
            status=status(rt),
            message=f"swapped {old or 'its implementation'} for {swap.target}, state handed over",
        )
    if verb == "restart":
        fresh = None
        impl = rt.node.implementation
        if impl:
            fresh = await anyio.to_thread.run_sync(load_implementation, impl)
        restart: RestartRequest = _request(payload, RestartRequest)
        state = None
        how = "with the state it had"
        if restart.from_snapshot:
            snap = await _stored(rt.knowledge, name)  # none kept: refused, nothing done
            state = snap.state
            how = f"from its snapshot taken at {_when(snap.ts)} UTC"
        await rt.restart(fresh, state)
        return done(status=status(rt), message=f"restarted {how}")
    if verb == "snapshot":
        info = await _snapshot(rt)
        return done(
            snapshot=info,
            message=f"kept as {info.key} version {info.version}",
        )
    if verb == "restore":
        rr: RestoreRequest = _request(payload, RestoreRequest)
        snap = await _stored(rt.knowledge, name, rr.version)
        async with rt.exclusive():
            rt.node.restore(snap.state)
        return done(
            status=status(rt),
            message=f"restored the snapshot of {snap.implementation} taken at {_when(snap.ts)} UTC",
        )
    return _refused(verb, rt, f"unknown verb {verb!r}; the verbs: {', '.join(ADMIN_VERBS)}")


def is_read(verb: str, payload: bytes) -> bool:
    """Whether a request only reads (``status``, ``config`` without values): any
    identity of the system may make it, and it does not wait behind a pause or swap."""
    if verb == "status":
        return True
    if verb != "config" or len(payload) > MAX_REQUEST:
        return False
    if not payload.strip(b" \t\r\n{}"):
        return True
    try:
        return not msgspec.json.decode(payload, type=ConfigRequest).values
    except (msgspec.ValidationError, msgspec.DecodeError):
        return False


def _cut(text: str, limit: int) -> str:
    return text if len(text) <= limit else text[:limit] + f"... [{len(text) - limit} more]"


def summary(payload: bytes) -> str:
    """A request as its audit record keeps it: its text, cut to :data:`SUMMARY_CHARS`."""
    text = payload.decode("utf-8", "replace").strip()
    return "" if text in ("", "{}") else _cut(text, SUMMARY_CHARS)


def audit(
    *,
    verb: str,
    component: str,
    result: str,
    caller: Caller | None,
    checked: bool,
    key: str = "",
    via: str = "fabric",
    request: str = "",
    reason: str = "",
    read: bool = False,
    kind: str = "",
    throttle: Throttle | None = None,
) -> AuditRecord | None:
    """Log one admin action as an :class:`~rap_schemas.admin.AuditRecord` on
    ``rap.audit`` (its message the record as JSON, its component ``component``): at
    WARNING when ``result`` is not ``ok``, else at DEBUG for a ``read``, INFO otherwise.
    With a ``throttle`` (a :class:`Gate`'s), refusals are recorded at most once a second
    per component, verb, caller and ``kind`` (the reason's kind), each record with how
    many like it came since (``repeated``). Returns the record (None: counted for the
    next one)."""
    repeated = 0
    if result == "refused" and throttle is not None:
        who = caller.name if caller is not None else ""
        count = throttle.hit(f"{component}\0{verb}\0{who}\0{kind or reason[:60]}")
        if not count:
            return None
        repeated = count - 1
    rec = AuditRecord(
        ts=time.time_ns(),
        who=caller.name if caller is not None else UNAUTHENTICATED,
        role=caller.role if caller is not None else "",
        checked=checked,
        verb=verb,
        component=component,
        via=via,
        key=key,
        request=request,
        result=result,
        reason=_cut(reason, REASON_CHARS),
        repeated=repeated,
    )
    level = logging.WARNING if result != "ok" else logging.DEBUG if read else logging.INFO
    if audit_log.isEnabledFor(level):
        audit_log.log(level, "%s", _encode(rec).decode(), extra={"component": component})
    return rec


class Gate:
    """Who may call a process's admin verbs (or the trust checker's hot swap): the
    process's :class:`~rap_sdk.identity.Verifier`, given or taken from ``RAP_CERTS``
    (read once, in a worker thread, on the first request). Without one every request is
    let in; with one whose CA cannot be read every request is refused, saying why (a
    process set up to check identities never falls back to trusting everyone)."""

    def __init__(self, verifier: Verifier | None = None, *, env: bool = True) -> None:
        self.verifier = verifier
        self.problem = ""
        self.refusals = Throttle()
        """What :func:`audit` records of the refusals (at most one a second of a kind)."""
        self._loaded = verifier is not None or not env or not os.environ.get(CERTS_ENV)

    @property
    def checks(self) -> bool:
        """Whether requests are checked (identities configured, or failing to load)."""
        return self.verifier is not None or bool(self.problem) or not self._loaded

    async def load(self) -> None:
        if self._loaded:
            return
        try:
            self.verifier = await anyio.to_thread.run_sync(verifier_from_env)
        except IdentityError as exc:
            self.problem = (
                f"this process cannot check who calls it (${CERTS_ENV}: {exc}); every "
                "request is refused until it is fixed and the process restarted"
            )
            log.error("%s", self.problem)
        self._loaded = True

    async def check(
        self,
        target: str,
        verb: str,
        body: bytes,
        signed: SignedRequest | bytes | None,
        *,
        scope: str,
        what: str,
    ) -> Caller | None:
        """The caller of a request (None: nothing is checked here). Raises
        :class:`~rap_sdk.identity.AuthError` when it is refused; a request that is not
        :func:`is_read` needs an operator."""
        await self.load()
        if self.problem:
            raise AuthError(self.problem, kind="identities not loadable")
        if self.verifier is None:
            return None
        caller = self.verifier.verify(target, verb, body, signed, scope=scope)
        if not is_read(verb, body):
            require_role(caller, OPERATOR, what)
        return caller


def serve_admin(rt: NodeRuntime, *, verifier: Verifier | None = None) -> Queryable:
    """Answer the admin verbs of ``rt`` on its fabric (NodeRuntime.run calls it).
    ``verifier``: check who calls with it (default: ``RAP_CERTS``'s CA when the variable
    is set; else every request is taken)."""
    name = rt.node.name
    pattern = keys.pattern(rt.system, keys.Kind.ADMIN, f"{name}/*")
    gate = Gate(verifier)

    async def handler(req: QueryRequest) -> Iterable[Reply]:
        verb = req.key.rsplit("/", 1)[-1]
        if verb not in ADMIN_VERBS:
            if verb in ("*", "**"):
                return []  # a wildcard over verbs names none: nothing to answer
            try:
                key = keys.admin(rt.system, name, verb)
            except keys.KeyError_:
                return []  # not a verb's name at all: no key to answer on
            reply = _refused(
                verb, rt, f"unknown verb {verb!r}; the verbs: {', '.join(ADMIN_VERBS)}"
            )
            return [Reply(key, _encode(reply))]
        key = keys.admin(rt.system, name, verb)
        # what only reads does not wait behind a pause or swap waiting for a handler
        reading = is_read(verb, req.payload)
        checked = gate.checks
        try:
            caller = await gate.check(
                req.key, verb, req.payload, req.attachment, scope=name, what=f"{verb} {name}"
            )
        except AuthError as exc:
            audit(
                verb=verb,
                component=name,
                result="refused",
                caller=exc.caller,
                checked=True,
                key=req.key,
                request=summary(req.payload),
                reason=exc.reason,
                read=reading,
                kind=exc.kind,
                throttle=gate.refusals,
            )
            denied = AdminReply(
                ok=False, verb=verb, component=name, message=exc.reason, denied=True
            )
            return [Reply(key, _encode(denied))]
        async with contextlib.nullcontext() if reading else rt.admin_lock:
            try:
                reply = await _verb(rt, verb, req.payload)
            except (ConfigError, KnowledgeError, LifecycleError) as exc:
                reply = _refused(verb, rt, str(exc))
            except Exception as exc:  # a user's hook (snapshot, restore, factory) failed
                log.exception("node %s: admin %s failed", name, verb)
                reply = _refused(verb, rt, f"{type(exc).__name__}: {exc}")
        # the audit trail: what changed a component at INFO, what only read it at DEBUG
        audit(
            verb=verb,
            component=name,
            result="ok" if reply.ok else "error",
            caller=caller,
            checked=checked,
            key=req.key,
            request=summary(req.payload),
            reason=reply.message,
            read=reading,
        )
        return [Reply(key, _encode(reply))]

    return rt.fabric.serve(pattern, handler)


async def call(
    fabric: Fabric,
    system: str,
    component: str,
    verb: str,
    request: msgspec.Struct | None = None,
    *,
    timeout: float = 5.0,
    signer: Signer | None = None,
) -> list[AdminReply]:
    """Call ``verb`` on ``component`` (``*``: every component of ``system``) and return
    the replies, sorted by component; an empty list when nobody answered. For one
    component a reply that cannot be read raises :class:`AdminError`; for ``*`` it is
    logged and left out, as are components that do not answer within ``timeout`` (the
    others' replies are kept). ``signer``: sign the request as that identity (what a
    component with identities wants; see the module docstring)."""
    every = component == "*"
    if every:
        selector = keys.pattern(system, keys.Kind.ADMIN, f"*/{verb}")
        keys.admin(system, "x", verb)  # validates the verb as a key chunk
    else:
        selector = keys.admin(system, component, verb)
    payload = _encode(request) if request is not None else b""
    attachment = signer.attachment(selector, verb, payload) if signer is not None else b""
    replies = await fabric.query(
        selector, payload, timeout=timeout, partial=every, attachment=attachment
    )
    out: list[AdminReply] = []
    for r in replies:
        try:
            if not r.ok:
                raise AdminError(f"{r.key}: {r.payload.decode('utf-8', 'replace')}")
            try:
                out.append(_reply_decoder.decode(r.payload))
            except (msgspec.ValidationError, msgspec.DecodeError) as exc:
                raise AdminError(f"{r.key}: not an admin reply: {exc}") from None
        except AdminError as exc:
            if not every:
                raise
            log.warning("admin %s: a reply left out: %s", verb, exc)
    return sorted(out, key=lambda r: r.component)
