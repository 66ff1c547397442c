"""Declaring MAPLE-K nodes: a name, a stage, typed handlers, config and state hooks.

    analyse = Node("analysis", stage="analyse")

    @analyse.on_event("new-data")
    async def detect(ctx: Context) -> None: ...

    @analyse.on_data("scan")
    async def on_scan(ctx: Context, scan: LaserScan) -> None: ...

    @analyse.on_trust("stage_order_ok")          # a trust checker's output stream
    async def on_verdict(ctx: Context, out: TrustOutput) -> None: ...

    @analyse.every(0.1)                          # every 100 ms, on the event loop's clock
    async def poll(ctx: Context) -> None: ...

A handler takes the :class:`~rap_sdk.runtime.Context` and, optionally, the message; the
message's annotation picks the decoder (built once, at declaration). Handlers are plain
async functions that tests may call directly. A Node is only a declaration; it runs on a
fabric through :func:`rap_sdk.run_nodes` or :func:`rap_sdk.run`.
"""

from __future__ import annotations

import inspect
import math
import types
import typing
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any, Literal, TypeVar

import msgspec
from rap_schemas import (
    NEW_PLAN,
    VERDICT,
    Empty,
    Message,
    PlanProposal,
    Stage,
    TrustOutput,
    Verdict,
    keys,
)
from rap_schemas.limits import MAX_SAMPLE_BYTES

from .envelope import TypedEnvelope, typed_decoder
from .errors import ConfigError, HandlerError
from .inbox import InboxPolicy, Overflow

__all__ = [
    "DATA_POLICY",
    "EVENT_POLICY",
    "TRUST_POLICY",
    "Node",
    "Periodic",
    "Route",
    "acceptor",
    "message_class",
]

F = TypeVar("F", bound=Callable[..., Awaitable[None]])

DATA_POLICY = InboxPolicy(capacity=8, overflow=Overflow.LATEST)
"""Default for data topics: keep the newest samples."""
EVENT_POLICY = InboxPolicy(capacity=256, overflow=Overflow.FIFO, block=True, max_bytes=64 << 20)
"""Default for events: in order, local senders wait for room; at most 64 MiB queued."""
TRUST_POLICY = InboxPolicy(capacity=64, overflow=Overflow.LATEST)
"""Default for trust-checker outputs: the newest verdicts matter (a checker never waits
for a slow node)."""

RouteKind = Literal["data", "event", "trust"]
_BUILDERS: dict[str, Callable[[str, str], str]] = {
    "data": keys.data,
    "event": keys.event,
    "trust": keys.trust,
}


@dataclass(frozen=True, slots=True)
class Route:
    kind: RouteKind
    name: str
    fn: Callable[..., Awaitable[None]]
    msg_type: type[Message]
    """The declared message type: every sample on the route is checked against it and
    its body decoded with it, whether or not the handler takes the message."""
    takes_message: bool
    """Whether the handler is ``fn(ctx, message)`` (else ``fn(ctx)``)."""
    decode: Callable[[bytes], TypedEnvelope[Any]]
    """Envelope and body in one pass, typed."""
    policy: InboxPolicy
    check: Callable[[Any], str | None] | None = None
    """A further check of a decoded body (None: accept); a reason rejects the sample."""
    max_bytes: int = MAX_SAMPLE_BYTES
    """Samples larger than this are rejected before they are decoded."""
    accepts: Callable[[Any], bool] | None = None
    """Whether a message object sent in this process is of the route's type, so that it
    may be handed over as it is, with no encoding nor decoding (None: never; the sample
    is then decoded from its bytes)."""

    handler_name: str = field(init=False)
    """The handler's qualified name (in trace records and logs)."""
    traced: bool = field(init=False)
    """Calls are traced as stage records; not for trust outputs (a handler of a
    checker's verdicts runs outside any MAPLE-K cycle, and its records would feed the
    checker its own consequences)."""

    def __post_init__(self) -> None:
        name = getattr(self.fn, "__qualname__", None)
        object.__setattr__(self, "handler_name", name if name is not None else repr(self.fn))
        object.__setattr__(self, "traced", self.kind != "trust")

    def key(self, system: str) -> str:
        """The key this route handles in ``system``."""
        return _BUILDERS[self.kind](system, self.name)


