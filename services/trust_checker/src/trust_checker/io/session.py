"""A running checker: one monitor fed by transports, its outputs given to sinks.

Transports (MQTT, the fabric) turn messages into :class:`~.ticks.Arrival` values and
spec updates into :class:`SwapRequest` and hand both to :meth:`Session.submit` (or
several arrivals at once to :meth:`Session.submit_many`, one hand-off for a transport
catching up), in arrival order, through one bounded stream; :meth:`Session.run` is the
only task that touches the monitor. It applies the tick policy, drives periodic outputs (it waits,
with a deadline, until the monitor's ``next_due``, then steps with no inputs) and swaps
specs between ticks, so a swap never splits a tick.

Bad input never stops the session: a payload a transport cannot read is
:meth:`Session.reject`-ed, an input the monitor refuses (``InputError``) or a tick that
fails (``EvalError``) is counted and logged (rate-limited), and the next message is
taken. A refused spec update leaves the running spec in place.

With ``explain=True`` (a real :class:`~trust_checker.monitor.Monitor` only) the session
steps the monitor through an :class:`~trust_checker.explain.Explainer` and gives each
tick's verdicts (Bool outputs that turned false, triggers that fired, as
``rap.TrustVerdict``) to every sink that has a ``verdicts`` method
(:class:`~.ports.VerdictSink`), after that tick's outputs.
"""

from __future__ import annotations

import logging
import math
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Final

import anyio
from anyio.abc import TaskStatus
from rap_schemas import TrustSpecStatus, TrustVerdict

from ..errors import EvalError, InputError, SpecError, TrustError
from ..explain import Explainer, to_message
from ..monitor import Monitor
from .ports import Clock, MonitorLike, OutputLike, Sink, SpecLoader, VerdictSink
from .ticks import MESSAGE, Arrival, TickPolicy, merge

__all__ = ["Session", "SessionStats", "SwapRequest", "SystemClock"]

log = logging.getLogger(__name__)

DEFAULT_CAPACITY: Final = 1024


class SystemClock:
    @staticmethod
    def time_ns() -> int:
        return time.time_ns()


@dataclass(slots=True)
class SessionStats:
    messages: int = 0
    """Arrivals submitted (each message that set at least one stream)."""
    ticks: int = 0
    """Ticks the monitor took (input and periodic)."""
    periodic_ticks: int = 0
    ignored: int = 0
    """Messages (or merged bursts) that set none of the spec's inputs: not a tick."""
    rejected: int = 0
    """Payloads a transport could not read (bad JSON, bad envelope, bad tagged value)."""
    input_errors: int = 0
    """Ticks refused by the monitor (a value of the wrong type)."""
    eval_errors: int = 0
    outputs: int = 0
    verdicts: int = 0
    """Verdicts given to the sinks (with ``explain``)."""
    swaps: int = 0
    swaps_rejected: int = 0


@dataclass(eq=False, slots=True)
class SwapRequest:
    """Replace the running spec by ``text`` (history carried over)."""

    text: str
    path: str = "<swap>"
    origin: str = ""
    done: anyio.Event = field(default_factory=anyio.Event)
    result: TrustSpecStatus | None = None


class _RateLog:
    """Log the first few occurrences of a kind of trouble, then every 1000th."""

    __slots__ = ("_seen",)

    def __init__(self) -> None:
        self._seen: dict[str, int] = {}

    def __call__(self, kind: str, msg: str, *args: object) -> None:
        n = self._seen[kind] = self._seen.get(kind, 0) + 1
        if n <= 5 or n % 1000 == 0:
            if n == 1:
                log.warning(msg, *args)
            else:
                log.warning("%s (%d so far)", msg % args, n)


_TIMEOUT: Final = object()
_CLOSED: Final = object()


@dataclass(frozen=True, slots=True)
class _Batch:
    """Arrivals handed over in one go (a transport that fell behind catching up)."""

    arrivals: Sequence[Arrival]


_Item = Arrival | SwapRequest | _Batch


