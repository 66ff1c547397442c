"""The checker on the RAP fabric (Zenoh, or the in-memory fabric in tests).

Inputs, by default (``FabricConfig.default_inputs``), are a system's trace records and
events. Each event is one tick (under the ``message`` policy); a ``rap.StageTrace``
record of a handler call is several, in this order: the handler's start (records of
phase ``call`` or ``start``), one tick per knowledge access it lists (as a
``rap.KnowledgeAccess`` record would be), its end (``call`` or ``end``). A tick that
sets none of the running spec's inputs is not a tick. The streams each sets:

=====================================  ====================  ==========================
message                                stream                value
=====================================  ====================  ==========================
``rap.StageTrace`` (start, end) on     ``stage``             the stage (Str); ``""`` for
``rap/<system>/trace/<node>``                                a node that declares none
                                       ``phase``             ``"start"`` or ``"end"``
                                       ``node``              the node id (Str)
                                       ``handler``           the handler's name (Str)
                                       ``cycle``             the cycle id, hex (Str)
                                       ``ok``                the handler did not fail
                                                             (Bool)
                                       ``acted``             an ``end`` record of a
                                                             handler that published on
                                                             a data topic (it acted on
                                                             the managed system); false
                                                             otherwise (Bool)
                                       ``<stage>_<phase>``   the cycle id, hex, e.g.
                                                             ``analyse_start`` (only
                                                             for a node with a stage)
a knowledge access listed in a        ``kb_op``             ``read``, ``write``,
``rap.StageTrace``, or a                                     ``delete``
``rap.KnowledgeAccess`` on
``rap/<system>/trace/<node>``
                                       ``kb_key``            the knowledge key (Str)
                                       ``kb_node``           the node id (Str)
                                       ``kb_cycle``          the cycle id, hex; ``""``
                                                             when not known
                                       ``kb_<op>``           the key, e.g. ``kb_write``
any event on                           ``event``             the event name (Str)
``rap/<system>/event/<name>``          ``ev_cycle``          the cycle id, hex (the
                                                             envelope's own uid for a
                                                             root)
                                       ``ev_<name>``         the cycle id, hex; ``-``
                                                             and ``/`` in the name
                                                             become ``_``
                                                             (``ev_new_plan``)
... whose body is a ``rap.Verdict``    ``verdict_approved``  Bool
                                       ``verdict_plan``      the plan uid, hex (Str)
=====================================  ====================  ==========================

Each family sets its own streams (trace records ``cycle``, knowledge records
``kb_cycle``, events ``ev_cycle``), so a held value never mixes families: a spec that
reads only one family's common streams (``stage``, ``phase``, ``cycle``, ...; not the
per-name ones like ``analyse_start``) ticks only on that family's messages, each tick
setting every one of them. A spec that reads several families tells which stream is
fresh at a tick with a tick counter (``docs/trust_checker.md``, "MAPLE-K specs and
veto").

Explicit inputs (``FabricConfig.inputs``): ``stream <- key expression``, the value being
the message body decoded without a type, as plain data (bytes as hex strings), or one
``field`` of it; its lists and maps may nest at most ``rap_schemas.limits.MAX_DEPTH``
levels, and map keys must be strings (or numbers, taken as their text). A sample
matched both by the defaults and by explicit inputs sets all of their streams in one
tick. With the default inputs the transport subscribes to ``rap/<system>/**`` once, so a
sender's records and events keep their order; explicit inputs outside the system get a
subscription each (no order is promised between different subscriptions). Every sample
is an envelope of at most ``rap_schemas.limits.MAX_SAMPLE_BYTES``, opened with
:class:`rap_sdk.Opener` (duplicates dropped).

Bad input never stops the transport: a sample that is too large, cannot be opened, whose
body is not what its envelope says (undecodable, nested too deeply, not UTF-8) or whose
value is not a stream value is rejected: counted by reason in ``stats.rejections`` (a
:class:`rap_sdk.rejections.Rejections`), logged rate-limited and reported as a
``rap.Rejection`` on ``rap/<system>/log/<node>`` (at most one record per key a second,
with how many since); the next sample is taken.

Outputs: each output that ticks is published as a ``rap.TrustOutput`` on
``rap/<system>/trust/<stream>``, sealed by :class:`rap_sdk.Sealer` (source: the node id),
so any node can subscribe to it typed. Verdicts (a session with ``explain=True``): each
``rap.TrustVerdict`` on ``rap/<system>/trust/<stream>/verdict`` (a trigger's stream is
``trigger.<n>``), sealed the same way; ``rap/<system>/trust/*/verdict`` subscribes to
them all, ``rap/<system>/trust/*`` to the outputs alone.

Hot swap: a queryable on ``rap/<system>/admin/<node>/swap`` (``node``, the session's,
defaults to ``trust_checker``). The query's payload is a sealed ``rap.TrustSpecUpdate``
of at most ``MAX_SAMPLE_BYTES``; the reply a sealed ``rap.TrustSpecStatus`` (``ok``, or
the spec's ``problems``; the old spec keeps running then). A malformed request is
rejected (counted as above) and gets an error reply saying why. A checker with
identities takes the request only with an operator's signature as the query's
attachment (:func:`trust_checker.io.auth.fabric_swap`); any other gets an error reply
``swap refused: <why>``, is counted, logged and audited. Every swap leaves an audit record
(``rap.audit``) with who asked and what came of it.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Final

import anyio
import msgspec
from anyio.abc import TaskStatus
from rap_schemas import (
    KnowledgeAccess,
    Rejection,
    StageTrace,
    TrustOutput,
    TrustSpecStatus,
    TrustSpecUpdate,
    TrustVerdict,
    Verdict,
    keys,
)
from rap_schemas.limits import (
    DECODE_ERRORS,
    MAX_DEPTH,
    MAX_SAMPLE_BYTES,
    DecodeRejected,
    SafeDecoder,
    decode_failure,
)
from rap_sdk import Fabric, InboxPolicy, Opener, Overflow, QueryRequest, RapError, Reply, Sealer
from rap_sdk.admin import Gate, audit
from rap_sdk.envelope import TypedEnvelope
from rap_sdk.errors import QueryError, RejectedSample
from rap_sdk.fabric import Sample, Subscription
from rap_sdk.identity import AuthError, Caller
from rap_sdk.keyexpr import intersects, validate
from rap_sdk.rejections import Rejections, Throttle

from ..config import FabricConfig
from ..values import BOTTOM, ValueError_, from_plain, to_plain
from .auth import SWAP_VERB, outcome, spec_summary
from .ports import OutputLike
from .session import Session
from .ticks import Arrival

__all__ = [
    "MAX_BATCH",
    "SWAP_TIMEOUT",
    "FabricTransport",
    "FabricTransportStats",
    "default_ticks",
    "event_stream_name",
]

log = logging.getLogger(__name__)

_trace_body = msgspec.msgpack.Decoder(StageTrace).decode
_access_body = msgspec.msgpack.Decoder(KnowledgeAccess).decode
_verdict_body = msgspec.msgpack.Decoder(Verdict).decode
"""A ``rap.Verdict`` of any plan type: its plan stays plain data, never looked at."""
_any_body: Callable[[bytes], Any] = SafeDecoder(Any, max_depth=MAX_DEPTH, what="body").decode
_open_update: Callable[[bytes], TypedEnvelope[TrustSpecUpdate]] = SafeDecoder(
    TypedEnvelope[TrustSpecUpdate], max_bytes=MAX_SAMPLE_BYTES, what="swap request"
).decode
SWAP_TIMEOUT: Final = 4.0
"""Seconds a swap query waits for the session (under Zenoh's 5 s handler deadline)."""
MAX_BATCH: Final = 256
"""At most this many waiting samples are taken in one go."""


def event_stream_name(name: str) -> str:
    """``new-plan`` -> ``ev_new_plan`` (``-`` and ``/`` become ``_``)."""
    return "ev_" + name.replace("-", "_").replace("/", "_")


def _plain(x: Any) -> Any:
    """Untyped msgpack data (depth-checked) to plain JSON-like data: bytes become hex
    strings, number keys their text; :class:`ValueError_` for any other map key."""
    if isinstance(x, bytes | bytearray | memoryview):
        return bytes(x).hex()
    if isinstance(x, list):
        return [_plain(e) for e in x]
    if isinstance(x, dict):
        out: dict[str, Any] = {}
        for k, v in x.items():
            if type(k) is not str:
                if type(k) not in (int, float, bool):
                    raise ValueError_(
                        f"a map key is a {type(k).__name__} - use string (or number) keys"
                    )
                k = str(k)
            out[k] = _plain(v)
        return out
    return x


def _is_data(key: str) -> bool:
    """``key`` is a data topic (``rap/<system>/data/...``)."""
    parts = key.split("/", 3)
    return len(parts) == 4 and parts[0] == keys.ROOT and parts[2] == keys.Kind.DATA.value


def default_ticks(
    kind: keys.Kind, name: str, env: TypedEnvelope[msgspec.Raw]
) -> list[dict[str, object]]:
    """The ticks a trace record or an event makes, each with the streams it sets (the
    table in the module docstring): one for an event or a ``KnowledgeAccess`` record;
    for a ``StageTrace`` the handler's start (``call``, ``start``), then each knowledge
    access it lists, then its end (``call``, ``end``). Raises one of
    ``rap_schemas.limits.DECODE_ERRORS`` for a body that is not what its envelope says
    (wrong fields, undecodable, nested too deeply, not UTF-8)."""
    if kind is keys.Kind.TRACE:
        if env.type == StageTrace.TYPE:
            return _stage_ticks(_trace_body(env.body))
        if env.type == KnowledgeAccess.TYPE:
            acc = _access_body(env.body)
            cycle = "" if acc.cycle is None else acc.cycle.hex()
            return [_access_tick(acc.op, acc.key, acc.node, cycle)]
        return []
    if kind is keys.Kind.EVENT:
        cycle = (env.cycle if env.cycle is not None else env.uid).hex()
        out: dict[str, object] = {"event": name, "ev_cycle": cycle}
        out[event_stream_name(name)] = cycle
        if env.type == Verdict.TYPE:
            verdict = _verdict_body(env.body)
            out.update(verdict_approved=verdict.approved, verdict_plan=verdict.plan_uid.hex())
        return [out]
    return []


def _stage_ticks(rec: StageTrace) -> list[dict[str, object]]:
    cycle = rec.cycle.hex()
    stage = "" if rec.stage is None else str(rec.stage)
    ticks: list[dict[str, object]] = []

    def tick(phase: str, ok: bool, acted: bool) -> None:
        out: dict[str, object] = {
            "stage": stage,
            "phase": phase,
            "node": rec.node,
            "handler": rec.handler,
            "cycle": cycle,
            "ok": ok,
            "acted": acted,
        }
        if rec.stage is not None:
            out[f"{rec.stage}_{phase}"] = cycle
        ticks.append(out)

    if rec.phase != "end":
        tick("start", True, False)
    ticks.extend(_access_tick(a.op, a.key, rec.node, cycle) for a in rec.access)
    if rec.phase != "start":
        tick("end", rec.ok, any(_is_data(k) for k in rec.sent))
    return ticks


def _access_tick(op: str, key: str, node: str, cycle: str) -> dict[str, object]:
    return {"kb_op": op, "kb_key": key, "kb_node": node, "kb_cycle": cycle, f"kb_{op}": key}


@dataclass(frozen=True, slots=True)
class _Route:
    """What a concrete key feeds: a default family (trace or event) and explicit inputs."""

    kind: keys.Kind | None
    name: str
    explicit: tuple[tuple[str, str | None], ...]


@dataclass(slots=True)
class FabricTransportStats:
    rejections: Rejections
    """Samples and swap requests refused, counted by reason (``rejections.by_reason``,
    ``rejections.total``)."""
    samples: int = 0
    duplicates: int = 0
    published: int = 0
    lost: int = 0
    """Input samples dropped because the checker's inbox was full (it fell behind)."""
    dropped: int = 0
    """Outputs (or verdicts) that could not be published (fabric closing, inbox full past
    the deadline)."""
    verdicts: int = 0
    """Verdicts published."""
    swap_queries: int = 0
    records: int = 0
    """``rap.Rejection`` records published on ``rap/<system>/log/<node>``."""


class FabricTransport:
    """Feeds ``session`` from ``fabric`` and publishes its outputs there (it adds itself
    to the session's sinks). Run :meth:`run` in a task group, next to ``session.run``
    (:func:`trust_checker.service.open_service` does both). The node id (envelope
    source, admin key) is the session's."""

    def __init__(
        self, session: Session, config: FabricConfig, *, fabric: Fabric, gate: Gate | None = None
    ) -> None:
        self.session = session
        self.fabric = fabric
        self.config = config
        self.gate = gate if gate is not None else Gate()
        """Who may swap the spec (default: ``RAP_CERTS``'s CA when it is set)."""
        self.node = session.node
        self.stats = FabricTransportStats(
            Rejections(session.node, log, clock=session.clock.time_ns)
        )
        self.system = config.system
        keys.system_pattern(config.system)  # validates the system name
        self.swap_key = keys.admin(config.system, self.node, "swap")
        self.log_key = keys.log(config.system, self.node)
        for stream, inp in config.inputs.items():
            try:
                validate(inp.key)
            except ValueError as exc:
                raise ValueError(
                    f"fabric input {stream!r}: {exc} - write a key expression such as "
                    f"'rap/{config.system}/data/<topic>'"
                ) from None
        self._sealer = Sealer(self.node, session.clock)
        self._opener = Opener()
        self._throttle = Throttle()
        self._out_keys: dict[str, str] = {}
        self._verdict_keys: dict[str, str] = {}
        self._routes: dict[str, _Route] = {}
        self._dropped_seen: dict[str, int] = {}
        self._lost_logged = (-math.inf, 0)
        """When the last loss was logged, and stats.lost then."""
        self._records: list[Rejection] = []
        """Rejection records due, published after the batch being taken."""
        session.sinks.append(self)

    @property
    def key_exprs(self) -> list[str]:
        """What the transport subscribes to: with the default inputs, the whole system in
        one subscription (so that one sender's trace records and events keep their
        order), plus each explicit input's key outside it."""
        exprs: list[str] = []
        inside = f"{keys.ROOT}/{self.system}/"
        if self.config.default_inputs:
            exprs.append(keys.system_pattern(self.system))
        for inp in self.config.inputs.values():
            covered = self.config.default_inputs and inp.key.startswith(inside)
            if not covered and inp.key not in exprs:
                exprs.append(inp.key)
        return exprs

    def _route(self, key: str) -> _Route:
        route = self._routes.get(key)
        if route is None:
            kind: keys.Kind | None = None
            name = ""
            if self.config.default_inputs:
                try:
                    parsed = keys.parse(key)
                except keys.KeyError_:
                    parsed = None
                if (
                    parsed is not None
                    and parsed.system == self.system
                    and parsed.kind in (keys.Kind.TRACE, keys.Kind.EVENT)
                ):
                    kind, name = parsed.kind, parsed.name
            explicit = tuple(
                (stream, inp.field)
                for stream, inp in self.config.inputs.items()
                if intersects(inp.key, key)
            )
            if len(self._routes) >= 4096:
                self._routes.clear()
            route = self._routes[key] = _Route(kind, name, explicit)
        return route

    async def run(self, *, task_status: TaskStatus[None] = anyio.TASK_STATUS_IGNORED) -> None:
        """Subscribe and serve the swap queryable, then take samples until cancelled."""
        subs: list[Subscription] = []
        queryable = self.fabric.serve(self.swap_key, self._on_swap)
        try:
            inbox = InboxPolicy(
                capacity=self.config.inbox,
                overflow=Overflow.FIFO,
                block=False,
                max_bytes=self.config.inbox_bytes,
            )
            subs = [self.fabric.subscribe(k, inbox) for k in self.key_exprs]
            async with anyio.create_task_group() as tg:
                for sub in subs:
                    tg.start_soon(self._pump, sub)
                log.info(
                    "fabric: reading %s; hot swap on %s",
                    ", ".join(self.key_exprs) or "nothing",
                    self.swap_key,
                )
                task_status.started()
        finally:
            for sub in subs:
                sub.close()
            queryable.undeclare()
            with anyio.move_on_after(1.0, shield=True):
                self._records += self.stats.rejections.flush()
                await self._publish_records()

    async def _pump(self, sub: Subscription) -> None:
        """Samples in arrival order. When the checker falls behind, what has piled up is
        taken in one go (up to :data:`MAX_BATCH`) and handed to the session as one batch:
        one hand-off between tasks per batch instead of per sample. Samples the inbox had
        to drop (it was full) are counted and logged: ticks after a gap judge a trace
        with records missing."""
        async for first in sub:
            arrivals: list[Arrival] = []
            sample: Sample | None = first
            n = 0
            while sample is not None:
                self._arrivals(sample, arrivals)
                n += 1
                sample = sub.get_nowait() if n < MAX_BATCH else None
            self._gaps(sub)
            if arrivals:
                await self.session.submit_many(arrivals)
            if self._records:
                await self._publish_records()

    def _gaps(self, sub: Subscription) -> None:
        """Count what ``sub``'s inbox dropped since the last look; log it as an error at
        most once a second (the count since the previous line)."""
        dropped = sub.stats.dropped
        seen = self._dropped_seen.get(sub.key_expr, 0)
        if dropped <= seen:
            return
        self._dropped_seen[sub.key_expr] = dropped
        self.stats.lost += dropped - seen
        now = time.monotonic()
        if now - self._lost_logged[0] < 1.0:
            return
        since = self.stats.lost - self._lost_logged[1]
        self._lost_logged = (now, self.stats.lost)
        log.error(
            "fabric: %d input samples lost (%d in all; last on %s): the checker fell more "
            "than %d samples behind its inputs, so verdicts from here on judge a trace "
            "with records missing; give it a faster machine or fewer inputs",
            since,
            self.stats.lost,
            sub.key_expr,
            self.config.inbox,
        )

    # -- rejections ------------------------------------------------------------------

    def _reject(self, key: str, reason: str, *, source: str = "", type_: str = "") -> None:
        """Count a rejection; a record due is published after the current batch."""
        rec = self.stats.rejections.reject(key, reason, source=source, type=type_)
        if rec is not None:
            self._records.append(rec)

    async def _publish_records(self) -> None:
        records, self._records = self._records, []
        for rec in records:
            payload, _ = self._sealer.seal_message(self.log_key, rec)
            try:
                await self.fabric.publish(
                    self.log_key, payload, timeout=self.config.publish_timeout
                )
            except RapError as exc:
                self.stats.dropped += 1
                if self._throttle.hit(self.log_key):
                    log.warning("fabric: rejection record not published: %s", exc)
                continue
            self.stats.records += 1

    # -- input -----------------------------------------------------------------------

    def _arrivals(self, sample: Sample, into: list[Arrival]) -> None:
        """The ticks of one sample, added to ``into`` (none for a sample refused or
        of a key no input reads)."""
        key = sample.key
        route = self._route(key)
        if route.kind is None and not route.explicit:
            return  # a key no input reads (data, knowledge, logs, our own outputs)
        self.stats.samples += 1
        size = len(sample.payload)
        if size > MAX_SAMPLE_BYTES:
            self._reject(
                key,
                f"sample of {size} bytes is over the limit of {MAX_SAMPLE_BYTES} - send "
                "smaller messages",
            )
            return
        try:
            env = self._opener.open(key, sample.payload)
        except RejectedSample as exc:
            self._reject(key, exc.reason, source=exc.source, type_=exc.type)
            return
        if env is None:
            self.stats.duplicates += 1
            return
        try:
            ticks = self._ticks(route, env)
        except DecodeRejected as exc:
            self._reject(key, f"{env.type} {exc.reason}", source=env.source, type_=env.type)
            return
        except DECODE_ERRORS as exc:
            reason = f"invalid {env.type} body: {decode_failure(exc)}"
            self._reject(key, reason, source=env.source, type_=env.type)
            return
        except ValueError_ as exc:
            self._reject(key, f"{env.type}: {exc}", source=env.source, type_=env.type)
            return
        if ticks:
            now = self.session.clock.time_ns()
            into.extend(Arrival(values, now, key) for values in ticks)

    def _ticks(self, route: _Route, env: TypedEnvelope[msgspec.Raw]) -> list[dict[str, object]]:
        ticks = default_ticks(route.kind, route.name, env) if route.kind is not None else []
        if route.explicit:
            values = self._explicit(route, env)
            if ticks:
                ticks[0].update(values)  # one tick sets the explicit inputs' streams too
            elif values:
                ticks.append(values)
        return ticks

    def _explicit(self, route: _Route, env: TypedEnvelope[msgspec.Raw]) -> dict[str, object]:
        values: dict[str, object] = {}
        body = _plain(_any_body(env.body))  # depth-checked before _plain recurses
        for stream, fld in route.explicit:
            if fld is None:
                values[stream] = from_plain(body)
            elif isinstance(body, dict) and fld in body:
                values[stream] = from_plain(body[fld])
            else:
                have = sorted(body) if isinstance(body, dict) else "none"
                raise ValueError_(
                    f"stream {stream!r} reads field {fld!r}, which the body does not "
                    f"have (fields: {have}) - fix the input's field or the sender"
                )
        return values

    # -- hot swap --------------------------------------------------------------------

    async def _on_swap(self, request: QueryRequest) -> list[Reply]:
        self.stats.swap_queries += 1
        checked = self.gate.checks
        try:
            caller = await self.gate.check(
                request.key,
                SWAP_VERB,
                request.payload,
                request.attachment,
                scope=f"{self.node}:fabric",
                what=f"swap the spec of {self.node}",
            )
        except AuthError as exc:
            reason = f"swap refused: {exc.reason}"
            self._reject(self.swap_key, f"swap refused: {exc.kind} ({exc.reason})")
            await self._publish_records()
            self._audit("refused", exc.reason, request, checked, exc.caller, kind=exc.kind)
            raise QueryError(reason) from None
        try:
            env = _open_update(request.payload)
        except DecodeRejected as exc:
            self._reject(self.swap_key, exc.reason)
            await self._publish_records()
            self._audit("error", exc.reason, request, checked, caller)
            raise QueryError(
                f"swap request refused: {exc.reason} - send a sealed {TrustSpecUpdate.TYPE}"
            ) from None
        if env.type != TrustSpecUpdate.TYPE:
            reason = f"swap request: expected type {TrustSpecUpdate.TYPE}, got {env.type!r}"
            self._reject(self.swap_key, reason, source=env.source, type_=env.type)
            await self._publish_records()
            self._audit("error", reason, request, checked, caller)
            raise QueryError(f"{reason} - send a sealed {TrustSpecUpdate.TYPE}")
        update: TrustSpecUpdate = env.body
        who = str(caller) if caller is not None else repr(env.source)
        what = spec_summary(update.spec, update.path)
        try:
            status = await self.session.request_swap(
                update.spec,
                path=update.path,
                origin=f"{self.swap_key} from {who}",
                timeout=SWAP_TIMEOUT,
            )
        except TimeoutError:
            reason = f"the checker did not take the new spec within {SWAP_TIMEOUT:g} s"
            self._audit("error", reason, request, checked, caller, what)
            raise QueryError(f"{reason} (it is busy) - ask again") from None
        result, reason = outcome(status)
        self._audit(result, reason, request, checked, caller, what)
        payload, _ = self._sealer.seal_message(self.swap_key, status, cause=env.uid)
        return [Reply(self.swap_key, payload)]

    def _audit(
        self,
        result: str,
        reason: str,
        request: QueryRequest,
        checked: bool,
        caller: Caller | None,
        what: str = "",
        kind: str = "",
    ) -> None:
        if not what:
            try:
                update: TrustSpecUpdate = _open_update(request.payload).body
                what = spec_summary(update.spec, update.path)
            except DecodeRejected:
                what = f"{len(request.payload)} bytes"
        audit(
            verb=SWAP_VERB,
            component=self.node,
            result=result,
            caller=caller,
            checked=checked,
            key=request.key,
            request=what,
            reason=reason,
            kind=kind,
            throttle=self.gate.refusals,
        )

    # -- the sink --------------------------------------------------------------------

    async def _publish(self, key: str, payload: bytes, what: str) -> bool:
        try:
            await self.fabric.publish(key, payload, timeout=self.config.publish_timeout)
        except RapError as exc:
            self.stats.dropped += 1
            n = self._throttle.hit(key)
            if n:
                log.warning("fabric: %d %s(s) on %s not published: %s", n, what, key, exc)
            return False
        return True

    async def outputs(self, outs: Sequence[OutputLike]) -> None:
        for out in outs:
            key = self._out_keys.get(out.stream)
            if key is None:
                key = self._out_keys[out.stream] = keys.trust(self.system, out.stream)
            deferred = out.value is BOTTOM
            msg = TrustOutput(
                stream=out.stream,
                tick=out.tick,
                ts=out.ts_ns if out.ts_ns is not None else self.session.clock.time_ns(),
                value=None if deferred else to_plain(out.value),
                deferred=deferred,
            )
            payload, _ = self._sealer.seal_message(key, msg)
            if await self._publish(key, payload, "output"):
                self.stats.published += 1

    async def verdicts(self, verdicts: Sequence[TrustVerdict]) -> None:
        for verdict in verdicts:
            key = self._verdict_keys.get(verdict.stream)
            if key is None:
                if len(self._verdict_keys) >= 4096:
                    self._verdict_keys.clear()
                key = keys.trust(self.system, f"{verdict.stream}/verdict")
                self._verdict_keys[verdict.stream] = key
            payload, _ = self._sealer.seal_message(key, verdict)
            if await self._publish(key, payload, "verdict"):
                self.stats.verdicts += 1

    async def status(self, status: TrustSpecStatus) -> None:
        """Swap outcomes reach the querier in its reply (and the log)."""
