"""What the I/O layer needs from a runner and gives its outputs to (Protocols), so that
transports can be tested with a small hand-written runner and a recording sink.

The wall clock is :class:`rap_sdk.envelope.Clock` (``time_ns()``, UTC nanoseconds), the
one every RAP component injects.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Protocol, runtime_checkable

from anyio.abc import TaskStatus
from rap_schemas import TrustSpecStatus, TrustVerdict

__all__ = ["OutputLike", "RunnerLike", "RunningSink", "Sink", "SpecLoader", "VerdictSink"]


class OutputLike(Protocol):
    """One output that ticked (``trust_checker.engine.Output``)."""

    @property
    def stream(self) -> str: ...
    @property
    def tick(self) -> int: ...
    @property
    def value(self) -> object: ...
    @property
    def ts_ns(self) -> int | None: ...


class RunnerLike(Protocol):
    """The part of :class:`trust_checker.engine.SpecRunner` the I/O layer uses."""

    @property
    def inputs(self) -> Sequence[str]: ...
    @property
    def outputs(self) -> Sequence[str]: ...
    @property
    def tick(self) -> int: ...

    def step(self, inputs: dict[str, object], ts_ns: int | None = None) -> Sequence[OutputLike]:
        """One tick; ``InputError`` for a bad input (tick not taken), ``EvalError`` for a
        run-time error (that tick's outputs lost)."""

    def swap(self, spec: Any) -> RunnerLike:
        """A runner for ``spec`` with the streams' history carried over; ``SpecError``."""

    def next_due(self, ts: int) -> int | None:
        """When (tick time, ns) a periodic output is next due after ``ts``; None: never."""


class SpecLoader(Protocol):
    def __call__(self, text: str, path: str) -> Any:
        """Parse and check a spec; raise ``SpecError`` with every problem."""


class Sink(Protocol):
    """Where a session's results go (a transport's publisher, the console)."""

    async def outputs(self, outs: Sequence[OutputLike]) -> None:
        """The outputs of one tick, in console order (NoVal never appears)."""

    async def status(self, status: TrustSpecStatus) -> None:
        """A spec update was taken (``ok``) or refused (``problems``)."""


@runtime_checkable
class VerdictSink(Protocol):
    """A sink that also takes verdicts (a session with ``explain=True`` gives them to
    every sink that has this method)."""

    async def verdicts(self, verdicts: Sequence[TrustVerdict]) -> None:
        """The verdicts of one tick (outputs that turned false, triggers that fired),
        after that tick's outputs."""


@runtime_checkable
class RunningSink(Protocol):
    """A sink with a task of its own (the console's writer):
    :func:`trust_checker.service.open_service` starts its ``run`` next to the session."""

    async def run(self, *, task_status: TaskStatus[None] = ...) -> None:
        """Serve until cancelled; ``task_status.started()`` once ready."""
