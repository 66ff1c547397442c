"""The manager on a fabric: what it follows, what it asks, what it answers.

    async with ZenohFabric(conf) as fabric, anyio.create_task_group() as tg:
        manager = Manager(fabric=fabric, system="demo")
        await tg.start(manager.run)            # subscribed, watching, serving
        reply = await manager.command("monitor", "pause")

It follows ``alive/*`` (liveliness), ``trace/**``, ``event/**``, ``trust/**`` and
``log/**``; it asks every component's ``status`` every ``status_interval`` s (and at once
when one comes alive); it answers ``rap trace`` on ``rap/<system>/admin/manager/trace``
from its cycle history; it declares the liveliness token ``rap/<system>/alive/manager``
(and refuses to start when another manager of the system is alive). Its own subscriptions
never hold a sender back (FIFO inboxes that drop and count when full).

With a ``signer`` (its own identity: ``RAP_CERTS`` and ``RAP_AS`` under ``rap up`` with
TLS) every admin request it makes is signed, as components with identities want: its
status polls (any identity may read) and the dashboard's commands (which such a
component takes only from an operator, so a manager with a process identity has its
pause, resume and restart refused, saying so on the page).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable
from typing import Any, Final

import anyio
import msgspec
from anyio.abc import TaskStatus
from rap_schemas import (
    NEW_PLAN,
    PLAN_REJECTED,
    LogRecord,
    PlanProposal,
    Rejection,
    StageTrace,
    TrustOutput,
    TrustVerdict,
    Verdict,
    keys,
)
from rap_schemas.admin import AdminReply
from rap_schemas.limits import DECODE_ERRORS, MAX_SAMPLE_BYTES
from rap_sdk import admin
from rap_sdk.envelope import TypedEnvelope, typed_decoder
from rap_sdk.errors import FabricError, LifecycleError, RapError
from rap_sdk.fabric import Fabric, QueryRequest, Reply, Sample
from rap_sdk.identity import Signer
from rap_sdk.inbox import InboxPolicy, Overflow

from .state import Registry
from .views import MANAGER, TRACE_VERB, TraceReply, TraceRequest

__all__ = ["COMMANDS", "CommandResult", "Manager"]

log = logging.getLogger("adaptation_manager")

COMMANDS: Final = ("pause", "resume", "restart")
"""The admin verbs the dashboard may call."""
_POLICY: Final = InboxPolicy(
    capacity=4096, overflow=Overflow.FIFO, block=False, max_bytes=4 * MAX_SAMPLE_BYTES
)
_envelope = typed_decoder(None)
_reply = msgspec.json.Decoder(AdminReply).decode
_trace_request = msgspec.json.Decoder(TraceRequest).decode
_encode = msgspec.json.encode
_stage_trace = msgspec.msgpack.Decoder(StageTrace).decode
_proposal = msgspec.msgpack.Decoder(PlanProposal[Any]).decode
_verdict = msgspec.msgpack.Decoder(Verdict[Any]).decode
_trust_output = msgspec.msgpack.Decoder(TrustOutput).decode
_trust_verdict = msgspec.msgpack.Decoder(TrustVerdict).decode
_log_record = msgspec.msgpack.Decoder(LogRecord).decode
_rejection = msgspec.msgpack.Decoder(Rejection).decode
MAX_TRACE_REQUEST: Final = 4096


class CommandResult(msgspec.Struct, kw_only=True):
    """What a dashboard command did."""

    ok: bool
    component: str
    verb: str
    message: str
    state: str = ""


class Manager:
    def __init__(
        self,
        *,
        fabric: Fabric,
        system: str,
        registry: Registry | None = None,
        status_interval: float = 1.0,
        status_timeout: float = 2.0,
        admin_timeout: float = 5.0,
        name: str = MANAGER,
        signer: Signer | None = None,
    ) -> None:
        keys.system_pattern(system)
        if status_interval <= 0 or status_timeout <= 0 or admin_timeout <= 0:
            raise ValueError("status_interval, status_timeout and admin_timeout must be > 0")
        self.fabric = fabric
        self.system = system
        self.name = name
        self.registry = registry or Registry(system)
        self.registry.rejected_event = keys.event(system, PLAN_REJECTED)
        self.registry.ignored.add(name)
        self.status_interval = status_interval
        self.status_timeout = status_timeout
        self.admin_timeout = admin_timeout
        self.signer = signer
        """Who its admin requests are signed as (None: unsigned)."""
        self._poke = anyio.Event()
        self._new_due = anyio.Event()
        self.polls = 0
        """Status queries made (tests wait on it)."""
        self.on_poll: Callable[[], None] | None = None

    # -- running ------------------------------------------------------------------------

    async def run(self, *, task_status: TaskStatus[None] = anyio.TASK_STATUS_IGNORED) -> None:
        """Follow the system until cancelled. Raises :class:`LifecycleError` when another
        manager of the system is alive."""
        me = keys.alive(self.system, self.name)
        if await self.fabric.alive(me, timeout=1.0):
            raise LifecycleError(
                f"an adaptation manager of system {self.system!r} is running already ({me} is "
                "alive): one per system - use its dashboard, or stop it first"
            )
        fab = self.fabric
        subs = [
            (fab.subscribe(keys.pattern(self.system, kind), _POLICY), handle)
            for kind, handle in (
                (keys.Kind.TRACE, self._on_trace),
                (keys.Kind.EVENT, self._on_event),
                (keys.Kind.TRUST, self._on_trust),
                (keys.Kind.LOG, self._on_log),
            )
        ]
        watch = fab.watch_liveliness(keys.pattern(self.system, keys.Kind.ALIVE, "*"))
        queryable = fab.serve(keys.admin(self.system, self.name, TRACE_VERB), self._answer_trace)
        token = fab.declare_token(me)
        try:
            async with anyio.create_task_group() as tg:
                for sub, handle in subs:
                    tg.start_soon(self._consume, sub, handle)
                tg.start_soon(self._watch, watch)
                tg.start_soon(self._poll)
                tg.start_soon(self._deadlines)
                log.info("manager of system %r: following its components and cycles", self.system)
                task_status.started()
        finally:
            token.undeclare()
            queryable.undeclare()
            watch.close()
            for sub, _ in subs:
                sub.close()

    async def _consume(self, sub: Any, handle: Callable[[str, TypedEnvelope[Any]], None]) -> None:
        async for sample in sub:
            env = self._open(sample)
            if env is None:
                continue
            try:
                handle(sample.key, env)
            except DECODE_ERRORS as exc:  # a string not UTF-8, nesting too deep: refused too
                self.registry.unreadable(
                    _kind(sample.key), sample.key, f"invalid {env.type} body: {exc}"
                )
            except keys.KeyError_ as exc:
                self.registry.unreadable(_kind(sample.key), sample.key, str(exc))
            self._wake_deadlines()

    def _open(self, sample: Sample) -> TypedEnvelope[Any] | None:
        try:
            payload = sample.payload
            if len(payload) > MAX_SAMPLE_BYTES:
                raise ValueError(f"{len(payload)} bytes, over {MAX_SAMPLE_BYTES}")
            return _envelope(payload)
        except DECODE_ERRORS as exc:
            self.registry.unreadable(_kind(sample.key), sample.key, f"not an envelope: {exc}")
            return None

    def _on_trace(self, key: str, env: TypedEnvelope[Any]) -> None:
        if env.type == StageTrace.TYPE:
            self.registry.trace(_stage_trace(env.body))

    def _on_event(self, key: str, env: TypedEnvelope[Any]) -> None:
        name = keys.parse(key).name
        reg = self.registry
        reg.event(name, key, env.uid, env.source, env.ts, env.cycle, env.cause)
        if env.type == PlanProposal.TYPE and name == NEW_PLAN:
            reg.proposal(env.cycle, _proposal(env.body))
        elif env.type == Verdict.TYPE and name != NEW_PLAN:
            reg.verdict(
                env.cycle, env.uid, env.source, _verdict(env.body), rejected=name == PLAN_REJECTED
            )

    def _on_trust(self, key: str, env: TypedEnvelope[Any]) -> None:
        if env.type == TrustOutput.TYPE:
            self.registry.trust_output(_trust_output(env.body))
        elif env.type == TrustVerdict.TYPE:
            self.registry.trust_verdict(_trust_verdict(env.body))

    def _on_log(self, key: str, env: TypedEnvelope[Any]) -> None:
        source = keys.parse(key).name
        if env.type == LogRecord.TYPE:
            self.registry.log_record(source, _log_record(env.body))
        elif env.type == Rejection.TYPE:
            self.registry.rejection(_rejection(env.body))
        else:
            self.registry.other_log(source, env.type[:80])

    async def _watch(self, watch: Any) -> None:
        while True:
            try:
                change = await watch.get()
            except LifecycleError:
                return  # the fabric closed
            try:
                name = keys.parse(change.key).name
            except keys.KeyError_ as exc:
                self.registry.unreadable("alive", change.key, str(exc))
                continue
            if name == self.name:
                continue
            self.registry.liveliness(name, change.alive)
            if change.alive:
                self._poke.set()  # ask it at once

    async def _poll(self) -> None:
        while True:
            await self.poll_status()
            with anyio.move_on_after(self.status_interval):
                await self._poke.wait()
            self._poke = anyio.Event()

    async def poll_status(self) -> None:
        """Ask every component of the system for its status (one query)."""
        selector = keys.pattern(self.system, keys.Kind.ADMIN, "*/status")
        signer = self.signer
        attachment = signer.attachment(selector, "status", b"") if signer is not None else b""
        try:
            replies = await self.fabric.query(
                selector, b"", timeout=self.status_timeout, attachment=attachment
            )
        except FabricError as exc:
            self.registry.unreadable("admin", selector, f"status query failed: {exc}")
        else:
            self.registry.unanswered(self._statuses(replies))
        self.polls += 1
        if self.on_poll is not None:
            self.on_poll()

    def _statuses(self, replies: Iterable[Reply]) -> set[str]:
        """Apply the status answers; the names that answered."""
        answered: set[str] = set()
        for r in replies:
            if not r.ok:
                self.registry.unreadable("admin", r.key, r.payload[:200].decode("utf-8", "replace"))
                continue
            try:
                reply = _reply(r.payload)
            except (msgspec.ValidationError, msgspec.DecodeError) as exc:
                self.registry.unreadable("admin", r.key, f"not an admin reply: {exc}")
                continue
            if not reply.ok:  # a component that refused to tell (who asks, say)
                self.registry.unreadable("admin", r.key, f"{reply.component}: {reply.message}")
                continue
            if reply.status is not None:
                self.registry.status(reply.status)
                answered.add(reply.status.name)
        return answered

    def _wake_deadlines(self) -> None:
        if not self._new_due.is_set():
            self._new_due.set()

    async def _deadlines(self) -> None:
        """Check each cycle at its deadline (sleeps until the next one; wakes when a new
        cycle gives one while none was pending)."""
        reg = self.registry
        while True:
            due = reg.next_due()
            if due is None:
                await self._new_due.wait()
                self._new_due = anyio.Event()
                continue
            delay = due - reg.monotonic()
            if delay > 0:
                await anyio.sleep(delay)
            reg.check_due()

    # -- commands -------------------------------------------------------------------------

    async def command(self, component: str, verb: str) -> CommandResult:
        """Call admin ``verb`` (pause, resume, restart) on ``component`` with
        :func:`rap_sdk.admin.call`; the status it answers updates the registry."""
        metrics = self.registry.metrics
        if verb not in COMMANDS:
            metrics.admin_calls.labels(verb="other", result="refused").inc()
            return CommandResult(
                ok=False,
                component=component,
                verb=verb[:40],
                message=f"verb {verb[:40]!r} is not one of {', '.join(COMMANDS)}",
            )
        try:
            keys.admin(self.system, component, verb)
        except keys.KeyError_ as exc:
            metrics.admin_calls.labels(verb=verb, result="refused").inc()
            return CommandResult(ok=False, component=component[:200], verb=verb, message=str(exc))
        try:
            replies = await admin.call(
                self.fabric,
                self.system,
                component,
                verb,
                timeout=self.admin_timeout,
                signer=self.signer,
            )
        except RapError as exc:  # AdminError, QueryError, FabricError
            metrics.admin_calls.labels(verb=verb, result="error").inc()
            log.warning("admin %s %s from the dashboard failed: %s", verb, component, exc)
            return CommandResult(
                ok=False, component=component, verb=verb, message=f"{verb} {component}: {exc}"
            )
        if not replies:
            metrics.admin_calls.labels(verb=verb, result="error").inc()
            return CommandResult(
                ok=False,
                component=component,
                verb=verb,
                message=f"{component} did not answer {verb} within {self.admin_timeout:g} s "
                "(is it running?)",
            )
        reply = replies[0]
        if reply.status is not None:
            self.registry.status(reply.status)
        metrics.admin_calls.labels(verb=verb, result="ok" if reply.ok else "refused").inc()
        log.info(
            "admin %s %s from the dashboard: %s",
            verb,
            component,
            reply.message or ("done" if reply.ok else "refused"),
        )
        return CommandResult(
            ok=reply.ok,
            component=component,
            verb=verb,
            message=reply.message or ("done" if reply.ok else "refused"),
            state=reply.status.state.value if reply.status is not None else "",
        )

    # -- rap trace ------------------------------------------------------------------------

    async def _answer_trace(self, req: QueryRequest) -> list[Reply]:
        reply = self.trace(req.payload)
        return [Reply(keys.admin(self.system, self.name, TRACE_VERB), _encode(reply))]

    def trace(self, payload: bytes) -> TraceReply:
        """Answer a ``rap trace`` request: a :class:`TraceRequest` as JSON, or the cycle's
        hex (a unique prefix is enough) as text."""
        if len(payload) > MAX_TRACE_REQUEST:
            return TraceReply(ok=False, message=f"request over {MAX_TRACE_REQUEST} bytes")
        text = payload.strip()
        try:
            req = (
                _trace_request(text)
                if text.startswith(b"{")
                else TraceRequest(cycle=text.decode("ascii"))
            )
        except (msgspec.ValidationError, msgspec.DecodeError, UnicodeDecodeError) as exc:
            return TraceReply(ok=False, message=f"bad trace request: {exc}")
        reg = self.registry
        held = f"the manager holds the last {len(reg.cycles)} cycle(s)"
        if req.last:
            cyc = reg.last_complete(executed=req.executed)
            if cyc is None:
                what = "in which a plan reached the execute stage " if req.executed else ""
                return TraceReply(
                    ok=False, message=f"no complete cycle {what}yet ({held}); try again later"
                )
            return TraceReply(ok=True, trace=reg.chain(cyc))
        text_ = req.cycle.lower()
        suffix = text_.startswith("..")
        digits = text_.removeprefix("..")
        if not digits or any(ch not in "0123456789abcdef" for ch in digits):
            return TraceReply(
                ok=False,
                message=f"cycle {req.cycle[:80]!r} is not hex - give (a prefix of) a cycle's "
                "hex uid, '..' and its end, or --last",
            )
        found = reg.find(digits, suffix=suffix)
        if not found:
            return TraceReply(
                ok=False,
                message=f"no cycle {text_} in the manager's history ({held}) - it is older, "
                "or not a cycle of this system",
            )
        if len(found) > 1 and found[0].hex != digits:
            return TraceReply(
                ok=False,
                message=f"cycle {text_} matches {len(found)} cycles - give more digits",
                matches=[c.hex for c in found[:8]],
            )
        return TraceReply(ok=True, trace=reg.chain(found[0]))


def _kind(key: str) -> str:
    parts = key.split("/")
    return parts[2] if len(parts) > 2 else "other"
