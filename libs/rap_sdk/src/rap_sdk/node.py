"""Declaring MAPLE-K nodes: a name, a stage, typed handlers, config and state hooks.

    analyse = Node("analysis", stage="analyse")

    @analyse.on_event("new-data")
    async def detect(ctx: Context) -> None: ...

    @analyse.on_data("scan")
    async def on_scan(ctx: Context, scan: LaserScan) -> None: ...

    @analyse.on_trust("stage_order_ok")          # a trust checker's output stream
    async def on_verdict(ctx: Context, out: TrustOutput) -> None: ...

A handler takes the :class:`~rap_sdk.runtime.Context` and, optionally, the message; the
message's annotation picks the decoder (built once, at declaration). Handlers are plain
async functions that tests may call directly. A Node is only a declaration; it runs on a
fabric through :func:`rap_sdk.run_nodes` or :func:`rap_sdk.run`.
"""

from __future__ import annotations

import inspect
import typing
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any, Literal, TypeVar

import msgspec
from rap_schemas import Message, Stage, keys

from .envelope import TypedEnvelope, typed_decoder
from .errors import ConfigError, HandlerError
from .inbox import InboxPolicy, Overflow

__all__ = ["DATA_POLICY", "EVENT_POLICY", "TRUST_POLICY", "Node", "Route"]

F = TypeVar("F", bound=Callable[..., Awaitable[None]])

DATA_POLICY = InboxPolicy(capacity=8, overflow=Overflow.LATEST)
"""Default for data topics: keep the newest samples."""
EVENT_POLICY = InboxPolicy(capacity=256, overflow=Overflow.FIFO, block=True)
"""Default for events: in order, local senders wait for room."""
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
    msg_type: type[Message] | None
    """None: the handler takes no message; the body is not decoded."""
    decode: Callable[[bytes], TypedEnvelope[Any]]
    """Envelope and body in one pass (body left raw when ``msg_type`` is None)."""
    policy: InboxPolicy

    @property
    def handler_name(self) -> str:
        return getattr(self.fn, "__qualname__", repr(self.fn))

    def key(self, system: str) -> str:
        """The key this route handles in ``system``."""
        return _BUILDERS[self.kind](system, self.name)

    @property
    def traced(self) -> bool:
        """Calls are traced as stage records; not for trust outputs (a handler of a
        checker's verdicts runs outside any MAPLE-K cycle, and its records would feed
        the checker its own consequences)."""
        return self.kind != "trust"


def _message_type(fn: Callable[..., Any], where: str) -> type[Message] | None:
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
        return None
    try:
        hints = typing.get_type_hints(fn)
    except (NameError, TypeError) as exc:
        raise HandlerError(
            f"{where}: cannot resolve the annotations of {fn.__qualname__} ({exc}); define "
            "message types at module level"
        ) from None
    ann = hints.get(params[1].name)
    if not (isinstance(ann, type) and issubclass(ann, Message) and ann.TYPE):
        raise HandlerError(
            f"{where}: the message parameter {params[1].name!r} of {fn.__qualname__} must "
            f"be annotated with a rap_schemas.Message subclass, got {ann!r}"
        )
    return ann


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
        self.routes: list[Route] = []
        self._snapshot: Callable[[], Any] | None = None
        self._restore: tuple[Callable[[Any], Any], type[Any]] | None = None

    def __repr__(self) -> str:
        stage = self.stage.value if self.stage else "-"
        return f"Node({self.name!r}, stage={stage}, routes={len(self.routes)})"

    def _route(
        self,
        kind: RouteKind,
        name: str,
        policy: InboxPolicy,
    ) -> Callable[[F], F]:
        _BUILDERS[kind]("x", name)  # validates the topic / event name / trust stream

        def register(fn: F) -> F:
            where = f"node {self.name!r}, {kind} {name!r}"
            msg_type = _message_type(fn, where)
            self.routes.append(Route(kind, name, fn, msg_type, typed_decoder(msg_type), policy))
            return fn

        return register

    def on_data(self, topic: str, *, policy: InboxPolicy | None = None) -> Callable[[F], F]:
        """Handle samples on ``rap/<system>/data/<topic>``."""
        return self._route("data", topic, policy or DATA_POLICY)

    def on_event(self, name: str, *, policy: InboxPolicy | None = None) -> Callable[[F], F]:
        """Handle events on ``rap/<system>/event/<name>``."""
        return self._route("event", name, policy or EVENT_POLICY)

    def on_trust(self, stream: str, *, policy: InboxPolicy | None = None) -> Callable[[F], F]:
        """Handle a trust checker's output ``stream`` (``rap/<system>/trust/<stream>``,
        messages :class:`rap_schemas.TrustOutput`). These calls are not traced."""
        return self._route("trust", stream, policy or TRUST_POLICY)

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
