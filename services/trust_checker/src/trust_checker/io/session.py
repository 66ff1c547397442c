"""A running checker: one spec runner fed by transports, its outputs given to sinks.

Transports (MQTT, the fabric) turn messages into :class:`~.ticks.Arrival` values and
spec updates into :class:`SwapRequest` and hand both to :meth:`Session.submit` (or
several arrivals at once to :meth:`Session.submit_many`, one hand-off for a transport
catching up), in arrival order, through one bounded stream; :meth:`Session.run` is the
only task that touches the runner. It applies the tick policy, drives periodic outputs
(it waits, with a deadline, until the runner's ``next_due``, then steps with no inputs)
and swaps specs between ticks, so a swap never splits a tick.

Bad input never stops the session: a payload a transport cannot read is rejected by the
transport (counted by reason in its ``stats.rejections``), an input the runner refuses
(``InputError``) or a tick that fails (``EvalError``) is counted here and logged
(rate-limited: the first at once, then at most one line a second with how many came
since), and the next message is taken. A refused spec update leaves the running spec in
place.

With ``explain=True`` (a real :class:`~trust_checker.engine.SpecRunner` only) the session
steps the runner through an :class:`~trust_checker.explain.Explainer` and gives each
tick's verdicts (Bool outputs that turned false, triggers that fired, as
``rap.TrustVerdict``) to every sink that has a ``verdicts`` method
(:class:`~.ports.VerdictSink`), after that tick's outputs.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Final

import anyio
from anyio.abc import TaskStatus
from rap_schemas import TrustSpecStatus, TrustVerdict
from rap_schemas.limits import MAX_DEPTH, DecodeRejected, check_depth
from rap_sdk.envelope import Clock, SystemClock
from rap_sdk.rejections import Throttle

from ..engine import SpecRunner
from ..errors import EvalError, InputError, SpecError, TrustError
from ..explain import Explainer, to_message
from .ports import OutputLike, RunnerLike, Sink, SpecLoader, VerdictSink
from .ticks import MESSAGE, Arrival, TickPolicy, merge

__all__ = ["DEFAULT_CAPACITY", "Session", "SessionStats", "SwapRequest"]

log = logging.getLogger(__name__)

DEFAULT_CAPACITY: Final = 1024
"""Items (arrivals, batches, swap requests) that may wait for the session."""


@dataclass(slots=True)
class SessionStats:
    messages: int = 0
    """Arrivals submitted (each message that set at least one stream)."""
    ticks: int = 0
    """Ticks the runner took (input and periodic)."""
    periodic_ticks: int = 0
    ignored: int = 0
    """Messages (or merged bursts) that set none of the spec's inputs: not a tick."""
    input_errors: int = 0
    """Ticks refused by the runner (a value of the wrong type, an unknown stream)."""
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
    on_done: Callable[[TrustSpecStatus], None] | None = None
    """Called with the outcome, once the swap is done or refused (the audit of a
    transport that does not wait for it)."""


_TIMEOUT: Final = object()
_CLOSED: Final = object()


@dataclass(frozen=True, slots=True)
class _Batch:
    """Arrivals handed over in one go (a transport that fell behind catching up)."""

    arrivals: Sequence[Arrival]


_Item = Arrival | SwapRequest | _Batch