@dataclass(frozen=True, slots=True)
class Periodic:
    """A handler that the runtime calls every ``period`` seconds (:meth:`Node.every`)."""

    name: str
    """Its name within the node (default: the function's name)."""
    period: float
    """Seconds between two calls (> 0, finite)."""
    fn: Callable[..., Awaitable[None]]
    """``async def fn(ctx)``."""

    handler_name: str = field(init=False)
    """The handler's qualified name (in trace records and logs)."""
    traced: bool = field(default=True, init=False)
    """Calls are traced as stage records, each the root of a cycle of its own."""
    takes_message: bool = field(default=False, init=False)
    """Always False: a periodic handler is ``fn(ctx)``."""

    def __post_init__(self) -> None:
        name = getattr(self.fn, "__qualname__", None)
        object.__setattr__(self, "handler_name", name if name is not None else repr(self.fn))

    def trigger(self, node: str) -> str:
        """What its calls name as their trigger key (``ctx.key``, ``trigger_key`` of
        their trace records): ``every:<node>/<name>``, not a key of the fabric (nothing
        arrives on it)."""
        return f"every:{node}/{self.name}"


def _signature(fn: Callable[..., Any], where: str) -> tuple[bool, Any]:
    """(takes a message, its annotation or None)."""
    if not inspect.iscoroutinefunction(fn):
        raise HandlerError(f"{where}: handler {fn!r} must be an 'async def' function")
    params = list(inspect.signature(fn).parameters.values())
    if len(params) not in (1, 2) or any(
        p.kind not in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD) for p in params
    ):
        raise HandlerError(
            f"{where}: handler {fn.__qualname__} must take (ctx) or (ctx, message), "
            f"got ({', '.join(p.name for p in params)})"
        )
    if len(params) == 1:
        return False, None
    try:
        hints = typing.get_type_hints(fn)
    except (NameError, TypeError) as exc:
        raise HandlerError(
            f"{where}: cannot resolve the annotations of {fn.__qualname__} ({exc}); define "
            "message types at module level"
        ) from None
    return True, hints.get(params[1].name)


def message_class(ann: Any) -> type[Message] | None:
    """The Message class of an annotation (``LaserScan``, or ``PlanProposal[SpinPlan]``
    for a generic message), or None when it is not one."""
    cls = typing.get_origin(ann) or ann
    if isinstance(cls, type) and issubclass(cls, Message) and cls.TYPE:
        return cls
    return None


def acceptor(tp: Any) -> Callable[[Any], bool] | None:
    """A check that an object is exactly of type ``tp`` (a frozen Struct, or a
    parametrized generic one such as ``PlanProposal[SpinPlan]``, its type parameters
    checked in the fields that hold them), or None when ``tp`` cannot be checked so
    cheaply: local objects are then not handed over as they are. A mutable Struct is
    never handed over (a receiver could change the sender's object)."""
    if tp is None or tp is type(None):
        return lambda v: v is None
    origin = typing.get_origin(tp)
    if origin is typing.Union or origin is types.UnionType:
        alts = [acceptor(a) for a in typing.get_args(tp)]
        if any(a is None for a in alts):
            return None
        checks = tuple(a for a in alts if a is not None)
        return lambda v: any(c(v) for c in checks)
    if origin is None:
        if isinstance(tp, type) and issubclass(tp, msgspec.Struct):
            if not tp.__struct_config__.frozen:
                return None
            return lambda v: type(v) is tp
        return None
    if not (isinstance(origin, type) and issubclass(origin, msgspec.Struct)):
        return None
    if not origin.__struct_config__.frozen:
        return None
    bound = dict(zip(getattr(origin, "__parameters__", ()), typing.get_args(tp), strict=False))
    fields: list[tuple[str, Callable[[Any], bool]]] = []
    for name, ann in typing.get_type_hints(origin).items():
        if name not in origin.__struct_fields__ or not _has_params(ann):
            continue
        check = acceptor(_bind(ann, bound))
        if check is None:
            return None
        fields.append((name, check))

    def accepts(v: Any) -> bool:
        return type(v) is origin and all(c(getattr(v, n)) for n, c in fields)

    return accepts


