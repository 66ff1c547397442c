"""What the I/O layer needs from a monitor and gives its outputs to (Protocols), so that
transports can be tested with a small hand-written monitor and a recording sink."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Protocol, runtime_checkable

from rap_schemas import TrustSpecStatus, TrustVerdict

__all__ = ["Clock", "MonitorLike", "OutputLike", "Sink", "SpecLoader", "VerdictSink"]


class OutputLike(Protocol):
    """One output that ticked (``trust_checker.monitor.Output``)."""

    @property
    def stream(self) -> str: ...
    @property
    def tick(self) -> int: ...
    @property
    def value(self) -> object: ...
    @property
    def ts_ns(self) -> int | None: ...


class MonitorLike(Protocol):
    """The part of ``trust_checker.monitor.Monitor`` the I/O layer uses."""

    @property
    def inputs(self) -> Sequence[str]: ...
    @property
    def outputs(self) -> Sequence[str]: ...
    @property
    def tick(self) -> int: ...

    def step(self, inputs: dict[str, object], ts_ns: int | None = None) -> Sequence[OutputLike]:
        """One tick; ``InputError`` for a bad input (tick not taken), ``EvalError`` for a
        run-time error (that tick's outputs lost)."""

    def swap(self, spec: Any) -> MonitorLike:
        """A monitor for ``spec`` with the streams' history carried over; ``SpecError``."""

    def next_due(self, ts: int) -> int | None:
        """When (tick time, ns) a periodic output is next due after ``ts``; None: never."""


class SpecLoader(Protocol):
    def __call__(self, text: str, path: str) -> Any:
        """Parse and check a spec; raise ``SpecError`` with every problem."""


class Clock(Protocol):
    def time_ns(self) -> int:
        """UTC wall clock, integer nanoseconds."""


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