class Session:
    """Owns the monitor. ``loader(text, path)`` parses and checks a new spec for hot swap;
    ``sinks`` get every tick's outputs and every swap's status, and with ``explain``
    its verdicts (see the module docstring)."""

    def __init__(
        self,
        monitor: MonitorLike,
        *,
        loader: SpecLoader,
        sinks: Sequence[Sink] = (),
        policy: TickPolicy = MESSAGE,
        clock: Clock | None = None,
        node: str = "trust_checker",
        capacity: int = DEFAULT_CAPACITY,
        explain: bool = False,
    ) -> None:
        self.monitor = monitor
        self.explainer: Explainer | None = None
        if explain:
            if not isinstance(monitor, Monitor):
                raise TypeError(
                    f"explain=True needs a trust_checker Monitor, got {type(monitor).__name__}"
                )
            self.explainer = Explainer(monitor)
        self.loader = loader
        self.sinks = list(sinks)
        self.policy = policy
        self.clock: Clock = clock or SystemClock()
        self.node = node
        self.stats = SessionStats()
        self._rate = _RateLog()
        self._send, self._receive = anyio.create_memory_object_stream[_Item](capacity)
        self._backlog: deque[Arrival] = deque()
        """The rest of a batch being taken (before anything queued after it)."""
        self._inputs: tuple[MonitorLike, frozenset[str]] | None = None
        self._in_flight = 0
        """Items submitted and not yet taken from the stream."""
        self._last_ts = 0
        self._last_periodic = -1
        self.idle = anyio.Event()
        """Set whenever the session has taken everything submitted so far (tests await
        it instead of sleeping); replaced by a fresh event on the next submit."""
        self.idle.set()

    # -- what transports call ------------------------------------------------------------

    async def submit(self, item: Arrival | SwapRequest) -> None:
        """Queue a message's values or a spec update (waits while the queue is full)."""
        if isinstance(item, Arrival):
            if not item.values:
                return
            self.stats.messages += 1
        await self._queue(item)

    async def submit_many(self, arrivals: Sequence[Arrival]) -> None:
        """Queue several messages' values in order, as one hand-off: each is still its
        own arrival (one tick, or part of a window's burst)."""
        batch = [a for a in arrivals if a.values]
        if not batch:
            return
        self.stats.messages += len(batch)
        await self._queue(batch[0] if len(batch) == 1 else _Batch(batch))

    async def _queue(self, item: _Item) -> None:
        self._in_flight += 1  # counted before the send yields: not idle until taken
        if self.idle.is_set():
            self.idle = anyio.Event()
        try:
            await self._send.send(item)
        except BaseException:
            self._in_flight -= 1
            raise

    async def request_swap(
        self, text: str, *, path: str = "<swap>", origin: str = "", timeout: float = 10.0
    ) -> TrustSpecStatus:
        """Submit a spec update and wait (at most ``timeout`` s) for its status."""
        req = SwapRequest(text, path, origin)
        with anyio.fail_after(timeout):
            await self.submit(req)
            await req.done.wait()
        assert req.result is not None
        return req.result

    def reject(self, origin: str, reason: str) -> None:
        """A payload that could not be read: counted and logged (rate-limited)."""
        self.stats.rejected += 1
        self._rate(f"reject:{origin}", "rejected a message on %s: %s", origin, reason)

    def close(self) -> None:
        """No more input: :meth:`run` returns once it has taken what was queued."""
        self._send.close()

    async def wait_idle(self, timeout: float = 5.0) -> None:
        """Wait until everything submitted so far has been taken."""
        with anyio.fail_after(timeout):
            while not self.idle.is_set():
                await self.idle.wait()

    # -- the one task that runs the monitor ----------------------------------------------

    async def run(self, *, task_status: TaskStatus[None] = anyio.TASK_STATUS_IGNORED) -> None:
        task_status.started()
        try:
            await self._loop()
        finally:
            self._receive.close()
            self._send.close()

    async def _loop(self) -> None:
        pending: SwapRequest | None = None
        while True:
            if pending is not None:
                await self._swap(pending)
                pending = None
            item = await self._next(self._periodic_delay())
            if item is _CLOSED:
                return
            if item is _TIMEOUT:
                await self._periodic()
                continue
            if isinstance(item, SwapRequest):
                await self._swap(item)
                continue
            assert isinstance(item, Arrival)
            if self.policy.kind == "window":
                burst = [item]
                end = anyio.current_time() + self.policy.window_s
                while True:
                    nxt = await self._next(max(end - anyio.current_time(), 0.0), burst=True)
                    if nxt is _TIMEOUT or nxt is _CLOSED:
                        break
                    if isinstance(nxt, SwapRequest):
                        pending = nxt  # a swap ends the burst and follows its tick
                        break
                    assert isinstance(nxt, Arrival)
                    burst.append(nxt)
                item = merge(burst)
            await self._step(item)

    async def _next(self, timeout: float | None, *, burst: bool = False) -> object:
        if self._backlog:
            return self._backlog.popleft()
        try:
            item = self._receive.receive_nowait()
        except anyio.WouldBlock:
            if not burst and self._in_flight <= 0:  # (< 0 after a send cancelled late)
                self.idle.set()
            with anyio.move_on_after(math.inf if timeout is None else timeout):
                try:
                    item = await self._receive.receive()
                except anyio.EndOfStream:
                    return _CLOSED
                return self._unbatch(item)
            return _TIMEOUT
        except anyio.EndOfStream:
            return _CLOSED
        return self._unbatch(item)

    def _unbatch(self, item: _Item) -> object:
        self._in_flight -= 1
        if isinstance(item, _Batch):
            self._backlog.extend(item.arrivals)
            return self._backlog.popleft()
        return item

    def _now(self) -> int:
        ts = self.clock.time_ns()
        return max(ts, self._last_ts)  # tick times never go back

    def _periodic_delay(self) -> float | None:
        due = self.monitor.next_due(self._now())
        if due is None or due <= self._last_periodic:
            return None
        return max(due - self.clock.time_ns(), 0) / 1e9

    async def _periodic(self) -> None:
        due = self.monitor.next_due(self._now())
        if due is None or due <= self._last_periodic:
            return
        self._last_periodic = due
        self.stats.periodic_ticks += 1
        await self._take({}, max(due, self._last_ts), "periodic tick")

    async def _step(self, arrival: Arrival) -> None:
        cached = self._inputs
        if cached is None or cached[0] is not self.monitor:
            cached = self._inputs = (self.monitor, frozenset(self.monitor.inputs))
        inputs = cached[1]
        values = {k: v for k, v in arrival.values.items() if k in inputs}
        if not values:
            self.stats.ignored += arrival.count
            log.debug("not a tick: %s set none of the inputs %s", arrival.origin, sorted(inputs))
            return
        await self._take(values, max(arrival.ts_ns, self._last_ts), arrival.origin)

    async def _take(self, values: dict[str, object], ts: int, origin: str) -> None:
        self._last_ts = ts
        verdicts: Sequence[TrustVerdict] = ()
        try:
            if self.explainer is not None:
                outs: Sequence[OutputLike]
                outs, explained = self.explainer.step(values, ts)
                if explained:
                    verdicts = [to_message(v) for v in explained]
            else:
                outs = self.monitor.step(values, ts)
        except InputError as exc:
            self.stats.input_errors += 1
            self._rate("input", "input from %s not taken: %s", origin or "?", exc)
            return
        except EvalError as exc:
            self.stats.eval_errors += 1
            self._rate("eval", "tick failed (%s): %s", origin or "?", exc)
            return
        self.stats.ticks += 1
        if outs:
            self.stats.outputs += len(outs)
            for sink in self.sinks:
                await sink.outputs(outs)
        if verdicts:
            await self._verdicts(verdicts)

    async def _verdicts(self, verdicts: Sequence[TrustVerdict]) -> None:
        self.stats.verdicts += len(verdicts)
        for sink in self.sinks:
            if isinstance(sink, VerdictSink):
                await sink.verdicts(verdicts)

    async def _swap(self, req: SwapRequest) -> None:
        problems: list[str] = []
        try:
            spec = self.loader(req.text, req.path)
            if self.explainer is not None:
                explainer = self.explainer.swap(spec)
                new: MonitorLike = explainer.monitor
            else:
                new = self.monitor.swap(spec)
        except SpecError as exc:
            problems = [str(p) for p in exc.problems] or [str(exc)]
        except TrustError as exc:
            problems = [str(exc)]
        else:
            self.monitor = new
            if self.explainer is not None:
                self.explainer = explainer
        ok = not problems
        if ok:
            self.stats.swaps += 1
            log.info(
                "spec swapped (from %s) at tick %d: inputs %s, outputs %s",
                req.origin or "?",
                self.monitor.tick,
                list(self.monitor.inputs),
                list(self.monitor.outputs),
            )
        else:
            self.stats.swaps_rejected += 1
            log.warning(
                "spec update from %s refused, the running spec stays:\n%s",
                req.origin or "?",
                "\n".join(problems),
            )
        status = TrustSpecStatus(
            ok=ok,
            node=self.node,
            ts=self.clock.time_ns(),
            tick=self.monitor.tick,
            problems=problems,
            inputs=list(self.monitor.inputs),
            outputs=list(self.monitor.outputs),
        )
        req.result = status
        req.done.set()
        for sink in self.sinks:
            await sink.status(status)
