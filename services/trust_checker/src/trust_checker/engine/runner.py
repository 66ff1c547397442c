"""Running a spec: one tick at a time, with the semantics of docs/trust_checker.md.

:class:`SpecRunner` compiles a spec (:class:`~.plan.CompiledSpec`: expressions to
closures, nothing walks the syntax tree at run time) and steps it. Per tick,
:meth:`SpecRunner.step` takes the inputs (checked against their declared types), pushes
last tick's held values into the bounded histories, then runs the plan for the inputs that
arrived: the computed streams in dependency order, each updating its stateful nodes and
storing its value. The first tick, and the tick after a run-time error, compute everything.

Finite traces: :meth:`SpecRunner.finish` runs the drain ticks after the last input,
during which a stream is computed while the tick is below ``T + extra`` (see the docs).
Hot swap: :meth:`SpecRunner.swap` builds a runner for a new spec that keeps the held
values and histories of the streams that keep their names, and the operator state of the
streams whose equations did not change.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from typing import NamedTuple, NoReturn

from trust_checker.engine.nodes import INF, ExprNode, Stream
from trust_checker.engine.plan import CompiledSpec, Plan
from trust_checker.errors import EvalError, InputError
from trust_checker.lang import ast
from trust_checker.lang.check import Limits
from trust_checker.operators import Fault, Mismatch
from trust_checker.values import INT_MAX, INT_MIN, NOVAL

__all__ = ["Fired", "Output", "SpecRunner"]


class Output(NamedTuple):
    """One output value at one tick (never NoVal; ``BOTTOM`` for ⊥)."""

    stream: str
    tick: int
    value: object
    ts_ns: int | None


class Fired(NamedTuple):
    """A trigger whose condition was true at ``tick``; ``trigger`` is its index in
    ``spec.triggers`` (two triggers may share a message)."""

    message: str
    severity: str
    tick: int
    ts_ns: int | None
    trigger: int


_new_output = tuple.__new__
"""``Output`` rows are built with ``tuple.__new__`` (the same tuple, without the Python
call of the generated ``__new__``)."""


class SpecRunner:
    """A running spec. ``step`` takes one tick, ``finish`` drains a finite trace,
    ``swap`` hot-swaps the spec keeping stream history; see API.md."""

    def __init__(self, spec: ast.Spec, *, limits: Limits | None = None) -> None:
        """Compiles ``spec``; :class:`~trust_checker.errors.SpecError` if it does not
        check."""
        self._limits = limits if limits is not None else Limits()
        self._spec = spec
        c = self._compiled = CompiledSpec(spec, self._limits)
        self._clock = c.time
        self._tick = 0
        self._ran = False
        self._finished = False
        self.fired: list[Fired] = []
        # the compiled layout's parts read on every tick (one attribute lookup each)
        self._streams = c.streams
        self._in = c.inputs
        self._owner = c.owner
        self._trigger_streams = c.triggers
        self._hist_push = c.hist_push
        self._plan = c.plan
        self._plans = c.plans
        self._outputs = c.outputs
        self._periodic = c.periodic
        self._after = c.after
        self.nodes: dict[str, ExprNode] = c.nodes
        """The compiled root node of every computed stream (for inspection)."""
        self._full = True
        """Compute every stream at the next tick (the first, and after an error)."""
        self._due: dict[str, int] = {}
        self._last_mask = 0
        self._last_arrived: tuple[Stream, ...] = ()
        """The inputs given at the last tick (their ``cur`` goes back to NoVal)."""

    # -- the API ----------------------------------------------------------------------------

    @property
    def spec(self) -> ast.Spec:
        return self._spec

    @property
    def tick(self) -> int:
        """Ticks taken so far (the next tick's number)."""
        return self._tick

    @property
    def inputs(self) -> tuple[str, ...]:
        return self._spec.inputs

    @property
    def outputs(self) -> tuple[str, ...]:
        return self._spec.outputs

    @property
    def finished(self) -> bool:
        return self._finished

    def held(self, name: str) -> object:
        """The held value of stream ``name`` after the last tick (NoVal: none yet)."""
        return self._stream(name).held

    def value(self, name: str) -> object:
        """The value of stream ``name`` at the last tick (NoVal: it did not tick)."""
        return self._stream(name).cur

    def _stream(self, name: str) -> Stream:
        s = self._streams.get(name)
        if s is None or s.hidden:
            raise KeyError(
                f"no stream {name!r} in the spec (its streams: {', '.join(self._spec.order)})"
            )
        return s

    def step(self, inputs: Mapping[str, object], ts_ns: int | None = None) -> list[Output]:
        """One tick: ``inputs`` maps input names to values (absent: NoVal). Returns the
        outputs that ticked, in console order. Raises :class:`InputError` (the tick is not
        taken) or :class:`EvalError` (the tick is taken, its outputs are lost)."""
        if self._finished:
            raise InputError(
                f"the runner has finished (finish() ran after tick {self._tick - 1}) - "
                "create a new SpecRunner to check another trace"
            )
        mask = 0
        known = self._in
        for name, v in inputs.items():
            entry = known.get(name)
            if entry is None:
                self._unknown_input(name)
            s, plain, conform, bit = entry
            if type(v) is not plain or (plain is int and not INT_MIN <= v <= INT_MAX):  # type: ignore[operator]
                if v is NOVAL:
                    continue
                v = self._conform(s, name, v, conform)
            s.next = v
            mask |= bit
        # the tick itself (as _run, on the fast path: a plan for this set of inputs)
        if self.fired:
            self.fired = []
        if self._ran:
            for push, h in self._hist_push:
                push(h.held)
        else:
            self._ran = True
        cached = self._plans.get(mask)
        if cached is None:
            cached = self._compiled.plan_for(mask)
        arrived, plan = cached
        if mask != self._last_mask:
            for s in self._last_arrived:
                s.cur = NOVAL
            self._last_mask, self._last_arrived = mask, arrived
        for s in arrived:
            s.cur = s.held = s.next
        if ts_ns is not None:
            self._clock.ts = ts_ns
        tick = self._tick
        self._tick = tick + 1
        if self._full:
            plan = self._plan
        current: Stream | None = None
        try:
            for current, run in plan:
                v = run()
                current.cur = v
                if v is not NOVAL:
                    current.held = v
        except Fault as f:
            self._abort(current, self._plan)
            raise EvalError(
                f.message, stream=self._name(current), tick=tick, where=f.where
            ) from None
        except (TypeError, ValueError, ArithmeticError) as x:  # a bug, but keep running
            self._abort(current, self._plan)
            raise EvalError(f"internal error: {x!r}", stream=self._name(current), tick=tick) from x
        self._full = False
        outs: list[Output] = []
        add = outs.append
        for o in self._outputs:
            v = o.cur
            if v is not NOVAL:
                add(_new_output(Output, (o.name, tick, v, ts_ns)))
        if self._after:
            return self._after_tick(outs, tick, ts_ns, True)
        return outs

    def _conform(
        self, s: Stream, name: str, v: object, conform: Callable[[object], object]
    ) -> object:
        try:
            return conform(v)
        except Mismatch as m:
            declared = s.decl.type if s.decl is not None else None
            raise InputError(
                f"input {name!r} at tick {self._tick}: {m}"
                + (f" (declared {name}: {declared})" if declared is not None else "")
                + " - the tick was not taken; send a value of the declared type"
            ) from None

    def _unknown_input(self, name: str) -> NoReturn:
        s = self._streams.get(name)
        if s is not None and not s.hidden:
            raise InputError(
                f"{name!r} is an {s.kind} stream, computed by the spec; only inputs "
                f"({', '.join(self.inputs) or 'none'}) can be given"
            )
        raise InputError(
            f"unknown input {name!r}; the spec's inputs are {', '.join(self.inputs) or 'none'} "
            "(declare it with: in NAME: T)"
        )

    def _drain_tick(self, ts_ns: int | None, plan: Plan, stopped: list[Stream]) -> list[Output]:
        """A drain tick (``finish``): no input; ``stopped`` streams do not tick."""
        self.fired = []
        if self._ran:
            for push, h in self._hist_push:
                push(h.held)
        self._ran = True
        for s in self._last_arrived:
            s.cur = NOVAL
        self._last_mask, self._last_arrived = 0, ()
        for s in stopped:
            s.cur = NOVAL
        if ts_ns is not None:
            self._clock.ts = ts_ns
        tick = self._tick
        self._tick = tick + 1
        current: Stream | None = None
        try:
            for current, run in plan:
                v = run()
                current.cur = v
                if v is not NOVAL:
                    current.held = v
        except Fault as f:
            self._abort(current, plan)
            raise EvalError(
                f.message, stream=self._name(current), tick=tick, where=f.where
            ) from None
        except (TypeError, ValueError, ArithmeticError) as x:  # a bug, but keep running
            self._abort(current, plan)
            raise EvalError(f"internal error: {x!r}", stream=self._name(current), tick=tick) from x
        outs = [Output(o.name, tick, o.cur, ts_ns) for o in self._outputs if o.cur is not NOVAL]
        return self._after_tick(outs, tick, ts_ns, False)

    def _after_tick(
        self, outs: list[Output], tick: int, ts_ns: int | None, live: bool
    ) -> list[Output]:
        """Periodic outputs (on a live tick) and the triggers that fired."""
        if self._periodic and ts_ns is not None and live:
            outs = self._periodic_outputs(outs, tick, ts_ns)
        for ts, trig, i in self._trigger_streams:
            if ts.cur is True:
                self.fired.append(Fired(trig.message, trig.severity, tick, ts_ns, i))
        return outs

    def _name(self, s: Stream | None) -> str:
        return "" if s is None else self._owner.get(s.name, s.name)

    def _abort(self, failed: Stream | None, plan: Plan) -> None:
        """After a run-time error: the failed stream and every later one did not tick."""
        self._full = True
        seen = failed is None
        for s, _ in plan:
            seen = seen or s is failed
            if seen:
                s.cur = NOVAL

    def _periodic_outputs(self, outs: list[Output], tick: int, ts_ns: int) -> list[Output]:
        if not self._due:
            self.next_due(ts_ns)
            return outs
        due_now: set[str] = set()
        for s, period in self._periodic:
            d = self._due[s.name]
            if ts_ns >= d:
                due_now.add(s.name)
                self._due[s.name] = d + period * ((ts_ns - d) // period + 1)
        if not due_now:
            return outs
        ticked = {o.stream for o in outs}
        out: list[Output] = []
        for o in self._outputs:
            if o.name in ticked:
                out.append(next(x for x in outs if x.stream == o.name))
            elif o.name in due_now and o.held is not NOVAL:
                out.append(Output(o.name, tick, o.held, ts_ns))
        return out

    def next_due(self, ts_ns: int) -> int | None:
        """When the next periodic output is due (ns), for a timer tick ``step({}, due)``;
        None if the spec has no periodic output. The schedule starts at the first
        timestamp seen."""
        if not self._periodic:
            return None
        if not self._due:
            for s, period in self._periodic:
                self._due[s.name] = ts_ns + period
        return min(self._due.values())

    def finish(self) -> list[Output]:
        """The drain ticks of a finite trace: inputs have ended; every output runs for
        ``T + extra`` ticks (docs/trust_checker.md, "Finite traces"). Afterwards
        :attr:`fired` holds the triggers that fired at any drain tick. Idempotent."""
        outs: list[Output] = []
        fired: list[Fired] = []
        for tick_outs in self.drain():
            outs += tick_outs
            fired += self.fired
        if fired:
            self.fired = fired
        return outs

    def drain(self) -> Iterator[list[Output]]:
        """:meth:`finish` one drain tick at a time: each item is a drain tick's outputs,
        and while it is current :attr:`fired` and the streams' values are that tick's
        (what an explanation reads). Yields nothing once finished."""
        if self._finished:
            return
        self._finished = True
        computed = [s for s, _ in self._plan]
        for j in range(self._compiled.drain_ticks):
            plan = [(s, r) for s, r in self._plan if j < s.extra < INF]
            stopped = [s for s in computed if not j < s.extra < INF]
            yield self._drain_tick(None, plan, stopped)

    def swap(self, new_spec: ast.Spec) -> SpecRunner:
        """A runner for ``new_spec`` continuing this one: same tick count; streams with
        the same name keep their held values and history; streams whose equation is
        unchanged also keep their operators' state. Raises :class:`SpecError` (and this
        runner stays as it was) if ``new_spec`` does not check."""
        new = SpecRunner(new_spec, limits=self._limits)
        new._tick, new._ran = self._tick, self._ran
        new._clock.ts = self._clock.ts
        old_exprs, new_exprs = self._compiled.exprs, new._compiled.exprs
        old_state, new_state = self._compiled.stateful, new._compiled.stateful
        for name, s in new._streams.items():
            old = self._streams.get(name)
            if old is None or old.hidden != s.hidden:
                continue
            if s.hidden and old_exprs.get(name) != new_exprs.get(name):
                continue
            s.held = old.held
            if s.hist is not None:
                past = list(old.hist) if old.hist is not None else []
                s.hist.extend(past[-(s.hist.maxlen or 0) :] if past else [])
            if name in new_state and old_exprs.get(name) == new_exprs.get(name):
                mine, theirs = new_state[name], old_state.get(name, [])
                if len(mine) == len(theirs):
                    for a, b in zip(mine, theirs, strict=True):
                        a.restore(b.export())
        if self._due:
            for s, period in new._periodic:
                now = self._clock.ts if self._clock.ts is not None else 0
                new._due[s.name] = self._due.get(s.name, now + period)
        return new
