"""The admin verbs of a running component, and the client that calls them.

Each :class:`~rap_sdk.runtime.NodeRuntime` answers queries on
``rap/<system>/admin/<component>/<verb>`` while it runs (``rap_schemas.admin`` lists the
verbs, their requests and the :class:`~rap_schemas.admin.AdminReply`). Verbs on one
component run one at a time; each is logged (the audit trail) with what it did.

    replies = await call(fabric, "demo", "monitor", "pause")
    replies = await call(fabric, "demo", "*", "status")   # every component
"""

from __future__ import annotations

import contextlib
import importlib
import logging
import re
import time
from collections.abc import Iterable
from typing import TYPE_CHECKING, Any

import anyio
import msgspec
from rap_schemas import keys
from rap_schemas.admin import (
    ADMIN_VERBS,
    PAUSE_POLICY,
    AdminReply,
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
from .knowledge import KnowledgeClient, KnowledgeError
from .node import Node

if TYPE_CHECKING:
    from .fabric import Fabric, Queryable
    from .runtime import NodeRuntime

__all__ = ["AdminError", "call", "load_implementation", "resume_from_knowledge", "serve_admin"]

log = logging.getLogger("rap.admin")

_encode = msgspec.json.encode
_reply_decoder = msgspec.json.Decoder(AdminReply)
_PATH = re.compile(r"`(\$[^`]*)`")
MAX_REQUEST = 64 * 1024
"""Bytes an admin request may have."""


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


def serve_admin(rt: NodeRuntime) -> Queryable:
    """Answer the admin verbs of ``rt`` on its fabric (NodeRuntime.run calls it)."""
    name = rt.node.name
    pattern = keys.pattern(rt.system, keys.Kind.ADMIN, f"{name}/*")

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
        reading = verb == "status" or (verb == "config" and not req.payload.strip(b" {}"))
        async with contextlib.nullcontext() if reading else rt.admin_lock:
            try:
                reply = await _verb(rt, verb, req.payload)
            except (ConfigError, KnowledgeError, LifecycleError) as exc:
                reply = _refused(verb, rt, str(exc))
            except Exception as exc:  # a user's hook (snapshot, restore, factory) failed
                log.exception("node %s: admin %s failed", name, verb)
                reply = _refused(verb, rt, f"{type(exc).__name__}: {exc}")
        # the audit trail: what changed a component at INFO, what only read it at DEBUG
        reads = reading
        (log.warning if not reply.ok else log.debug if reads else log.info)(
            "node %s: admin %s %s%s",  # the node first: structured logs name it
            name,
            verb,
            "done" if reply.ok else "refused",
            f": {reply.message}" if reply.message else "",
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
) -> list[AdminReply]:
    """Call ``verb`` on ``component`` (``*``: every component of ``system``) and return
    the replies, sorted by component; an empty list when nobody answered. For one
    component a reply that cannot be read raises :class:`AdminError`; for ``*`` it is
    logged and left out, as are components that do not answer within ``timeout`` (the
    others' replies are kept)."""
    every = component == "*"
    if every:
        selector = keys.pattern(system, keys.Kind.ADMIN, f"*/{verb}")
        keys.admin(system, "x", verb)  # validates the verb as a key chunk
    else:
        selector = keys.admin(system, component, verb)
    payload = _encode(request) if request is not None else b""
    replies = await fabric.query(selector, payload, timeout=timeout, partial=every)
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