class Session:
    """Owns the runner. ``loader(text, path)`` parses and checks a new spec for hot swap;
    ``sinks`` get every tick's outputs and every swap's status, and with ``explain``
    its verdicts (see the module docstring)."""

    def __init__(
        self,
        runner: RunnerLike,
        *,
        loader: SpecLoader,
        sinks: Sequence[Sink] = (),
        policy: TickPolicy = MESSAGE,
        clock: Clock | None = None,
        node: str = "trust_checker",
        capacity: int = DEFAULT_CAPACITY,
        explain: bool = False,
    ) -> None:
        self.runner = runner
        self.explainer: Explainer | None = None
        if explain:
            if not isinstance(runner, SpecRunner):
                raise TypeError(
                    f"explain=True needs a trust_checker SpecRunner, got {type(runner).__name__}"
                    " - pass explain=False, or a SpecRunner"
                )
            self.explainer = Explainer(runner)
        self.loader = loader
        self.sinks = list(sinks)
        self.policy = policy
        self.clock: Clock = clock or SystemClock()
        self.node = node
        self.stats = SessionStats()
        self._throttle = Throttle()
        self._send, self._receive = anyio.create_memory_object_stream[_Item](capacity)
        self._backlog: deque[Arrival] = deque()
        """The rest of a batch being taken (before anything queued after it)."""
        self._inputs: tuple[RunnerLike, frozenset[str]] | None = None
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

    def close(self) -> None:
        """No more input: :meth:`run` returns once it has taken what was queued."""
        self._send.close()

    def discard(self) -> None:
        """Release a session that will never run (its queue, both ends)."""
        self._send.close()
        self._receive.close()

    async def wait_idle(self, timeout: float = 5.0) -> None:
        """Wait until everything submitted so far has been taken."""
        with anyio.fail_after(timeout):
            while not self.idle.is_set():
                await self.idle.wait()

    # -- the one task that runs the runner -----------------------------------------------

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
        due = self.runner.next_due(self._now())
        if due is None or due <= self._last_periodic:
            return None
        return max(due - self.clock.time_ns(), 0) / 1e9

    async def _periodic(self) -> None:
        due = self.runner.next_due(self._now())
        if due is None or due <= self._last_periodic:
            return
        self._last_periodic = due
        self.stats.periodic_ticks += 1
        await self._take({}, max(due, self._last_ts), "periodic tick")

    async def _step(self, arrival: Arrival) -> None:
        cached = self._inputs
        if cached is None or cached[0] is not self.runner:
            cached = self._inputs = (self.runner, frozenset(self.runner.inputs))
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
                outs = self.runner.step(values, ts)
        except InputError as exc:
            self.stats.input_errors += 1
            self._warn("input", "input from %s not taken: %s", origin or "?", exc)
            return
        except (EvalError, RecursionError) as exc:  # a value the spec nested without bound
            self.stats.eval_errors += 1
            self._warn("eval", "tick failed (%s): %s", origin or "?", exc)
            return
        self.stats.ticks += 1
        deep = [o for o in outs if _too_deep(o.value)]
        if deep:
            self.stats.eval_errors += len(deep)
            self._warn(
                "deep",
                "output %s nests lists or maps more than %d levels deep: not given to the "
                "sinks (the spec builds a value that grows without bound; fix the spec)",
                deep[0].stream,
                MAX_DEPTH,
            )
            outs = [o for o in outs if o not in deep]
        if outs:
            self.stats.outputs += len(outs)
            for sink in self.sinks:
                await sink.outputs(outs)
        if verdicts:
            await self._verdicts(verdicts)

    def _warn(self, kind: str, msg: str, *args: object) -> None:
        """Log a warning of this kind at once the first time, then at most once a second
        with how many came since."""
        n = self._throttle.hit(kind)
        if n:
            log.warning("%s (%d like it since the last report)", msg % args, n)

    async def _verdicts(self, verdicts: Sequence[TrustVerdict]) -> None:
        self.stats.verdicts += len(verdicts)
        for sink in self.sinks:
            if isinstance(sink, VerdictSink):
                await sink.verdicts(verdicts)

    async def _swap(self, req: SwapRequest) -> None:
        problems: list[str] = []
        try:
            # parsed and checked on a worker thread: a large spec from the network
            # (up to MAX_SPEC_CHARS) must not stop the ticks and the other requests
            spec = await anyio.to_thread.run_sync(self.loader, req.text, req.path)
            if self.explainer is not None:
                explainer = self.explainer.swap(spec)
                new: RunnerLike = explainer.runner
            else:
                new = self.runner.swap(spec)
        except SpecError as exc:
            problems = [str(p) for p in exc.problems] or [str(exc)]
        except TrustError as exc:
            problems = [str(exc)]
        except (ValueError, RecursionError, MemoryError) as exc:
            # a spec from the network that trips the parser or the checker: a refused
            # swap (with the traceback in the log), never the end of the checker
            log.exception("spec update from %s failed inside the checker", req.origin or "?")
            problems = [f"{req.path}: the checker failed on this spec: {type(exc).__name__}: {exc}"]
        else:
            self.runner = new
            if self.explainer is not None:
                self.explainer = explainer
        ok = not problems
        if ok:
            self.stats.swaps += 1
            log.info(
                "spec swapped (from %s) at tick %d: inputs %s, outputs %s",
                req.origin or "?",
                self.runner.tick,
                list(self.runner.inputs),
                list(self.runner.outputs),
            )
        else:
            self.stats.swaps_rejected += 1
            self._warn(  # a flood of bad updates is logged at most once a second
                "swap",
                "spec update from %s refused, the running spec stays:\n%s",
                req.origin or "?",
                "\n".join(problems[:5])
                + (f"\n(and {len(problems) - 5} more)" if len(problems) > 5 else ""),
            )
        status = TrustSpecStatus(
            ok=ok,
            node=self.node,
            ts=self.clock.time_ns(),
            tick=self.runner.tick,
            problems=problems,
            inputs=list(self.runner.inputs),
            outputs=list(self.runner.outputs),
        )
        req.result = status
        req.done.set()
        if req.on_done is not None:
            try:
                req.on_done(status)
            except Exception:  # a transport's hook: logged, never the end of the session
                log.exception("the hook of a spec update from %s failed", req.origin or "?")
        for sink in self.sinks:
            await sink.status(status)


def _too_deep(value: object) -> bool:
    """An output value nested past :data:`~rap_schemas.limits.MAX_DEPTH` (every sink
    converts values recursively)."""
    if not isinstance(value, (tuple, dict)):
        return False
    try:
        check_depth(value, MAX_DEPTH, "output")
    except DecodeRejected:
        return True
    return False