def _has_params(ann: Any) -> bool:
    return isinstance(ann, TypeVar) or any(_has_params(a) for a in typing.get_args(ann))


def _bind(ann: Any, bound: dict[Any, Any]) -> Any:
    """``ann`` with its type variables replaced by what ``bound`` maps them to."""
    if isinstance(ann, TypeVar):
        return bound.get(ann, Any)
    args = typing.get_args(ann)
    if not args:
        return ann
    new = tuple(_bind(a, bound) for a in args)
    origin = typing.get_origin(ann)
    if origin is typing.Union or origin is types.UnionType:
        return typing.Union[new]  # noqa: UP007 (built from a tuple)
    return ann.__origin__[new] if len(new) > 1 else ann.__origin__[new[0]]


class Node:
    """A MAPLE-K component: a name, a stage, handlers, an optional config Struct."""

    def __init__(
        self,
        name: str,
        *,
        stage: Stage | str | None = None,
        config: msgspec.Struct | None = None,
    ) -> None:
        keys.trace("x", name)  # validates the name as one key chunk
        self.name = name
        try:
            self.stage: Stage | None = Stage(stage) if stage is not None else None
        except ValueError:
            raise ConfigError(
                f"node {name!r}: unknown stage {stage!r}; use one of "
                f"{', '.join(s.value for s in Stage)}"
            ) from None
        self.config = config
        self.implementation = ""
        """``module:attr`` it was loaded from (set by the loader; in status replies)."""
        self.routes: list[Route] = []
        self.periodic: list[Periodic] = []
        """Its periodic handlers (:meth:`every`), in declaration order."""
        self._snapshot: Callable[[], Any] | None = None
        self._restore: tuple[Callable[[Any], Any], type[Any]] | None = None

    def __repr__(self) -> str:
        stage = self.stage.value if self.stage else "-"
        every = f", periodic={len(self.periodic)}" if self.periodic else ""
        return f"Node({self.name!r}, stage={stage}, routes={len(self.routes)}{every})"

    def _route(
        self,
        kind: RouteKind,
        name: str,
        policy: InboxPolicy,
        declared: Any = None,
        *,
        check: Callable[[Any], str | None] | None = None,
        gated: bool = False,
        max_bytes: int | None = None,
        accepts: Callable[[Any], bool] | None = None,
    ) -> Callable[[F], F]:
        """Register a handler. ``declared``: the message type given by the decorator (may
        be a parametrized generic such as ``PlanProposal[SpinPlan]``); the handler's
        annotation may give it instead; without either a handler that takes no message
        gets ``rap.Empty/1`` events (``rap.TrustOutput/1`` on trust routes). ``accepts``:
        which local objects the handler takes as they are (default: exactly ``declared``,
        see :func:`acceptor`)."""
        _BUILDERS[kind]("x", name)  # validates the topic / event name / trust stream

        def register(fn: F) -> F:
            where = f"node {self.name!r}, {kind} {name!r}"
            takes, ann = _signature(fn, where)
            if takes and message_class(ann) is None:
                raise HandlerError(
                    f"{where}: the message parameter of {fn.__qualname__} must be annotated "
                    f"with a rap_schemas.Message subclass, got {ann!r}"
                )
            wire = declared if declared is not None else ann
            if wire is None:
                wire = TrustOutput if kind == "trust" else Empty
            cls = message_class(wire)
            if cls is None:
                raise HandlerError(
                    f"{where}: type={wire!r} is not a rap_schemas.Message subclass with a TYPE"
                )
            if takes and declared is not None and message_class(ann) is not cls:
                raise HandlerError(
                    f"{where}: {fn.__qualname__} takes a {ann!r} but the route is declared "
                    f"with type={cls.__name__}; make them agree (or drop type=)"
                )
            if not gated:
                self._refuse_ungated_plans(kind, name, cls, fn, where)
            twin = next((r for r in self.routes if (r.kind, r.name) == (kind, name)), None)
            if twin is not None:
                raise HandlerError(
                    f"{where}: {fn.__qualname__} would be a second handler of that key, next "
                    f"to {twin.handler_name}; a node handles a key once: do both in one "
                    "handler, or use another node (two gates on one node: give each its "
                    "own verdict event)"
                )
            self.routes.append(
                Route(
                    kind,
                    name,
                    fn,
                    cls,
                    takes,
                    typed_decoder(wire),
                    policy,
                    check,
                    MAX_SAMPLE_BYTES if max_bytes is None else max_bytes,
                    accepts if accepts is not None else acceptor(wire),
                )
            )
            return fn

        return register

    def _refuse_ungated_plans(
        self, kind: str, name: str, cls: type[Message], fn: Callable[..., Any], where: str
    ) -> None:
        """An execute stage acts only on approved plans: it may not take proposals or
        verdicts except through the Legitimate gate."""
        if self.stage is not Stage.EXECUTE:
            return
        if cls in (PlanProposal, Verdict) or (kind == "event" and name in (NEW_PLAN, VERDICT)):
            raise HandlerError(
                f"{where}: {fn.__qualname__} would take plans directly, but node "
                f"{self.name!r} is an execute stage: it may act only on plans that the "
                "Legitimate stage approved; declare the handler with "
                "'@gate.on_approved(node)' (gate = rap_sdk.gate.ApprovalGate(...))"
            )

    def on_data(
        self,
        topic: str,
        *,
        type: Any = None,
        policy: InboxPolicy | None = None,
        max_bytes: int | None = None,
    ) -> Callable[[F], F]:
        """Handle samples on ``rap/<system>/data/<topic>``. ``type``: the message type
        of the topic when the handler does not take the message. ``max_bytes``: larger
        samples are rejected (default ``rap_schemas.limits.MAX_SAMPLE_BYTES``, 4 MiB)."""
        return self._route("data", topic, policy or DATA_POLICY, type, max_bytes=max_bytes)

    def on_event(
        self,
        name: str,
        *,
        type: Any = None,
        policy: InboxPolicy | None = None,
        max_bytes: int | None = None,
    ) -> Callable[[F], F]:
        """Handle events on ``rap/<system>/event/<name>``. ``type``: the event's message
        type when the handler does not take the message (default ``rap.Empty/1``);
        ``max_bytes`` as for :meth:`on_data`."""
        return self._route("event", name, policy or EVENT_POLICY, type, max_bytes=max_bytes)

    def on_trust(self, stream: str, *, policy: InboxPolicy | None = None) -> Callable[[F], F]:
        """Handle a trust checker's output ``stream`` (``rap/<system>/trust/<stream>``,
        messages :class:`rap_schemas.TrustOutput`). These calls are not traced."""
        return self._route("trust", stream, policy or TRUST_POLICY)

    def every(self, period_s: float, *, name: str | None = None) -> Callable[[F], F]:
        """Call ``async def fn(ctx)`` every ``period_s`` seconds while the node runs,
        the first time one period after it starts. Calls take the node's turn like
        any handler (never two at once, nor next to another handler of the node); a
        call that overruns skips the ticks it missed (counted in
        ``NodeStats.ticks_skipped``, logged at most once a second). A call that raises
        is logged and counted (``NodeStats.failed``), and the timer goes on. The timer
        stops with the node. Periods are on the event loop's monotonic clock (anyio's),
        not on a simulator's time. ``name``: the handler's name within the node
        (default: the function's name); each name once per node."""
        where = f"node {self.name!r}, every({period_s!r})"
        if (
            isinstance(period_s, bool)
            or not isinstance(period_s, int | float)
            or not math.isfinite(period_s)
            or period_s <= 0
        ):
            raise HandlerError(
                f"{where}: the period must be a finite number of seconds > 0, got "
                f"{period_s!r}; e.g. node.every(0.1) for 10 Hz"
            )
        period = float(period_s)

        def register(fn: F) -> F:
            takes, _ = _signature(fn, where)
            if takes:
                raise HandlerError(
                    f"{where}: periodic handler {fn.__qualname__} must take (ctx) only: "
                    "no message triggers it"
                )
            label = name if name is not None else getattr(fn, "__name__", "")
            try:
                keys.trace("x", label)  # one key chunk, as a node name
            except ValueError as exc:
                raise HandlerError(
                    f"{where}: {label!r} is not a valid periodic handler name ({exc}); "
                    "pass name= with letters, digits and _.-~+:@=%,"
                ) from None
            twin = next((p for p in self.periodic if p.name == label), None)
            if twin is not None:
                raise HandlerError(
                    f"{where}: {fn.__qualname__} would be a second periodic handler named "
                    f"{label!r}, next to {twin.handler_name}; give it another name= "
                    "(each name once per node)"
                )
            self.periodic.append(Periodic(label, period, fn))
            return fn

        return register

    def on_snapshot(self, fn: Callable[[], Any]) -> Callable[[], Any]:
        """``fn()`` returns the node's state (any msgspec-encodable value)."""
        self._snapshot = fn
        return fn

    def on_restore(self, fn: Callable[[Any], Any]) -> Callable[[Any], Any]:
        """``fn(state)`` reinstates a snapshot; the annotation of ``state`` types it."""
        params = list(inspect.signature(fn).parameters.values())
        if len(params) != 1:
            raise HandlerError(f"node {self.name!r}: restore hook takes exactly (state)")
        hint = typing.get_type_hints(fn).get(params[0].name, Any)
        self._restore = (fn, hint)
        return fn

    def snapshot(self) -> bytes:
        """The node's state as msgpack (``nil`` when it declares no snapshot hook)."""
        state = self._snapshot() if self._snapshot is not None else None
        return msgspec.msgpack.encode(state)

    def restore(self, state: bytes) -> None:
        """Decode ``state`` with the restore hook's type and hand it over."""
        if self._restore is None:
            if msgspec.msgpack.decode(state) is not None:
                raise ConfigError(
                    f"node {self.name!r} has state to restore but no @node.on_restore hook"
                )
            return
        fn, hint = self._restore
        try:
            value = msgspec.msgpack.decode(state, type=hint)
        except (msgspec.ValidationError, msgspec.DecodeError) as exc:
            raise ConfigError(
                f"node {self.name!r}: snapshot does not match the restore "
                f"hook's type {hint!r}: {exc}"
            ) from None
        fn(value)

    def configure(self, values: dict[str, Any]) -> msgspec.Struct:
        """Validate ``values`` against the node's config Struct and apply them.

        Raises :class:`ConfigError` with the ``$.path`` of the bad field; the old
        config stays in force then.
        """
        if self.config is None:
            raise ConfigError(f"node {self.name!r} declares no config Struct")
        merged = {**msgspec.structs.asdict(self.config), **values}
        try:
            new = msgspec.convert(merged, type(self.config))
        except msgspec.ValidationError as exc:
            raise ConfigError(f"node {self.name!r}: invalid config: {exc}") from None
        self.config = new
        return new
